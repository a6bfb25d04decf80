"""Calibration procedures: known weights on known areas, or people's pressure maps as a reference mat
read them, to a pressure calibration; and the thesis's experimental sensitivity (an object on each
pixel in turn, eq. 3.4.1).

A procedure needs two things from its surroundings: ``acquire()``, giving a frame
(``.volts`` and ``.temperature_c``: a scan engine on the hardware, or the virtual
bed's front end), and ``place(load)``, putting a load on the mat or taking it off
(``None``): on the virtual bed a scene with that weight, on the hardware a
prompt to the operator. So the same procedure runs on both.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from appliance.core.iterative import affordable_iterate
from appliance.core.model_cache import ReconstructionModel
from appliance.core.pressure import (PressureCalibration, PressureCurve, ZoneCurve, fit_pressure_curve,
                                     layout_fingerprint, matched_curve, temperature_corrected)
from appliance.errors import ConfigError

KPA_PER_GRAM_PER_CM2 = 0.0980665    # 1 g on 1 cm2 (Table 6.3.1: 100 g on 4 cm2 is 2.45 kPa)
THESIS_WEIGHTS_G = (200, 400, 600, 800, 1000)
INSIDE_SHARE = 0.999                # a pixel counts as under a load only if it lies wholly under it

BED_MIN_LENGTH_MM = 1500.0          # a mat this long is a bed: a body lies along it, heels at its foot end
FOOT_END_MM = 350.0                 # the heels' band: on a 1900 mm bed a 175 cm patient's heels lie 100-200 mm
                                    # from the end (sim/body.py), shorter or shifted patients up to ~300 mm
HEEL_SIDE_MM = 50.0                 # a heel's contact on foam: ~20-25 cm2 at or above 32 mmHg (heel peak 55 mmHg)
FOOT_END = "foot-end"
HEAD_END_MM = 240.0                 # where a lying patient's head rests on a bed: its own curve from people's maps
HEAD_END = "head-end"


@dataclass(frozen=True)
class Load:
    """A flat square weight: centre and side in mm, pressure in kPa."""

    x_mm: float
    y_mm: float
    side_mm: float
    pressure_kpa: float
    zone: str | None = None         # a zone's own curve is fitted to its loads (FOOT_END); None: the main curve

    def pixel_pressure(self, grid) -> np.ndarray:
        """The load's pressure on each pixel of ``grid`` (rows, cols), by the share of the pixel it covers."""
        w, h = grid.pixel_mm
        x = np.arange(grid.cols) * w
        y = np.arange(grid.rows) * h
        half = self.side_mm / 2
        share_x = np.clip(np.minimum(x + w, self.x_mm + half) - np.maximum(x, self.x_mm - half), 0, None) / w
        share_y = np.clip(np.minimum(y + h, self.y_mm + half) - np.maximum(y, self.y_mm - half), 0, None) / h
        return self.pressure_kpa * np.outer(share_y, share_x)


def thesis_loads(width_mm: float, height_mm: float, areas_cm2=(9.0, 16.0, 25.0), positions: int = 3,
                 weights_g=THESIS_WEIGHTS_G) -> list[Load]:
    """Table 6.3.1's weights on square areas, at ``positions`` x ``positions`` places across the mat."""
    loads = []
    for area in areas_cm2:
        side = 10 * np.sqrt(area)
        xs = np.linspace(side / 2 + 0.1 * width_mm, width_mm - side / 2 - 0.1 * width_mm, positions)
        ys = np.linspace(side / 2 + 0.1 * height_mm, height_mm - side / 2 - 0.1 * height_mm, positions)
        for y in ys:
            for x in xs:
                for grams in weights_g:
                    loads.append(Load(float(x), float(y), float(side), grams * KPA_PER_GRAM_PER_CM2 / area))
    return loads


