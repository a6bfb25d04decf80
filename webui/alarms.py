"""Alarms: the open ones with acknowledge and audio pause, and the history of who did what and when.

The screen does not touch the alarm engine: it queues a command in the monitor's
store (``appliance.db``), which the monitor applies at its next frame and logs
with the events it causes. A request for an alarm that is not open, or a pause
outside what the standard allows, is refused with the reason and queues nothing;
every request that is queued is also in the screen's audit log. The live view
sends the same forms with ``fetch`` and asks for JSON: it gets the message and
the command's id instead of a redirect, and stays on the page.
"""

from __future__ import annotations

import time
from pathlib import Path

from flask import Blueprint, abort, current_app, flash, g, jsonify, redirect, render_template, request, url_for

from appliance.alerts.alarms import DEFAULT_MAX_AUDIO_PAUSE_S
from appliance.store import Store
from webui.clocks import clock
from webui.live import snapshot

bp = Blueprint("alarms", __name__)
HISTORY_S = 24 * 3600.0


def wants_json() -> bool:
    """Whether the request came from a script asking for JSON rather than from a form."""
    return request.is_json or request.accept_mimetypes.best == "application/json"


def store() -> Store:
    """The monitor's store opened to queue a command: a write, which waits its turn behind the monitor's."""
    return Store.open(current_app.config["STORE_PATH"])


def reader() -> Store:
    """The monitor's store opened to read, for a page view: it takes no write lock, so a view neither waits for
    the monitor's commit nor holds it up. A store no monitor has made yet is made first (no monitor to wait for)."""
    path = Path(current_app.config["STORE_PATH"])
    if not path.exists():
        Store.open(path).close()
    return Store.open_read_only(path)


@bp.route("/alarms")
def page():
    live = snapshot()
    with reader() as s:
        last = s.last_time() or 0.0
        history = list(reversed(s.events_since(last - HISTORY_S)))
    return render_template("alarms.html", alarms=live.get("alarms", []), stale=live["stale"], history=history,
                           clock=clock, max_pause_min=DEFAULT_MAX_AUDIO_PAUSE_S / 60)


@bp.route("/alarms/<int:alarm_id>/acknowledge", methods=["POST"])
def acknowledge(alarm_id: int):
    open_alarms = {a["alarm_id"]: a for a in snapshot().get("alarms", [])}
    if alarm_id not in open_alarms:
        return _answer(f"alarm {alarm_id} is not open: nothing was acknowledged", 409)
    with store() as s:
        command = s.queue_command("acknowledge", {"alarm_id": alarm_id}, g.user.name)
    current_app.extensions["users"].audit(g.user.name, "acknowledged alarm",
                                          f"{alarm_id} {open_alarms[alarm_id]['key']} (command {command})")
    return _answer(f"alarm {alarm_id} acknowledged; the monitor applies it at its next frame", 202, command)


@bp.route("/alarms/pause-audio", methods=["POST"])
def pause_audio():
    """Pause every alarm's sound, or with ``alarm_id`` only that open alarm's, for ``minutes``."""
    try:
        minutes = float(request.form.get("minutes", ""))
    except ValueError:
        minutes = float("nan")
    if not 0 < minutes <= DEFAULT_MAX_AUDIO_PAUSE_S / 60:
        return _answer(f"an audio pause lasts more than 0 and at most {DEFAULT_MAX_AUDIO_PAUSE_S / 60:g} minutes "
                       f"(IEC 60601-1-8); got {request.form.get('minutes', '')!r}", 400)
    args: dict = {"duration_s": minutes * 60}
    which = "alarm audio"
    if request.form.get("alarm_id"):
        open_ids = {a["alarm_id"] for a in snapshot().get("alarms", [])}
        alarm_id = request.form["alarm_id"]
        if not alarm_id.isdigit() or int(alarm_id) not in open_ids:
            return _answer(f"alarm {alarm_id!r} is not open: no sound was paused", 409)
        args["alarm_id"] = int(alarm_id)
        which = f"alarm {alarm_id}'s audio"
    with store() as s:
        command = s.queue_command("pause-audio", args, g.user.name)
    current_app.extensions["users"].audit(g.user.name, "paused alarm audio",
                                          f"{which}, {minutes:g} min (command {command})")
    return _answer(f"{which} paused for {minutes:g} min", 202, command)


def _answer(message: str, status: int, command: int | None = None):
    return answer(message, status, "alarms.page", command_id=command)


def answer(message: str, status: int, page: str, **found):
    """A JSON answer (the message and ``found``) for a page's ``fetch``; for a form, the message flashed on
    ``page``, as news when the request was taken (a status below 400) and as an error when not."""
    if wants_json():
        return jsonify({"message": message, **found}), status
    flash(message, "info" if status < 400 else "error")
    return redirect(url_for(page)), 303


@bp.route("/api/commands/<int:command_id>")
def command_state(command_id: int):
    with reader() as s:
        command = s.command(command_id)
    if command is None:
        abort(404, description=f"no command {command_id}")
    return jsonify({**command, "checked_at": time.time()})
