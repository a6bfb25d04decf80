"""The shift report: a PDF whose text (read back by pypdf) has the patient, the turns and the alarms with who
acknowledged them, and a CSV of the period's events that matches the store, from the screen and the command
line."""

import csv
import io

import numpy as np
import pytest
from pypdf import PdfReader

from appliance.alerts.events import Event
from appliance.cli import main
from appliance.service.live import LiveChannel
from appliance.store import Store
from webui import create_app
from webui_client import client_as, set_up

T0 = 1_780_000_000.0
HOUR = 3600.0


@pytest.fixture
def data_dir(tmp_path):
    with Store.open(tmp_path / "appliance.db", history_interval_s=0) as store:
        for n, peak in enumerate((30.0, 45.0, 52.0, 28.0, 40.0)):
            store.record_map(T0 + n * 1800, np.full((2, 3), 1.0),
                             [{"id": 1, "zone": "sacrum", "peak_mmhg": peak, "area_cm2": 12.0, "dose": 0.1 * n},
                              {"id": 2, "zone": "heel-left", "peak_mmhg": peak / 2, "area_cm2": 3.0, "dose": None}])
        store.record_events([
            Event(T0, "episode", "admitted", message="admitted MRN-0042 (Ada Lovelace)", user="nurse.kim",
                  patient="MRN-0042"),
            Event(T0 + 1800, "alarm", "raised", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1,
                  message="sustained pressure at the sacrum: reposition the patient", patient="MRN-0042"),
            Event(T0 + 2100, "alarm", "acknowledged", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1,
                  message="sustained pressure at the sacrum", user="nurse.jones", patient="MRN-0042"),
            Event(T0 + 2400, "turn", "recorded", posture="left-30", user="nurse.jones", patient="MRN-0042",
                  message="turn recorded by nurse.jones"),
            Event(T0 + 5400, "turn", "repositioned", posture="supine", patient="MRN-0042",
                  message="repositioned: left side, 30 degrees to on the back"),
            Event(T0 + 6000, "alarm", "ended", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1,
                  patient="MRN-0042"),
        ])
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "ward3-bed12", "time_s": T0 + 7200, "sequence": 1,
                  "patient": {"patient_id": "MRN-0042", "name": "Ada Lovelace"}})
    live.close()
    return tmp_path


def pdf_text(data: bytes) -> str:
    assert data.startswith(b"%PDF-")
    return " ".join(" ".join(page.extract_text().split()) for page in PdfReader(io.BytesIO(data)).pages)


def check_pdf(text: str) -> None:
    assert "Shift report, bed ward3-bed12" in text and "Ada Lovelace (MRN-0042)" in text
    assert "turn recorded by nurse.jones" in text and "left side, 30 degrees to on the back" in text
    assert "2 turn(s)" in text
    assert "sustained pressure at the sacrum: reposition the patient" in text
    assert "nurse.jones 5 min" in text                             # acknowledged after 300 s
    assert "Sacrum" in text or "sacrum" in text
    assert "Peak pressure by site" in text and "left heel" in text


def check_csv(text: str, data_dir) -> None:
    rows = list(csv.DictReader(io.StringIO(text)))
    with Store.open(data_dir / "appliance.db") as store:
        logged = store.events_since(0)
    assert len(rows) == len(logged) == 6
    for row, event in zip(rows, logged):
        assert float(row["time_s"]) == event["time_s"]
        assert (row["type"], row["kind"], row["user"], row["message"]) == (
            event["type"], event["kind"], event.get("user") or "", event.get("message") or "")
    assert rows[2]["time_utc"] == "2026-05-28T21:01:40+00:00" and rows[1]["alarm"] == "Pressure at the sacrum"


def test_the_screen_gives_the_pdf_and_csv_to_a_nurse(data_dir):
    app = create_app(data_dir, secure_cookies=False, TESTING=True)
    nurse = client_as(app, "nurse")
    page = nurse.get("/history/summary?hours=12").get_data(as_text=True)
    assert "/history/report.pdf?hours=12" in page and "/history/report.csv?hours=12" in page
    answer = nurse.get("/history/report.pdf?hours=12")
    assert answer.status_code == 200 and answer.mimetype == "application/pdf"
    assert 'filename="shift-ward3-bed12.pdf"' in answer.headers["Content-Disposition"]
    check_pdf(pdf_text(answer.data))
    answer = nurse.get("/history/report.csv?hours=12")
    assert answer.status_code == 200 and answer.mimetype == "text/csv"
    check_csv(answer.get_data(as_text=True), data_dir)
    assert nurse.get("/history/report.txt").status_code == 404
    assert nurse.get("/history/report.pdf?hours=200").status_code == 400