@dataclass(frozen=True, eq=False)
class MapLoad:
    """A whole pressure map on the mat: what a person lying on it presses, as a reference pressure
    mat under them read it. ``pressure_kpa`` holds square cells of ``pitch_mm`` covering the mat, rows
    head to foot along its long side (as scenes lie); ``name`` says whose map it is.
    """

    pressure_kpa: np.ndarray
    pitch_mm: float
    name: str = ""

    def pixel_pressure(self, grid) -> np.ndarray:
        """The map's mean pressure over each pixel of ``grid`` (rows, cols), turned to lie along the grid."""
        cells = np.asarray(self.pressure_kpa, dtype=float)
        if (grid.width_mm > grid.height_mm) != (cells.shape[1] > cells.shape[0]):
            cells = cells.T
        rows, cols = cells.shape
        if abs(cols * self.pitch_mm - grid.width_mm) > self.pitch_mm or \
                abs(rows * self.pitch_mm - grid.height_mm) > self.pitch_mm:
            raise ConfigError(f"map {self.name!r} covers {cols * self.pitch_mm:g} x {rows * self.pitch_mm:g} mm, "
                              f"the mat {grid.width_mm:g} x {grid.height_mm:g} mm")
        across = _shares(rows, self.pitch_mm, grid.rows, grid.height_mm)
        along = _shares(cols, self.pitch_mm, grid.cols, grid.width_mm)
        return across @ cells @ along.T


def _shares(cells: int, pitch_mm: float, pixels: int, length_mm: float) -> np.ndarray:
    """Share of each pixel (rows) that each cell (columns) covers along one side."""
    cell_edges = np.arange(cells + 1) * pitch_mm
    pixel_edges = np.linspace(0.0, length_mm, pixels + 1)
    low = np.maximum(pixel_edges[:-1, None], cell_edges[None, :-1])
    high = np.minimum(pixel_edges[1:, None], cell_edges[None, 1:])
    return np.clip(high - low, 0.0, None) / np.diff(pixel_edges)[:, None]


CALIBRATION_PRESSURES_KPA = (2.0, 3.5, 5.0, 7.5, 10.0, 14.0, 20.0)
SIDES_PER_SPACING = (1.2, 1.6, 2.0)


def calibration_loads(layout, positions: int = 2, pressures_kpa=CALIBRATION_PRESSURES_KPA) -> list[Load]:
    """The default load set: squares of 1.2, 1.6 and 2 electrode spacings (9, 16 and 25 cm2 on the
    thesis's 25 mm grid, as Table 6.3.1), each at ``positions`` x ``positions`` places and at the
    centre, each pressed to every pressure of the range a bed sees (2 to 20 kPa).

    The centre is always loaded: the flat field is interpolated between loaded
    places, and a mat's middle responds least (about 30 % below its corners' on grid-4x4).
    """
    width, height = layout.sheet.size_mm
    rows, cols = layout.grid_shape if layout.is_grid else (4, 4)
    spacing = min(width / cols, height / rows)
    edge = 0.1 if layout.is_grid else 0.3          # a round sheet keeps its loads near the middle
    loads = []
    for side in (round(f * spacing, 1) for f in SIDES_PER_SPACING):
        xs = np.linspace(side / 2 + edge * width, width - side / 2 - edge * width, positions) if positions > 1 \
            else np.empty(0)
        ys = np.linspace(side / 2 + edge * height, height - side / 2 - edge * height, positions) if positions > 1 \
            else np.empty(0)
        places = {(float(x), float(y)) for y in ys for x in xs} | {(width / 2, height / 2)}
        for x, y in sorted(places, key=lambda p: (p[1], p[0])):
            loads += [Load(x, y, side, float(p)) for p in pressures_kpa]
    return loads + foot_end_loads(layout, pressures_kpa)


def _long_axis(layout) -> tuple[float, float, bool]:
    """(long side, short side, whether the long side runs along x) of the mat, mm."""
    width, height = layout.sheet.size_mm
    return (width, height, True) if width >= height else (height, width, False)


def foot_end_loads(layout, pressures_kpa=CALIBRATION_PRESSURES_KPA) -> list[Load]:
    """On a bed, heel-size weights across the foot end (where the heels lie), each at every pressure;
    none on a smaller mat. Their own curve reads heels, which the main loads are three times too wide for."""
    long, short, along_x = _long_axis(layout)
    if long < BED_MIN_LENGTH_MM:
        return []
    places = [(a, c) for a in (long - 250.0, long - 120.0) for c in (short / 2 - 80.0, short / 2, short / 2 + 80.0)]
    return [Load(a if along_x else c, c if along_x else a, HEEL_SIDE_MM, float(p), FOOT_END)
            for a, c in places for p in pressures_kpa]


def foot_end_mask(layout, grid) -> np.ndarray:
    """Pixels (rows, cols) whose centre lies in the last ``FOOT_END_MM`` of a bed's long side."""
    long, _, along_x = _long_axis(layout)
    along = grid.centres_mm[:, 0 if along_x else 1]
    return (along >= long - FOOT_END_MM).reshape(grid.shape)


