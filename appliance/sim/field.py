"""A pressure field: pressure in kPa on a regular grid over the mat, in the layouts' coordinates.

Cell (i, j) covers x from ``j * pitch_mm`` to ``(j + 1) * pitch_mm`` and y from
``i * pitch_mm`` down, measured from the sheet's top-left corner (x right, y
down), as layouts are. Scenes produce fields; the mat's mechanics consume them.

>>> field = PressureField.uniform(100.0, 100.0, 2.0, 0.0)
>>> field.pressure_kpa.shape, field.size_mm
((50, 50), (100.0, 100.0))
>>> field.with_square_load(50, 50, 20, 4.9).peak_kpa
4.9
>>> field.with_square_load(50, 50, 20, 4.9).coarsened(5).pressure_kpa.shape
(10, 10)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.core.pressure import KPA_PER_MMHG  # noqa: F401  (scenes speak mmHg too)
from appliance.errors import ModelInputInvalid


@dataclass(frozen=True)
class PressureField:
    """Pressure (kPa, never negative) on square cells of side ``pitch_mm``; shape (rows, cols)."""

    pressure_kpa: np.ndarray
    pitch_mm: float

    def __post_init__(self):
        p = np.asarray(self.pressure_kpa, dtype=float)
        if p.ndim != 2 or min(p.shape) < 1:
            raise ModelInputInvalid(f"a pressure field needs a 2-D grid, got shape {p.shape}")
        if not (np.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise ModelInputInvalid(f"pressure field pitch must be positive, got {self.pitch_mm!r} mm")
        if not np.isfinite(p).all():
            raise ModelInputInvalid("pressure field holds a non-finite value")
        if (p < 0).any():
            i, j = np.unravel_index(np.argmin(p), p.shape)
            raise ModelInputInvalid(f"pressure field holds a negative pressure ({p[i, j]:.3g} kPa at row {i}, "
                                    f"column {j}); a mat can only be pressed")
        object.__setattr__(self, "pressure_kpa", p)

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) in mm."""
        rows, cols = self.pressure_kpa.shape
        return cols * self.pitch_mm, rows * self.pitch_mm

    @property
    def peak_kpa(self) -> float:
        return float(self.pressure_kpa.max())

    def centres_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell centres: x of each column, y of each row."""
        rows, cols = self.pressure_kpa.shape
        return (np.arange(cols) + 0.5) * self.pitch_mm, (np.arange(rows) + 0.5) * self.pitch_mm

    @classmethod
    def uniform(cls, width_mm: float, height_mm: float, pitch_mm: float, pressure_kpa: float = 0.0):
        cols, rows = round(width_mm / pitch_mm), round(height_mm / pitch_mm)
        return cls(np.full((rows, cols), float(pressure_kpa)), pitch_mm)

    def coarsened(self, factor: int) -> PressureField:
        """Cells merged ``factor`` x ``factor`` (their mean pressure: the force is kept)."""
        rows, cols = self.pressure_kpa.shape
        if factor < 1 or rows % factor or cols % factor:
            raise ModelInputInvalid(f"a {rows} x {cols} field cannot be merged in blocks of {factor}")
        blocks = self.pressure_kpa.reshape(rows // factor, factor, cols // factor, factor)
        return PressureField(blocks.mean(axis=(1, 3)), self.pitch_mm * factor)

    def with_square_load(self, x_mm: float, y_mm: float, side_mm: float, pressure_kpa: float) -> PressureField:
        """This field plus a flat square load centred at (x, y); cells count by the share they overlap."""
        w, h = self.size_mm
        half = side_mm / 2
        if not (0 <= x_mm - half and x_mm + half <= w and 0 <= y_mm - half and y_mm + half <= h):
            raise ModelInputInvalid(f"a {side_mm:g} mm square load at ({x_mm:g}, {y_mm:g}) mm lies outside the "
                                    f"{w:g} x {h:g} mm mat")
        xs, ys = self.centres_mm()
        share_x = _overlap(xs, self.pitch_mm, x_mm - half, x_mm + half)
        share_y = _overlap(ys, self.pitch_mm, y_mm - half, y_mm + half)
        return PressureField(self.pressure_kpa + pressure_kpa * np.outer(share_y, share_x), self.pitch_mm)


def _overlap(centres: np.ndarray, pitch: float, low: float, high: float) -> np.ndarray:
    """Share of each cell [c - pitch/2, c + pitch/2] inside [low, high]."""
    left = np.maximum(centres - pitch / 2, low)
    right = np.minimum(centres + pitch / 2, high)
    return np.clip(right - left, 0, None) / pitch
