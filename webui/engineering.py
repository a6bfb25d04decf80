"""The engineering page (engineer and admin): the thesis's operator functions on the running monitor.

The monitor daemon owns the front end, so every task (acquire, a timed series,
contact check, self-test, a new empty-mat reference, pressure calibration,
rebuilding the model, saving the map as an image, loading a calibration) is a
command queued in its store, as the alarms page queues an acknowledgement; the
page follows each one's progress through ``/api/commands/<id>``. Arguments are
checked here with the daemon's own rules (``appliance.service.engineering_tasks``),
so bad input is refused with the field and its allowed values, and nothing is
queued or audited.

What the tasks write lands in ``<data_dir>/engineering/``; the page lists it for
download, draws a readings file as bars per drive pair, and takes uploads of a
pressure calibration (JSON) or a monitor configuration (TOML), each checked
before it is saved.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path

from flask import (Blueprint, abort, current_app, flash, g, jsonify, redirect, render_template, request,
                   send_from_directory, url_for)

from appliance.core.csv_files import read_rows
from appliance.core.frames import FRAME_HEADER, load_frame
from appliance.core.pressure import check_plausible, load_pressure_calibration
from appliance.errors import ApplianceError
from appliance.files import write_atomic
from appliance.service.config_sections import read_config
from appliance.service.engineering_tasks import ENGINEERING_DIR, TASKS, checked_args, engineering_file
from webui.alarms import reader, store, wants_json
from webui.security import requires

bp = Blueprint("engineering", __name__)

RECENT_S = 24 * 3600.0
MAX_UPLOAD_BYTES = 1024 * 1024
UPLOAD_KINDS = {".json": "a pressure calibration", ".toml": "a monitor configuration"}
READINGS_PREFIXES = ("readings-", "series-")


class Refused(Exception):
    """Input the page refuses: the message says what is wrong and what is allowed."""


def folder() -> Path:
    return Path(current_app.config["STORE_PATH"]).parent / ENGINEERING_DIR


def files() -> list[dict]:
    """The engineering folder's files, newest first."""
    if not folder().is_dir():
        return []
    found = [p for p in folder().iterdir() if p.is_file() and not p.name.endswith(".tmp")]
    found.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    return [{"name": p.name, "bytes": p.stat().st_size, "modified_s": p.stat().st_mtime,
             "readings": p.suffix == ".csv" and p.name.startswith(READINGS_PREFIXES)} for p in found]


def _page(error: str | None = None, status: int = 200):
    with reader() as s:
        commands = s.commands_since(time.time() - RECENT_S, TASKS)
    listed = files()
    return render_template("engineering.html", commands=commands, files=listed, error=error, tasks=TASKS,
                           calibrations=[f["name"] for f in listed if f["name"].endswith(".json")],
                           readings=[f["name"] for f in listed if f["readings"]]), status


def _refuse(message: str):
    if wants_json():
        return jsonify({"error": message}), 400
    return _page(message, 400)


@bp.route("/engineering")
@requires("engineer")
def page():
    return _page()


@bp.route("/engineering/<task>", methods=["POST"])
@requires("engineer")
def run_task(task: str):
    if task not in TASKS:
        abort(404, description=f"no engineering task {task!r}: one of {', '.join(TASKS)}")
    if request.is_json:
        fields = request.get_json(silent=True)
        if not isinstance(fields, dict):
            return _refuse(f"{task}: send the arguments as a JSON object")
    else:
        fields = {name: request.form[name] for name in TASKS[task] if name in request.form}
    try:
        args = checked_args(task, fields)
    except ValueError as exc:
        return _refuse(str(exc))
    if "file" in args and not (folder() / args["file"]).is_file():     # refused now, not when the monitor runs it
        return _refuse(f"{task}: no file {args['file']} in {ENGINEERING_DIR}/")
    with store() as s:
        command = s.queue_command(task, args, g.user.name)
    current_app.extensions["users"].audit(g.user.name, "engineering task",
                                          f"{task} {json.dumps(args, sort_keys=True)} (command {command})")
    if wants_json():
        return jsonify({"command_id": command, "task": task, "args": args}), 202
    flash(f"{task} queued (command {command}); the monitor runs it between frames", "info")
    return redirect(url_for("engineering.page")), 303


@bp.route("/api/engineering/files")
@requires("engineer")
def file_list():
    return jsonify(files())


