"""The event record: every alarm change and every turn as one flat record, the same for every channel.

The store logs it, the notifiers send it, ``appliance sim run`` writes it as
JSON lines. A pressure alarm's key ``pressure:<zone>:<id>`` gives the region
(``sacrum``, ``heel-left``, ..., or ``region`` where no zone applies) and the
tracked region's id, so a nurse reading any channel knows which site it is.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.turns import TurnEvent

EVENT_TYPES = ("alarm", "turn")
TURN_MESSAGES = {"repositioned": "repositioned: {share:.0%} of the at-risk load relieved",
                 "bed-empty": "the bed is empty", "turn-due": "repositioning is due"}


@dataclass(frozen=True)
class Event:
    """``type`` alarm (kind raised, escalated, acknowledged, ended, audio-paused, ...) or turn (repositioned,
    bed-empty, turn-due)."""

    time_s: float
    type: str
    kind: str
    priority: str | None = None
    category: str | None = None
    key: str | None = None
    region: str | None = None
    region_id: int | None = None
    alarm_id: int | None = None
    message: str = ""
    user: str | None = None
    channel: str | None = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def as_event(event: AlarmEvent | TurnEvent) -> Event:
    """The record of a pipeline event."""
    if isinstance(event, TurnEvent):
        return Event(event.time_s, "turn", event.kind, message=TURN_MESSAGES.get(event.kind, event.kind).format(
            share=event.relieved_share))
    region = region_id = None
    if event.key and event.key.startswith("pressure:"):
        _, region, number = event.key.split(":")
        region_id = int(number)
    return Event(event.time_s, "alarm", event.kind, event.priority, event.category, event.key, region, region_id,
                 event.alarm_id, event.message, event.user, event.channel)
