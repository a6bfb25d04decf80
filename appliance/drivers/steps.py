"""Parallel steps: all of one drive's readings from one conversion of every channel, auto-ranged per drive.

A parallel front end (``front_end.parallel``) converts every channel at once, so
the range is chosen per drive, not per reading: the AD7606 RANGE pin serves all
channels. A step starts at the range the last frame's plan gave that drive (or
the least sensitive, probing, on the first frame), steps down a range when a
channel it needs came out over range, and up to the most sensitive range that
keeps every reading of the drive under the headroom, as the serial chains'
"largest gain that does not saturate". A reading still over range at the least
sensitive range is saturated.

The scan engine (:mod:`appliance.drivers.scan`) runs the steps and handles
faults; this module is one step and the checks that need the converters'
identity (a stuck converter is one AD7606, named).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.drivers.frontend import OVER_RANGE

MAX_RANGE_STEPS = 3


@dataclass(frozen=True)
class StepResult:
    """One drive's readings: signed volts (V(meas+) - V(meas-)), share of full scale, (ADC, code), the range
    used, which readings were over range at the least sensitive range, and when the sample was held."""

    volts: np.ndarray
    fraction: np.ndarray
    codes: list[tuple[int, int]]
    range_index: int
    saturated: np.ndarray
    sampled_at_s: float


def take_step(front_end, drive: tuple[int, int], channels: np.ndarray, signs: np.ndarray, planned_range: int, *,
              then: tuple[int, int] | None = None, conversions: int = 1) -> StepResult:
    """The readings of ``channels`` (signs: each reading's orientation on its channel) with ``drive`` routed.

    ``then`` (the next drive) is routed straight after the last conversion when the
    range is planned; a probing step does not, since it may have to convert again.
    """
    probing = planned_range < 0
    r = 0 if probing else planned_range
    for _ in range(MAX_RANGE_STEPS):
        used = r
        samples = [front_end.step(drive, channels, used, then=then if not probing and k == conversions - 1 else None)
                   for k in range(conversions)]
        volts = np.mean([s.volts for s in samples], axis=0)
        fraction = np.mean([s.fraction for s in samples], axis=0)
        over = np.max([s.fraction for s in samples], axis=0) > OVER_RANGE
        if over.any() and r > 0:
            r -= 1
            continue
        best = front_end.best_range(volts[~over])
        if best > r and not over.any():
            r = best
            continue
        break
    last = samples[-1]
    codes = [(int(a), int(c)) for a, c in zip(last.adcs, last.codes)]
    return StepResult(signs * volts, fraction, codes, used, over & (used == 0), last.sampled_at_s)


def stuck_converters(codes: np.ndarray, usable: np.ndarray, times: np.ndarray, *, run: int) -> dict[int, int]:
    """{ADC: code} for each converter that gave one identical code for at least ``run`` usable readings from more
    than one step: different readings cannot all land on one 16-bit code."""
    seen: dict[int, list[tuple[int, float]]] = {}
    for code, ok, t in zip(codes, usable, times):
        if code is not None and ok:
            seen.setdefault(code[0], []).append((code[1], t))
    stuck = {}
    for adc, values in seen.items():
        distinct_codes = {c for c, _ in values}
        if len(values) >= run and len(distinct_codes) == 1 and len({t for _, t in values}) > 1:
            stuck[adc] = values[0][0]
    return stuck
