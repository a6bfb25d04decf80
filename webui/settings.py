"""Settings: the patient's (nurse), the bed's (engineer) and the site's clock (admin), shown with where each value
comes from, and changed.

A change is checked by the monitor configuration's own rules, written to the
settings file in the data directory (``appliance.service.settings``), queued as
an ``apply-settings`` command that the monitor applies at its next frame, and
audited with each old and new value. A value that is not accepted is answered
with HTTP 400 naming the field and what it may be, and nothing is written,
queued or audited; a form sent back unchanged queues nothing. A new mat layout
needs another reconstruction model, so it applies when the monitor restarts.
The time zone, an IANA name, sets the clock times of every page, the live view
and the shift report.

Each patient setting that could blind the monitor has a safe range
(``appliance.alerts.limits``); inside it the ward's policy, which only an admin
changes (audited with the old and new spans), bounds what a nurse may set. Both
are checked where the settings file is, so a form, a JSON body and a loaded file
meet the same limits.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from flask import Blueprint, Response, current_app, flash, g, jsonify, redirect, render_template, request, url_for

from appliance.alerts.dose import BUILT_IN as BUILT_IN_CURVES
from appliance.alerts.dose import RECOVERY_MODES
from appliance.alerts.limits import POLICY, SAFE_RANGES, check_policy, check_within_policy, span_text
from appliance.core.named_layouts import BUILTIN_NAMES
from appliance.errors import ConfigError
from appliance.service import settings as monitor_settings
from appliance.service.config_sections import read_sections
from webui.alarms import reader, store
from webui.security import requires

bp = Blueprint("settings", __name__)
HISTORY_S = 24 * 3600.0
MAX_FILE_BYTES = 64 * 1024
FORMS = {"patient": ("alerts", tuple(monitor_settings.PATIENT_FIELDS)),
         "bed": ("monitor", monitor_settings.BED_KEYS),
         "clock": ("monitor", monitor_settings.CLOCK_KEYS)}
"""Each form: the settings file's table it changes, and its keys there."""
ADMIN_KEYS = monitor_settings.CLOCK_KEYS
"""Settings only an admin changes, on this page: not saved to or loaded from a settings file."""
LABELS = {"threshold_mmhg": "Pressure threshold (mmHg)", "curve": "Tolerance curve",
          "alarm_dose": "Alarm at dose (share of tolerance)", "recovery": "Dose recovery off load",
          "relief_min": "Offloaded this long relieves a site (min)",
          "turn_interval_min": "Turn interval (min)",
          "turn_grace_min": "A due turn is overdue after (min)",
          "reminder_repeat_min": "Repeat an overdue reminder every (min)",
          "escalate_after_min": "Escalate an unacknowledged alarm after (min)",
          "bed_id": "Bed id", "layout": "Mat layout",
          "time_zone": "Time zone of the clock times shown (IANA name, such as Europe/London)"}
CHOICES = {"curve": tuple(BUILT_IN_CURVES), "recovery": tuple(RECOVERY_MODES), "layout": BUILTIN_NAMES}


class SettingsRefused(Exception):
    """A change that cannot be made; ``status`` is the HTTP status to answer with."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


def settings_file():
    """The settings file in the monitor's data directory, beside its store."""
    return monitor_settings.settings_path(current_app.config["STORE_PATH"].parent)


