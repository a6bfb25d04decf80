"""Pressure-time dose per skin location: how much of its tolerance each pixel has used up.

Tissue tolerates a high pressure for a short time and a low one for longer, so a
plain timer over-warns on a soft mattress and under-warns on a bony prominence.
A :class:`ToleranceCurve` gives the tolerable time at each pressure; a
:class:`DoseMap` adds ``dt / tolerable_time(P)`` per pixel every frame (Miner's
rule: 1.0 means the tolerance is used up, whatever the pressure history) and
clears it again once the pixel has been offloaded long enough to recover.

Built-in curves (``tolerance_curve(name)``):

- ``"reswick-rogers"``: human interface pressure, Reswick & Rogers 1976, as the
  tri-exponential fit of Linares, Mawson & Suarez 2012 (about 6.3 h at 60 mmHg);
- ``"linder-ganz"``: rat muscle cell death, Linder-Ganz et al. 2006 sigmoid with
  the constants of Osuagwu et al. 2023 (never accumulates at or below 9 kPa).

Both see research/clinical-anchors.md sections 2.2, 2.3 and 2.7. Neither is a
patient-specific limit; they are screening boundaries.

>>> curve = tolerance_curve("linder-ganz")
>>> dose = DoseMap((1, 2), curve)
>>> for _ in range(60):
...     dose.update(np.array([[10.0, 2.0]]), 60.0)
>>> round(dose.fraction(np.array([[True, False]])), 2), dose.fraction(np.array([[False, True]]))
(0.54, 0.0)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.core.pressure import KPA_PER_MMHG
from appliance.core.pressure_map import HIGH_PRESSURE_KPA
from appliance.errors import ConfigError, CurveInvalid, DataFileInvalid

FORMAT = "appliance-dose/1"
MIN_TOLERABLE_S = 60.0       # no pressure uses up the tolerance faster than this: bounds the dose one frame adds
RELIEF_S = 15 * 60           # LS-HAPI: at least 15 min offloaded counts as tissue recovery
MAX_DT_S = 3600.0            # a longer step is a clock or caller error, not a frame interval
RECOVERY_MODES = ("reset", "decay")

# Reswick & Rogers tri-exponential fit: (mmHg, 1/h) terms; P(t) in mmHg, t in hours.
RESWICK_ROGERS_TERMS = ((650.0, 1.1469), (457.0, 0.4905), (77.0, 0.1117))
RESWICK_ROGERS_HOURS = 24.0  # the fit is sampled up to here (P = 5 mmHg); it is extrapolation beyond ~12 h
RESWICK_ROGERS_STEP_S = 10.0


@dataclass(frozen=True, eq=False, kw_only=True)
class ToleranceCurve:
    """Tolerable time (s) against pressure (kPa): decreasing, infinite at or below ``floor_kpa``.

    ``floor_kpa`` is where tissue counts as loaded (32 mmHg, capillary closing
    pressure, by default); ``min_s`` keeps a crushing pressure from using up
    the tolerance in less than one frame.
    """

    name: str
    floor_kpa: float = HIGH_PRESSURE_KPA
    min_s: float = MIN_TOLERABLE_S

    def tolerable_s(self, pressure_kpa: np.ndarray | float) -> np.ndarray:
        """Seconds each pressure can be held; ``inf`` at or below the floor and for NaN (unknown is not load)."""
        p = np.asarray(pressure_kpa, dtype=float)
        seconds = np.maximum(self._seconds(p), self.min_s)
        return np.where(p > self.floor_kpa, seconds, np.inf)

    def _seconds(self, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True, eq=False, kw_only=True)
class TabulatedCurve(ToleranceCurve):
    """A curve through knots, linear between them.

    Below the lowest pressure knot (and above the floor) the longest time holds,
    which errs short. Above the highest knot the pressure-time product of that
    knot holds (t = t_k P_k / P), so a higher pressure never tolerates longer.
    """

    pressure_kpa: np.ndarray   # increasing
    seconds: np.ndarray        # decreasing

    def _seconds(self, p: np.ndarray) -> np.ndarray:
        inside = np.interp(p, self.pressure_kpa, self.seconds)
        with np.errstate(divide="ignore", invalid="ignore"):
            beyond = self.seconds[-1] * self.pressure_kpa[-1] / p
        return np.where(p > self.pressure_kpa[-1], beyond, inside)


@dataclass(frozen=True, eq=False, kw_only=True)
class SigmoidCurve(ToleranceCurve):
    """P(t) = K / (1 + exp(alpha (t - t0))) + C inverted: t = t0 + ln(K / (P - C) - 1) / alpha.

    At or below C nothing accumulates (t = inf); at or above K + C the time is
    0 and ``min_s`` applies.
    """

    k_kpa: float
    c_kpa: float
    alpha_per_min: float
    t0_min: float

    def _seconds(self, p: np.ndarray) -> np.ndarray:
        above_c = p > self.c_kpa
        x = np.where(above_c, self.k_kpa / np.where(above_c, p - self.c_kpa, 1.0) - 1.0, np.inf)
        with np.errstate(divide="ignore"):
            minutes = self.t0_min + np.log(np.maximum(x, 0.0)) / self.alpha_per_min
        return 60.0 * minutes

    def pressure_kpa(self, minutes: np.ndarray | float) -> np.ndarray:
        """The sigmoid itself: the damage threshold after ``minutes`` of load."""
        return self.k_kpa / (1.0 + np.exp(self.alpha_per_min * (np.asarray(minutes, float) - self.t0_min))) + self.c_kpa


def reswick_rogers_mmhg(hours: np.ndarray | float) -> np.ndarray:
    """Reswick & Rogers 1976 acceptable interface pressure after ``hours``, tri-exponential fit.

    Source: Reswick JB, Rogers JE, in Kenedi et al. (eds) *Bedsore Biomechanics*,
    Macmillan 1976, 301-310 (980 subjects); fit by Linares, Mawson & Suarez,
    *J Basic Appl Sci* 2012;8:720-728. Data cover about 1-12 h.
    """
    t = np.asarray(hours, dtype=float)
    return np.sum([a * np.exp(-k * t) for a, k in RESWICK_ROGERS_TERMS], axis=0)


def reswick_rogers(*, floor_kpa: float = HIGH_PRESSURE_KPA, min_s: float = MIN_TOLERABLE_S) -> TabulatedCurve:
    """Reswick & Rogers inverted on a 10-s grid over 0-24 h (see :func:`reswick_rogers_mmhg` for the source).

    Above P(0) = 1184 mmHg the time is 0, so ``min_s``; a pressure above the
    floor but below P(24 h) = 5 mmHg (only with a floor set that low) gets 24 h.
    """
    seconds = np.arange(0.0, RESWICK_ROGERS_HOURS * 3600 + 1, RESWICK_ROGERS_STEP_S)
    kpa = reswick_rogers_mmhg(seconds / 3600) * KPA_PER_MMHG
    return TabulatedCurve(name="reswick-rogers", floor_kpa=floor_kpa, min_s=min_s,
                          pressure_kpa=kpa[::-1].copy(), seconds=seconds[::-1].copy())


def linder_ganz(*, floor_kpa: float = HIGH_PRESSURE_KPA, min_s: float = MIN_TOLERABLE_S) -> SigmoidCurve:
    """Linder-Ganz/Gefen cell-death sigmoid for rat muscle: K = 23 kPa, C = 9 kPa, alpha = 0.15/min, t0 = 90 min.

    Source: Linder-Ganz E, Engelberg S, Scheinowitz M, Gefen A, *J Biomech*
    2006;39(14):2725-2732 (> 32 kPa kills within 1 h, > 9 kPa within 2 h);
    constants from Osuagwu, McCaughey & Purcell, *BMC Biomed Eng* 2023, after
    Fig. 4 of the paper. Applied to muscle, not skin interface pressure.
    """
    return SigmoidCurve(name="linder-ganz", floor_kpa=floor_kpa, min_s=min_s,
                        k_kpa=23.0, c_kpa=9.0, alpha_per_min=0.15, t0_min=90.0)


BUILT_IN = {"reswick-rogers": reswick_rogers, "linder-ganz": linder_ganz}


def tolerance_curve(name: str, *, floor_kpa: float = HIGH_PRESSURE_KPA,
                    min_s: float = MIN_TOLERABLE_S) -> ToleranceCurve:
    """A built-in curve by name."""
    if name not in BUILT_IN:
        raise CurveInvalid(f"unknown tolerance curve {name!r}; known: {', '.join(BUILT_IN)}")
    return BUILT_IN[name](floor_kpa=floor_kpa, min_s=min_s)


def custom_curve(points: Sequence[Sequence[float]], *, name: str = "custom", floor_kpa: float = HIGH_PRESSURE_KPA,
                 min_s: float = MIN_TOLERABLE_S) -> TabulatedCurve:
    """A curve through ``(minutes, mmHg)`` points as a care plan or config gives them: time rising, pressure falling.

    Points are numbered from 1 in errors, as a person counts them in a file.
    """
    if len(points) < 2:
        raise CurveInvalid(f"tolerance curve {name!r} needs at least 2 (minutes, mmHg) points, got {len(points)}")
    parsed: list[tuple[float, float]] = []
    for i, point in enumerate(points, start=1):
        try:
            minutes, mmhg = (float(v) for v in point)
        except (TypeError, ValueError):
            raise CurveInvalid(f"tolerance curve {name!r} point {i} {point!r} is not a (minutes, mmHg) pair") from None
        if not (math.isfinite(minutes) and math.isfinite(mmhg) and minutes > 0 and mmhg > 0):
            raise CurveInvalid(f"tolerance curve {name!r} point {i} ({minutes:g} min, {mmhg:g} mmHg): "
                               "minutes and mmHg must be finite and positive")
        if parsed and not (minutes > parsed[-1][0] and mmhg < parsed[-1][1]):
            raise CurveInvalid(f"tolerance curve {name!r} point {i} ({minutes:g} min, {mmhg:g} mmHg) does not follow "
                               f"point {i - 1} ({parsed[-1][0]:g} min, {parsed[-1][1]:g} mmHg): "
                               "time must rise and pressure fall")
        parsed.append((minutes, mmhg))
    minutes, mmhg = np.array(parsed[::-1]).T
    return TabulatedCurve(name=name, floor_kpa=floor_kpa, min_s=min_s,
                          pressure_kpa=mmhg * KPA_PER_MMHG, seconds=minutes * 60.0)


class DoseMap:
    """Pressure-time dose per pixel, with recovery after a long enough offload.

    Each :meth:`update` holds the frame's pressure over the ``dt_s`` before it.
    NaN pixels (off the sheet, or unknown) neither accumulate nor recover. A
    pixel at or below ``relief_kpa`` (default the curve's floor) recovers:

    - ``"reset"``: after ``relief_s`` of continuous relief the dose returns to 0
      (fixed relief period, after Temes & Harder 1977 and Linder-Ganz 2009, with
      the LS-HAPI 15 min); a shorter offload changes nothing;
    - ``"decay"``: from the first second of relief the dose decays with time
      constant ``relief_s`` (halves in ``relief_s`` ln 2, 10.4 min by default).

    Gaps in the data are the caller's call: passing the real ``dt_s`` with the
    last map would assume the load stayed; passing an all-NaN map with it
    treats the gap as unknown (no load, no relief).
    """

    def __init__(self, shape: tuple[int, int], curve: ToleranceCurve, *, relief_kpa: float | None = None,
                 relief_s: float = RELIEF_S, recovery: str = "reset"):
        relief_kpa = curve.floor_kpa if relief_kpa is None else float(relief_kpa)
        if relief_kpa > curve.floor_kpa:
            raise ConfigError(f"relief_kpa {relief_kpa:g} is above the curve's floor {curve.floor_kpa:g} kPa: "
                              "a pixel would accumulate dose and recover at once")
        if not relief_s > 0:
            raise ConfigError(f"relief_s must be positive, got {relief_s!r}")
        if recovery not in RECOVERY_MODES:
            raise ConfigError(f"recovery {recovery!r} is not one of {', '.join(RECOVERY_MODES)}")
        self.shape = (int(shape[0]), int(shape[1]))
        self.curve = curve
        self.relief_kpa = relief_kpa
        self.relief_s = float(relief_s)
        self.recovery = recovery
        self._dose = np.zeros(self.shape)
        self._relieved_s = np.zeros(self.shape)

    @property
    def dose(self) -> np.ndarray:
        """A copy of the dose per pixel (1.0 = tolerance used up)."""
        return self._dose.copy()

    @property
    def relieved_s(self) -> np.ndarray:
        """A copy of how long each pixel has been continuously relieved."""
        return self._relieved_s.copy()

    def update(self, pressure_kpa: np.ndarray, dt_s: float) -> None:
        """Add one frame held for ``dt_s`` seconds (0 < dt_s <= 1 h)."""
        p = np.asarray(pressure_kpa, dtype=float)
        if p.shape != self.shape:
            raise ValueError(f"pressure map of shape {p.shape} for a dose map of shape {self.shape}")
        dt = float(dt_s)
        if not (math.isfinite(dt) and 0 < dt <= MAX_DT_S):
            raise ValueError(f"dt_s = {dt_s!r} s: a frame interval must be positive and at most {MAX_DT_S:g} s")
        self._dose += dt / self.curve.tolerable_s(p)
        known = np.isfinite(p)
        relieved = known & (p <= self.relief_kpa)
        self._relieved_s = np.where(relieved, self._relieved_s + dt, np.where(known, 0.0, self._relieved_s))
        if self.recovery == "reset":
            self._dose[self._relieved_s >= self.relief_s] = 0.0
        else:
            self._dose[relieved] *= math.exp(-dt / self.relief_s)

    def fraction(self, mask: np.ndarray) -> float:
        """The highest dose in a region: the region is at risk as soon as one spot of it is; 0 if empty."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != self.shape:
            raise ValueError(f"mask of shape {mask.shape} for a dose map of shape {self.shape}")
        return float(self._dose[mask].max()) if mask.any() else 0.0

    def state(self) -> dict:
        """Plain JSON types, to persist every few frames and survive a restart exactly."""
        return {"format": FORMAT, "curve": self.curve.name, "shape": list(self.shape),
                "relief_kpa": self.relief_kpa, "relief_s": self.relief_s, "recovery": self.recovery,
                "dose": self._dose.tolist(), "relieved_s": self._relieved_s.tolist()}

    @classmethod
    def from_state(cls, state: dict, curve: ToleranceCurve) -> DoseMap:
        """The map :meth:`state` saved, continued with ``curve``, which must be the one it was saved with."""
        if state.get("format") != FORMAT:
            raise DataFileInvalid(f"dose state format {state.get('format')!r}, expected {FORMAT!r}")
        if state.get("curve") != curve.name:
            raise DataFileInvalid(f"dose state was saved with curve {state.get('curve')!r}, not {curve.name!r}")
        try:
            dose_map = cls(tuple(state["shape"]), curve, relief_kpa=state["relief_kpa"],
                           relief_s=state["relief_s"], recovery=state["recovery"])
            dose = np.array(state["dose"], dtype=float)
            relieved = np.array(state["relieved_s"], dtype=float)
        except (KeyError, TypeError, ValueError, ConfigError) as e:
            raise DataFileInvalid(f"dose state is incomplete or malformed: {e}") from None
        for key, values in (("dose", dose), ("relieved_s", relieved)):
            if values.shape != dose_map.shape or not np.isfinite(values).all() or (values < 0).any():
                raise DataFileInvalid(f"dose state {key!r} is not a {dose_map.shape} grid of finite values >= 0")
        dose_map._dose, dose_map._relieved_s = dose, relieved
        return dose_map


class SiteDose:
    """Pressure-time dose per named tissue site: a :class:`DoseMap` with one cell per site.

    Keyed by the site's name, not by where its load lies on the mat or which region of
    the map holds it, so a site keeps its dose when the patient slides, when two loaded
    regions merge or one splits, and when the map's segmentation loses it for a frame:
    only ``relief_s`` below the relief pressure clears it, as for a pixel. A site not
    located in a frame is unloaded in that frame.
    """

    def __init__(self, sites: Sequence[str], curve: ToleranceCurve, **relief):
        self.sites = tuple(sites)
        self._index = {site: i for i, site in enumerate(self.sites)}
        self.cells = DoseMap((1, len(self.sites)), curve, **relief)

    def update(self, peaks_kpa: dict[str, float], dt_s: float) -> None:
        """Add one frame held for ``dt_s`` with each located site's peak pressure."""
        row = np.zeros((1, len(self.sites)))
        for site, kpa in peaks_kpa.items():
            if site not in self._index:
                raise ValueError(f"site {site!r} is not one of the sites dosed here")
            row[0, self._index[site]] = kpa
        self.cells.update(row, dt_s)

    def doses(self) -> dict[str, float]:
        """Each site's dose (1.0 = tolerance used up)."""
        return dict(zip(self.sites, self.cells.dose[0].tolist()))

    def relieved_s(self) -> dict[str, float]:
        return dict(zip(self.sites, self.cells.relieved_s[0].tolist()))

    def state(self) -> dict:
        return {"sites": list(self.sites), "cells": self.cells.state()}

    @classmethod
    def from_state(cls, state: dict, curve: ToleranceCurve, **relief) -> SiteDose:
        """The doses :meth:`state` saved, continued with ``curve`` and ``relief`` (settings may have changed
        since; each site's used share of its tolerance carries over)."""
        try:
            sites, cells = list(state["sites"]), dict(state["cells"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataFileInvalid(f"site dose state is incomplete or malformed: {exc!r}") from None
        dose = cls(sites, curve, **relief)
        cells.update({"curve": curve.name, "recovery": dose.cells.recovery, "relief_kpa": dose.cells.relief_kpa,
                      "relief_s": dose.cells.relief_s})
        dose.cells = DoseMap.from_state(cells, curve)
        return dose
