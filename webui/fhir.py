"""The read-only FHIR R4 API: the bed's patients and their observations for the hospital's systems.

``GET /fhir/Patient``, ``/fhir/Patient/<id>`` and
``/fhir/Observation?patient=<id>&date=ge<when>&date=le<when>`` answer in FHIR
JSON (searchset Bundles for searches; :mod:`appliance.charting.fhir` makes the
resources). A machine, not a nurse, calls it, so it is authorised by a bearer
token (``appliance fhir-token --create NAME``), not a login: none or a wrong
one is 401. A search parameter this API does not know, or a value it cannot
read, is 400 with an OperationOutcome naming it, rather than a silently wider
answer.
"""

from __future__ import annotations

import datetime
import json
import math

from flask import Blueprint, Response, current_app, request

from appliance.charting import fhir
from appliance.store.api_tokens import TOKENS_FILE, ApiTokens
from webui.alarms import reader
from webui.live import snapshot

PREFIX = "/fhir"
bp = Blueprint("fhir", __name__, url_prefix=PREFIX)

MEDIA_TYPE = "application/fhir+json"
DATE_PREFIXES = ("ge", "gt", "le", "lt")


class BadSearch(ValueError):
    """A search parameter that cannot be answered; the message names it."""


def answer(body: dict, status: int = 200, **headers) -> Response:
    return Response(json.dumps(body), status=status, mimetype=MEDIA_TYPE, headers=headers)


@bp.before_request
def authorise() -> Response | None:
    scheme, _, token = request.headers.get("Authorization", "").partition(" ")
    tokens = ApiTokens(current_app.config["STORE_PATH"].parent / TOKENS_FILE)
    if scheme.lower() != "bearer" or not token.strip() or tokens.client(token.strip()) is None:
        return answer(fhir.outcome("a bearer token is needed (appliance fhir-token --create NAME makes one)",
                                   "login"), 401, **{"WWW-Authenticate": 'Bearer realm="fhir"'})
    return None


@bp.errorhandler(BadSearch)
def bad_search(exc: BadSearch) -> Response:
    return answer(fhir.outcome(str(exc)), 400)


def only(allowed: set[str]) -> None:
    unknown = sorted(set(request.args) - allowed)
    if unknown:
        raise BadSearch(f"unknown search parameter(s) {', '.join(unknown)}; this API reads "
                        f"{', '.join(sorted(allowed)) or 'none here'}")


def names() -> dict[str, str]:
    """The admitted patient's name (the live view has it; the store keeps only the patient id)."""
    patient = snapshot().get("patient") or {}
    return {patient["patient_id"]: patient["name"]} if patient.get("name") else {}


def base_url() -> str:
    return request.url_root.rstrip("/") + PREFIX


@bp.route("/Patient")
def patients():
    only(set())
    with reader() as s:
        found = fhir.patients(s.episodes(), names())
    return answer(fhir.searchset(found, request.url, base_url()))


@bp.route("/Patient/<ident>")
def patient(ident: str):
    with reader() as s:
        found = [p for p in fhir.patients(s.episodes(), names()) if p["id"] == ident]
    if not found:
        return answer(fhir.outcome(f"no Patient {ident}", "not-found"), 404)
    return answer(found[0])


@bp.route("/Observation")
def observations():
    only({"patient", "date"})
    ident = request.args.get("patient", "").removeprefix("Patient/")
    if not ident:
        raise BadSearch("patient: the search needs a patient (patient=<id>)")
    t0, t1 = date_range(request.args.getlist("date"))
    with reader() as s:
        stays = {fhir.resource_id(mrn): (mrn, spans) for mrn, spans in fhir.stays(s.episodes()).items()}
        if ident not in stays:
            raise BadSearch(f"patient: no Patient {ident}")
        mrn, spans = stays[ident]
        found: list[dict] = []
        bed_id = snapshot().get("bed_id") or "bed"
        for start, end in spans:
            a, b = max(start, t0), min(end, t1)
            if a <= b:
                found += fhir.peak_observations(mrn, s.regions_between(a, b), bed_id)
        events = [e for e in s.patient_events(mrn) if t0 <= e["time_s"] <= t1]
        found += fhir.turn_observations(mrn, events, bed_id)
    found.sort(key=lambda r: (r["effectiveDateTime"], r["id"]))
    return answer(fhir.searchset(found, request.url, base_url()))


def date_range(values: list[str]) -> tuple[float, float]:
    """The ``date`` parameters (``ge``, ``gt``, ``le``, ``lt`` and an ISO 8601 date or time) as unix seconds."""
    t0, t1 = -math.inf, math.inf
    for value in values:
        prefix, text = value[:2], value[2:]
        if prefix not in DATE_PREFIXES:
            raise BadSearch(f"date: {value!r} must start with one of {', '.join(DATE_PREFIXES)}")
        try:
            when = datetime.datetime.fromisoformat(text)
        except ValueError:
            raise BadSearch(f"date: {text!r} is not an ISO 8601 date or date and time") from None
        if when.tzinfo is None:
            when = when.replace(tzinfo=datetime.UTC)
        day = len(text) == 10                    # a date alone: le/gt take in the whole day
        t = when.timestamp() + (86400.0 if day and prefix in ("le", "gt") else 0.0)
        if prefix in ("ge", "gt"):
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
    if t0 > t1:
        raise BadSearch("date: the range is empty (its start is after its end)")
    return t0, t1
