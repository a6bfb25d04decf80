"""The live view: the monitor's newest frame as a page, as JSON, and as a server-sent event stream.

The monitor writes ``live.json`` (``appliance.service.live``); this process only
reads it, so any number of screens costs the monitor nothing. The stream checks
the file five times a second and sends each new snapshot once; a comment line
every 15 s keeps proxies from closing an idle stream. A snapshot older than
``STALE_AFTER_FRAMES`` frames is marked stale, so a screen never shows an old map
as if it were live.
"""

from __future__ import annotations

import json
import threading
import time

from flask import Blueprint, Response, current_app, jsonify, render_template

from appliance.service.live import read_live

bp = Blueprint("live", __name__)
STALE_AFTER_FRAMES = 3
POLL_S = 0.2
HEARTBEAT_S = 15.0
STREAM_MAX_S = 600.0
"""A stream ends after this long and the browser reconnects at once (``retry``), so a client that vanished
without closing its connection holds a server thread for at most this long."""
RECONNECT_MS = 1000


def snapshot() -> dict:
    """The newest snapshot with ``stale`` and ``age_s`` added; ``{"stale": True}`` before the first one."""
    data = read_live(current_app.config["LIVE_PATH"])
    if data is None:
        return {"stale": True, "age_s": None, "message": "the monitor has not written a frame yet"}
    age = time.time() - data["written_at"]
    data["age_s"] = age
    period = data.get("wall_interval_s") or data.get("frame_interval_s", 1.0)     # wall seconds between frames
    data["stale"] = age > STALE_AFTER_FRAMES * max(float(period), 1.0)
    return data


@bp.route("/")
def page():
    return render_template("live.html")


@bp.route("/api/live")
def current():
    return jsonify(snapshot())


@bp.route("/api/live/stream")
def stream():
    path, max_s = current_app.config["LIVE_PATH"], current_app.config.get("STREAM_MAX_S", STREAM_MAX_S)
    app = current_app._get_current_object()
    shared = app.extensions.setdefault("live_events", LiveEvents())

    def events():
        started = last_beat = time.monotonic()
        last_mtime = None
        yield f"retry: {RECONNECT_MS}\n\n"
        while time.monotonic() - started < max_s:
            try:
                mtime = path.stat().st_mtime_ns
            except FileNotFoundError:
                mtime = None
            if mtime is not None and mtime != last_mtime:
                last_mtime = mtime
                with app.app_context():
                    yield shared.event(mtime)
                last_beat = time.monotonic()
            elif time.monotonic() - last_beat > HEARTBEAT_S:
                yield ": keep-alive\n\n"
                last_beat = time.monotonic()
            time.sleep(POLL_S)

    return Response(events(), mimetype="text/event-stream", headers={"Cache-Control": "no-store"})


class LiveEvents:
    """The event for each version of ``live.json``, read and encoded once for every open stream: twenty
    screens cost the server one read per frame, not twenty."""

    def __init__(self):
        self._lock = threading.Lock()
        self._mtime: int | None = None
        self._event = ""

    def event(self, mtime: int) -> str:
        with self._lock:
            if mtime != self._mtime:
                self._mtime = mtime
                self._event = f"data: {json.dumps(snapshot(), separators=(',', ':'))}\n\n"
            return self._event
