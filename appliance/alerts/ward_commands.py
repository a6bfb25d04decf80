"""What the ward station asks a bed to do, and the bed's answer: the payloads and their checks.

A nurse at the ward station can acknowledge a bed's alarm or record its turn. The station publishes::

    <prefix>/<bed_id>/command          QoS 1, not retained
        {id, bed_id, kind, args, user, station, issued_at, expires_at}

and the bed answers each one it has taken, once the frame that applied or refused it is committed::

    <prefix>/<bed_id>/command-result   QoS 1, not retained
        {id, state: "done" | "refused", result, answered_at}

``id`` is the station's, unique per command (``uuid4().hex``) and the same in every resend, so the bed can
apply each command once however often it arrives: QoS 1 delivers twice, the station resends until it has an
answer, after a reconnect and after its own restart. The bed keeps the ids it has applied in its store, with
the frame that applied them, and answers a repeat with the answer it gave first. Times are wall-clock unix
times: a command is refused as expired when the bed takes it after ``expires_at``, so an acknowledgement a nurse
gave minutes ago is never applied to what the bed has become since. ``user`` is the station's account; the
bed records it as ``ward:<user>``, so the audit never mistakes it for a person logged in at the bedside.
"""

from __future__ import annotations

import json
import math
import re
import uuid
from dataclasses import asdict, dataclass

COMMAND_TOPIC = "command"
RESULT_TOPIC = "command-result"
COMMAND_KINDS = ("acknowledge", "record-turn")
ANSWERS = ("done", "refused")
WARD_USER_PREFIX = "ward:"
MAX_USER = 64
_ID = re.compile(r"^[0-9a-f]{32}$")


@dataclass(frozen=True)
class WardCommand:
    """One command from the ward station to one bed."""

    id: str
    bed_id: str
    kind: str
    args: dict
    user: str
    station: str
    issued_at: float
    expires_at: float

    @property
    def bed_user(self) -> str:
        """The name the bed records it under: the ward's account, marked as the ward's."""
        return WARD_USER_PREFIX + self.user

    def to_payload(self) -> str:
        return json.dumps(asdict(self))


def new_command(bed_id: str, kind: str, args: dict, user: str, station: str, now: float,
                expiry_s: float) -> WardCommand:
    """A fresh command with its own id, checked as the bed will check it."""
    return checked(WardCommand(uuid.uuid4().hex, bed_id, kind, dict(args), user, station, now, now + expiry_s))


def parse_command(payload: bytes, bed_id: str) -> WardCommand:
    """The command in ``payload`` for bed ``bed_id``; ValueError naming what is wrong with it."""
    body = json.loads(payload)
    if not isinstance(body, dict):
        raise ValueError(f"a command must be a JSON object, got {type(body).__name__}")
    fields = set(WardCommand.__dataclass_fields__)
    if set(body) != fields:
        raise ValueError(f"a command has exactly the fields {sorted(fields)}; missing "
                         f"{sorted(fields - set(body))}, unknown {sorted(set(body) - fields)}")
    command = checked(WardCommand(**body))
    if command.bed_id != bed_id:
        raise ValueError(f"command {command.id} is for bed {command.bed_id!r}, not {bed_id!r}")
    return command


def checked(command: WardCommand) -> WardCommand:
    """``command`` if every field is what the protocol says, else ValueError naming the field."""
    if not isinstance(command.id, str) or not _ID.match(command.id):
        raise ValueError(f"command id must be 32 lower-case hex digits, got {command.id!r}")
    if command.kind not in COMMAND_KINDS:
        raise ValueError(f"command {command.id}: kind must be one of {', '.join(COMMAND_KINDS)}, "
                         f"got {command.kind!r}")
    if not isinstance(command.args, dict):
        raise ValueError(f"command {command.id}: args must be an object, got {command.args!r}")
    if command.kind == "acknowledge":
        alarm_id = command.args.get("alarm_id")
        if set(command.args) != {"alarm_id"} or not isinstance(alarm_id, int) or isinstance(alarm_id, bool) \
                or alarm_id < 1:
            raise ValueError(f"command {command.id}: acknowledge takes args {{alarm_id: a positive integer}}, "
                             f"got {command.args!r}")
    elif command.args:
        raise ValueError(f"command {command.id}: {command.kind} takes no args, got {command.args!r}")
    for name in ("user", "station", "bed_id"):
        value = getattr(command, name)
        if not isinstance(value, str) or not 1 <= len(value) <= MAX_USER or not value.isprintable():
            raise ValueError(f"command {command.id}: {name} must be 1-{MAX_USER} printable characters, got "
                             f"{value!r}")
    for name in ("issued_at", "expires_at"):
        value = getattr(command, name)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise ValueError(f"command {command.id}: {name} must be a unix time, got {value!r}")
    if command.expires_at <= command.issued_at:
        raise ValueError(f"command {command.id}: expires_at ({command.expires_at}) must come after issued_at "
                         f"({command.issued_at})")
    return command


def result_payload(command_id: str, state: str, result: str, answered_at: float) -> str:
    if state not in ANSWERS:
        raise ValueError(f"an answer's state is one of {', '.join(ANSWERS)}, got {state!r}")
    return json.dumps({"id": command_id, "state": state, "result": result, "answered_at": answered_at})


def parse_result(payload: bytes) -> dict:
    """The bed's answer in ``payload``; ValueError naming what is wrong with it."""
    body = json.loads(payload)
    if not isinstance(body, dict) or set(body) != {"id", "state", "result", "answered_at"}:
        raise ValueError(f"an answer has exactly the fields answered_at, id, result and state, got "
                         f"{sorted(body) if isinstance(body, dict) else type(body).__name__}")
    if not isinstance(body["id"], str) or not _ID.match(body["id"]) or body["state"] not in ANSWERS \
            or not isinstance(body["result"], str):
        raise ValueError(f"an answer needs a command id, a state of {', '.join(ANSWERS)} and a result text, got "
                         f"{body!r}")
    return body
