"""The ward station's screen: every bed of the ward at once, alarming beds first, each linked to its own screen.

The station (``appliance.ward.station.WardStation`` on the ward's broker, or
``appliance.ward.engine_station.EngineStation`` on the hospital engine) runs in
this process and keeps each bed's state; this blueprint only shows it: as a page, as
JSON (``/api/ward``), and as a server-sent event stream sent whenever the
station took a message or a bed went on- or offline, checked four times a second.

A nurse can also act on a bed from here: acknowledge one of its open alarms or
record its turn. The request is checked against what the station shows (the
bed known, the alarm open), written to the screen's audit log and the
station's command journal, and sent to the bed
(:class:`~appliance.ward.commands.CommandSender`); each bed's tile shows its
latest commands, pending until the bed answers done or refused (with the bed's
reason), or expired. The screen never touches a bed's alarms itself.

On the hospital engine a banner says when a notification service's pages are not going out, or when it has
not said for too long whether they do (``paging``: :meth:`appliance.ward.board.WardBoard.paging`).

A station configured with ``[history]`` also shows, from the hospital history, each bed's peak pressure over
the last hours as a sparkline and the ward's events of that time (``webui.ward_history``).
"""

from __future__ import annotations

import time

from flask import Blueprint, abort, current_app, g, jsonify, render_template

from webui.alarms import answer
from webui.live import SIMULATED
from webui.security import requires
from webui.streams import event_stream

bp = Blueprint("ward", __name__)
POLL_S = 0.25
REGIONS_SHOWN = 3       # the most loaded sites of a bed; its own screen has them all
COMMANDS_SHOWN = 3      # a bed's latest commands from the ward, with their state
COMMANDS_SHOWN_S = 900.0  # how far back a tile looks for them; the station's journal keeps them all
COMMAND_FIELDS = ("id", "kind", "args", "user", "issued_at", "state", "result")


def ward_view() -> dict:
    """The ward as the screen shows it: the broker connection, counts, and each bed in the station's order."""
    station, config = current_app.extensions["ward_station"], current_app.config["WARD"]
    now = time.time()
    commands: dict[str, list[dict]] = {}
    if station.commands is not None:
        for command in station.commands.journal.recent(now - COMMANDS_SHOWN_S):
            commands.setdefault(command["bed_id"], []).append({k: command[k] for k in COMMAND_FIELDS})
    beds = [{**_bed(bed, now, config), "commands": commands.get(bed["bed_id"], [])[:COMMANDS_SHOWN]}
            for bed in station.beds(events=False)]
    return {"now": now, "connected": station.connected, "stale_after_s": station.stale_after_s,
            "can_act": station.commands is not None, "paging": station.paging(),
            "counts": {"beds": len(beds), "offline": sum(not b["online"] for b in beds),
                       "alarming": sum(b["highest_priority"] is not None for b in beds)},
            "beds": beds}


def _bed(bed: dict, now: float, config) -> dict:
    summary = bed["summary"] or {}
    regions = sorted(summary.get("regions", []), key=lambda r: -(r.get("dose") or 0.0))[:REGIONS_SHOWN]
    turn = summary.get("turn") or {}
    return {"bed_id": bed["bed_id"], "online": bed["online"], "status": bed["status"],
            "heard_s_ago": None if bed["last_heard_at"] is None else round(now - bed["last_heard_at"], 1),
            "highest_priority": bed["highest_priority"], "alarms": bed["alarms"],
            "peak_mmhg": summary.get("peak_mmhg"), "turn_due_in_s": turn.get("due_in_s"), "regions": regions,
            "screen_url": config.screen_of(bed["bed_id"]),
            "simulated": SIMULATED.get((summary.get("status") or {}).get("source"))}


def _change_key() -> tuple:
    """Changes when the station took a message, lost or regained the broker, or a bed or a notification service
    went silent."""
    station = current_app.extensions["ward_station"]
    return (station.version, station.connected, station.online_flags(),
            tuple((service["notifier"], service["state"]) for service in station.paging()))


@bp.route("/ward")
def page():
    return render_template("ward.html", history=current_app.extensions.get("ward_history"))


@bp.route("/api/ward")
def current():
    return jsonify(ward_view())


@bp.route("/ward/<bed_id>/alarms/<int:alarm_id>/acknowledge", methods=["POST"])
@requires("nurse")
def acknowledge(bed_id: str, alarm_id: int):
    bed = _shown_bed(bed_id)
    alarm = next((a for a in bed["alarms"] if a["alarm_id"] == alarm_id), None)
    if alarm is None:
        return _answer(f"alarm {alarm_id} is not open at bed {bed_id}: nothing was sent", 409)
    return _send(bed, "acknowledge", {"alarm_id": alarm_id}, f"acknowledge alarm {alarm_id} ({alarm['key']})")


@bp.route("/ward/<bed_id>/turn", methods=["POST"])
@requires("nurse")
def record_turn(bed_id: str):
    return _send(_shown_bed(bed_id), "record-turn", {}, "record a turn")


def _shown_bed(bed_id: str) -> dict:
    """The bed as the station shows it; 404 for one the station has never heard of."""
    bed = next((b for b in current_app.extensions["ward_station"].beds(events=False) if b["bed_id"] == bed_id), None)
    if bed is None:
        abort(404, description=f"no bed {bed_id!r} on this ward")
    return bed


def _send(bed: dict, kind: str, args: dict, what: str):
    """Journal, audit and send one command; the answer says whether the bed is there to take it now."""
    sender = current_app.extensions["ward_station"].commands
    if sender is None:
        return _answer("this station has no command journal: it only watches the beds", 503)
    try:
        command = sender.send(bed["bed_id"], kind, args, g.user.name)
    except ValueError as exc:                       # what no bed would take, e.g. a bed id longer than any may be
        return _answer(f"not sent: {exc}", 400)
    current_app.extensions["users"].audit(g.user.name, f"ward: {what}", f"bed {bed['bed_id']}, command "
                                                                        f"{command['id']}")
    when = "the bed applies it at its next frame" if bed["online"] else \
        f"the bed is offline: sent when it is back, given up after {sender.expiry_s:.0f} s"
    return _answer(f"{what} at bed {bed['bed_id']}: sent; {when}", 202, command)


def _answer(message: str, status: int, command: dict | None = None):
    return answer(message, status, "ward.page", command=command)


@bp.route("/api/ward/stream")
def stream():
    return event_stream("ward_events", ward_view, _change_key, POLL_S)
