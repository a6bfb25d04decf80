"""The live view: the monitor's newest frame as a page, as JSON, and as a server-sent event stream.

The monitor writes ``live.json`` (``appliance.service.live``); this process only
reads it, so any number of screens costs the monitor nothing. The stream checks
the file five times a second and sends each new snapshot once
(``webui.streams``). A snapshot older than
``STALE_AFTER_FRAMES`` frames is marked stale, so a screen never shows an old map
as if it were live. Its age is the larger of the wall clock's (``written_at``)
and how long this process has seen the same snapshot on the monotonic clock: a
wall clock set back makes the first negative, and the second still grows.
Before its first frame the monitor writes start-up snapshots (``starting``: the
phase and the share done), which the page shows as a progress bar.
"""

from __future__ import annotations

import time

from flask import Blueprint, current_app, jsonify, render_template

from appliance.alerts.alarms import DEFAULT_MAX_AUDIO_PAUSE_S
from appliance.service.live import read_live
from webui.clocks import zone_name
from webui.streams import event_stream

bp = Blueprint("live", __name__)
SIMULATED: dict[str | None, str] = {"virtual": "SIMULATED: the virtual bed, not a patient",
                                     "emulated": "SIMULATED: an emulated front end, not a patient's mat"}
"""The banner every page shows, by the monitor's ``source``; a real front end ("hardware") shows none."""
STALE_AFTER_FRAMES = 3
STARTING_QUIET_S = 120.0
"""Start-up without a step of progress for this long is shown stale (an alarm): a cold model build's steps
come seconds apart (benchmarks/first_start.md), so a normal start never sounds the stale-data tone."""
POLL_S = 0.2
wall, monotonic = time.time, time.monotonic             # the clocks, replaceable by a test
_first_seen: dict = {}                                   # live file -> (its snapshot's identity, monotonic time)


def snapshot() -> dict:
    """The newest snapshot with ``stale`` and ``age_s`` added; ``{"stale": True}`` before the first one."""
    path = current_app.config["LIVE_PATH"]
    try:
        data = read_live(path)
    except ValueError as exc:           # damaged (a disk fault): shown as stale until the monitor rewrites it
        current_app.logger.warning("the live view %s cannot be read: %s", path, exc)
        return {"stale": True, "age_s": None,
                "message": "the monitor's newest frame cannot be read: it is written again at the next frame"}
    if data is None:
        return {"stale": True, "age_s": None, "message": "the monitor has not written a frame yet"}
    if "starting" in data:              # no map yet: how far its start-up is, for the page's progress bar
        starting, age = data["starting"], max(wall() - data["written_at"], 0.0)
        if starting.get("failed"):
            return {"stale": True, "age_s": age, "starting": starting,
                    "message": f"the monitor could not start ({starting['phase']}): call the clinical engineer"}
        return {"stale": age > STARTING_QUIET_S, "age_s": age, "starting": starting,
                "message": f"the monitor is starting: {starting['phase']}"}
    identity = (data.get("sequence"), data["written_at"])
    if _first_seen.get(path, (None,))[0] != identity:
        _first_seen[path] = (identity, monotonic())
    age = max(wall() - data["written_at"], monotonic() - _first_seen[path][1])
    data["age_s"] = age
    period = data.get("wall_interval_s") or data.get("frame_interval_s", 1.0)     # wall seconds between frames
    data["stale"] = age > STALE_AFTER_FRAMES * max(float(period), 1.0)
    return data


def simulated_banner() -> str | None:
    """The SIMULATED banner for the monitor whose ``live.json`` this screen reads, or None for real data.

    A screen with no live view (the ward station's) or none written yet shows none: the live page says so.
    """
    path = current_app.config.get("LIVE_PATH")
    try:
        data = read_live(path) if path is not None else None
    except ValueError:
        return None
    return SIMULATED.get(((data or {}).get("status") or {}).get("source"))


@bp.app_context_processor
def header_patient() -> dict:
    """``header_patient``: the admitted patient every page's header names, so no screen is read as another bed's.

    Read from ``live.json`` like the SIMULATED banner (one small file per page); None before a frame, or
    when none is admitted, or when the file cannot be read (the live view says why).
    """
    path = current_app.config.get("LIVE_PATH")
    try:
        data = read_live(path) if path is not None else None
    except ValueError:
        return {"header_patient": None}
    return {"header_patient": (data or {}).get("patient")}


@bp.route("/")
def page():
    return render_template("live.html", max_pause_min=DEFAULT_MAX_AUDIO_PAUSE_S / 60, time_zone=zone_name())


@bp.route("/api/live")
def current():
    return jsonify(snapshot())


@bp.route("/api/live/stream")
def stream():
    path = current_app.config["LIVE_PATH"]
    return event_stream("live_events", snapshot, lambda: _mtime(path), POLL_S)


def _mtime(path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return None
