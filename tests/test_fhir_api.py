"""The read-only FHIR API: token-protected, patients from the episodes, observations from the store, each
answer checked against FHIR's R4 models by fhir.resources (its R4B package: FHIR 4.3, whose Patient,
Observation, Bundle and OperationOutcome are R4's)."""

import sqlite3

import numpy as np
import pytest
from fhir.resources.R4B.bundle import Bundle
from fhir.resources.R4B.observation import Observation
from fhir.resources.R4B.operationoutcome import OperationOutcome
from fhir.resources.R4B.patient import Patient

from appliance.alerts.events import Event
from appliance.cli import main
from appliance.service.live import LiveChannel
from appliance.store import Store
from appliance.store.api_tokens import ApiTokens
from webui import create_app

T0 = 1_780_000_000.0                # 2026-05-28 20:26:40 UTC
ADA, BOB = "MRN-0042", "MRN 77/B"   # the second is no FHIR id: it is served under a digest
SACRUM = [(600.0, 41.0), (1200.0, 52.5), (4200.0, 60.0)]


@pytest.fixture
def app(tmp_path):
    with Store.open(tmp_path / "appliance.db", history_interval_s=0) as store:
        for t, peak in SACRUM:
            store.record_map(T0 + t, np.full((2, 3), 1.0),
                             [{"id": 1, "zone": "sacrum", "peak_mmhg": peak, "area_cm2": 12.0, "dose": 0.1},
                              {"id": 2, "zone": "sacrum", "peak_mmhg": peak - 5, "area_cm2": 3.0, "dose": 0.1},
                              {"id": 3, "zone": None, "peak_mmhg": 90.0, "area_cm2": 1.0, "dose": None}])
        store.record_events([
            Event(T0, "episode", "admitted", message=f"admitted {ADA}", user="nurse.kim", patient=ADA),
            Event(T0 + 900, "turn", "repositioned", posture="left-30", patient=ADA,
                  message="repositioned: on the back to left side, 30 degrees"),
            Event(T0 + 1500, "turn", "recorded", user="nurse.kim", patient=ADA, message="turn recorded by nurse.kim"),
            Event(T0 + 3000, "episode", "discharged", message=f"discharged {ADA}", user="nurse.kim", patient=ADA),
            Event(T0 + 3600, "episode", "admitted", message=f"admitted {BOB}", user="nurse.kim", patient=BOB),
        ])
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "ward3-bed12", "time_s": T0 + 4200, "sequence": 1,
                  "patient": {"patient_id": BOB, "name": "Bob Jones"}})
    live.close()
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


@pytest.fixture
def token(tmp_path):
    return ApiTokens(tmp_path / "api-tokens.db").create("ehr", T0)


def get(app, path, token, **query):
    return app.test_client().get(path, query_string=query, headers={"Authorization": f"Bearer {token}"})


def bundle(answer) -> Bundle:
    assert answer.status_code == 200 and answer.mimetype == "application/fhir+json"
    parsed = Bundle.model_validate(answer.get_json())
    assert parsed.type == "searchset" and parsed.total == len(parsed.entry or [])
    return parsed


def test_without_a_current_token_everything_is_refused(app, token, tmp_path):
    for path in ("/fhir/Patient", f"/fhir/Patient/{ADA}", f"/fhir/Observation?patient={ADA}"):
        for headers in ({}, {"Authorization": "Bearer nonsense"}, {"Authorization": f"Basic {token}"}):
            answer = app.test_client().get(path, headers=headers)
            assert answer.status_code == 401 and answer.headers["WWW-Authenticate"].startswith("Bearer")
            OperationOutcome.model_validate(answer.get_json())
    assert get(app, "/fhir/Patient", token).status_code == 200
    ApiTokens(tmp_path / "api-tokens.db").revoke("ehr")
    assert get(app, "/fhir/Patient", token).status_code == 401


def test_tokens_are_kept_only_as_hashes(tmp_path, token):
    with sqlite3.connect(tmp_path / "api-tokens.db") as db:
        kept = db.execute("SELECT name, hash FROM tokens").fetchall()
    assert len(kept) == 1 and kept[0][0] == "ehr" and token not in kept[0][1] and len(token) >= 43


