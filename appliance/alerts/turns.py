"""The turn clock: repositionings seen in the body's posture and sites, and graded reminders when none comes.

A repositioning is what moves the load off the tissue that bore it, for long enough to relieve it: the new
position must hold for ``hold_s`` (the dose rule's relief time, 15 min by default), and the turn is then dated
from when it began. A change held for less is no turn: a supine patient read for a few minutes as lying on
the side (arms raised), or rolled briefly and back, relieved nothing. It is seen as:

- a change of lying posture group (back, left side, right side, front), the head of the bed raised counting
  as the back; a change of tilt on the same side (30 to 60 degrees) is not one by itself, since the posture
  estimate may waver between neighbouring tilts and the same side stays loaded;
- or, in the same posture, the offloading of the sites at risk (those loaded at or above the threshold for
  ``settle_s`` since the last turn): at least half of them below half the threshold, as a pillow that floats
  the heels and a small tilt the posture estimate misses do. A restless patient moves a few centimetres and
  the sites move with the body, so nothing is offloaded. A site at risk that has stayed below half the
  threshold for ``hold_s`` while no offloading was being held has recovered and is no longer at risk: an elbow
  loaded for a while after a shift, or a site named only while the posture was misread, must not make a
  later small shift look like the offloading of half the sites;
- or a nurse recording a turn by hand (who and when), which counts at once.

While a change is being held no reminder is raised (the patient is being turned); if the patient goes back
before ``hold_s``, the reminders carry on.

Not repositionings: lying down (the clock starts), sitting up for a meal (the head of the bed raised from the
back, or sitting on the edge: the clock runs on, and the lying posture after it is compared with the one
before), and leaving the bed. Sitting up in bed from a side for longer than ``hold_s`` does relieve that side,
and counts as a turn onto the back. The clock stops once the patient has been away for ``away_s`` (the relief
time, after which the tissue has recovered) and starts again when they lie down; a shorter absence changes
nothing. After a turn, each site that was alarmed and is still loaded is reported ("left heel still loaded").

Reminders are graded: due at the interval (medium), overdue after ``grace_s`` (high, escalated), and
repeated every ``repeat_s`` while overdue, each repeat a new alarm, until a turn is seen or recorded.
"""

from __future__ import annotations

from dataclasses import dataclass

from appliance.alerts.anatomy import LYING, check_posture, in_bed, posture_group
from appliance.alerts.dose import RELIEF_S
from appliance.core.pressure_map import HIGH_PRESSURE_KPA
from appliance.errors import ConfigError

DEFAULT_INTERVAL_S = 2 * 3600.0       # the guidelines' default two-hourly turn (EPUAP/NPIAP 2019)
DEFAULT_GRACE_S = 30 * 60.0           # a reminder turns overdue half an hour after it fell due
DEFAULT_REPEAT_S = 30 * 60.0          # and is repeated every half hour until a turn
SETTLE_S = 60.0                       # a posture estimate must hold this long before it is taken as the posture
OFFLOADED_SHARE = 0.5                 # share of the sites at risk that an offloading turn relieves
TURN_KINDS = ("lay-down", "repositioned", "recorded", "still-loaded", "bed-empty")


@dataclass(frozen=True)
class TurnEvent:
    """``lay-down`` (the clock starts), ``repositioned`` (seen: ``how`` is "posture" or "offloaded"),
    ``recorded`` (by hand, by ``user``), ``still-loaded`` (``site``, after a turn) or ``bed-empty``."""

    time_s: float
    kind: str
    posture: str | None = None
    previous: str | None = None
    how: str = ""
    site: str | None = None
    user: str | None = None


