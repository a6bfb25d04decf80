"""The true map: what a scene presses into the mat, averaged over the monitor's pixels.

The monitor reads the mat through the front end and the reconstruction; the
truth it is judged against is the scene's own pressure field, averaged over
each of the same pixels (force kept), as a perfect mat on the same grid would
read it. Replaying true maps straight into the alert layer
(``appliance sim replay``) checks the alert logic apart from the sensor.

>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.pixels import pixel_grid
>>> from appliance.sim.scenes import load_scene
>>> m = true_map(load_scene("supine-still"), 600.0, pixel_grid(get_layout("grid-16x32")))
>>> m.pressure_kpa.shape, round(m.peak_kpa / KPA_PER_MMHG)
((30, 64), 49)
"""

from __future__ import annotations

import numpy as np

from appliance.core.pixels import PixelGrid
from appliance.core.pressure import KPA_PER_MMHG  # noqa: F401  (the doctest speaks mmHg)
from appliance.core.pressure_map import PressureMap, loaded_regions
from appliance.sim.recordings import area_shares
from appliance.sim.scene_base import Scene


def on_pixels(pressure_kpa: np.ndarray, pitch_mm: float, grid: PixelGrid) -> np.ndarray:
    """A scene field (rows head to foot, cells of ``pitch_mm`` from the mat's corner) averaged over ``grid``'s
    pixels; a bed grid lying along x gets the field turned onto it, as the virtual bed turns it."""
    p = np.asarray(pressure_kpa, dtype=float)
    w, h = grid.pixel_mm
    turned = grid.width_mm > grid.height_mm
    along_mm, across_mm = (w, h) if turned else (h, w)
    along_cells, across_cells = (grid.cols, grid.rows) if turned else (grid.rows, grid.cols)
    wy = area_shares(np.arange(p.shape[0] + 1) * pitch_mm, np.arange(along_cells + 1) * along_mm)
    wx = area_shares(np.arange(p.shape[1] + 1) * pitch_mm, np.arange(across_cells + 1) * across_mm)
    view = wy @ p @ wx.T / (along_mm * across_mm)
    return view.T if turned else view


def true_map(scene: Scene, t_s: float, grid: PixelGrid) -> PressureMap:
    """The scene's field at ``t_s`` on ``grid``'s pixels, as a pressure map with its loaded regions."""
    field = scene.pressure_at(t_s)
    kpa = on_pixels(field.pressure_kpa, field.pitch_mm, grid)
    return PressureMap(float(t_s), kpa, loaded_regions(kpa, grid), None, 0)