def current() -> dict:
    """The settings as shown: each one's value and where it comes from (settings file, monitor, default), the
    file's tables (``saved``), the layout the monitor runs, and the error of a settings file that cannot be read."""
    try:
        saved, file_error = monitor_settings.read_settings(settings_file()), None
    except ConfigError as exc:
        saved, file_error = {}, str(exc)
    with reader() as s:
        running = s.load_state(monitor_settings.STATE)
    shown_running = running or {}
    defaults = monitor_settings.settings_values(read_sections({}))
    values: dict[str, dict] = {}
    for section, table in defaults.items():
        values[section] = {}
        for key, default in table.items():
            if key in saved.get(section, {}):
                values[section][key] = {"value": saved[section][key], "source": "settings file"}
            elif key in shown_running.get(section, {}):
                values[section][key] = {"value": shown_running[section][key], "source": "monitor"}
            else:
                values[section][key] = {"value": default, "source": "default"}
    running_layout = running["monitor"]["layout"] if running is not None else None
    policy = monitor_settings.policy_of(saved) if file_error is None else check_policy({})
    return {"settings": values, "file": str(settings_file()), "file_error": file_error, "saved": saved,
            "running": running,
            "policy": {key: {"low": low, "high": high, "safe_low": SAFE_RANGES[key].low,
                             "safe_high": SAFE_RANGES[key].high, "unit": SAFE_RANGES[key].unit}
                       for key, (low, high) in policy.items()},
            "running_layout": running_layout,
            "restart_pending": running_layout is not None and values["monitor"]["layout"]["value"] != running_layout}


@bp.route("/settings")
def page():
    return _page()


@bp.route("/api/settings")
def api():
    state = current()
    return jsonify({key: state[key] for key in ("settings", "policy", "file", "file_error", "running_layout",
                                                "restart_pending")})


@bp.route("/settings/patient", methods=["POST"])
def patient():
    return _change("patient")


@bp.route("/settings/bed", methods=["POST"])
@requires("engineer")
def bed():
    return _change("bed")


@bp.route("/settings/clock", methods=["POST"])
@requires("admin")
def clock():
    return _change("clock")


@bp.route("/settings/policy", methods=["POST"])
@requires("admin")
def policy():
    """The ward policy: a [low, high] span per setting inside its safe range; only an admin changes it."""
    try:
        changed = _apply_policy()
    except SettingsRefused as exc:
        message = f"ward policy not changed: {exc}"
        if request.is_json:
            return jsonify({"error": message}), exc.status
        return _page(error=message, status=exc.status)
    message = (f"ward policy changed: {_describe_spans(changed)}" if changed else "nothing changed in the ward policy")
    if request.is_json:
        return jsonify({"message": message, "changed": [{"key": k, "old": list(old), "new": list(new)}
                                                        for k, old, new in changed]})
    flash(message, "info")
    return redirect(url_for("settings.page")), 303


def _apply_policy() -> list[tuple[str, tuple, tuple]]:
    """The spans changed (key, old, new); the policy written to the settings file and audited."""
    state = current()
    if state["file_error"]:
        raise SettingsRefused(f"{state['file_error']}: an engineer must fix or remove it first", 409)
    old = {key: (entry["low"], entry["high"]) for key, entry in state["policy"].items()}
    wanted = dict(old)
    for key, span in _submitted_policy(old).items():
        wanted[key] = span
    try:
        table = {key: list(span) for key, span in wanted.items()
                 if span != (SAFE_RANGES[key].low, SAFE_RANGES[key].high)}
        check_policy(table)
        check_within_policy({key: entry["value"] for key, entry in state["settings"]["alerts"].items()},
                            check_policy(table))
    except ConfigError as exc:
        raise SettingsRefused(f"{exc}; change the setting first" if "outside the ward policy" in str(exc)
                              else str(exc)) from None
    changed = [(key, old[key], wanted[key]) for key in wanted if wanted[key] != old[key]]
    if not changed:
        return []
    saved = {**state["saved"], POLICY: table}
    monitor_settings.write_settings(settings_file(), {k: v for k, v in saved.items() if v})
    current_app.extensions["users"].audit(g.user.name, "changed ward policy", _describe_spans(changed))
    return changed


