"""Pressure maps on the virtual bed: map files (mmHg) placed on a mat, and played one after another as a scene.

A map is placed centred on the mat's grid with the resampling recordings use
(:func:`~appliance.sim.recordings.resample_onto`: each sensel's force shared among
the cells it overlaps), so its force is kept, except what falls off a mat smaller
than the map, which is lost and reported as ``share_off_mat``. Its rows run head to
foot along the grid's y, its column 0 at x = 0, as scenes lie; the bed turns the
grid onto a layout whose long side runs along x (:mod:`appliance.sim.bed`).

Pressures are taken as they are (no scaling to a weight): a map must lay some
force on the mat and stay within what the mat model accepts.

>>> from appliance.sim.body import MatGrid
>>> placed = place_map(np.full((2, 2), 30.0), 50.0, MatGrid(100.0, 100.0, 10.0), "two by two")
>>> placed.kpa.shape, round(float(placed.kpa.max()) / KPA_PER_MMHG, 6), placed.share_off_mat
((10, 10), 30.0, 0.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.errors import DataFileInvalid
from appliance.sim.body import MatGrid
from appliance.sim.field import KPA_PER_MMHG
from appliance.sim.map_files import read_map_mmhg
from appliance.sim.recordings import RecordedScene, force_n, resample_onto


@dataclass(frozen=True)
class PlacedMap:
    """A map as given (mmHg, ``pitch_mm`` sensels) and as it lies on ``grid`` (kPa), with the share of its
    force that fell off the mat (0 when all of it lies on the mat, to rounding)."""

    source: str
    mmhg: np.ndarray
    pitch_mm: float
    grid: MatGrid
    kpa: np.ndarray
    share_off_mat: float

    def offset_mm(self) -> tuple[float, float]:
        """Where the map's top-left corner lies on the grid (x, y), mm: negative when it overhangs."""
        rows, cols = self.mmhg.shape
        return (self.grid.width_mm - cols * self.pitch_mm) / 2, (self.grid.height_mm - rows * self.pitch_mm) / 2


def mat_limit_mmhg() -> float:
    """The highest pressure the mat model accepts (:class:`~appliance.sim.mechanics.MatParameters`), mmHg."""
    from appliance.sim.mechanics import DEFAULT_PARAMETERS

    return DEFAULT_PARAMETERS.max_pressure_kpa / KPA_PER_MMHG


def load_map(path) -> np.ndarray:
    """The map in ``path`` (mmHg), refused naming the cell if a pressure is beyond the mat model's limit."""
    mmhg = read_map_mmhg(path)
    limit = mat_limit_mmhg()
    if mmhg.max() > limit:
        i, j = np.unravel_index(np.argmax(mmhg), mmhg.shape)
        raise DataFileInvalid(f"pressure map {path}, row {i}, column {j}: {mmhg[i, j]:g} mmHg is beyond what the mat "
                              f"model accepts ({limit:.0f} mmHg, {limit * KPA_PER_MMHG:g} kPa)")
    return mmhg


def place_map(mmhg: np.ndarray, pitch_mm: float, grid: MatGrid, source: str) -> PlacedMap:
    """``mmhg`` centred on ``grid``, force kept; refused if none of its force lands on the mat."""
    kpa = resample_onto(np.asarray(mmhg, dtype=float) * KPA_PER_MMHG, pitch_mm, grid)
    given = float(force_n(mmhg, pitch_mm)) * KPA_PER_MMHG
    kept = float(force_n(kpa, grid.pitch_mm))
    if not kept > 0:
        rows, cols = np.shape(mmhg)
        why = "it is zero everywhere" if given == 0 else "all of it falls off"
        raise DataFileInvalid(f"{source} lays no force on the {grid.width_mm:g} x {grid.height_mm:g} mm mat ({why}: "
                              f"{rows} x {cols} sensels of {pitch_mm:g} mm, centred)")
    lost = 1.0 - kept / given
    return PlacedMap(source, np.asarray(mmhg, dtype=float), pitch_mm, grid, kpa, lost if lost > 1e-9 else 0.0)


def map_recording(paths: list[Path], pitch_mm: float, grid: MatGrid, each_s: float) -> RecordedScene:
    """The maps in ``paths`` played in order on ``grid``, each held ``each_s``; ``info`` names the files and the
    share of each map's force that fell off the mat (0 when all of it lies on the mat, to rounding)."""
    placed = [place_map(load_map(path), pitch_mm, grid, f"pressure map {path}") for path in paths]
    info = {"source": "maps", "files": [str(p) for p in paths], "pitch_mm": pitch_mm, "each_s": each_s,
            "share_off_mat": [p.share_off_mat for p in placed]}
    return RecordedScene(np.stack([p.kpa for p in placed]), np.arange(len(placed)) * each_s, grid, info,
                         duration_s=len(placed) * each_s)


def scene_grid(layout) -> MatGrid:
    """The grid a map lies on over ``layout``'s sheet: head to foot along its long side, in the cells the
    calibration's weights are laid on (:func:`~appliance.sim.loads.empty_mat`)."""
    from appliance.sim.loads import empty_mat

    width, height = layout.sheet.size_mm
    return MatGrid(min(width, height), max(width, height), empty_mat(layout).grid.pitch_mm)
