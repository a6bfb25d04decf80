"""Pressure calibration: a reconstructed conductivity change to pressure in kPa (and mmHg) per pixel.

Pressing the mat thins the liquid under the load, so the reconstructed relative
change is negative there; the deeper the press, the more negative. The map from
change to pressure is monotone but not linear (the membrane stiffens as the
liquid runs out) and the mat's sensitivity varies across it (higher near
electrodes), so a calibration holds

- a monotone curve: pressure against the size of the change, fitted by isotonic
  regression to calibration loads (known weights on known areas, as the thesis's
  Table 6.3.1), through zero;
- optionally a flat field: the response of each pixel to one standard load
  placed there (the thesis's experimental sensitivity procedure), which divides
  the change before the curve is applied;
- the temperature at which it was made: saline's conductivity rises about 2 %
  per degree, so readings are brought to that temperature before reconstruction.

It is tied to the layout and the reconstruction (algorithm and pixel grid) it was
fitted with, and refuses to be applied to any other.

>>> import numpy as np
>>> curve = fit_pressure_curve(np.array([0.0, 0.1, 0.2, 0.3]), np.array([0.0, 4.0, 9.0, 14.0]))
>>> np.round(curve.pressure_kpa(np.array([[0.0, -0.15], [-0.3, 0.05]])), 2).tolist()
[[0.0, 6.5], [14.0, 0.0]]
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import isotonic_regression

from appliance.core.layout_files import layout_to_toml
from appliance.core.layouts import Layout
from appliance.errors import ConfigError, DataFileInvalid
from appliance.files import write_atomic

FORMAT = "appliance-pressure-calibration/1"
KPA_PER_MMHG = 0.133322
SALINE_COEFFICIENT_PER_C = 0.02
CURVE_KNOTS = 24
PLAUSIBLE_FULL_CHANGE_MMHG = (40.0, 1500.0)
"""What a plausible curve reads at a change of 1 (the liquid film's whole conductance gone under the load): the
calibrations made here read 148 mmHg (the bed) and about 155 mmHg (the 4x4 bench mat) there. Under 40 mmHg a
curve reads a real load at a quarter or less of itself (a scale slipped, a curve made with no weights on); over
1500 mmHg, ten times the measured, the image's noise would read as load."""


@dataclass(frozen=True)
class PressureCurve:
    """Monotone knots: pressure (kPa) against the size of the change, -image (dimensionless)."""

    change: np.ndarray
    pressure: np.ndarray

    def pressure_kpa(self, image: np.ndarray, flat_field: np.ndarray | None = None) -> np.ndarray:
        """Pressure of each pixel; a rise in conductivity or nothing reads 0; NaN stays NaN."""
        size = -np.asarray(image, dtype=float)
        if flat_field is not None:
            size = size / flat_field
        slope = (self.pressure[-1] - self.pressure[-2]) / max(self.change[-1] - self.change[-2], 1e-12)
        inside = np.interp(size, self.change, self.pressure, left=0.0)
        beyond = self.pressure[-1] + slope * (size - self.change[-1])
        out = np.where(size > self.change[-1], beyond, inside)
        return np.where(np.isnan(size), np.nan, np.clip(out, 0.0, None))


def fit_pressure_curve(change: np.ndarray, pressure_kpa: np.ndarray, weights: np.ndarray | None = None,
                       knots: int = CURVE_KNOTS) -> PressureCurve:
    """The monotone curve through (0, 0) best fitting pressure against the size of the change.

    ``change`` is the size of the change (-image, positive when pressed) at pixels
    whose true pressure is ``pressure_kpa``; pixels with both near zero anchor the
    curve at the origin. Centred isotonic regression: the isotonic fit's constant
    blocks, each put at the mean change of its pixels and joined by straight lines,
    so that pressures the data cannot tell apart are interpolated, not stepped (a
    step would read every pixel near it as the block's top); then thinned to
    ``knots`` points at quantiles of the change.
    """
    change, pressure_kpa = np.ravel(change).astype(float), np.ravel(pressure_kpa).astype(float)
    keep = np.isfinite(change) & np.isfinite(pressure_kpa)
    if keep.sum() < 3:
        raise ConfigError("a pressure curve needs at least three calibration pixels")
    order = np.argsort(change[keep])
    x = np.r_[0.0, change[keep][order]]
    w = np.r_[10.0 * keep.sum(), (np.ones(keep.sum()) if weights is None else np.ravel(weights)[keep][order])]
    fit = isotonic_regression(np.r_[0.0, pressure_kpa[keep][order]], weights=w, increasing=True)
    starts = fit.blocks[:-1]
    centres = np.add.reduceat(w * x, starts) / np.add.reduceat(w, starts)
    values = fit.x[starts]
    centres, first = np.unique(centres, return_index=True)
    values = values[first]
    if centres[0] > 0:
        centres, values = np.r_[0.0, centres], np.r_[0.0, values]
    if len(centres) > knots:
        grid = np.unique(np.r_[0.0, np.quantile(centres[1:], np.linspace(0, 1, knots - 1))])
        centres, values = grid, np.interp(grid, centres, values)
    if len(centres) < 2:
        centres, values = np.array([0.0, max(x.max(), 1e-6)]), np.array([0.0, max(values.max(), 0.0)])
    values[0] = 0.0
    return PressureCurve(centres, np.maximum.accumulate(values))


def matched_curve(change: np.ndarray, pressure_kpa: np.ndarray, knots: int = CURVE_KNOTS) -> PressureCurve:
    """The monotone curve that reads the changes of many pixels with the distribution of their true pressures:
    the k-th largest change reads the k-th largest pressure (quantile matching).

    Regressing pressure on a noisy change (:func:`fit_pressure_curve`) gives the mean pressure of the pixels
    showing that change, which pulls the highest pressures toward the middle; matching keeps the spread of the
    truth, so the peaks a dose follows are read at their height. Only the two sets of values are compared, so
    the pairing of a pixel's change with its own pressure does not enter.
    """
    change, pressure_kpa = np.ravel(change).astype(float), np.ravel(pressure_kpa).astype(float)
    if change.shape != pressure_kpa.shape:
        raise ConfigError(f"a matched pressure curve needs a pressure for each change, got {change.size} "
                          f"changes and {pressure_kpa.size} pressures")
    keep = np.isfinite(change) & np.isfinite(pressure_kpa)
    return fit_pressure_curve(np.sort(change[keep]), np.sort(pressure_kpa[keep]), knots=knots)


def layout_fingerprint(layout: Layout) -> str:
    """SHA-256 of the layout's TOML: two mats match only if every electrode matches."""
    return hashlib.sha256(layout_to_toml(layout).encode()).hexdigest()


def temperature_corrected(volts: np.ndarray, temperature_c: float | None, reference_temperature_c: float,
                          coefficient_per_c: float = SALINE_COEFFICIENT_PER_C) -> np.ndarray:
    """Readings brought to the reference temperature: a warmer liquid conducts better, reads lower."""
    if temperature_c is None:
        return np.asarray(volts, dtype=float)
    return np.asarray(volts, dtype=float) * (1 + coefficient_per_c * (temperature_c - reference_temperature_c))


@dataclass(frozen=True)
class ZoneCurve:
    """A curve for the pixels of ``mask`` (rows, cols), fitted to loads the size of what lies there.

    A reconstruction spreads a contact smaller than its resolution over several
    pixels, so one curve cannot read both a pelvis and a heel: at a bed's foot end,
    where only heels and feet lie, a curve from heel-size loads reads them.
    """

    name: str
    mask: np.ndarray
    curve: PressureCurve


@dataclass(frozen=True)
class PressureCalibration:
    """A fitted calibration and what it is valid for; ``zones`` replace the main curve on their pixels."""

    layout_name: str
    layout_sha256: str
    algorithm: str
    pixels: tuple[int, int]
    curve: PressureCurve
    reference_temperature_c: float
    temperature_coefficient_per_c: float = SALINE_COEFFICIENT_PER_C
    flat_field: np.ndarray | None = None
    notes: dict = field(default_factory=dict)
    zones: tuple[ZoneCurve, ...] = ()

    def check_fits(self, layout: Layout, algorithm: str, pixels: tuple[int, int]) -> None:
        """Refuse to be applied to another mat or another reconstruction."""
        if layout_fingerprint(layout) != self.layout_sha256:
            raise ConfigError(f"the pressure calibration was made for layout {self.layout_name!r}, not for "
                              f"{layout.name!r} (or that layout has changed since)")
        if algorithm != self.algorithm or tuple(pixels) != tuple(self.pixels):
            raise ConfigError(f"the pressure calibration was fitted to {self.algorithm} images of "
                              f"{self.pixels[0]} x {self.pixels[1]} pixels, not {algorithm} images of "
                              f"{pixels[0]} x {pixels[1]}")

    def pressure_kpa(self, image: np.ndarray) -> np.ndarray:
        if image.shape != tuple(self.pixels):
            raise ConfigError(f"image of shape {image.shape} given to a calibration for {self.pixels}")
        pressure = self.curve.pressure_kpa(image, self.flat_field)
        for zone in self.zones:
            pressure = np.where(zone.mask, zone.curve.pressure_kpa(image), pressure)
        return pressure


def save_pressure_calibration(path: Path, calibration: PressureCalibration) -> None:
    """Write a calibration as JSON (exact floats, human-readable)."""
    c = calibration
    data = {"format": FORMAT, "layout": c.layout_name, "layout_sha256": c.layout_sha256,
            "algorithm": c.algorithm, "pixels": list(c.pixels),
            "curve": {"change": c.curve.change.tolist(), "pressure_kpa": c.curve.pressure.tolist()},
            "reference_temperature_c": c.reference_temperature_c,
            "temperature_coefficient_per_c": c.temperature_coefficient_per_c,
            "flat_field": None if c.flat_field is None else c.flat_field.tolist(), "notes": c.notes,
            "zones": [{"name": z.name, "mask": z.mask.astype(int).tolist(),
                       "curve": {"change": z.curve.change.tolist(), "pressure_kpa": z.curve.pressure.tolist()}}
                      for z in c.zones]}
    write_atomic(Path(path), json.dumps(data, indent=1) + "\n")


def load_pressure_calibration(path: Path) -> PressureCalibration:
    """Read a calibration file; anything missing or malformed is named."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataFileInvalid(f"pressure calibration {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFileInvalid(f"pressure calibration {path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise DataFileInvalid(f"{path} is not a pressure calibration ({FORMAT})")
    try:
        change = np.array(data["curve"]["change"], dtype=float)
        pressure = np.array(data["curve"]["pressure_kpa"], dtype=float)
        flat = data.get("flat_field")
        zones = tuple(ZoneCurve(str(z["name"]), np.array(z["mask"], dtype=bool),
                                PressureCurve(np.array(z["curve"]["change"], dtype=float),
                                              np.array(z["curve"]["pressure_kpa"], dtype=float)))
                      for z in data.get("zones", []))
        rows, cols = (int(v) for v in data["pixels"])
        calibration = PressureCalibration(
            str(data["layout"]), str(data["layout_sha256"]), str(data["algorithm"]),
            (rows, cols), PressureCurve(change, pressure),
            float(data["reference_temperature_c"]), float(data["temperature_coefficient_per_c"]),
            None if flat is None else np.array(flat, dtype=float), dict(data.get("notes", {})), zones)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFileInvalid(f"pressure calibration {path}: missing or malformed field ({exc})") from None
    for name, curve in _curves(calibration):
        problem = _shape_problem(name, curve)
        if problem:
            raise DataFileInvalid(f"pressure calibration {path}: {problem}")
    if any(z.mask.shape != calibration.pixels for z in calibration.zones):
        raise DataFileInvalid(f"pressure calibration {path}: a zone's mask does not match the pixels")
    if calibration.flat_field is not None and calibration.flat_field.shape != calibration.pixels:
        raise DataFileInvalid(f"pressure calibration {path}: flat field shape does not match the pixels")
    return calibration


def _curves(calibration: PressureCalibration) -> list[tuple[str, PressureCurve]]:
    return [("curve", calibration.curve)] + [(f"zone {z.name}", z.curve) for z in calibration.zones]


def _shape_problem(name: str, curve: PressureCurve) -> str | None:
    """What is wrong with the knots of ``curve`` as knots (start at (0, 0), change rising, pressure never
    falling), named; None when nothing is."""
    c, p = np.asarray(curve.change, dtype=float), np.asarray(curve.pressure, dtype=float)
    if len(c) < 2 or len(c) != len(p) or not (np.isfinite(c).all() and np.isfinite(p).all()) or c[0] != 0 \
            or p[0] != 0 or np.any(np.diff(c) <= 0):
        return f"the {name} must start at (0, 0) and rise"
    falls = np.flatnonzero(np.diff(p) < 0)
    if falls.size:
        k = int(falls[0])
        return (f"the {name} is not monotonic: it falls from {p[k]:g} kPa at change {c[k]:g} to {p[k + 1]:g} kPa "
                f"at change {c[k + 1]:g}")
    return None


def implausible(calibration: PressureCalibration) -> str | None:
    """Why ``calibration`` cannot be a mat's (a curve constant, falling, or reading a change of 1 outside
    ``PLAUSIBLE_FULL_CHANGE_MMHG``; a flat field not finite and positive), or None. A monitor reading through
    such a curve would show an empty mat under a patient and end their alarms with no technical alarm."""
    low, high = PLAUSIBLE_FULL_CHANGE_MMHG
    for name, curve in _curves(calibration):
        problem = _shape_problem(name, curve)
        if problem:
            return problem
        if np.all(curve.pressure == curve.pressure[0]):
            return f"the {name} is constant: it reads every change as {curve.pressure[0]:g} kPa"
        full = float(curve.pressure_kpa(np.array([-1.0]))[0]) / KPA_PER_MMHG
        if not low <= full <= high:
            return (f"the {name} reads a change of 1 (the liquid film's whole conductance) as {full:.3g} mmHg; a "
                    f"mat's curve reads {low:g} to {high:g} mmHg there")
    flat = calibration.flat_field
    if flat is not None and not (np.isfinite(flat).all() and (flat > 0).all()):
        return "the flat field holds values that are not finite and positive"
    return None


def check_plausible(calibration: PressureCalibration, name: str = "the pressure calibration") -> None:
    """Refuse (ConfigError naming what is wrong) a calibration :func:`implausible` finds fault with."""
    problem = implausible(calibration)
    if problem:
        raise ConfigError(f"{name} is implausible: {problem}; it is not taken into use")
