"""Alarm engine after IEC 60601-1-8: priorities, latching, acknowledgement, audio pause, escalation.

Pure logic: every call takes the time explicitly (seconds on one monotonic
clock), so the monitor, a simulated clock and the tests drive it alike, and a
replay gives the same events. Each change is an ``AlarmEvent``; ``history``
keeps them all and each call returns the ones it produced, which is what the
store and the notifiers consume.

Timers (escalation, end of an audio pause) fire when the next call reaches
their time; their events carry the time they were due, not the time of the
call, so the log says when the escalation was owed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from appliance.errors import ConfigError

PRIORITIES = ("low", "medium", "high")
CATEGORIES = ("clinical", "technical")

# States of an alarm that has not ended (ended alarms live on only in history).
ACTIVE = "active"
AWAITING_ACK = "cleared-awaiting-ack"

# IEC 60601-1-8 AUDIO PAUSED is of limited duration; two minutes is the usual
# bedside default. The responsible organisation may configure another bound.
DEFAULT_MAX_AUDIO_PAUSE_S = 120.0

STATE_VERSION = 1


def _raise_priority(priority: str) -> str:
    """One level up, capped at high: escalation must never lower a priority."""
    return PRIORITIES[min(PRIORITIES.index(priority) + 1, len(PRIORITIES) - 1)]


def _require_user(user) -> str:
    """Audited actions need a named person, or the log cannot say who silenced what."""
    if not isinstance(user, str) or not user.strip():
        raise ConfigError("a named user is required (got an empty name)")
    return user.strip()


@dataclass(frozen=True)
class Escalation:
    """One rung of the ladder: ``after_s`` seconds after the raise, still unacknowledged, notify ``channel``."""

    after_s: float
    channel: str


@dataclass(frozen=True)
class AlarmCondition:
    """What an alarm is: fixed by risk management, not by the bedside user.

    ``escalation`` is a ladder of rungs with strictly increasing ``after_s``
    (measured from the raise); each rung raises the priority one level.
    """

    key: str
    category: str
    priority: str
    latching: bool
    message: str
    escalation: tuple[Escalation, ...] = ()

    def __post_init__(self):
        if not isinstance(self.key, str) or not self.key:
            raise ConfigError(f"alarm condition key must be a non-empty string, got {self.key!r}")
        if self.category not in CATEGORIES:
            raise ConfigError(f"alarm condition {self.key}: category {self.category!r} is not one of {CATEGORIES}")
        if self.priority not in PRIORITIES:
            raise ConfigError(f"alarm condition {self.key}: priority {self.priority!r} is not one of {PRIORITIES}")
        if not isinstance(self.latching, bool):
            raise ConfigError(f"alarm condition {self.key}: latching must be True or False")
        if not isinstance(self.message, str) or not self.message:
            raise ConfigError(f"alarm condition {self.key}: message must be a non-empty string")
        steps = tuple(self.escalation)
        previous = 0.0
        for step in steps:
            if not isinstance(step, Escalation):
                raise ConfigError(f"alarm condition {self.key}: escalation rungs must be Escalation, got {step!r}")
            if not step.after_s > previous:
                raise ConfigError(
                    f"alarm condition {self.key}: escalation times must be positive and increasing, "
                    f"got {step.after_s} after {previous}")
            if not isinstance(step.channel, str) or not step.channel:
                raise ConfigError(f"alarm condition {self.key}: escalation channel must be a non-empty string")
            previous = step.after_s
        object.__setattr__(self, "escalation", steps)

    def to_dict(self) -> dict:
        return {"key": self.key, "category": self.category, "priority": self.priority,
                "latching": self.latching, "message": self.message,
                "escalation": [[s.after_s, s.channel] for s in self.escalation]}

    @classmethod
    def from_dict(cls, d: Mapping) -> AlarmCondition:
        return cls(key=d["key"], category=d["category"], priority=d["priority"], latching=d["latching"],
                   message=d["message"], escalation=tuple(Escalation(float(a), c) for a, c in d["escalation"]))


@dataclass(frozen=True)
class AlarmEvent:
    """One change, as the store logs it and the notifiers route it.

    Audio-pause events for all alarms have no alarm, so ``alarm_id``, ``key``,
    ``category`` and ``priority`` are None there.
    """

    time_s: float
    kind: str
    alarm_id: int | None
    key: str | None
    category: str | None
    priority: str | None
    message: str
    user: str | None = None
    channel: str | None = None


@dataclass
class Alarm:
    """One occurrence of a condition, from its raise to its end; queries hand out copies."""

    alarm_id: int
    condition: AlarmCondition
    detail: str | None
    raised_s: float
    state: str = ACTIVE
    priority: str = ""
    escalations_done: int = 0
    acknowledged_by: str | None = None
    acknowledged_s: float | None = None
    audio_paused_until: float | None = None

    def __post_init__(self):
        if not self.priority:
            self.priority = self.condition.priority

    @property
    def key(self) -> str:
        return self.condition.key

    @property
    def category(self) -> str:
        return self.condition.category

    @property
    def acknowledged(self) -> bool:
        return self.acknowledged_by is not None

    @property
    def message(self) -> str:
        return f"{self.condition.message}: {self.detail}" if self.detail else self.condition.message

    def next_escalation_s(self) -> float | None:
        """When the next rung is owed, or None once acknowledged or the ladder is exhausted."""
        if self.acknowledged or self.escalations_done >= len(self.condition.escalation):
            return None
        return self.raised_s + self.condition.escalation[self.escalations_done].after_s

    def to_dict(self) -> dict:
        return {"alarm_id": self.alarm_id, "condition": self.condition.to_dict(), "detail": self.detail,
                "raised_s": self.raised_s, "state": self.state, "priority": self.priority,
                "escalations_done": self.escalations_done, "acknowledged_by": self.acknowledged_by,
                "acknowledged_s": self.acknowledged_s, "audio_paused_until": self.audio_paused_until}

    @classmethod
    def from_dict(cls, d: Mapping) -> Alarm:
        fields = dict(d)
        fields["condition"] = AlarmCondition.from_dict(d["condition"])
        return cls(**fields)


class AlarmEngine:
    """Turns per-frame condition reports and operator actions into alarms and events.

    ``max_audio_pause_s`` bounds every audio pause (set by the responsible
    organisation). Call ``assess`` once per frame with every condition that is
    currently true; ``tick`` only advances the timers.
    """

    def __init__(self, *, max_audio_pause_s: float = DEFAULT_MAX_AUDIO_PAUSE_S):
        if not max_audio_pause_s > 0:
            raise ConfigError(f"max_audio_pause_s must be positive, got {max_audio_pause_s}")
        self.max_audio_pause_s = float(max_audio_pause_s)
        self.history: list[AlarmEvent] = []
        self._alarms: dict[int, Alarm] = {}      # every alarm that has not ended, by id
        self._by_key: dict[str, int] = {}        # condition key -> its open alarm's id
        self._next_id = 1
        self._now: float | None = None
        self._audio_paused_until: float | None = None

    # --- per-frame input -------------------------------------------------

    def assess(self, now_s: float, active: Mapping[str, tuple[AlarmCondition, str | None]]) -> list[AlarmEvent]:
        """Report the full set of true conditions at ``now_s``; conditions absent from ``active`` have cleared."""
        events = self._advance(now_s)
        for key, (condition, detail) in sorted(active.items()):     # simultaneous alarms in one order, after a
            # restart too (the sites' order in the restored state need not be the order they were first loaded)
            if not isinstance(condition, AlarmCondition) or condition.key != key:
                raise ConfigError(f"active condition {key!r} must map to an AlarmCondition with that key")
            alarm_id = self._by_key.get(key)
            if alarm_id is None:
                events.append(self._raise(now_s, condition, detail))
                continue
            alarm = self._alarms[alarm_id]
            alarm.detail = detail
            if alarm.state == AWAITING_ACK:
                alarm.state = ACTIVE
                events.append(self._event(now_s, "reactivated", alarm))
        cleared = [a for a in self._alarms.values() if a.state == ACTIVE and a.key not in active]
        for alarm in sorted(cleared, key=lambda a: a.alarm_id):
            if alarm.condition.latching and not alarm.acknowledged:
                alarm.state = AWAITING_ACK
                events.append(self._event(now_s, AWAITING_ACK, alarm))
            else:
                events.append(self._end(now_s, alarm))
        return self._record(events)

    def tick(self, now_s: float) -> list[AlarmEvent]:
        """Advance the timers only (escalation, end of audio pause) when no frame arrives."""
        return self._record(self._advance(now_s))

    # --- operator actions ------------------------------------------------

    def acknowledge(self, now_s: float, alarm_id: int, user: str) -> list[AlarmEvent]:
        """Acknowledge one alarm: silences it and stops its escalation; new conditions still alarm.

        A latched alarm whose condition has cleared ends here; an active one
        stays visible, silent, until its condition clears.
        """
        user = _require_user(user)
        events = self._advance(now_s)
        alarm = self._open_alarm(alarm_id)
        if alarm.acknowledged:
            return self._record(events)
        alarm.acknowledged_by, alarm.acknowledged_s = user, float(now_s)
        events.append(self._event(now_s, "acknowledged", alarm, user=user))
        if alarm.state == AWAITING_ACK:
            events.append(self._end(now_s, alarm, user=user))
        return self._record(events)

    def pause_audio(self, now_s: float, user: str, duration_s: float,
                    alarm_id: int | None = None) -> list[AlarmEvent]:
        """Silence all alarms (or one) for a bounded time; audio resumes by itself, with an event."""
        user = _require_user(user)
        if not 0 < duration_s <= self.max_audio_pause_s:
            raise ConfigError(
                f"audio pause of {duration_s} s refused: it must be more than 0 and at most "
                f"{self.max_audio_pause_s:g} s")
        events = self._advance(now_s)
        until = float(now_s) + float(duration_s)
        message = f"audio paused for {duration_s:g} s by {user}"
        if alarm_id is None:
            self._audio_paused_until = until
            events.append(AlarmEvent(float(now_s), "audio-paused", None, None, None, None, message, user=user))
        else:
            alarm = self._open_alarm(alarm_id)
            alarm.audio_paused_until = until
            events.append(self._event(now_s, "audio-paused", alarm, user=user, message=message))
        return self._record(events)

    def end_category(self, now_s: float, category: str, user: str) -> list[AlarmEvent]:
        """End every alarm of ``category`` at once, acknowledged or not: a patient discharged or replaced
        takes their clinical alarms with them (the new patient's start afresh)."""
        user = _require_user(user)
        if category not in CATEGORIES:
            raise ConfigError(f"category {category!r} is not one of {CATEGORIES}")
        events = self._advance(now_s)
        for alarm in sorted((a for a in self._alarms.values() if a.category == category), key=lambda a: a.alarm_id):
            events.append(self._end(now_s, alarm, user=user))
        return self._record(events)

    # --- queries ---------------------------------------------------------

    def alarms(self, category: str | None = None) -> list[Alarm]:
        """Alarms not yet ended, highest priority first then oldest; one category if given."""
        if category is not None and category not in CATEGORIES:
            raise ConfigError(f"category {category!r} is not one of {CATEGORIES}")
        chosen = [a for a in self._alarms.values() if category in (None, a.category)]
        chosen.sort(key=lambda a: (-PRIORITIES.index(a.priority), a.alarm_id))
        return [dataclasses.replace(a) for a in chosen]

    def clinical(self) -> list[Alarm]:
        return self.alarms("clinical")

    def technical(self) -> list[Alarm]:
        return self.alarms("technical")

    def alarm(self, alarm_id: int) -> Alarm:
        return dataclasses.replace(self._open_alarm(alarm_id))

    def audible(self, now_s: float) -> str | None:
        """Priority the bedside should sound at ``now_s``, or None.

        Reads the state without advancing it, so pauses end at their stated
        time even if no call has processed them yet.
        """
        if self._audio_paused_until is not None and now_s < self._audio_paused_until:
            return None
        loud = [a for a in self._alarms.values()
                if not a.acknowledged and (a.audio_paused_until is None or now_s >= a.audio_paused_until)]
        if not loud:
            return None
        return max((self._priority_at(a, now_s) for a in loud), key=PRIORITIES.index)

    # --- persistence -----------------------------------------------------

    def state(self) -> dict:
        """Everything needed to carry on after a restart, as plain JSON types.

        History is not included: the store has already logged every event.
        """
        return {"version": STATE_VERSION, "max_audio_pause_s": self.max_audio_pause_s,
                "next_id": self._next_id, "now_s": self._now, "audio_paused_until": self._audio_paused_until,
                "alarms": [a.to_dict() for a in sorted(self._alarms.values(), key=lambda a: a.alarm_id)]}

    @classmethod
    def from_state(cls, state: Mapping) -> AlarmEngine:
        """Rebuild an engine from ``state()``: open alarms keep their ids, timers and acknowledgements."""
        if not isinstance(state, Mapping) or state.get("version") != STATE_VERSION:
            raise ConfigError(f"alarm state is not version {STATE_VERSION} engine state")
        try:
            engine = cls(max_audio_pause_s=state["max_audio_pause_s"])
            engine._next_id = int(state["next_id"])
            engine._now = state["now_s"]
            engine._audio_paused_until = state["audio_paused_until"]
            for d in state["alarms"]:
                alarm = Alarm.from_dict(d)
                if alarm.alarm_id >= engine._next_id or alarm.key in engine._by_key:
                    raise ConfigError(f"alarm state is inconsistent at alarm {alarm.alarm_id} ({alarm.key})")
                engine._alarms[alarm.alarm_id] = alarm
                engine._by_key[alarm.key] = alarm.alarm_id
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"alarm state is malformed: {exc!r}") from exc
        return engine

    # --- internals -------------------------------------------------------

    def _advance(self, now_s: float) -> list[AlarmEvent]:
        """Fire every timer due by ``now_s``, stamped with its due time, in time order."""
        if self._now is not None and now_s < self._now:
            raise ConfigError(f"time went backwards: {now_s} after {self._now}")
        self._now = float(now_s)
        events = []
        if self._audio_paused_until is not None and self._audio_paused_until <= now_s:
            events.append(AlarmEvent(self._audio_paused_until, "audio-resumed", None, None, None, None,
                                     "audio pause ended"))
            self._audio_paused_until = None
        for alarm in sorted(self._alarms.values(), key=lambda a: a.alarm_id):
            if alarm.audio_paused_until is not None and alarm.audio_paused_until <= now_s:
                events.append(self._event(alarm.audio_paused_until, "audio-resumed", alarm,
                                          message="audio pause ended"))
                alarm.audio_paused_until = None
            while (due := alarm.next_escalation_s()) is not None and due <= now_s:
                step = alarm.condition.escalation[alarm.escalations_done]
                alarm.escalations_done += 1
                alarm.priority = _raise_priority(alarm.priority)
                events.append(self._event(due, "escalated", alarm, channel=step.channel))
        events.sort(key=lambda e: e.time_s)
        return events

    def _priority_at(self, alarm: Alarm, now_s: float) -> str:
        """Priority including rungs already owed at ``now_s`` but not yet processed."""
        priority = alarm.priority
        for step in alarm.condition.escalation[alarm.escalations_done:]:
            if alarm.raised_s + step.after_s <= now_s:
                priority = _raise_priority(priority)
        return priority

    def _raise(self, now_s: float, condition: AlarmCondition, detail: str | None) -> AlarmEvent:
        alarm = Alarm(self._next_id, condition, detail, float(now_s))
        self._next_id += 1
        self._alarms[alarm.alarm_id] = alarm
        self._by_key[alarm.key] = alarm.alarm_id
        return self._event(now_s, "raised", alarm)

    def _end(self, now_s: float, alarm: Alarm, user: str | None = None) -> AlarmEvent:
        del self._alarms[alarm.alarm_id]
        del self._by_key[alarm.key]
        return self._event(now_s, "ended", alarm, user=user)

    def _open_alarm(self, alarm_id: int) -> Alarm:
        try:
            return self._alarms[alarm_id]
        except KeyError:
            raise ConfigError(f"alarm {alarm_id} is unknown or has already ended") from None

    @staticmethod
    def _event(time_s: float, kind: str, alarm: Alarm, *, user: str | None = None,
               channel: str | None = None, message: str | None = None) -> AlarmEvent:
        return AlarmEvent(float(time_s), kind, alarm.alarm_id, alarm.key, alarm.category, alarm.priority,
                          message if message is not None else alarm.message, user=user, channel=channel)

    def _record(self, events: Iterable[AlarmEvent]) -> list[AlarmEvent]:
        events = list(events)
        self.history.extend(events)
        return events