def test_patients_come_from_the_episodes(app, token):
    found = bundle(get(app, "/fhir/Patient", token))
    patients = [Patient.model_validate(e.resource.model_dump()) for e in found.entry]
    assert [(p.identifier[0].value, p.active) for p in patients] == [(ADA, False), (BOB, True)]
    assert patients[0].id == ADA and patients[1].id.startswith("p-") and patients[1].name[0].text == "Bob Jones"
    assert found.entry[1].fullUrl == f"http://localhost/fhir/Patient/{patients[1].id}"
    one = get(app, f"/fhir/Patient/{patients[1].id}", token)
    assert one.status_code == 200 and Patient.model_validate(one.get_json()).identifier[0].value == BOB
    assert get(app, "/fhir/Patient/nobody", token).status_code == 404


def test_observations_are_the_patients_peaks_turns_and_postures_within_the_dates(app, token):
    found = bundle(get(app, "/fhir/Observation", token, patient=ADA))
    observations = [Observation.model_validate(e.resource.model_dump()) for e in found.entry]
    peaks = [(o.effectiveDateTime.timestamp(), o.valueQuantity.value, o.valueQuantity.code)
             for o in observations if o.code.coding[0].code == "PEAK.sacrum"]
    assert peaks == [(T0 + 600, 41.0, "mm[Hg]"), (T0 + 1200, 52.5, "mm[Hg]")]     # not Bob's map at 4200
    assert {o.code.coding[0].system for o in observations} == {"urn:appliance:codes:99PSM"}
    turns = [o.valueCodeableConcept.coding[0].code for o in observations if o.code.coding[0].code == "TURN"]
    postures = [o.valueCodeableConcept.coding[0].code for o in observations if o.code.coding[0].code == "POSTURE"]
    assert turns == ["repositioned", "recorded"] and postures == ["left-30"]
    assert {o.subject.reference for o in observations} == {f"Patient/{ADA}"}
    narrowed = bundle(get(app, "/fhir/Observation", token, patient=f"Patient/{ADA}",
                          date=["ge2026-05-28T20:45:00Z", "le2026-05-28T20:55:00+00:00"]))
    assert [e.resource.effectiveDateTime.timestamp() for e in narrowed.entry] == [T0 + 1200, T0 + 1500]
    whole_day = bundle(get(app, "/fhir/Observation", token, patient=ADA, date=["ge2026-05-28", "le2026-05-28"]))
    assert whole_day.total == found.total == 5


@pytest.mark.parametrize("query, problem", [
    ({"patient": ADA, "code": "x"}, "unknown search parameter(s) code"),
    ({}, "patient: the search needs a patient"),
    ({"patient": "nobody"}, "patient: no Patient nobody"),
    ({"patient": ADA, "date": "2026-05-28"}, "date: '2026-05-28' must start with one of ge, gt, le, lt"),
    ({"patient": ADA, "date": "geyesterday"}, "date: 'yesterday' is not an ISO 8601"),
    ({"patient": ADA, "date": ["ge2026-05-30", "le2026-05-28"]}, "date: the range is empty"),
])
def test_bad_searches_are_refused_naming_the_parameter(app, token, query, problem):
    answer = get(app, "/fhir/Observation", token, **query)
    assert answer.status_code == 400
    assert problem in OperationOutcome.model_validate(answer.get_json()).issue[0].diagnostics


def test_patient_search_takes_no_parameters(app, token):
    answer = get(app, "/fhir/Patient", token, name="Bob")
    assert answer.status_code == 400 and "unknown search parameter(s) name" in answer.get_data(as_text=True)


def test_the_command_line_makes_lists_and_revokes_tokens(tmp_path, capsys):
    assert main(["fhir-token", "--data-dir", str(tmp_path), "--create", "ehr"]) == 0
    made = capsys.readouterr().out.strip()
    assert ApiTokens(tmp_path / "api-tokens.db").client(made) == "ehr"
    assert main(["fhir-token", "--data-dir", str(tmp_path), "--list"]) == 0
    assert capsys.readouterr().out == "ehr\n"
    assert main(["fhir-token", "--data-dir", str(tmp_path), "--create", "ehr"]) == 2
    assert "a token named 'ehr' exists" in capsys.readouterr().err
    assert main(["fhir-token", "--data-dir", str(tmp_path), "--create", "no good"]) == 2
    assert "a token's name is 1-64 letters" in capsys.readouterr().err
    assert main(["fhir-token", "--data-dir", str(tmp_path / "none"), "--list"]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert main(["fhir-token", "--data-dir", str(tmp_path), "--revoke", "ehr"]) == 0
    assert ApiTokens(tmp_path / "api-tokens.db").client(made) is None
    assert main(["fhir-token", "--data-dir", str(tmp_path), "--revoke", "ehr"]) == 2
