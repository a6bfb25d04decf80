"""Where a hospital's messages go: one subject per bed and kind, one replicated alarm stream per ward.

``hospital.<ward>.<bed>.<kind>``: a bed publishes its ``alarm``, ``turn`` and ``episode`` events (kept in the
ward's stream), its ``status`` and ``summary``, and reads its ``confirm``. A station stores each confirmation
first as ``hospital.<ward>.<bed>.confirmed.<seq>`` in the ward's confirmation stream, and only once that is
acknowledged sends it to the bed on ``confirm``. A notification service (``appliance.hospital.notify``) records
what it did with an alarm change as ``hospital.<ward>.<bed>.notified.<seq>.<service>`` in the same stream, once
the messaging gateway took the page or refused it for good, and says on ``hospital.<ward>.paging.status.<service>``
whether its gateway takes pages (a plain message, repeated: ``appliance.hospital.notify``); five tokens, so no bed's
subject and no stream's takes it, whatever the names. A station's commands to a bed go on the bed's
``command`` and the bed answers on its ``command-result`` (payloads in ``appliance.alerts.ward_commands``), plain
messages that no stream keeps: the station sends a command again until it is answered. Over MQTT the same subject is the
topic ``hospital/<ward>/<bed>/<kind>``, and the kinds are the MQTT ward's topics. Every event carries the
header ``Nats-Msg-Id: <bed>:<seq>`` (the bed's own sequence number), so the stream keeps one copy of a resend
inside its duplicate window and a station applies each number once after it.

>>> bed_subject("ward3", "w3-bed01", "alarm")
'hospital.ward3.w3-bed01.alarm'
>>> stream_name("ward3")
'ALARMS_ward3'
>>> message_id("w3-bed01", 17)
'w3-bed01:17'
>>> parse_message_id("w3-bed01:17")
('w3-bed01', 17)
>>> confirmation_subject("ward3", "w3-bed01", 17)
'hospital.ward3.w3-bed01.confirmed.17'
>>> notified_subject("ward3", "w3-bed01", 17, "phones")
'hospital.ward3.w3-bed01.notified.17.phones'
>>> paging_status_subject("ward3", "phones")
'hospital.ward3.paging.status.phones'
>>> command_subject("ward3", "w3-bed01"), answer_subject("ward3", "w3-bed01")
('hospital.ward3.w3-bed01.command', 'hospital.ward3.w3-bed01.command-result')
"""

from __future__ import annotations

from appliance.alerts.events import EVENT_TYPES
from appliance.alerts.ward_commands import COMMAND_TOPIC, RESULT_TOPIC

ROOT = "hospital"
SUMMARY = "summary"
BED_KINDS = (*EVENT_TYPES, "status", SUMMARY)
"""What a bed publishes; the events (EVENT_TYPES) are the ones the ward's stream keeps."""
CONFIRM = "confirm"
CONFIRMED = "confirmed"
NOTIFIED = "notified"
PAGING_STATUS = "paging.status"
COMMAND = COMMAND_TOPIC
"""What a station asks a bed to do."""
ANSWER = RESULT_TOPIC
"""The bed's answer to a command."""
MSG_ID = "Nats-Msg-Id"
"""JetStream's de-duplication header: a second publish with an id the stream has seen inside its window is
acknowledged as a duplicate and not stored again."""


def bed_subject(ward: str, bed: str, kind: str) -> str:
    return f"{ROOT}.{ward}.{bed}.{kind}"


def command_subject(ward: str, bed: str) -> str:
    """Where ``bed``'s commands from its ward's station go (``bed`` may be ``*``: every bed of the ward)."""
    return bed_subject(ward, bed, COMMAND)


def answer_subject(ward: str, bed: str) -> str:
    """Where ``bed`` answers its commands (``bed`` may be ``*``: every bed of the ward)."""
    return bed_subject(ward, bed, ANSWER)


def stream_name(ward: str) -> str:
    return f"ALARMS_{ward}"


def stream_subjects(ward: str) -> list[str]:
    """The subjects the ward's stream keeps: every bed's events, not its status or summary."""
    return [bed_subject(ward, "*", kind) for kind in EVENT_TYPES]


def confirms_stream_name(ward: str) -> str:
    return f"CONFIRMS_{ward}"


def confirmation_subject(ward: str, bed: str, seq: int) -> str:
    """Where the confirmation of ``bed``'s event ``seq`` is kept: one subject per event, so a bed can look its
    own up by number."""
    return f"{bed_subject(ward, bed, CONFIRMED)}.{seq}"


def notified_subject(ward: str, bed: str, seq: int | str, service: str) -> str:
    """Where notification service ``service`` records what became of ``bed``'s event ``seq``: one subject per
    event and service, so each service's record of an event is kept beside the station's confirmation (any of
    them may be ``*``)."""
    return f"{bed_subject(ward, bed, NOTIFIED)}.{seq}.{service}"


def paging_status_subject(ward: str, service: str) -> str:
    """Where notification service ``service`` says whether ``ward``'s pages go out (``service`` may be ``*``)."""
    return f"{ROOT}.{ward}.{PAGING_STATUS}.{service}"


def inbox_prefix(user: str) -> str:
    """The user's own reply subjects: a client may subscribe to its own inbox alone, so no one reads another's
    acknowledgements."""
    return f"_INBOX.{user}"


def message_id(bed: str, seq: int) -> str:
    return f"{bed}:{seq}"


def parse_message_id(value: str) -> tuple[str, int]:
    """The bed and sequence number of a ``Nats-Msg-Id``; a ValueError naming it when it is not ``<bed>:<seq>``."""
    bed, colon, seq = value.rpartition(":")
    if not (colon and bed and seq.isdigit()):
        raise ValueError(f"{MSG_ID} {value!r} is not <bed>:<sequence number>")
    return bed, int(seq)