@bp.route("/engineering/files/<name>")
@requires("engineer")
def download(name: str):
    try:
        path = engineering_file(folder().parent, name)
    except ValueError as exc:
        abort(400, description=str(exc))
    if not path.is_file():
        abort(404, description=f"no file {name} in {ENGINEERING_DIR}/")
    return send_from_directory(folder(), path.name, as_attachment=True)


@bp.route("/api/engineering/readings/<name>")
@requires("engineer")
def readings(name: str):
    """A saved readings file as JSON: one group per drive pair (projection), its readings in file order."""
    try:
        path = engineering_file(folder().parent, name)
    except ValueError as exc:
        return jsonify({"error": str(exc)}), 400
    if not path.is_file():
        return jsonify({"error": f"no file {name} in {ENGINEERING_DIR}/"}), 404
    try:
        frame = load_frame(path, _highest_electrode(path))
    except (ApplianceError, ValueError) as exc:
        return jsonify({"error": str(exc)}), 400
    groups: dict[tuple[int, int], list] = {}
    for (a, b, m, n), v in zip(frame.protocol.readings.tolist(), frame.volts.tolist()):
        groups.setdefault((a, b), []).append({"measure": [m, n], "volts": None if math.isnan(v) else v})
    finite = [v for v in frame.volts.tolist() if not math.isnan(v)]
    return jsonify({"file": path.name, "readings": len(frame.volts), "usable": len(finite),
                    "min_volts": min(finite, default=None), "max_volts": max(finite, default=None),
                    "groups": [{"drive": list(drive), "readings": rows} for drive, rows in groups.items()]})


def _highest_electrode(path: Path) -> int:
    """The highest electrode number a frame file names: ``load_frame`` checks every row against it."""
    highest = 2
    for _, row in read_rows(path, FRAME_HEADER, "frame file"):
        highest = max([highest] + [int(cell) for cell in row[:4] if cell.strip().isdigit()])
    return highest


@bp.route("/engineering/upload", methods=["POST"])
@requires("engineer")
def upload():
    sent = request.files.get("file")
    try:
        if sent is None or not sent.filename:
            raise Refused("choose a file to upload (a pressure calibration .json or a monitor configuration .toml)")
        try:
            target = engineering_file(folder().parent, sent.filename)
        except ValueError as exc:
            raise Refused(str(exc)) from None
        kind = UPLOAD_KINDS.get(target.suffix.lower())
        if kind is None:
            raise Refused(f"file: {sent.filename} is neither .json (a pressure calibration) nor .toml (a monitor "
                          "configuration)")
        if target.exists():
            raise Refused(f"file: {target.name} is already in {ENGINEERING_DIR}/; rename the upload")
        with sent.stream:                          # a large upload is spooled to a temporary file: close it
            content = sent.stream.read(MAX_UPLOAD_BYTES + 1)
        if len(content) > MAX_UPLOAD_BYTES:
            raise Refused(f"file: {sent.filename} is over the {MAX_UPLOAD_BYTES // 1024} KiB an upload may be")
        _check_upload(target.name, content)
    except Refused as exc:
        return _refuse(str(exc))
    folder().mkdir(parents=True, exist_ok=True)
    write_atomic(target, content)
    current_app.extensions["users"].audit(g.user.name, "engineering upload", f"{target.name} ({kind})")
    if wants_json():
        return jsonify({"file": target.name, "kind": kind}), 201
    flash(f"{target.name} saved ({kind}); load a calibration with Load to use it", "info")
    return redirect(url_for("engineering.page")), 303


def _check_upload(name: str, content: bytes) -> None:
    """Refuse an upload that is not what its name says: a pressure calibration (.json) or a monitor
    configuration (.toml), each read by the monitor's own reader (a configuration's every section; its board
    profile and scenario, which the front end's and the simulator's data judge, are checked when the monitor
    starts with it, as ``appliance run --check-config`` does)."""
    try:
        text = content.decode("utf-8")
    except UnicodeDecodeError:
        raise Refused(f"file: {name} is not UTF-8 text") from None
    if name.lower().endswith(".json"):
        try:
            json.loads(text)
        except json.JSONDecodeError as exc:
            raise Refused(f"file: {name} is not valid JSON ({exc})") from None
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / name
        path.write_bytes(content)
        try:
            if name.lower().endswith(".json"):
                check_plausible(load_pressure_calibration(path), name)
            else:
                read_config(path)
        except (ApplianceError, ValueError) as exc:
            raise Refused(f"file: {str(exc).replace(str(path), name)}") from None