def map_curves(images, truths, layout, grid, *, fit: Callable = matched_curve,
               head_end: bool = True) -> tuple[PressureCurve, tuple[ZoneCurve, ...]]:
    """The curve, and on a bed the head end's own, fitted to every pixel of people's maps (``truths``, kPa) and
    their ``images``.

    Every pixel of every map counts: a body's loads come in every size, and the curve learns how the mat and
    the reconstruction read them all, narrow heels with wide buttocks. ``fit`` is :func:`matched_curve` (the k-th
    largest change reads the k-th largest pressure) rather than a regression of pressure on change, whose mean
    pressure for a change pulls every peak toward the middle (the change is noisy), and a site's peak is what its
    dose follows. The head, at the mat's end where the image is least sensitive, is read low by the body's curve,
    so the first ``HEAD_END_MM`` of a bed gets its own. benchmarks/calibration_curve.md chose both on people left
    out of the fit.
    """
    inside = np.isfinite(images[0])
    zone = head_end_mask(layout, grid) if head_end else np.zeros_like(inside)
    head, body = zone & inside, inside & ~zone
    curve = fit(_sizes(images, body), np.array([truth[body] for truth in truths]))
    if not head.any():
        return curve, ()
    return curve, (ZoneCurve(HEAD_END, zone, fit(_sizes(images, head), np.array([truth[head] for truth in truths]))),)


def head_end_mask(layout, grid) -> np.ndarray:
    """Pixels (rows, cols) whose centre lies in the first ``HEAD_END_MM`` of a bed's long side; none on a
    smaller mat."""
    long, _, along_x = _long_axis(layout)
    along = grid.centres_mm[:, 0 if along_x else 1]
    return ((along < HEAD_END_MM) & (long >= BED_MIN_LENGTH_MM)).reshape(grid.shape)


def _sizes(images, mask: np.ndarray) -> np.ndarray:
    """The size of each image's change on ``mask``'s pixels (a rise reads nothing)."""
    return np.clip(-np.array([image[mask] for image in images]), 0.0, None)


def grams_for(load: Load) -> float:
    """The weight that presses ``load``'s area to its pressure (what an operator puts down)."""
    return load.pressure_kpa * (load.side_mm / 10.0) ** 2 / KPA_PER_GRAM_PER_CM2


def _mean_frame(acquire, averages: int) -> tuple[np.ndarray, float | None]:
    frames = [acquire() for _ in range(averages)]
    volts = np.nanmean(np.array([f.volts for f in frames]), axis=0) if averages > 1 else frames[0].volts
    temperatures = [f.temperature_c for f in frames if f.temperature_c is not None]
    return volts, (float(np.mean(temperatures)) if temperatures else None)


def pressure_calibration(acquire: Callable, place: Callable, model: ReconstructionModel,
                         loads: Sequence[Load | MapLoad], *,
                         averages: int = 1, iterate: str | None = None,
                         progress: Callable | None = None) -> PressureCalibration:
    """Place each load in turn, image it against the empty mat, and fit curve and flat field to what it gave.

    ``iterate`` (default: what the layout affords, :func:`affordable_iterate`) is stored
    with the calibration; the monitor images the same way, or the curve would not hold.
    """
    if not loads:
        raise ConfigError("a pressure calibration needs at least one load")
    setup = model.setup
    iterate = iterate or affordable_iterate(setup.layout.n_electrodes)
    grid = model.reconstructor.grid
    place(None)
    reference, reference_temperature = _mean_frame(acquire, averages)
    reference_temperature = 24.0 if reference_temperature is None else reference_temperature
    images, truths = [], []
    try:
        for k, load in enumerate(loads, start=1):
            place(load)
            volts, temperature = _mean_frame(acquire, averages)
            image, _ = model.reconstruct(temperature_corrected(volts, temperature, reference_temperature),
                                         reference, iterate=iterate)
            images.append(image)
            truths.append(load.pixel_pressure(grid))
            if progress is not None:
                progress(k, len(loads), load)
    finally:
        place(None)
    notes = {"loads": len(loads), "averages": averages, "iterate": iterate, "made_at": time.time()}
    if any(isinstance(load, MapLoad) for load in loads):
        if not all(isinstance(load, MapLoad) for load in loads):
            raise ConfigError("a pressure calibration takes either weights or whole maps, not both")
        curve, head_zone = map_curves(images, truths, setup.layout, grid)
        return PressureCalibration(setup.layout.name, layout_fingerprint(setup.layout), setup.options.algorithm,
                                   grid.shape, curve, reference_temperature, zones=head_zone,
                                   notes={**notes, "kind": "maps",
                                          "maps": [load.name for load in loads if isinstance(load, MapLoad)]})
    weights = [load for load in loads if isinstance(load, Load)]      # all of them: maps were returned above
    main = [k for k, load in enumerate(weights) if load.zone is None]
    if not main:
        raise ConfigError("a pressure calibration needs at least one load for the main curve")
    curve, flat = fit_with_flat_field([weights[k] for k in main], [images[k] for k in main],
                                      [truths[k] for k in main], grid)
    foot = [k for k, load in enumerate(weights) if load.zone == FOOT_END]
    zones: tuple[ZoneCurve, ...] = ()
    if foot:
        peaks = [np.nanmax(np.where(truths[k] > 0, -images[k], np.nan)) for k in foot]
        zones = (ZoneCurve(FOOT_END, foot_end_mask(setup.layout, grid),
                           fit_pressure_curve(np.array(peaks), np.array([weights[k].pressure_kpa for k in foot]))),)
    return PressureCalibration(setup.layout.name, layout_fingerprint(setup.layout), setup.options.algorithm,
                               grid.shape, curve, reference_temperature, flat_field=flat,
                               notes={**notes, "kind": "weights"}, zones=zones)