def _submitted_policy(old: dict) -> dict[str, tuple[float, float]]:
    """The spans sent: a JSON object ``{key: [low, high]}``, or a form's ``<key>_low`` and ``<key>_high``."""
    if request.is_json:
        data = request.get_json(silent=True)
        if not isinstance(data, dict):
            raise SettingsRefused("send the policy as a form or a JSON object")
        sent = data
    else:
        form = request.form.to_dict()
        form.pop("csrf_token", None)
        sent = {}
        for name, value in form.items():
            key, _, end = name.rpartition("_")
            if key not in SAFE_RANGES or end not in ("low", "high"):
                raise SettingsRefused(f"unknown field {name!r}; the policy has <setting>_low and <setting>_high")
            span = list(sent.get(key, old[key]))
            span[0 if end == "low" else 1] = as_number(value)
            sent[key] = span
    unknown = sorted(set(sent) - set(SAFE_RANGES))
    if unknown:
        raise SettingsRefused(f"unknown setting {unknown[0]!r}; a policy bounds {', '.join(SAFE_RANGES)}")
    try:
        checked = check_policy(sent)
    except ConfigError as exc:
        raise SettingsRefused(str(exc)) from None
    return {key: checked[key] for key in sent}


def _describe_spans(changed) -> str:
    """``threshold_mmhg 20-60 -> 28-40 mmHg``."""
    return ", ".join(f"{key} {span_text(low, high)} -> {span_text(new_low, new_high, SAFE_RANGES[key].unit)}"
                     for key, (low, high), (new_low, new_high) in changed)


@bp.route("/settings/file")
@requires("engineer")
def save_file():
    """Every setting as the monitor runs with it, as a settings file to keep or to load on another bed."""
    state = current()
    values = {section: {key: entry["value"] for key, entry in table.items() if key not in ADMIN_KEYS}
              for section, table in state["settings"].items()}
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    bed = values["monitor"]["bed_id"]
    return Response(monitor_settings.settings_text(values), mimetype="application/toml",
                    headers={"Content-Disposition": f'attachment; filename="settings-{bed}-{stamp}.toml"'})


@bp.route("/settings/file", methods=["POST"])
@requires("engineer")
def load_file():
    """A settings file (as saved above) checked, then taken like a form: what differs is written, queued for
    the monitor and audited."""
    try:
        changed, command = _load(request.files.get("file"))
    except SettingsRefused as exc:
        return _page(error=f"settings not loaded: {exc}", status=exc.status)
    if not changed:
        flash("the file holds the settings already in use: nothing changed", "info")
    else:
        flash(f"settings loaded: {monitor_settings.describe(changed)}; the monitor applies them at its next frame",
              "info")
    return redirect(url_for("settings.page")), 303


def _load(sent) -> tuple[list, int | None]:
    if sent is None or not sent.filename:
        raise SettingsRefused("choose a settings file (.toml) to load")
    content = sent.stream.read(MAX_FILE_BYTES + 1)
    if len(content) > MAX_FILE_BYTES:
        raise SettingsRefused(f"file: {sent.filename} is over the {MAX_FILE_BYTES // 1024} KiB a settings file may be")
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / "settings.toml"
        path.write_bytes(content)
        try:
            loaded = monitor_settings.read_settings(path)
        except ConfigError as exc:
            raise SettingsRefused(str(exc).replace(str(path), sent.filename)) from None
    if POLICY in loaded:
        raise SettingsRefused(f"{sent.filename} holds a [{POLICY}]: the ward policy is set on this page by an "
                              "admin, not loaded from a file")
    if monitor_settings.CHARTING in loaded:
        raise SettingsRefused(f"{sent.filename} holds a [charting.hl7]: the charting target is set on the Charting "
                              "page by an admin, not loaded from a file")
    admin = sorted(set(loaded.get("monitor", {})) & set(ADMIN_KEYS))
    if admin:
        raise SettingsRefused(f"{sent.filename} sets {admin[0]}: it is set on this page by an admin, not loaded "
                              "from a file")
    state = current()
    if state["file_error"]:
        raise SettingsRefused(f"{state['file_error']}: an engineer must fix or remove it first", 409)
    changed: list[tuple] = []
    tables: dict[str, dict] = {}
    for section, table in loaded.items():
        for key, value in table.items():
            old = state["settings"][section][key]["value"]
            if not monitor_settings.same(old, value):
                changed.append((key, old, value))
                tables.setdefault(section, {})[key] = value
    if not changed:
        return [], None
    saved = {section: {**state["saved"].get(section, {}), **tables.get(section, {})}
             for section in ("alerts", "monitor")}
    try:
        monitor_settings.write_settings(settings_file(), {k: v for k, v in {**state["saved"], **saved}.items() if v})
    except ConfigError as exc:
        raise SettingsRefused(str(exc)) from None
    with store() as s:
        command = s.queue_command(monitor_settings.COMMAND, {k: v for k, v in saved.items() if v}, g.user.name)
    current_app.extensions["users"].audit(g.user.name, "loaded settings",
                                          f"{sent.filename}: {monitor_settings.describe(changed)} (command {command})")
    return changed, command


