"""The hospital overview: every ward at once, from the history in PostgreSQL, for the bed manager and the
night coordinator.

Per ward (in the description's order): its beds, how many were heard in the last ``HEARD_S``, its open alarms by
priority and the alarms raised in the last hour and day; then every open alarm of the hospital, highest priority
and oldest first, and the latest events. It reads (``appliance.hospital.history.reads``) and never writes: the
connection is read-only. The page is made on the server and reloads itself every ``REFRESH_S``: the ward
stations are where a nurse acts, this is where someone sees which ward needs help.
"""

from __future__ import annotations

import datetime as dt

from flask import Blueprint, current_app, jsonify, render_template

from appliance.hospital.history.reads import alarm_counts, beds_heard, open_alarms, reading, recent_events

bp = Blueprint("hospital", __name__)
HEARD_S = 180.0
"""A bed heard within this (three of the history's minutes) is reporting; the others are shown as silent."""
REACH = dt.timedelta(days=1)
"""How far back open alarms are looked for: no alarm stays unanswered that long on a working ward."""
REFRESH_S = 30
EVENTS_SHOWN = 30
PRIORITIES = ("high", "medium", "low")


def hospital_view(now: dt.datetime | None = None) -> dict:
    """The overview as data: the same for the page and ``/api/hospital``."""
    hospital = current_app.extensions["hospital"]
    now = now or dt.datetime.now(dt.UTC)
    with reading(current_app.extensions["history"]) as db:
        alarms = open_alarms(db, now - REACH)
        last_hour, last_day = alarm_counts(db, now - dt.timedelta(hours=1)), alarm_counts(db, now - REACH)
        heard = beds_heard(db, now - dt.timedelta(seconds=HEARD_S))
        events = recent_events(db, now - REACH, limit=EVENTS_SHOWN)
    wards = []
    for ward in hospital.wards:
        mine = [a for a in alarms if a["ward"] == ward.name]
        wards.append({"name": ward.name, "beds": len(ward.beds),
                      "heard": sum(bed in heard for bed in ward.beds),
                      "silent": [bed for bed in ward.beds if bed not in heard],
                      "open": {p: sum(a["priority"] == p for a in mine) for p in PRIORITIES},
                      "unacknowledged": sum(a["kind"] != "acknowledged" for a in mine),
                      "raised_last_hour": sum(last_hour.get(ward.name, {}).values()),
                      "raised_last_day": sum(last_day.get(ward.name, {}).values())})
    wards.sort(key=lambda w: tuple(-w["open"][p] for p in PRIORITIES))        # the ward that needs help first
    return {"now": now.isoformat(), "wards": wards,
            "open_alarms": [_jsonable(a) for a in alarms],
            "events": [_jsonable({k: v for k, v in e.items() if k != "body"}) for e in events]}


def _jsonable(row: dict) -> dict:
    return {k: v.isoformat() if isinstance(v, dt.datetime) else v for k, v in row.items()}


@bp.route("/hospital")
def page():
    return render_template("hospital.html", view=hospital_view(), refresh_s=REFRESH_S)


@bp.route("/api/hospital")
def current():
    return jsonify(hospital_view())