def fit_with_flat_field(loads, images, truths, grid):
    """A curve from each load's peak change to its pressure; each load's gain against that curve, spread
    over the pixels as the flat field; the curve again with the flat field taken out.

    The curve is fitted to peaks because the peak is what is read off a map: a
    blurred image's peak pixel changes more than the mean under the load, and a
    curve through all pixels under a load overstates every peak (by about a third
    on grid-4x4). The peak is taken among pixels wholly under the load.
    """
    footprints = [truth >= INSIDE_SHARE * truth.max() for truth in truths]
    pressures = np.array([load.pressure_kpa for load in loads])

    def peaks(flat):
        return np.array([np.nanmax(-(image / flat)[m]) for image, m in zip(images, footprints)])

    first = fit_pressure_curve(peaks(np.ones(grid.shape)), pressures)
    observed = peaks(np.ones(grid.shape))
    expected = np.interp(pressures, first.pressure, first.change)
    usable = (expected > 0) & np.isfinite(observed) & (observed > 0)
    if usable.sum() < 3:
        return first, None
    centres = np.array([(load.x_mm, load.y_mm) for load in loads])[usable]
    flat = _spread(centres, observed[usable] / expected[usable], grid)
    return fit_pressure_curve(peaks(flat), pressures), flat


def _spread(centres: np.ndarray, gains: np.ndarray, grid) -> np.ndarray:
    """Gains measured at load centres, spread to every pixel by inverse-distance weighting, mean 1."""
    points = grid.centres_mm
    d2 = ((points[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)
    weights = 1.0 / (d2 + (0.25 * min(grid.pixel_mm)) ** 2)
    flat = (weights @ np.log(gains)) / weights.sum(axis=1)
    flat = np.exp(flat - flat.mean())
    return flat.reshape(grid.shape)


def sensitivity_calibration(acquire: Callable, place: Callable, grid, protocol, side_mm: float,
                            pressure_kpa: float, *, progress: Callable | None = None) -> list[tuple]:
    """The thesis's procedure: one object on each imaged pixel in turn, its frame against the empty mat.

    Returns the rows of a calibration file (``core.frames.load_calibration``
    reads it): (pixel_row, pixel_col, drive_pos, drive_neg, meas_pos, meas_neg, volts).
    """
    place(None)
    rows = []
    pixels = grid.inside_index
    try:
        for k, flat_index in enumerate(pixels, start=1):
            r, c = divmod(int(flat_index), grid.cols)
            x, y = np.clip(grid.centres_mm[flat_index], side_mm / 2, [grid.width_mm - side_mm / 2,
                                                                      grid.height_mm - side_mm / 2])
            place(Load(float(x), float(y), side_mm, pressure_kpa))
            volts = acquire().volts
            rows += [(r, c, *map(int, reading), float(v)) for reading, v in zip(protocol.readings, volts)]
            if progress is not None:
                progress(k, len(pixels), (r, c))
    finally:
        place(None)
    return rows
