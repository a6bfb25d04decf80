"""Layout files: a sensor mat described in TOML, read and written.

>>> from appliance.core.named_layouts import get_layout
>>> text = layout_to_toml(get_layout("grid-4x4"))
>>> text.splitlines()[:2]
['name = "grid-4x4"', 'grid = [4, 4]']
"""

from __future__ import annotations

from pathlib import Path

from appliance.core.layouts import DiscSheet, Layout, RectElectrode, RectSheet, SectorElectrode
from appliance.core.toml_files import check_keys, read_toml, toml_value
from appliance.errors import LayoutInvalid


def load_layout(path: Path) -> Layout:
    """Read a layout from a TOML file (the format :func:`layout_to_toml` writes)."""
    data = read_toml(path, "layout file", LayoutInvalid)
    try:
        return layout_from_mapping(data)
    except LayoutInvalid as exc:
        raise LayoutInvalid(f"layout file {path}: {exc}") from None


def layout_from_mapping(data: dict) -> Layout:
    """Build a layout from parsed TOML (a dict); every missing or mistyped key is named."""
    check_keys(data, {"name", "grid", "sheet", "electrodes"}, "the layout", LayoutInvalid)
    name = _field(data, "name", str, "the layout")
    sheet_data = _field(data, "sheet", dict, "the layout")
    shape = _field(sheet_data, "shape", str, "[sheet]")
    sheet: RectSheet | DiscSheet
    if shape == "rectangle":
        sheet = RectSheet(_number(sheet_data, "width_mm", "[sheet]"), _number(sheet_data, "height_mm", "[sheet]"))
    elif shape == "disc":
        sheet = DiscSheet(_number(sheet_data, "radius_mm", "[sheet]"))
    else:
        raise LayoutInvalid(f"[sheet] shape must be 'rectangle' or 'disc', got {shape!r}")
    electrodes: list[RectElectrode | SectorElectrode] = []
    for i, item in enumerate(_field(data, "electrodes", list, "the layout"), start=1):
        where = f"[[electrodes]] entry {i}"
        if not isinstance(item, dict):
            raise LayoutInvalid(f"{where} must be a table")
        number = _field(item, "number", int, where)
        kind = _field(item, "shape", str, where)
        if kind == "rectangle":
            electrodes.append(RectElectrode(number, *(_number(item, k, where) for k in
                                                      ("x_mm", "y_mm", "width_mm", "height_mm"))))
        elif kind == "sector":
            electrodes.append(SectorElectrode(number, *(_number(item, k, where) for k in
                                                        ("angle_deg", "width_deg", "depth_mm"))))
        else:
            raise LayoutInvalid(f"{where}: shape must be 'rectangle' or 'sector', got {kind!r}")
    grid = data.get("grid")
    if grid is not None and not (isinstance(grid, list) and len(grid) == 2 and all(isinstance(g, int) for g in grid)):
        raise LayoutInvalid(f"grid must be [rows, columns], got {grid!r}")
    return Layout(name, sheet, tuple(electrodes), tuple(grid) if grid else None)


def _field(data: dict, key: str, kind: type, where: str):
    if key not in data:
        raise LayoutInvalid(f"{where} is missing {key!r}")
    value = data[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise LayoutInvalid(f"{where}: {key!r} must be {kind.__name__}, got {value!r}")
    return value


def _number(data: dict, key: str, where: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LayoutInvalid(f"{where}: {key!r} must be a number, got {value!r}")
    return float(value)


def layout_to_toml(layout: Layout) -> str:
    """The layout as TOML text that :func:`load_layout` reads back unchanged."""
    def pairs(**values) -> list[str]:
        return [f"{key} = {toml_value(value)}" for key, value in values.items()]

    lines = pairs(name=layout.name)
    if layout.grid_shape:
        lines += pairs(grid=list(layout.grid_shape))
    lines += ["", "[sheet]"]
    if isinstance(layout.sheet, DiscSheet):
        lines += pairs(shape="disc", radius_mm=float(layout.sheet.radius_mm))
    else:
        lines += pairs(shape="rectangle", width_mm=float(layout.sheet.width_mm),
                       height_mm=float(layout.sheet.height_mm))
    for e in layout.electrodes:
        lines += ["", "[[electrodes]]"] + pairs(number=e.number)
        if isinstance(e, SectorElectrode):
            lines += pairs(shape="sector", angle_deg=float(e.angle_deg), width_deg=float(e.width_deg),
                           depth_mm=float(e.depth_mm))
        else:
            lines += pairs(shape="rectangle", x_mm=float(e.x_mm), y_mm=float(e.y_mm), width_mm=float(e.width_mm),
                           height_mm=float(e.height_mm))
    return "\n".join(lines) + "\n"
