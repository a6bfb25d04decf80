"""Sensor-mat layouts: the sheet's outline and its electrodes, described by data.

Coordinates are millimetres with the origin at the sheet's top-left corner,
x to the right and y downwards, as an image is drawn; a disc of radius R has its
centre at (R, R). Electrodes are areas on the sheet (the liquid touches the whole
electrode face), numbered from 1: grids row-major from the top-left, peripheral
layouts clockwise as seen from above, electrode 1 at the top (disc) or the
top-left corner (square), as in the thesis's phantoms A and B.

>>> layout = grid_layout(4, 4, THESIS_SHEET_MM, THESIS_SHEET_MM)
>>> layout.n_electrodes, layout.grid_shape
(16, (4, 4))
>>> [round(float(c), 3) for c in layout.centroids_mm()[:4, 0]]
[3.125, 34.375, 65.625, 96.875]
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np

from appliance.errors import LayoutInvalid

_EPS_MM = 1e-9


@dataclass(frozen=True)
class RectSheet:
    """A rectangular sheet ``width_mm`` x ``height_mm``."""

    width_mm: float
    height_mm: float

    @property
    def area_mm2(self) -> float:
        return self.width_mm * self.height_mm

    @property
    def size_mm(self) -> tuple[float, float]:
        return self.width_mm, self.height_mm


@dataclass(frozen=True)
class DiscSheet:
    """A circular sheet of radius ``radius_mm``, centred at (radius, radius)."""

    radius_mm: float

    @property
    def area_mm2(self) -> float:
        return math.pi * self.radius_mm**2

    @property
    def size_mm(self) -> tuple[float, float]:
        return 2 * self.radius_mm, 2 * self.radius_mm


@dataclass(frozen=True)
class RectElectrode:
    """An axis-aligned rectangular electrode centred at (``x_mm``, ``y_mm``)."""

    number: int
    x_mm: float
    y_mm: float
    width_mm: float
    height_mm: float

    @property
    def bounds_mm(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the electrode face."""
        hw, hh = self.width_mm / 2, self.height_mm / 2
        return self.x_mm - hw, self.y_mm - hh, self.x_mm + hw, self.y_mm + hh

    @property
    def area_mm2(self) -> float:
        return self.width_mm * self.height_mm

    def centroid_mm(self, sheet) -> tuple[float, float]:
        return self.x_mm, self.y_mm

    def contains(self, sheet, points: np.ndarray) -> np.ndarray:
        """Mask of ``points`` (n, 2) lying on the electrode face (edges included)."""
        x0, y0, x1, y1 = self.bounds_mm
        x, y = points[:, 0], points[:, 1]
        return (x >= x0 - _EPS_MM) & (x <= x1 + _EPS_MM) & (y >= y0 - _EPS_MM) & (y <= y1 + _EPS_MM)


@dataclass(frozen=True)
class SectorElectrode:
    """An electrode on the rim of a disc: an annular sector.

    ``angle_deg`` is its centre, clockwise from the top; it spans ``width_deg``
    and reaches ``depth_mm`` in from the rim.
    """

    number: int
    angle_deg: float
    width_deg: float
    depth_mm: float

    def area_mm2_on(self, sheet: RectSheet | DiscSheet) -> float:
        r = disc_of(sheet).radius_mm
        return math.radians(self.width_deg) / 2 * (r**2 - (r - self.depth_mm) ** 2)

    def centroid_mm(self, sheet: RectSheet | DiscSheet) -> tuple[float, float]:
        sheet = disc_of(sheet)
        r_mid = sheet.radius_mm - self.depth_mm / 2
        phi = math.radians(self.angle_deg)
        return sheet.radius_mm + r_mid * math.sin(phi), sheet.radius_mm - r_mid * math.cos(phi)

    def contains(self, sheet: RectSheet | DiscSheet, points: np.ndarray) -> np.ndarray:
        """Mask of ``points`` (n, 2) lying on the sector (edges included)."""
        sheet = disc_of(sheet)
        r, phi = polar_clockwise(sheet, points)
        offset = (phi - self.angle_deg + 180.0) % 360.0 - 180.0
        return (r >= sheet.radius_mm - self.depth_mm - 1e-6) & (np.abs(offset) <= self.width_deg / 2 + 1e-7)


def disc_of(sheet: RectSheet | DiscSheet) -> DiscSheet:
    """``sheet`` as the disc a rim sector lies on (a layout pairs sectors with a disc only)."""
    if not isinstance(sheet, DiscSheet):
        raise LayoutInvalid("a sector electrode lies on the rim of a disc sheet, not on a rectangle")
    return sheet


