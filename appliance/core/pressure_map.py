"""What a nurse reads off a pressure map: the loaded regions, their peak, area and centre.

A region is a connected set of pixels at or above a threshold (32 mmHg, 4.3 kPa,
the capillary closing pressure the clinical literature uses, unless told
otherwise). Its centre is the pressure-weighted centroid of its pixels, which
places a load between pixel centres; its area counts whole pixels.

>>> from appliance.core.layouts import get_layout
>>> from appliance.core.pixels import pixel_grid
>>> grid = pixel_grid(get_layout("grid-4x4"), 4, 4)
>>> kpa = np.zeros((4, 4)); kpa[1, 1:3] = [6.0, 6.0]
>>> [(round(r.peak_kpa, 1), r.area_cm2, r.x_mm, r.y_mm) for r in loaded_regions(kpa, grid)]
[(6.0, 12.5, 50.0, 37.5)]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from appliance.core.pixels import PixelGrid
from appliance.core.pressure import KPA_PER_MMHG

HIGH_PRESSURE_KPA = 4.3          # 32 mmHg


@dataclass(frozen=True)
class LoadedRegion:
    """One connected region at or above the threshold."""

    peak_kpa: float
    mean_kpa: float
    area_cm2: float
    x_mm: float
    y_mm: float
    mask: np.ndarray

    @property
    def peak_mmhg(self) -> float:
        return self.peak_kpa / KPA_PER_MMHG


def loaded_regions(pressure_kpa: np.ndarray, grid: PixelGrid,
                   threshold_kpa: float = HIGH_PRESSURE_KPA) -> list[LoadedRegion]:
    """Regions of ``pressure_kpa`` (the grid's shape, NaN off the sheet) at or above ``threshold_kpa``,
    highest peak first."""
    pressure = np.asarray(pressure_kpa, dtype=float)
    if pressure.shape != grid.shape:
        raise ValueError(f"pressure map of shape {pressure.shape} for a {grid.shape} pixel grid")
    above = np.nan_to_num(pressure, nan=-np.inf) >= threshold_kpa
    labels, count = ndimage.label(above)
    w, h = grid.pixel_mm
    centres = grid.centres_mm.reshape(*grid.shape, 2)
    regions = []
    for k in range(1, count + 1):
        mask = labels == k
        p = pressure[mask]
        x, y = (centres[mask] * p[:, None]).sum(axis=0) / p.sum()
        regions.append(LoadedRegion(float(p.max()), float(p.mean()), float(mask.sum() * w * h / 100.0),
                                    float(x), float(y), mask))
    return sorted(regions, key=lambda r: -r.peak_kpa)


def loaded_area_cm2(pressure_kpa: np.ndarray, grid: PixelGrid, threshold_kpa: float) -> float:
    """Area of the sheet at or above ``threshold_kpa``."""
    w, h = grid.pixel_mm
    return float((np.nan_to_num(pressure_kpa, nan=-np.inf) >= threshold_kpa).sum() * w * h / 100.0)
