"""Layouts by name: the built-ins, ``grid-RxC`` bed mats, and TOML layout files.

Apart from :mod:`appliance.core.layouts` (the geometry) so that the geometry imports no file reading,
and the reading imports the geometry, never the reverse.

>>> layout = get_layout("grid-4x4")
>>> layout.n_electrodes, layout.grid_shape
(16, (4, 4))
"""

from __future__ import annotations

import re
from pathlib import Path

from appliance.core.layout_files import load_layout
from appliance.core.layouts import (BED_MAT_MM, THESIS_SHEET_MM, Layout, circular_layout, grid_layout, ktc_layout,
                                    square_perimeter_layout)
from appliance.errors import LayoutInvalid

_GRID_NAME = re.compile(r"^grid-(\d+)x(\d+)(?:@(\d+(?:\.\d+)?)x(\d+(?:\.\d+)?))?$")

BUILTIN_NAMES = ("circular-16", "square-16", "grid-4x4", "grid-8x16", "grid-16x32", "ktc-32")


def get_layout(name: str) -> Layout:
    """The layout called ``name``, or the one described by the TOML file ``name``.

    Built-ins: ``circular-16``, ``square-16``, ``grid-4x4`` (the thesis's sensor C),
    ``ktc-32`` (the KTC2023 tank) and ``grid-RxC`` for bed-size mats, R rows over the 900 mm side and C columns
    over the 1900 mm side, or ``grid-RxC@HxW`` for a sheet H x W mm.

    Raises
    ------
    LayoutInvalid
        The name is not a built-in and no such TOML file exists.
    """
    if name == "circular-16":
        return circular_layout(16)
    if name == "square-16":
        return square_perimeter_layout()
    if name == "grid-4x4":
        return grid_layout(4, 4, THESIS_SHEET_MM, THESIS_SHEET_MM, name="grid-4x4")
    if name == "ktc-32":
        return ktc_layout()
    match = _GRID_NAME.match(name)
    if match:
        rows, cols = int(match[1]), int(match[2])
        height, width = (float(match[3]), float(match[4])) if match[3] else BED_MAT_MM
        return grid_layout(rows, cols, height, width, name=name)
    if name.endswith(".toml"):
        return load_layout(Path(name))
    raise LayoutInvalid(
        f"unknown layout {name!r}: use one of {', '.join(BUILTIN_NAMES)}, grid-RxC, grid-RxC@HxW "
        f"(mm) or a .toml layout file"
    )
