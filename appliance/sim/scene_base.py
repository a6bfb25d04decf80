"""The scene every kind implements: pressure fields on a mat grid over time, and where they changed.

Apart from :mod:`appliance.sim.scenes` (scenario files), which builds body, recorded and map scenes, so that
the recorded and map scenes build on this and the scenario files on them, never the reverse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.errors import ModelInputInvalid
from appliance.sim.body import MatGrid
from appliance.sim.field import PressureField

CHANGE_TOLERANCE_KPA = 0.01
"""Cells whose pressure moves less than this (0.075 mmHg) do not count as changed."""


@dataclass(frozen=True)
class ElectrodeFault:
    """From ``at_s`` on, ``electrode`` (1-based) has contact (``connected``) or has lost it."""

    at_s: float
    electrode: int
    connected: bool


class Scene:
    """A timeline of pressure fields on ``grid`` lasting ``duration_s``, with the electrode faults a
    simulated front end plays alongside."""

    grid: MatGrid
    duration_s: float
    faults: tuple[ElectrodeFault, ...] = ()

    def pressure_at(self, t_s: float) -> PressureField:
        raise NotImplementedError

    def change_box_mm(self, t0_s: float, t1_s: float) -> tuple[float, float, float, float] | None:
        """(x0, y0, x1, y1) in mm of every cell that changed between the two times, or None."""
        raise NotImplementedError

    def changes(self, t0_s: float, t1_s: float) -> bool:
        """Whether anything changed between ``t0_s`` and ``t1_s``."""
        return self.change_box_mm(t0_s, t1_s) is not None

    def _check_times(self, *times_s: float) -> None:
        for t in times_s:
            if not (math.isfinite(t) and -1e-9 <= t <= self.duration_s + 1e-9):
                raise ModelInputInvalid(f"time {t!r} s is outside the scene (0 to {self.duration_s:g} s)")
        if len(times_s) == 2 and times_s[1] < times_s[0]:
            raise ModelInputInvalid(f"change interval runs backwards: {times_s[0]:g} s to {times_s[1]:g} s")

    def _box(self, change_kpa: np.ndarray) -> tuple[float, float, float, float] | None:
        rows, cols = np.nonzero(change_kpa > CHANGE_TOLERANCE_KPA)
        if rows.size == 0:
            return None
        p = self.grid.pitch_mm
        return float(cols.min() * p), float(rows.min() * p), float((cols.max() + 1) * p), float((rows.max() + 1) * p)
