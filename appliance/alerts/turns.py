"""The turn clock: repositioning detected from the pressure map, and the time to the next turn.

A turn is what relieves the skin that bore the load, so it is detected as that:
of the load on the pixels at risk (at or above 32 mmHg) in the posture held since
the last turn, the share now clearly relieved (below half of 32 mmHg). A restless
patient shifts by 2 to 4 cm, which on pixels finer than that moves a narrow peak
to the next pixel without relieving any skin, so a pixel counts as relieved only
when the pixels within ``SHIFT_MM`` of it are relieved too (``reach_px``). Measured
on the default bed's reconstructed maps (30 mm pixels, one pixel of reach): the
virtual bed's 30-degree turns relieve 12 to 14 % of the load at risk, its restless
shifts none (pixel by pixel they would be 25 to 46 % against up to 19 %); on
grid-8x16's 56 mm pixels (no reach) turns relieved 40 to 50 %, shifts none. So
the default threshold is 6 %. The new posture must hold for ``settle_s`` before
it counts, so a brief lift for a skin check does not restart the clock; the turn
is dated from when the relief began. On a bed the heels' pixels are left out
(``ignore``): a restless patient moves the feet by a few centimetres, which
relieves a heel-size contact without turning anyone.

Leaving the bed relieves everything and counts as the end of that posture; lying
down again on an empty mat is a new posture, and the clock starts from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter

from appliance.alerts.regions import zone_mask
from appliance.core.pixels import PixelGrid
from appliance.core.pressure_map import HIGH_PRESSURE_KPA, PressureMap
from appliance.errors import ConfigError

DEFAULT_INTERVAL_S = 2 * 3600.0       # the guidelines' default two-hourly turn
RELIEVED_SHARE = 0.06
SETTLE_S = 60.0
SHIFT_MM = 30.0                       # what a restless patient's shift moves a peak by, and no turn


@dataclass(frozen=True)
class TurnEvent:
    """``repositioned`` (a new posture held; the clock restarts), ``bed-empty`` or ``turn-due``."""

    time_s: float
    kind: str
    relieved_share: float


def turn_clock_for(grid: PixelGrid, **settings) -> "TurnClock":
    """The turn clock for a mat's pixel grid: its heels left out, and the reach that a shift of ``SHIFT_MM``
    spans on its pixels."""
    return TurnClock(ignore=zone_mask(grid, "heel"), reach_px=int(SHIFT_MM // min(grid.pixel_mm)), **settings)


class TurnClock:
    """Feed it every pressure map in time order; it says when the patient was turned and when a turn is due."""

    def __init__(self, *, interval_s: float = DEFAULT_INTERVAL_S, at_risk_kpa: float = HIGH_PRESSURE_KPA,
                 relieved_share: float = RELIEVED_SHARE, settle_s: float = SETTLE_S, ignore: np.ndarray | None = None,
                 reach_px: int = 0):
        if not (interval_s > 0 and settle_s >= 0 and 0 < relieved_share <= 1 and at_risk_kpa > 0 and reach_px >= 0):
            raise ConfigError(f"turn clock: interval {interval_s!r} s and at-risk pressure {at_risk_kpa!r} kPa must "
                              f"be positive, settle time {settle_s!r} s and reach {reach_px!r} pixels not negative, "
                              f"relieved share {relieved_share!r} in (0, 1]")
        self.interval_s, self.at_risk_kpa = interval_s, at_risk_kpa
        self.relieved_share, self.settle_s = relieved_share, settle_s
        self.ignore = ignore         # pixels whose relief is no turn: a bed's heels, which a restless patient moves
        self.reach_px = reach_px     # pixels around a relieved pixel that must be relieved too
        self.posture: np.ndarray | None = None      # the map of the posture held since the last turn
        self.last_turn_s: float | None = None
        self.candidate_since: float | None = None
        self.due_announced = False
        self.bed_empty = True

    def relieved(self, pressure_kpa: np.ndarray) -> float:
        """Share of the held posture's at-risk load that ``pressure_kpa`` relieves (0 when nothing was at risk)."""
        if self.posture is None:
            return 0.0
        before = np.nan_to_num(self.posture)
        at_risk = before >= self.at_risk_kpa
        if self.ignore is not None:
            at_risk &= ~self.ignore
        if not at_risk.any():
            return 0.0
        now = np.nan_to_num(pressure_kpa)
        if self.reach_px:
            now = maximum_filter(now, size=2 * self.reach_px + 1, mode="nearest")
        return float((before * (now < self.at_risk_kpa / 2))[at_risk].sum() / before[at_risk].sum())

    def update(self, pressure_map: PressureMap) -> list[TurnEvent]:
        """The events this map brings."""
        now = pressure_map.time_s
        kpa = pressure_map.pressure_kpa
        occupied = bool((np.nan_to_num(kpa) >= self.at_risk_kpa).any())
        events = []
        if self.posture is None or not (np.nan_to_num(self.posture) >= self.at_risk_kpa).any():
            changed, share = occupied, 1.0            # an empty posture ends when someone lies down
        else:
            share = self.relieved(kpa)
            changed = share >= self.relieved_share
        if not changed:
            self.candidate_since = None
        else:
            if self.candidate_since is None:
                self.candidate_since = now
            if now - self.candidate_since >= self.settle_s:
                self.posture = np.array(kpa, dtype=float)
                if occupied:
                    self.last_turn_s = self.candidate_since
                    self.due_announced = False
                    events.append(TurnEvent(self.candidate_since, "repositioned", share))
                else:
                    self.last_turn_s = None
                    events.append(TurnEvent(self.candidate_since, "bed-empty", share))
                self.bed_empty = not occupied
                self.candidate_since = None
        if self.last_turn_s is not None and not self.due_announced and self.due_in_s(now) <= 0:
            self.due_announced = True
            events.append(TurnEvent(self.last_turn_s + self.interval_s, "turn-due", 0.0))
        return events

    def due_in_s(self, now_s: float) -> float | None:
        """Seconds until the next turn is due (negative when overdue); None while the bed is empty."""
        return None if self.last_turn_s is None else self.last_turn_s + self.interval_s - now_s

    def state(self) -> dict:
        """Everything needed to carry on after a restart, as plain JSON types."""
        return {"posture": None if self.posture is None else np.where(np.isnan(self.posture), None,
                                                                      self.posture).tolist(),
                "last_turn_s": self.last_turn_s, "candidate_since": self.candidate_since,
                "due_announced": self.due_announced, "bed_empty": self.bed_empty}

    def restore(self, state: dict) -> "TurnClock":
        """This clock (new, with its settings) carrying on from :meth:`state`."""
        clock = self
        posture = state.get("posture")
        clock.posture = None if posture is None else np.array(posture, dtype=float)
        clock.last_turn_s = state.get("last_turn_s")
        clock.candidate_since = state.get("candidate_since")
        clock.due_announced = bool(state.get("due_announced", False))
        clock.bed_empty = bool(state.get("bed_empty", True))
        return clock
