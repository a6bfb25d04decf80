"""The event record: every alarm change and every turn as one flat record, the same for every channel.

The store logs it, the notifiers send it, ``appliance sim run`` writes it as
JSON lines. A record names the tissue site (``heel-left``; ``site_words`` says
"left heel"), its place on the mat (``x_mm``, ``y_mm``: where the site was last
found), the patient's posture and the patient's identifier, so a nurse reading
any channel knows whose tissue, where. A pressure alarm's key is
``pressure:<site>``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.anatomy import POSTURE_WORDS, SITES, SMALL_MAT_SITE, UNIDENTIFIED_SITE, site_words
from appliance.alerts.turns import TurnEvent

EVENT_TYPES = ("alarm", "turn", "episode")


@dataclass(frozen=True)
class Event:
    """``type`` alarm (kind raised, escalated, acknowledged, ended, audio-paused, ...), turn (lay-down,
    repositioned, recorded, still-loaded, bed-empty) or episode (admitted, discharged); the log also keeps type
    clock (kind clock-step), which is not sent to the notifiers."""

    time_s: float
    type: str
    kind: str
    priority: str | None = None
    category: str | None = None
    key: str | None = None
    site: str | None = None
    posture: str | None = None
    x_mm: float | None = None
    y_mm: float | None = None
    alarm_id: int | None = None
    message: str = ""
    user: str | None = None
    channel: str | None = None
    patient: str | None = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _turn_message(event: TurnEvent) -> str:
    posture = POSTURE_WORDS.get(event.posture or "", event.posture or "")
    if event.kind == "lay-down":
        return f"lay down ({posture}): the turn clock starts"
    if event.kind == "repositioned":
        if event.how == "posture":
            previous = POSTURE_WORDS.get(event.previous or "", event.previous)
            return f"repositioned: {previous} to {posture}"
        return f"repositioned: {event.how}"
    if event.kind == "recorded":
        return f"turn recorded by {event.user}"
    if event.kind == "still-loaded":
        return f"{site_words(event.site or '')} still loaded after the turn"
    if event.kind == "bed-empty":
        return "the bed is empty"
    return event.kind


def as_event(event: AlarmEvent | TurnEvent) -> Event:
    """The record of a pipeline event (the pipeline adds the place, posture and patient)."""
    if isinstance(event, TurnEvent):
        return Event(event.time_s, "turn", event.kind, site=event.site, posture=event.posture,
                     message=_turn_message(event), user=event.user)
    site = None
    if event.key and event.key.startswith("pressure:"):
        site = event.key.split(":", 1)[1]
        site = site if site in (*SITES, SMALL_MAT_SITE, UNIDENTIFIED_SITE) else None
    return Event(event.time_s, "alarm", event.kind, event.priority, event.category, event.key, site,
                 alarm_id=event.alarm_id, message=event.message, user=event.user, channel=event.channel)
