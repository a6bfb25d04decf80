"""What a nurse reads off a pressure map: the loaded regions, their peak, area and centre.

A :class:`PressureMap` is what the core hands on for each frame: pressure in kPa
per pixel with the regions at or above 32 mmHg, the time and the liquid's
temperature.

A region is a connected set of pixels at or above a threshold (32 mmHg, 4.27 kPa,
the capillary closing pressure the clinical literature uses, unless told
otherwise). Its centre is the pressure-weighted centroid of its pixels, which
places a load between pixel centres; its area counts whole pixels.

>>> from appliance.core.named_layouts import get_layout
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
from appliance.core.pressure import KPA_PER_MMHG, PressureCalibration

HIGH_PRESSURE_MMHG = 32.0
"""Where tissue counts as loaded: capillary closing pressure (Landis 1930), the threshold of the pressure-mapping
literature and of every alarm default here (clinical-anchors.md)."""
HIGH_PRESSURE_KPA = HIGH_PRESSURE_MMHG * KPA_PER_MMHG
FOOTPRINT_SHARE = 0.3            # a load's footprint on a blurred map: where it reads 30 % of its peak


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


def peak_region(pressure_kpa: np.ndarray, grid: PixelGrid, share: float = FOOTPRINT_SHARE) -> LoadedRegion | None:
    """The region around the map's highest pixel down to ``share`` of its peak: where one load lies.

    A wide footprint (30 %) centres a flat load better than its top, which a
    blurred image breaks into lumps (benchmarks/pressure.md).
    """
    peak = np.nanmax(pressure_kpa) if np.isfinite(pressure_kpa).any() else 0.0
    if peak <= 0:
        return None
    return loaded_regions(pressure_kpa, grid, share * peak)[0]


def loaded_area_cm2(pressure_kpa: np.ndarray, grid: PixelGrid, threshold_kpa: float) -> float:
    """Area of the sheet at or above ``threshold_kpa``."""
    w, h = grid.pixel_mm
    return float((np.nan_to_num(pressure_kpa, nan=-np.inf) >= threshold_kpa).sum() * w * h / 100.0)


@dataclass(frozen=True)
class PressureMap:
    """One frame's pressure (kPa per pixel, NaN off the sheet) and its regions above the threshold."""

    time_s: float
    pressure_kpa: np.ndarray
    regions: list[LoadedRegion]
    temperature_c: float | None
    usable_readings: int

    @property
    def peak_kpa(self) -> float:
        return float(np.nanmax(self.pressure_kpa)) if np.isfinite(self.pressure_kpa).any() else 0.0


def pressure_map(image: np.ndarray, calibration: PressureCalibration, grid: PixelGrid, *, time_s: float,
                 temperature_c: float | None = None, usable_readings: int = 0,
                 threshold_kpa: float = HIGH_PRESSURE_KPA) -> PressureMap:
    """A reconstructed image in kPa through ``calibration``, with its regions at or above ``threshold_kpa``."""
    kpa = calibration.pressure_kpa(image)
    return PressureMap(time_s, kpa, loaded_regions(kpa, grid, threshold_kpa), temperature_c, usable_readings)


LOAD_PRESENT_KPA = 1.3
"""About 10 mmHg: the least pressure that says a body lies on a place (the mat's noise reads well below)."""


def loaded_electrodes(pressure_kpa: np.ndarray, grid: PixelGrid, centres_mm: np.ndarray,
                      threshold_kpa: float = LOAD_PRESENT_KPA) -> list[int]:
    """The electrodes (1-based) under a body: those whose pixel, or a pixel next to it, reads at least
    ``threshold_kpa``. An adaptive front end reads finely around them next frame."""
    pressure = np.nan_to_num(np.asarray(pressure_kpa, dtype=float))
    if pressure.shape != grid.shape:
        raise ValueError(f"pressure map of shape {pressure.shape} for a {grid.shape} pixel grid")
    from scipy.ndimage import maximum_filter

    near = maximum_filter(pressure, size=3, mode="nearest").ravel()[grid.pixel_of(np.asarray(centres_mm))]
    return (np.flatnonzero(near >= threshold_kpa) + 1).tolist()