def test_a_report_made_after_the_discharge_still_names_the_patient_and_the_stay(data_dir):
    with Store.open(data_dir / "appliance.db", history_interval_s=0) as store:
        store.record_events([Event(T0 + 3000, "episode", "discharged", message="discharged MRN-0042",
                                   user="nurse.kim", patient="MRN-0042")])
    live = LiveChannel(data_dir / "live.json")
    live.publish({"bed_id": "ward3-bed12", "time_s": T0 + 7200, "sequence": 2})          # the bed is empty now
    live.close()
    text = pdf_text(client_as(create_app(data_dir, secure_cookies=False, TESTING=True), "nurse")
                    .get("/history/report.pdf?hours=12").data)
    assert "Patient: no patient admitted; discharged in the period: MRN-0042" in text
    assert "Admissions and discharges" in text
    assert "admitted MRN-0042 (Ada Lovelace) nurse.kim" in text and "discharged MRN-0042 nurse.kim" in text
    later = pdf_text(client_as(create_app(data_dir, secure_cookies=False, TESTING=True), "nurse")
                     .get("/history/report.pdf?hours=1").data)
    assert "Patient: no patient admitted Period" in later                 # the discharge came before this period
    assert "Admissions and discharges" not in later


def test_the_report_covers_only_the_period(data_dir):
    app = create_app(data_dir, secure_cookies=False, TESTING=True)
    rows = list(csv.DictReader(io.StringIO(client_as(app, "nurse").get("/history/report.csv?hours=1")
                                           .get_data(as_text=True))))
    assert [r["kind"] for r in rows] == ["repositioned", "ended"]      # the last hour up to T0 + 7200


def test_anonymous_reports_go_to_the_login(data_dir):
    app = create_app(data_dir, secure_cookies=False, TESTING=True)
    set_up(app.test_client())
    answer = app.test_client().get("/history/report.pdf")
    assert answer.status_code == 302 and "/login" in answer.headers["Location"]


def test_the_command_line_writes_both(data_dir, tmp_path, capsys):
    assert main(["report", "--data-dir", str(data_dir), "--hours", "12", "--out", str(tmp_path / "s.pdf")]) == 0
    check_pdf(pdf_text((tmp_path / "s.pdf").read_bytes()))
    assert main(["report", "--data-dir", str(data_dir), "--out", str(tmp_path / "s.csv")]) == 0
    check_csv((tmp_path / "s.csv").read_text(encoding="utf-8"), data_dir)


@pytest.mark.parametrize("args, problem", [
    (["--out", "{tmp}/s.txt"], "--out {tmp}/s.txt: the name must end in .pdf or .csv"),
    (["--out", "{tmp}/nowhere/s.pdf"], "no folder {tmp}/nowhere"),
    (["--out", "{tmp}/s.pdf", "--data-dir", "{tmp}/empty"], "no monitor store (appliance.db) there"),
])
def test_bad_command_lines_exit_2_naming_the_problem(data_dir, tmp_path, capsys, args, problem):
    (tmp_path / "empty").mkdir(exist_ok=True)
    argv = ["report", "--data-dir", str(data_dir)] + [a.format(tmp=tmp_path) for a in args]
    assert main(argv) == 2
    assert problem.format(tmp=tmp_path) in capsys.readouterr().err


@pytest.mark.parametrize("hours", ["0", "169", "abc"])
def test_bad_hours_exit_2_naming_the_option(data_dir, tmp_path, capsys, hours):
    with pytest.raises(SystemExit) as stop:
        main(["report", "--data-dir", str(data_dir), "--hours", hours, "--out", str(tmp_path / "s.pdf")])
    assert stop.value.code == 2 and "--hours" in capsys.readouterr().err
