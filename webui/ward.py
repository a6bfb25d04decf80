"""The ward station's screen: every bed of the ward at once, alarming beds first, each linked to its own screen.

The station (``appliance.ward.station.WardStation``) runs in this process and
keeps each bed's state from MQTT; this blueprint only shows it: as a page, as
JSON (``/api/ward``), and as a server-sent event stream sent whenever the
station took a message or a bed went on- or offline, checked four times a second.
"""

from __future__ import annotations

import time

from flask import Blueprint, current_app, jsonify, render_template

from webui.live import SIMULATED
from webui.streams import event_stream

bp = Blueprint("ward", __name__)
POLL_S = 0.25
REGIONS_SHOWN = 3       # the most loaded sites of a bed; its own screen has them all


def ward_view() -> dict:
    """The ward as the screen shows it: the broker connection, counts, and each bed in the station's order."""
    station, config = current_app.extensions["ward_station"], current_app.config["WARD"]
    now = time.time()
    beds = [_bed(bed, now, config) for bed in station.beds(events=False)]
    return {"now": now, "connected": station.connected, "stale_after_s": station.stale_after_s,
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
    """Changes when the station took a message, lost or regained the broker, or a bed went silent."""
    station = current_app.extensions["ward_station"]
    return station.version, station.connected, station.online_flags()


@bp.route("/ward")
def page():
    return render_template("ward.html")


@bp.route("/api/ward")
def current():
    return jsonify(ward_view())


@bp.route("/api/ward/stream")
def stream():
    return event_stream("ward_events", ward_view, _change_key, POLL_S)
