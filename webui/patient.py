"""The patient in the bed: admit, discharge, record a turn by hand, and any earlier patient's history.

Like every action on this screen, these are commands queued in the monitor's
store and applied at its next frame, where they are logged with the events they
cause (an admission ends the last patient's clinical alarms and starts doses and
the turn clock afresh). Bad input is refused here with what is wrong, before
anything is queued; the episode's own checks (:class:`appliance.alerts.episodes.Episode`)
run here too, so the nurse hears the reason at once.
"""

from __future__ import annotations

from typing import Any

from flask import Blueprint, current_app, flash, g, redirect, render_template, request, url_for

from appliance.alerts.episodes import DEFAULT_BED_EXIT_AFTER_S, Episode
from appliance.errors import ConfigError
from webui.alarms import reader, store
from webui.clocks import clock
from webui.live import snapshot

bp = Blueprint("patient", __name__)


@bp.route("/patient")
def page():
    live = snapshot()
    with reader() as s:
        episodes = list(reversed(s.episodes()))
    return render_template("patient.html", patient=live.get("patient"), posture=live.get("posture"),
                           turn=live.get("turn") or {}, stale=live["stale"], episodes=episodes, clock=clock,
                           bed_exit_min=DEFAULT_BED_EXIT_AFTER_S / 60)


@bp.route("/patient/history/<path:patient_id>")
def history(patient_id: str):
    with reader() as s:
        events = s.patient_events(patient_id)
    return render_template("patient_history.html", patient_id=patient_id, events=events, clock=clock)


def _queue(kind: str, args: dict, what: str, message: str):
    with store() as s:
        command = s.queue_command(kind, args, g.user.name)
    current_app.extensions["users"].audit(g.user.name, what, f"{args} (command {command})")
    flash(message, "info")
    return redirect(url_for("patient.page")), 303


@bp.route("/patient/admit", methods=["POST"])
def admit():
    form = request.form
    braden: int | str | None        # a score, or what was typed for Episode to refuse by name
    try:
        braden = int(form["braden"]) if form.get("braden", "").strip() else None
    except ValueError:
        braden = form["braden"]
    try:
        after_min = float(form.get("bed_exit_after_min") or DEFAULT_BED_EXIT_AFTER_S / 60)
    except ValueError:
        after_min = float("nan")
    args: dict[str, Any] = {"patient_id": form.get("patient_id", "").strip(),
                            "name": form.get("name", "").strip() or None,
                            "braden": braden, "bed_exit_alert": form.get("bed_exit_alert") == "on",
                            "bed_exit_after_s": after_min * 60}
    try:
        Episode(admitted_s=0.0, admitted_by=g.user.name, **args)
    except ConfigError as exc:
        flash(f"not admitted: {exc}", "error")
        return page(), 400              # refused input is an error to the client too, not a redirect like success
    return _queue("admit", args, "admitted patient",
                  f"{args['patient_id']} admitted; doses and the turn clock start afresh at the monitor's next frame")


@bp.route("/patient/discharge", methods=["POST"])
def discharge():
    patient = snapshot().get("patient")
    if not patient:
        flash("no patient is admitted to this bed: nothing was discharged", "error")
        return redirect(url_for("patient.page")), 303
    return _queue("discharge", {}, "discharged patient", f"{patient['patient_id']} discharged")


@bp.route("/patient/turn", methods=["POST"])
def record_turn():
    by = request.form.get("by", "").strip() or g.user.name
    if len(by) > 100 or not by.isprintable():
        flash("who turned the patient: a name of at most 100 printable characters", "error")
        return redirect(url_for("patient.page")), 303
    return _queue("record-turn", {"by": by}, "recorded a turn", f"turn by {by} recorded; the turn clock restarts")