def polar_clockwise(sheet: DiscSheet, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radius (mm) and angle (degrees clockwise from the top, in [0, 360)) of ``points``."""
    dx = points[:, 0] - sheet.radius_mm
    dy = sheet.radius_mm - points[:, 1]
    return np.hypot(dx, dy), np.degrees(np.arctan2(dx, dy)) % 360.0


@dataclass(frozen=True)
class Layout:
    """A named sheet with its numbered electrodes; validated when made.

    ``grid_shape`` is (rows, columns) for electrodes spread over the sheet in a
    grid, ``None`` for electrodes around the edge.
    """

    name: str
    sheet: RectSheet | DiscSheet
    electrodes: tuple[RectElectrode | SectorElectrode, ...]
    grid_shape: tuple[int, int] | None = None

    def __post_init__(self):
        _validate(self)

    @property
    def n_electrodes(self) -> int:
        return len(self.electrodes)

    @property
    def is_grid(self) -> bool:
        return self.grid_shape is not None

    def electrode_area_mm2(self, electrode) -> float:
        if isinstance(electrode, SectorElectrode):
            return electrode.area_mm2_on(self.sheet)
        return electrode.area_mm2

    @property
    def rectangles(self) -> tuple[RectElectrode, ...]:
        """The electrodes of a rectangular sheet, which are all rectangles."""
        if not all(isinstance(e, RectElectrode) for e in self.electrodes):
            raise LayoutInvalid(f"layout {self.name!r} has sector electrodes, not rectangles")
        return cast(tuple[RectElectrode, ...], self.electrodes)

    @property
    def sectors(self) -> tuple[SectorElectrode, ...]:
        """The electrodes of a disc sheet, which are all rim sectors."""
        if not all(isinstance(e, SectorElectrode) for e in self.electrodes):
            raise LayoutInvalid(f"layout {self.name!r} has rectangular electrodes, not rim sectors")
        return cast(tuple[SectorElectrode, ...], self.electrodes)

    def centroids_mm(self) -> np.ndarray:
        """Electrode centroids, shape (n_electrodes, 2), mm."""
        return np.array([e.centroid_mm(self.sheet) for e in self.electrodes], dtype=float)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Mask of ``points`` (n, 2) on the sheet."""
        if isinstance(self.sheet, DiscSheet):
            r, _ = polar_clockwise(self.sheet, points)
            return r <= self.sheet.radius_mm + 1e-6
        w, h = self.sheet.size_mm
        x, y = points[:, 0], points[:, 1]
        return (x >= -_EPS_MM) & (x <= w + _EPS_MM) & (y >= -_EPS_MM) & (y <= h + _EPS_MM)


def _validate(layout: Layout) -> None:
    sheet = layout.sheet
    if not layout.name or not isinstance(layout.name, str):
        raise LayoutInvalid("a layout needs a non-empty name")
    for dim, value in vars(sheet).items():
        if not (math.isfinite(value) and value > 0):
            raise LayoutInvalid(f"layout {layout.name!r}: sheet {dim} must be positive, got {value}")
    if not layout.electrodes:
        raise LayoutInvalid(f"layout {layout.name!r} has no electrodes")
    numbers = [e.number for e in layout.electrodes]
    if numbers != list(range(1, len(numbers) + 1)):
        raise LayoutInvalid(
            f"layout {layout.name!r}: electrodes must be numbered 1..{len(numbers)} in order, got {numbers}"
        )
    for e in layout.electrodes:
        _validate_electrode(layout, e)
    _check_disjoint(layout)
    if layout.grid_shape is not None:
        _check_grid_numbering(layout)


def _validate_electrode(layout: Layout, e) -> None:
    where = f"layout {layout.name!r}: electrode {e.number}"
    sheet = layout.sheet
    if isinstance(e, RectElectrode):
        if not isinstance(sheet, RectSheet):
            raise LayoutInvalid(f"{where}: a disc sheet takes sector electrodes on its rim, not rectangles")
        if not all(math.isfinite(v) for v in (e.x_mm, e.y_mm, e.width_mm, e.height_mm)):
            raise LayoutInvalid(f"{where}: position and size must be finite numbers")
        if e.width_mm <= 0 or e.height_mm <= 0:
            raise LayoutInvalid(f"{where}: width and height must be positive, got {e.width_mm} x {e.height_mm} mm")
        x0, y0, x1, y1 = e.bounds_mm
        w, h = sheet.size_mm
        for label, inside in (("left", x0 >= -_EPS_MM), ("top", y0 >= -_EPS_MM),
                              ("right", x1 <= w + _EPS_MM), ("bottom", y1 <= h + _EPS_MM)):
            if not inside:
                raise LayoutInvalid(
                    f"{where} (centre {e.x_mm:g}, {e.y_mm:g} mm, {e.width_mm:g} x {e.height_mm:g} mm) "
                    f"extends beyond the sheet's {label} edge ({w:g} x {h:g} mm)"
                )
    elif isinstance(e, SectorElectrode):
        if not isinstance(sheet, DiscSheet):
            raise LayoutInvalid(f"{where}: sector electrodes belong on a disc sheet")
        if not all(math.isfinite(v) for v in (e.angle_deg, e.width_deg, e.depth_mm)):
            raise LayoutInvalid(f"{where}: angle, width and depth must be finite numbers")
        if not 0 < e.width_deg < 360:
            raise LayoutInvalid(f"{where}: width must be between 0 and 360 degrees, got {e.width_deg}")
        if not 0 < e.depth_mm < sheet.radius_mm:
            raise LayoutInvalid(
                f"{where}: depth must be positive and less than the radius {sheet.radius_mm:g} mm, got {e.depth_mm}"
            )
    else:
        raise LayoutInvalid(f"{where}: unknown electrode shape {type(e).__name__}")


def _check_disjoint(layout: Layout) -> None:
    """Electrode faces may neither overlap nor touch: each must be its own conductor."""
    es = layout.electrodes
    for i, a in enumerate(es):
        for b in es[i + 1:]:
            if isinstance(a, RectElectrode) and isinstance(b, RectElectrode):
                ax0, ay0, ax1, ay1 = a.bounds_mm
                bx0, by0, bx1, by1 = b.bounds_mm
                apart = ax1 < bx0 - _EPS_MM or bx1 < ax0 - _EPS_MM or ay1 < by0 - _EPS_MM or by1 < ay0 - _EPS_MM
            else:
                # _validate_electrode gave a disc sectors only and a rectangle rectangles only.
                assert isinstance(a, SectorElectrode) and isinstance(b, SectorElectrode)
                gap = abs((a.angle_deg - b.angle_deg + 180.0) % 360.0 - 180.0)
                apart = gap > (a.width_deg + b.width_deg) / 2 + 1e-9
            if not apart:
                raise LayoutInvalid(
                    f"layout {layout.name!r}: electrodes {a.number} and {b.number} overlap or touch"
                )


def _check_grid_numbering(layout: Layout) -> None:
    assert layout.grid_shape is not None        # called for grid layouts only
    rows, cols = layout.grid_shape
    if rows < 1 or cols < 1 or rows * cols != layout.n_electrodes:
        raise LayoutInvalid(
            f"layout {layout.name!r}: a {rows} x {cols} grid needs {rows * cols} electrodes, "
            f"it has {layout.n_electrodes}"
        )
    c = layout.centroids_mm()
    order = np.lexsort((np.round(c[:, 0], 6), np.round(c[:, 1], 6)))
    if not np.array_equal(order, np.arange(layout.n_electrodes)):
        raise LayoutInvalid(
            f"layout {layout.name!r}: grid electrodes must be numbered row-major from the top-left"
        )
    ys = np.round(c[:, 1], 6).reshape(rows, cols)
    if not np.all(ys == ys[:, :1]):
        raise LayoutInvalid(f"layout {layout.name!r}: each grid row must share one y position")


# ---------------------------------------------------------------------------
# Built-in layouts

THESIS_SHEET_MM = 100.0
"""Side of the thesis's sensor C (and our square and disc phantoms)."""


def circular_layout(n_electrodes: int = 16, diameter_mm: float = THESIS_SHEET_MM,
                    electrode_mm: float | None = None, name: str | None = None) -> Layout:
    """Equally spaced rim electrodes on a disc, electrode 1 at the top, clockwise.

    The default electrode is a 1/17-of-diameter square-ish sector, the size of one
    element of the thesis's 17-element-wide phantom A.
    """
    radius = diameter_mm / 2
    size = electrode_mm if electrode_mm is not None else diameter_mm / 17
    width_deg = math.degrees(size / radius)
    electrodes = tuple(
        SectorElectrode(k + 1, 360.0 * k / n_electrodes, width_deg, size) for k in range(n_electrodes)
    )
    return Layout(name or f"circular-{n_electrodes}", DiscSheet(radius), electrodes)


def square_perimeter_layout(side_mm: float = THESIS_SHEET_MM) -> Layout:
    """The thesis's phantom B: 16 electrodes around a square, one at each corner.

    The square is 17 element-widths across with electrodes at every fourth element
    along the edge; numbering starts at the top-left corner and runs clockwise.
    """
    cell = side_mm / 17
    cells = [(0, c) for c in range(0, 17, 4)] + [(r, 16) for r in range(4, 17, 4)]
    cells += [(16, c) for c in range(12, -1, -4)] + [(r, 0) for r in range(12, 0, -4)]
    electrodes = tuple(
        RectElectrode(k + 1, (c + 0.5) * cell, (r + 0.5) * cell, cell, cell) for k, (r, c) in enumerate(cells)
    )
    return Layout("square-16", RectSheet(side_mm, side_mm), electrodes)


MAX_GRID_ELECTRODES = 4096
"""Far beyond any mat a front end can switch (a bed mat has 512); a larger grid is a typo that would only exhaust
the memory while its mesh is built."""


GRID_SHEET_RANGE_MM = (10.0, 10_000.0)
"""A grid sheet's sides: from a fingertip sensor to ten metres, far beyond any bed; outside it is a typo."""


def grid_layout(rows: int, cols: int, height_mm: float, width_mm: float, name: str | None = None) -> Layout:
    """Square electrodes in a grid over a rectangular sheet, outer ones flush with the edges.

    Electrode size and pitch keep the thesis's proportion: the pitch is five
    electrode widths (100 mm sheet, 6.25 mm electrodes, 31.25 mm pitch for 4 x 4).
    """
    if rows < 1 or cols < 1:
        raise LayoutInvalid(f"a grid needs at least one row and one column, got {rows} x {cols}")
    if rows * cols > MAX_GRID_ELECTRODES:
        raise LayoutInvalid(f"a grid of {rows} x {cols} electrodes is more than the {MAX_GRID_ELECTRODES} a mat "
                            "can have")
    if (rows == 1 and cols == 1):
        raise LayoutInvalid("a grid needs at least two electrodes")
    low, high = GRID_SHEET_RANGE_MM
    if not (low <= height_mm <= high and low <= width_mm <= high):
        raise LayoutInvalid(f"{name or 'a grid'}: the sheet must be {low:g} to {high:g} mm a side, got {height_mm:g} x "
                            f"{width_mm:g} mm")
    candidates = []
    if cols > 1:
        candidates.append(width_mm / (5 * (cols - 1) + 1))
    if rows > 1:
        candidates.append(height_mm / (5 * (rows - 1) + 1))
    size = min(candidates)
    xs = _spread(cols, width_mm, size)
    ys = _spread(rows, height_mm, size)
    electrodes = tuple(
        RectElectrode(r * cols + c + 1, float(xs[c]), float(ys[r]), size, size)
        for r in range(rows) for c in range(cols)
    )
    return Layout(name or f"grid-{rows}x{cols}", RectSheet(width_mm, height_mm), electrodes, (rows, cols))


def _spread(n: int, length: float, size: float) -> np.ndarray:
    if n == 1:
        return np.array([length / 2])
    return size / 2 + np.arange(n) * (length - size) / (n - 1)


BED_MAT_MM = (900.0, 1900.0)
"""(height, width) of a bed-size mat: a standard 90 x 190 cm mattress, drawn landscape."""


KTC_TANK_RADIUS_MM = 115.0
KTC_ELECTRODES = 32
KTC_ELECTRODE_WIDTH_DEG = 5.625
KTC_WALL_DEPTH_MM = 2.0
"""The Kuopio Tomography Challenge 2023 tank: a 230 mm disc, 32 wall electrodes 11.3 mm wide, each modelled
as a 2 mm-deep rim sector (its data files are read by :mod:`appliance.core.ktc`)."""


def ktc_layout() -> Layout:
    """The challenge's tank: 32 wall electrodes, counter-clockwise from the top."""
    electrodes = tuple(SectorElectrode(k + 1, (-360.0 * k / KTC_ELECTRODES) % 360.0, KTC_ELECTRODE_WIDTH_DEG,
                                       KTC_WALL_DEPTH_MM) for k in range(KTC_ELECTRODES))
    return Layout("ktc-32", DiscSheet(KTC_TANK_RADIUS_MM), electrodes)
