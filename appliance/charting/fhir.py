"""The store's episodes, turns and pressure history as FHIR R4 resources (JSON), for the read-only FHIR API.

Patients come from the episodes (admissions and discharges): a Patient per
patient id, ``active`` while admitted. Observations are the peak pressure at each
site at each kept map (``valueQuantity`` in UCUM ``mm[Hg]``), and each turn with
the posture it left the patient in (``valueCodeableConcept``), within the
patient's stays in the bed. Codes are the local ones of
:mod:`appliance.charting.codes` under ``codes.FHIR_SYSTEM``: LOINC and MDC have
none for pressure-injury sites. Resource ids are built from the record, so a
resource keeps its id from one search to the next.
"""

from __future__ import annotations

import datetime
import hashlib
import math
import re

from appliance.alerts.turns import TURN_KINDS
from appliance.charting import codes

FHIR_ID = re.compile(r"[A-Za-z0-9\-.]{1,64}")
UCUM = "http://unitsofmeasure.org"


def resource_id(patient: str) -> str:
    """The FHIR id of patient ``patient``: itself when it fits FHIR's id rules, else a digest of it.

    >>> resource_id("MRN-0042"), resource_id("MRN 0042/7")
    ('MRN-0042', 'p-7185937cf7b817ba')
    """
    if FHIR_ID.fullmatch(patient):
        return patient
    return "p-" + hashlib.sha256(patient.encode()).hexdigest()[:16]


def instant(time_s: float) -> str:
    """Unix seconds as a FHIR dateTime in UTC.

    >>> instant(0.5)
    '1970-01-01T00:00:00.500Z'
    """
    return datetime.datetime.fromtimestamp(time_s, datetime.UTC).isoformat(timespec="milliseconds")[:-6] + "Z"


def stays(episodes: list[dict]) -> dict[str, list[tuple[float, float]]]:
    """Each patient's stays in the bed: from an admission to the next episode record (a discharge, or another
    admission, which discharges first), or open (``inf``)."""
    found: dict[str, list[tuple[float, float]]] = {}
    for i, row in enumerate(episodes):
        if row["kind"] == "admitted" and row["patient"]:
            end = episodes[i + 1]["time_s"] if i + 1 < len(episodes) else math.inf
            found.setdefault(row["patient"], []).append((row["time_s"], end))
    return found


def patients(episodes: list[dict], names: dict[str, str]) -> list[dict]:
    """A Patient per patient id in ``episodes``, in order of first admission; ``names`` where known."""
    current = {}
    for row in episodes:
        if row["patient"]:
            current[row["patient"]] = row["kind"] == "admitted"
    return [patient(mrn, active, names.get(mrn)) for mrn, active in current.items()]


def patient(mrn: str, active: bool, name: str | None) -> dict:
    resource = {"resourceType": "Patient", "id": resource_id(mrn),
                "identifier": [{"use": "usual", "system": codes.PATIENT_ID_SYSTEM, "value": mrn}], "active": active}
    if name:
        resource["name"] = [{"text": name}]
    return resource


def _concept(code: tuple[str, str]) -> dict:
    return {"coding": [{"system": codes.FHIR_SYSTEM, "code": code[0], "display": code[1]}], "text": code[1]}


def _observation(ident: str, mrn: str, time_s: float, code: tuple[str, str], bed_id: str) -> dict:
    return {"resourceType": "Observation", "id": ident, "status": "final", "code": _concept(code),
            "subject": {"reference": f"Patient/{resource_id(mrn)}"}, "effectiveDateTime": instant(time_s),
            "device": {"display": bed_id}}


def peak_observations(mrn: str, regions: list[dict], bed_id: str) -> list[dict]:
    """The highest peak per site at each kept map in ``regions`` (Store.regions_between's rows)."""
    peaks: dict[tuple[float, str], float] = {}
    for row in regions:
        if row["zone"]:
            key = (row["time_s"], row["zone"])
            peaks[key] = max(peaks.get(key, -math.inf), row["peak_mmhg"])
    found = []
    for (time_s, zone), mmhg in sorted(peaks.items()):
        resource = _observation(f"peak-{zone}-{round(time_s * 1000)}", mrn, time_s, codes.peak_code(zone), bed_id)
        resource["valueQuantity"] = {"value": round(mmhg, 1), "unit": "mm[Hg]", "system": UCUM, "code": "mm[Hg]"}
        found.append(resource)
    return found


def turn_observations(mrn: str, events: list[dict], bed_id: str) -> list[dict]:
    """A TURN observation per turn event, and a POSTURE one where the event names the posture it left."""
    found = []
    for event in events:
        if event.get("type") != "turn" or event["kind"] not in TURN_KINDS:
            continue
        stamp = round(event["time_s"] * 1000)
        turn = _observation(f"turn-{event['kind']}-{stamp}", mrn, event["time_s"], codes.TURN, bed_id)
        turn["valueCodeableConcept"] = _concept((event["kind"], event.get("message") or event["kind"]))
        found.append(turn)
        if event.get("posture"):
            posture = _observation(f"posture-{stamp}", mrn, event["time_s"], codes.POSTURE, bed_id)
            posture["valueCodeableConcept"] = _concept(codes.posture_value(event["posture"]))
            found.append(posture)
    return found


def searchset(resources: list[dict], self_url: str, base_url: str) -> dict:
    """A searchset Bundle of ``resources``, each with its full URL under ``base_url``."""
    return {"resourceType": "Bundle", "type": "searchset", "total": len(resources),
            "link": [{"relation": "self", "url": self_url}],
            "entry": [{"fullUrl": f"{base_url}/{r['resourceType']}/{r['id']}", "resource": r,
                       "search": {"mode": "match"}} for r in resources]}


def outcome(problem: str, code: str = "invalid") -> dict:
    """An OperationOutcome saying ``problem``, the body of a refused request."""
    return {"resourceType": "OperationOutcome",
            "issue": [{"severity": "error", "code": code, "diagnostics": problem}]}
