"""Test loads on the mat: a scene holding one fixed pressure field, and square weights placed on it.

Calibration puts known weights on known areas (the thesis's Table 6.3.1), or people's
pressure maps; on the virtual bed a :class:`StaticScene` with a square load plays the
weight, on a rigid platen as the thesis's weights were, and one with the map plays the person.

>>> scene = square_load_scene(100, 100, 50, 50, 30, 4.36)
>>> round(scene.pressure_at(0.0).peak_kpa, 2), scene.changes(0.0, 10.0)
(4.36, False)
"""

from __future__ import annotations

import numpy as np

from appliance.calibration import Load, MapLoad
from appliance.sim.body import MatGrid
from appliance.sim.field import PressureField
from appliance.sim.scene_base import Scene

LOAD_PITCH_MM = 2.0
CELLS_ACROSS = 90               # a bed's scenes use 10 mm cells on its 900 mm side; finer buys nothing there
STILL_S = 1e9


class StaticScene(Scene):
    """One pressure field that never changes; ``platen`` marks cells under a rigid weight (they sink flat)."""

    def __init__(self, field: PressureField, platen=None):
        width, height = field.size_mm
        self.field, self.platen = field, platen
        self.grid = MatGrid(width, height, field.pitch_mm)
        self.duration_s = STILL_S

    def pressure_at(self, t_s: float) -> PressureField:
        return self.field

    def change_box_mm(self, t0_s: float, t1_s: float):
        return None


def square_load_scene(width_mm: float, height_mm: float, x_mm: float, y_mm: float, side_mm: float,
                      pressure_kpa: float, pitch_mm: float = LOAD_PITCH_MM) -> StaticScene:
    """A mat ``width_mm`` x ``height_mm`` with one flat square load (0 kPa for the empty mat)."""
    field = PressureField.uniform(width_mm, height_mm, pitch_mm)
    if pressure_kpa <= 0:
        return StaticScene(field)
    platen = field.with_square_load(x_mm, y_mm, side_mm, 1.0).pressure_kpa >= 0.5
    return StaticScene(field.with_square_load(x_mm, y_mm, side_mm, pressure_kpa), platen)


def _pitch_mm(layout) -> float:
    return max(LOAD_PITCH_MM, min(layout.sheet.size_mm) / CELLS_ACROSS)


def empty_mat(layout) -> StaticScene:
    """``layout``'s mat with nothing on it."""
    width, height = layout.sheet.size_mm
    return square_load_scene(width, height, width / 2, height / 2, 1.0, 0.0, _pitch_mm(layout))


def placer(bed):
    """``place(load)`` for the calibration procedures: puts ``load`` (or, for None, nothing) on ``bed``."""
    width, height = bed.layout.sheet.size_mm
    pitch = _pitch_mm(bed.layout)

    def place(load: Load | MapLoad | None) -> None:
        if load is None:
            bed.set_scene(empty_mat(bed.layout))
        elif isinstance(load, MapLoad):
            bed.set_scene(StaticScene(PressureField(load.pressure_kpa, load.pitch_mm)))
        else:
            bed.set_scene(square_load_scene(width, height, load.x_mm, load.y_mm, load.side_mm, load.pressure_kpa,
                                            pitch))

    return place


def square_loads_read_back(model, calibration, front, place, area_cm2: float, *, count: int = 10,
                           seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Peak errors (read / true - 1) and centre errors (mm) of ``count`` square loads of ``area_cm2`` placed
    anywhere on the mat, edges included, at 2 to 20 kPa, each read by ``front`` and imaged iterated as the
    monitor does against the empty mat read first: how well a small mat's chain locates and weighs a load."""
    from appliance.core.pressure_map import peak_region, pressure_map

    width, height = model.setup.layout.sheet.size_mm
    grid = model.reconstructor.grid
    place(None)
    reference = front.acquire().volts
    rng = np.random.default_rng(seed)
    side = 10 * np.sqrt(area_cm2)
    peak_errors, centre_errors = [], []
    for _ in range(count):
        x, y = rng.uniform((side / 2, side / 2), (width - side / 2, height - side / 2))
        load = Load(float(x), float(y), side, float(rng.uniform(2, 20)))
        place(load)
        frame = front.acquire()
        image, info = model.reconstruct(frame.volts, reference, iterate="always")
        kpa = pressure_map(image, calibration, grid, time_s=frame.time_s, usable_readings=info["usable_readings"])
        region = peak_region(kpa.pressure_kpa, grid)
        assert region is not None, "a load on the mat gives a loaded region"
        peak_errors.append(kpa.peak_kpa / load.pressure_kpa - 1)
        centre_errors.append(np.hypot(region.x_mm - load.x_mm, region.y_mm - load.y_mm))
    place(None)
    return np.array(peak_errors), np.array(centre_errors)