class TurnClock:
    """Feed it each frame's settled-or-not posture and site peaks in time order; it says when the patient was
    turned and which reminder is owed."""

    def __init__(self, *, interval_s: float = DEFAULT_INTERVAL_S, grace_s: float = DEFAULT_GRACE_S,
                 repeat_s: float = DEFAULT_REPEAT_S, settle_s: float = SETTLE_S,
                 at_risk_kpa: float = HIGH_PRESSURE_KPA, away_s: float = RELIEF_S, hold_s: float = RELIEF_S):
        if not (interval_s > 0 and grace_s >= 0 and repeat_s > 0 and settle_s >= 0 and at_risk_kpa > 0
                and away_s >= 0 and hold_s >= 0):
            raise ConfigError(f"turn clock: interval {interval_s!r} s, repeat {repeat_s!r} s and at-risk pressure "
                              f"{at_risk_kpa!r} kPa must be positive; grace {grace_s!r} s, settle {settle_s!r} s, "
                              f"away {away_s!r} s and hold {hold_s!r} s not negative")
        self.interval_s, self.grace_s, self.repeat_s = interval_s, grace_s, repeat_s
        self.settle_s, self.at_risk_kpa, self.away_s, self.hold_s = settle_s, at_risk_kpa, away_s, hold_s
        self.posture: str | None = None             # the settled posture (None: nothing seen yet)
        self.candidate: str | None = None           # a new posture waiting to settle, and since when
        self.candidate_since: float | None = None
        self.reference: str | None = None           # the lying posture the last turn (or lying down) left
        self.moved_since: float | None = None       # since when a lying posture of another group has held
        self.last_turn_s: float | None = None       # when the clock started: None while the bed is empty
        self.away_since: float | None = None
        self.loaded_since: dict[str, float] = {}    # sites at or above the threshold, since when
        self.at_risk: set[str] = set()              # sites loaded for settle_s since the last turn
        self.relieved_since: dict[str, float] = {}  # sites at risk below half the threshold, since when
        self.offloaded_since: float | None = None

    @property
    def bed_empty(self) -> bool:
        return self.last_turn_s is None

    def due_in_s(self, now_s: float) -> float | None:
        """Seconds until the next turn is due (negative when overdue); None while the bed is empty."""
        return None if self.last_turn_s is None else self.last_turn_s + self.interval_s - now_s

    @property
    def turning_since(self) -> float | None:
        """Since when a turn (a new posture group, or sites offloaded) is being held; None when none is."""
        pending = [t for t in (self.moved_since, self.offloaded_since) if t is not None]
        return min(pending) if pending else None

    def reminder(self, now_s: float) -> tuple[str, int] | None:
        """``("due", 0)``, ``("overdue", n)`` for the n-th overdue reminder, or None (also while a turn is
        being held)."""
        due = self.due_in_s(now_s)
        if due is None or due > 0 or self.turning_since is not None:
            return None
        late = -due - self.grace_s
        return ("due", 0) if late < 0 else ("overdue", 1 + int(late // self.repeat_s))

    def update(self, now_s: float, posture: str, peaks: dict[str, float],
               alarmed: frozenset[str] = frozenset()) -> list[TurnEvent]:
        """The events this frame brings: ``posture`` as estimated now, ``peaks`` the kPa at each located site,
        ``alarmed`` the sites with a pressure alarm open (reported if a turn leaves them loaded)."""
        check_posture(posture)
        loaded = {s for s, kpa in peaks.items() if kpa >= self.at_risk_kpa}
        self.loaded_since = {s: self.loaded_since.get(s, now_s) for s in loaded}
        events = self._settle(now_s, posture)
        if self.last_turn_s is not None and not events:
            events = self._moved(now_s)
        if self.posture in LYING and self.last_turn_s is not None and self.moved_since is None and not events:
            events = self._offloading(now_s, peaks)
        if self.posture == "out-of-bed" and self.last_turn_s is not None and self.away_since is not None \
                and now_s - self.away_since >= self.away_s:
            self.last_turn_s = self.reference = self.moved_since = self.offloaded_since = None
            self.at_risk.clear()
            self.relieved_since.clear()
            events.append(TurnEvent(self.away_since, "bed-empty", "out-of-bed"))
        self.at_risk |= {s for s, since in self.loaded_since.items() if now_s - since >= self.settle_s}
        if any(e.kind in ("repositioned", "recorded") for e in events):
            events += self._still_loaded(now_s, loaded, alarmed)
        return events

    def record(self, now_s: float, user: str, peaks: dict[str, float],
               alarmed: frozenset[str] = frozenset()) -> list[TurnEvent]:
        """A turn a nurse records by hand: the clock restarts now, whatever the map shows."""
        if not isinstance(user, str) or not user.strip():
            raise ConfigError("a turn recorded by hand needs the name of who turned the patient")
        self._turned(now_s)
        if in_bed(self.posture):
            self.reference = self.posture
        loaded = {s for s, kpa in peaks.items() if kpa >= self.at_risk_kpa}
        return [TurnEvent(now_s, "recorded", self.posture, how="by hand", user=user.strip()),
                *self._still_loaded(now_s, loaded, alarmed)]

    def _settle(self, now_s: float, posture: str) -> list[TurnEvent]:
        """Hold a new posture estimate for ``settle_s``, then take it as the posture, dated from when it began;
        a lying posture of another group than the last turn left starts a turn being held (:meth:`_moved`)."""
        if posture == self.posture:
            self.candidate = self.candidate_since = None
            return []
        if posture != self.candidate or self.candidate_since is None:
            self.candidate, self.candidate_since = posture, now_s
        if now_s - self.candidate_since < self.settle_s:
            return []
        since, previous = self.candidate_since, self.posture
        self.posture, self.candidate, self.candidate_since = posture, None, None
        if in_bed(previous) and in_bed(posture) and posture_group(posture) != posture_group(previous):
            self._at_risk_afresh()
        if posture == "out-of-bed":
            self.away_since = since
            return []
        self.away_since = None
        if self.last_turn_s is None:                               # into an empty bed: the clock starts
            self._turned(since)
            self.reference = posture if in_bed(posture) else None
            return [TurnEvent(since, "lay-down", posture, previous)]
        if not in_bed(posture):                                    # sitting on the edge: the clock runs on
            return []
        if self.reference is None:
            self.reference = posture
        elif posture_group(posture) == posture_group(self.reference):
            self.moved_since = None                                 # back as before: no turn
        elif self.moved_since is None:
            self.moved_since = since
        return []

    def _moved(self, now_s: float) -> list[TurnEvent]:
        """A new posture group held for ``hold_s``: a turn, dated from when it began."""
        if self.moved_since is None or not in_bed(self.posture) or now_s - self.moved_since < self.hold_s:
            return []
        since, before = self.moved_since, self.reference
        self._turned(since)
        self.reference = self.posture
        return [TurnEvent(since, "repositioned", self.posture, before, "posture")]

    def _offloading(self, now_s: float, peaks: dict[str, float]) -> list[TurnEvent]:
        """A turn in the same posture: most of the sites at risk below half the threshold for ``hold_s``; a site
        relieved for ``hold_s`` before any offloading was being held has recovered and leaves the sites at risk."""
        below = {s for s in self.at_risk if peaks.get(s, 0.0) < self.at_risk_kpa / 2}
        self.relieved_since = {s: self.relieved_since.get(s, now_s) for s in below}
        if self.offloaded_since is None:
            recovered = {s for s, since in self.relieved_since.items() if now_s - since >= self.hold_s}
            self.at_risk -= recovered
            self.relieved_since = {s: t for s, t in self.relieved_since.items() if s not in recovered}
        if not self.at_risk:
            self.offloaded_since = None
            return []
        relieved = sorted(self.relieved_since)
        if len(relieved) < OFFLOADED_SHARE * len(self.at_risk):
            self.offloaded_since = None
            return []
        if self.offloaded_since is None:
            self.offloaded_since = now_s
        if now_s - self.offloaded_since < self.hold_s:
            return []
        since = self.offloaded_since
        self._turned(since)
        return [TurnEvent(since, "repositioned", self.posture, self.posture,
                          f"offloaded {', '.join(sorted(relieved))}")]

    def _at_risk_afresh(self) -> None:
        """A new posture group: an offloading turn is judged within one posture, so the sites at risk are those
        loaded in it from now on. Kept across, the sites of a posture misread for a few minutes (a supine patient
        with the arms raised read as on the side) were at risk back on the back, unloaded there, and with the
        back's own sites unloaded while it was misread they held an offloading for 15 min: a turn no one made."""
        self.at_risk.clear()
        self.relieved_since.clear()
        self.offloaded_since = None

    def _turned(self, time_s: float) -> None:
        self.last_turn_s = time_s
        self._at_risk_afresh()
        self.moved_since = None
        self.loaded_since = {s: max(since, time_s) for s, since in self.loaded_since.items()}

    def _still_loaded(self, now_s: float, loaded: set[str], alarmed: frozenset[str]) -> list[TurnEvent]:
        return [TurnEvent(now_s, "still-loaded", self.posture, site=s) for s in sorted(alarmed & loaded)]

    def state(self) -> dict:
        """Everything needed to carry on after a restart, as plain JSON types."""
        return {"posture": self.posture, "candidate": self.candidate, "candidate_since": self.candidate_since,
                "reference": self.reference, "moved_since": self.moved_since, "last_turn_s": self.last_turn_s,
                "away_since": self.away_since,
                "loaded_since": dict(self.loaded_since), "at_risk": sorted(self.at_risk),
                "relieved_since": dict(self.relieved_since),
                "offloaded_since": self.offloaded_since}

    def restore(self, state: dict) -> TurnClock:
        """This clock (new, with its settings) carrying on from :meth:`state`."""
        for name in ("posture", "candidate", "candidate_since", "reference", "moved_since", "last_turn_s",
                     "away_since", "offloaded_since"):
            setattr(self, name, state.get(name))
        self.loaded_since = {str(s): float(t) for s, t in (state.get("loaded_since") or {}).items()}
        self.at_risk = set(state.get("at_risk") or ())
        self.relieved_since = {str(s): float(t) for s, t in (state.get("relieved_since") or {}).items()}
        return self