def _change(group: str):
    """Check, write, queue and audit the changed fields of form ``group`` (or its JSON body)."""
    try:
        changed, command = _apply(group)
    except SettingsRefused as exc:
        message = f"{group} settings not changed: {exc}"
        if request.is_json:
            return jsonify({"error": message}), exc.status
        return _page(error=message, status=exc.status)
    if not changed:
        message = f"nothing changed in the {group} settings"
    else:
        later = " (the layout applies when the monitor restarts)" if any(c[0] == "layout" for c in changed) else ""
        message = (f"{group} settings changed: {monitor_settings.describe(changed)}; the monitor applies them at its "
                   f"next frame{later}")
    if request.is_json:
        return jsonify({"message": message, "command": command,
                        "changed": [{"key": k, "old": old, "new": new} for k, old, new in changed]})
    flash(message, "info")
    return redirect(url_for("settings.page")), 303


def _apply(group: str) -> tuple[list, int | None]:
    """The changes made and the queued command's id (None when nothing changed)."""
    state = current()
    if state["file_error"]:
        raise SettingsRefused(f"{state['file_error']}: an engineer must fix or remove it first", 409)
    section, keys = FORMS[group]
    values = {key: state["settings"][section][key]["value"] for key in keys}
    submitted = _submitted(group, values)
    changed = [(key, values[key], value) for key, value in submitted.items()
               if not monitor_settings.same(values[key], value)]
    if not changed:
        return [], None
    saved = {**state["saved"], section: {**state["saved"].get(section, {}), **{k: new for k, _, new in changed}}}
    try:
        monitor_settings.write_settings(settings_file(), saved)
    except ConfigError as exc:
        raise SettingsRefused(str(exc)) from None
    with store() as s:
        command = s.queue_command(monitor_settings.COMMAND, {section: saved[section]}, g.user.name)
    current_app.extensions["users"].audit(g.user.name, "changed settings",
                                          f"{monitor_settings.describe(changed)} (command {command})")
    return changed, command


def _submitted(group: str, values: dict) -> dict:
    """The fields sent in form ``group``: a form's text as numbers where the setting is a number."""
    data = request.get_json(silent=True) if request.is_json else request.form.to_dict()
    if not isinstance(data, dict):
        raise SettingsRefused("send the settings as a form or a JSON object")
    data.pop("csrf_token", None)
    allowed = FORMS[group][1]
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise SettingsRefused(f"unknown field {unknown[0]!r}; {group} settings are {', '.join(allowed)}")
    return {key: as_number(value) if isinstance(values[key], (int, float)) else value for key, value in data.items()}


def as_number(value):
    """A form's text as an int or float when it reads as one; anything else as it came, for the check to name."""
    if not isinstance(value, str):
        return value
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            continue
    return value


def _page(error: str | None = None, status: int = 200):
    state = current()
    with reader() as s:
        history = s.commands_since(time.time() - HISTORY_S, [monitor_settings.COMMAND])
    return render_template("settings.html", state=state, error=error, labels=LABELS, choices=_choices(state),
                           forms=FORMS, history=history, restart_note=monitor_settings.RESTART_NOTE,
                           shown=monitor_settings.shown, span_text=span_text), status


def _choices(state: dict) -> dict:
    """Each choice field's options, the current value first when it is none of them (a ward's own curve)."""
    options = {}
    for table in state["settings"].values():
        for key in table.keys() & CHOICES.keys():
            value = table[key]["value"]
            options[key] = CHOICES[key] if value in CHOICES[key] else (value, *CHOICES[key])
    return options
