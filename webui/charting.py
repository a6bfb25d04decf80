"""Charting (admin): the HL7 v2 interface engine the bed charts to, its queue's state, and the FHIR API's tokens.

The target is the configuration's ``[charting.hl7]`` table. A new one is
checked by the configuration's own rules (a host name or IP address, a port
from 1 to 65535, HL7 names without its delimiters), written whole to the
settings file beside the bed's other settings, queued as an ``apply-settings``
command, which the monitor takes at its next frame by remaking its charting
link over the same queue (:mod:`appliance.service.charting_target`), and
audited with each changed key's old and new value. A value that is not accepted
is answered 400 naming the field; nothing is written, queued or audited. The
queue's state (messages waiting, delivered, refused, the last error) is the
monitor's, read from its live view.

A FHIR API token is made here as ``appliance fhir-token`` makes one
(:mod:`appliance.store.api_tokens`): shown once, on the page that answers, and
kept only as a hash; a revoked token is refused at its next request. Each is
audited by the client's name, never the token.
"""

from __future__ import annotations

import dataclasses
import time

from flask import Blueprint, current_app, flash, g, redirect, render_template, request, url_for

from appliance.errors import ConfigError
from appliance.service import settings as monitor_settings
from appliance.service.charting_target import hl7_values
from appliance.service.config_sections import HL7_KEYS, Hl7Settings, read_sections
from appliance.store.api_tokens import TOKENS_FILE, ApiTokens
from webui.alarms import store
from webui.clocks import clock
from webui.live import snapshot
from webui.security import requires
from webui.settings import SettingsRefused, as_number, current, settings_file

bp = Blueprint("charting", __name__)
LABELS = {"host": "Interface engine host (name or IP address)", "port": "Port (1-65535)",
          "enabled": "Send charting", "sending_facility": "Sending facility (MSH-4)",
          "sending_application": "Sending application (MSH-3)",
          "receiving_application": "Receiving application (MSH-5)",
          "receiving_facility": "Receiving facility (MSH-6)", "ack_timeout_s": "Wait for an ACK (s)",
          "undelivered_alarm_s": "Technical alarm when unacknowledged for (s)",
          "observation_interval_s": "Chart peak pressures every (s)"}
DEFAULTS = {f.name: f.default for f in dataclasses.fields(Hl7Settings) if f.default is not dataclasses.MISSING}
"""Keys with a default, which a field left empty takes."""
NUMBERS = {"port", "ack_timeout_s", "undelivered_alarm_s", "observation_interval_s"}


def tokens() -> ApiTokens:
    return ApiTokens(current_app.config["STORE_PATH"].parent / TOKENS_FILE)


def target(state: dict) -> tuple[dict, str]:
    """The target as shown (the ``[charting.hl7]`` keys and values, {} when there is none) and where it comes
    from: the settings file, the monitor (its configuration), or none."""
    saved = state["saved"].get(monitor_settings.CHARTING, {}).get("hl7")
    if saved:
        return hl7_values(read_sections({"charting": {"hl7": saved}}).hl7), "settings file"
    with_monitor = ((state["running"] or {}).get(monitor_settings.CHARTING) or {}).get("hl7")
    return (with_monitor, "monitor") if with_monitor else ({}, "none")


def _page(error: str | None = None, status: int = 200, new_token: tuple[str, str] | None = None):
    state = current()
    values, source = target(state)
    live = snapshot()
    response = current_app.make_response((render_template(
        "charting.html", error=error, labels=LABELS, keys=HL7_KEYS, values=values, source=source,
        defaults=DEFAULTS, queue=live.get("charting"), stale=live.get("stale", True),
        file_error=state["file_error"], tokens=tokens().made(), new_token=new_token, clock=clock), status))
    if new_token is not None:
        response.headers["Cache-Control"] = "no-store"        # the token is shown once: no copy in a cache
    return response


@bp.route("/charting")
@requires("admin")
def page():
    return _page()


@bp.route("/charting/hl7", methods=["POST"])
@requires("admin")
def change_target():
    try:
        changed, command = _apply()
    except SettingsRefused as exc:
        return _page(error=f"charting target not changed: {exc}", status=exc.status)
    if changed:
        flash(f"charting target changed: {monitor_settings.describe(changed)}; the monitor applies it at its next "
              f"frame (command {command})", "info")
    else:
        flash("nothing changed in the charting target", "info")
    return redirect(url_for("charting.page")), 303


def _apply() -> tuple[list, int | None]:
    """The keys changed (key, old, new) and the queued command's id (None when nothing changed)."""
    state = current()
    if state["file_error"]:
        raise SettingsRefused(f"{state['file_error']}: an engineer must fix or remove it first", 409)
    old, _ = target(state)
    sent = _submitted()
    try:
        new = hl7_values(read_sections({"charting": {"hl7": sent}}).hl7)
    except ConfigError as exc:
        raise SettingsRefused(str(exc)) from None
    changed = monitor_settings.changes({"hl7": old}, {"hl7": new})
    if not changed:
        return [], None
    tables = {**state["saved"], monitor_settings.CHARTING: {"hl7": new}}
    try:
        monitor_settings.write_settings(settings_file(), tables)
    except ConfigError as exc:
        raise SettingsRefused(str(exc)) from None
    with store() as s:
        command = s.queue_command(monitor_settings.COMMAND, {monitor_settings.CHARTING: {"hl7": new}}, g.user.name)
    current_app.extensions["users"].audit(g.user.name, "changed charting target",
                                          f"{monitor_settings.describe(changed)} (command {command})")
    return changed, command


def _submitted() -> dict:
    """The form as a ``[charting.hl7]`` table: numbers read as numbers, the tick box as true or false, an optional
    field left empty as its default; anything else as sent, for the configuration's check to name."""
    form = request.form.to_dict()
    form.pop("csrf_token", None)
    unknown = sorted(set(form) - set(HL7_KEYS))
    if unknown:
        raise SettingsRefused(f"unknown field {unknown[0]!r}; the target has {', '.join(HL7_KEYS)}")
    table: dict = {"enabled": form.pop("enabled", "") in ("on", "true", "1")}
    for key, value in form.items():
        value = value.strip()
        if value or key not in DEFAULTS:
            table[key] = as_number(value) if key in NUMBERS else value
    return table


@bp.route("/charting/tokens", methods=["POST"])
@requires("admin")
def make_token():
    name = request.form.get("name", "").strip()
    try:
        token = tokens().create(name, time.time())
    except ConfigError as exc:
        return _page(error=f"no token made: {exc}", status=400)
    current_app.extensions["users"].audit(g.user.name, "made FHIR API token", name)
    return _page(status=201, new_token=(name, token))


@bp.route("/charting/tokens/<name>/revoke", methods=["POST"])
@requires("admin")
def revoke_token(name: str):
    if not tokens().revoke(name):
        return _page(error=f"no token revoked: no token is named {name!r}", status=404)
    current_app.extensions["users"].audit(g.user.name, "revoked FHIR API token", name)
    flash(f"the FHIR API token of {name} is revoked: its next request is refused", "info")
    return redirect(url_for("charting.page")), 303
