"""When an alarm tone sounds, per priority, as IEC 60601-1-8 times auditory alarm signals.

High: a burst of 10 pulses in groups of 3 + 2 + 3 + 2, repeated after a rest of
2.5-15 s; medium: 3 pulses, rest 2.5-30 s; low: 2 pulses, rest over 15 s. Pulses
last 75-200 ms. The bedside buzzer switches on and off by this schedule; the
screen's ``webui/static/tones.js`` plays the same one (a browser test compares them).

>>> schedule = tone_schedule("medium")
>>> schedule.pulses, schedule.rest_s
(((0.0, 0.2), (0.4, 0.2), (0.8, 0.2)), 10.0)
>>> schedule.sounding(0.1), schedule.sounding(0.3), schedule.sounding(schedule.period_s + 0.1)
(True, False, True)
"""

from __future__ import annotations

from dataclasses import dataclass

from appliance.alerts.alarms import PRIORITIES

_TONES = {  # pulse length, silence between pulses, extra silence after each group but the last, groups, rest (s)
    "high": (0.15, 0.10, (0.35, 0.70, 0.35), (3, 2, 3, 2), 5.0),
    "medium": (0.20, 0.20, (), (3,), 10.0),
    "low": (0.20, 0.20, (), (2,), 20.0),
}


@dataclass(frozen=True)
class ToneSchedule:
    """One burst's pulses as (start, length) in seconds from its start, and the silence before it repeats."""

    pulses: tuple[tuple[float, float], ...]
    rest_s: float

    @property
    def burst_s(self) -> float:
        start, length = self.pulses[-1]
        return start + length

    @property
    def period_s(self) -> float:
        return self.burst_s + self.rest_s

    def sounding(self, t_s: float) -> bool:
        """Whether a pulse sounds ``t_s`` seconds after the first burst began (bursts repeat every period)."""
        if t_s < 0:
            raise ValueError(f"a time into the tone must not be negative, got {t_s}")
        into = t_s % self.period_s
        return any(start <= into < start + length for start, length in self.pulses)


def tone_schedule(priority: str) -> ToneSchedule:
    """The schedule for ``priority`` (high, medium or low)."""
    if priority not in _TONES:
        raise ValueError(f"priority must be one of {PRIORITIES}, got {priority!r}")
    pulse_s, space_s, group_gaps_s, groups, rest_s = _TONES[priority]
    pulses, at = [], 0.0
    for g, size in enumerate(groups):
        for _ in range(size):
            pulses.append((round(at, 6), pulse_s))
            at += pulse_s + space_s
        at += group_gaps_s[g] if g < len(group_gaps_s) else 0.0
    return ToneSchedule(tuple(pulses), rest_s)
