"""The patient page with the monitor running beside it: admit, record a turn, discharge, and an earlier
patient's history kept under their identifier; bad input refused with the reason and nothing queued."""

from test_daemon import FlakySource, small_daemon
from webui_client import client_as, token

from appliance.service.live import LiveChannel, read_live
from appliance.store import Store
from webui import create_app


def test_a_nurse_admits_turns_and_discharges_and_the_patients_history_stays(small_mat_calibration, tmp_path):
    daemon, events = small_daemon(small_mat_calibration, tmp_path, FlakySource(failing=()), alarm_dose=0.05)
    client = client_as(create_app(tmp_path, secure_cookies=False, TESTING=True), "nurse", "nurse.jones")
    daemon.run(1)
    csrf = token(client, "/patient")
    refused = client.post("/patient/admit", data={"csrf_token": csrf, "patient_id": "MRN-7", "braden": "40"},
                          follow_redirects=True).get_data(as_text=True)
    assert "not admitted: Braden score must be a whole number from 6 to 23" in refused
    with Store.open(tmp_path / "appliance.db") as store:
        assert store.pending_commands() == []
    answer = client.post("/patient/admit", data={"csrf_token": csrf, "patient_id": "MRN-7", "name": "A. Patient",
                                                 "braden": "14", "bed_exit_alert": "on"})
    assert answer.status_code == 303
    daemon.run(6)                                               # admitted at the next frame; the sensor alarms
    assert read_live(tmp_path / "live.json")["patient"] == {"patient_id": "MRN-7", "name": "A. Patient",
                                                            "braden": 14, "bed_exit_alert": True}
    client.post("/patient/turn", data={"csrf_token": csrf, "by": "nurse.kim"})
    daemon.run(1)
    client.post("/patient/discharge", data={"csrf_token": csrf})
    daemon.run(2)
    daemon.live.close()
    daemon.live = LiveChannel(tmp_path / "live.json")
    mine = [e for e in events if e.patient == "MRN-7"]
    assert [(e.type, e.kind, e.site) for e in mine if e.type != "alarm"] == [
        ("episode", "admitted", None), ("turn", "recorded", None), ("turn", "still-loaded", "mat"),
        ("episode", "discharged", None)]                      # the alarmed sensor was still loaded
    assert next(e for e in mine if e.kind == "recorded").user == "nurse.kim"
    assert [e.kind for e in mine if e.key == "pressure:mat"][-1] == "ended"      # ended with the discharge
    assert all(e.patient is None for e in events[events.index(mine[-1]) + 1:])
    page = client.get("/patient").get_data(as_text=True)
    assert "No patient admitted" in page and "MRN-7" in page
    history = client.get("/patient/history/MRN-7").get_data(as_text=True)
    assert "admitted MRN-7 (A. Patient, Braden 14, bed-exit alert on)" in history
    assert "turn recorded by nurse.kim" in history and "sensor still loaded after the turn" in history
    assert "discharged MRN-7" in history
    with Store.open(tmp_path / "appliance.db") as store:
        assert [e["kind"] for e in store.episodes()] == ["admitted", "discharged"]
    daemon.close()
