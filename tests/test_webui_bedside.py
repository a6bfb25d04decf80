"""The bedside live view with Flask's test client: the patient on every page, and acknowledge and audio pause
sent from the live view with fetch (JSON answers, the CSRF token from the page's meta tag)."""

import re

import pytest
from webui_client import nurse_beside_a_monitor, client_as

from appliance.service.live import LiveChannel
from appliance.store import Store
from webui import create_app

ALARM = {"alarm_id": 4, "key": "pressure:sacrum", "priority": "medium", "category": "clinical",
         "message": "sustained pressure at the sacrum", "state": "active", "raised_s": 600.0,
         "acknowledged_by": None, "audio_paused": False, "delivery": None}


def write_live(folder, **fields):
    channel = LiveChannel(folder / "live.json")
    channel.publish({"time_s": 1200.0, "frame_interval_s": 3600.0, "alarms": [ALARM], "audible": "medium",
                     "patient": {"patient_id": "MRN-0042", "name": "Ada Byron", "braden": 14,
                                 "bed_exit_alert": False},
                     "status": {"maps": 20, "faults": 0, "source": "hardware"}, **fields})
    channel.close()


@pytest.fixture
def app(tmp_path):
    write_live(tmp_path)
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


def meta_token(client) -> str:
    return re.search(r'<meta name="csrf-token" content="([^"]+)"', client.get("/").get_data(as_text=True)).group(1)


def queued(app) -> list[dict]:
    with Store.open(app.config["STORE_PATH"]) as store:
        return store.pending_commands()


@pytest.mark.parametrize("path", ["/", "/alarms", "/patient", "/history", "/settings"])
def test_every_nurse_page_names_the_admitted_patient_in_its_header(app, path):
    page = client_as(app, "nurse").get(path).get_data(as_text=True)
    header = page[page.index("<header>"):page.index("</header>")]
    assert "Ada Byron" in header and "MRN-0042" in header


def test_the_header_says_when_no_patient_is_admitted(app, tmp_path):
    write_live(tmp_path, patient=None)
    page = client_as(app, "nurse").get("/alarms").get_data(as_text=True)
    assert "No patient admitted" in page[page.index("<header>"):page.index("</header>")]


def test_the_live_view_loads_its_tones_and_token_from_files_and_tags_only(app):
    page = client_as(app, "nurse").get("/").get_data(as_text=True)
    assert re.search(r'<meta name="csrf-token" content="[^"]+">', page)
    assert 'src="/static/tones.js"' in page and 'id="sound-on"' in page
    assert "until you press Sound on" in page
    assert re.findall(r"<script(?![^>]*\bsrc=)[^>]*>", page) == []              # no inline script (CSP)
    assert 'data-max-pause-min="2"' in page


def test_acknowledge_from_the_live_view_answers_json_and_queues_the_command(app):
    client = client_as(app, "nurse", "nurse.jones")
    headers = {"X-CSRF-Token": meta_token(client), "Accept": "application/json"}
    answer = client.post("/alarms/4/acknowledge", headers=headers)
    assert answer.status_code == 202
    assert answer.get_json() == {"message": "alarm 4 acknowledged; the monitor applies it at its next frame",
                                 "command_id": 1}
    assert queued(app) == [{"id": 1, "user": "nurse.jones", "kind": "acknowledge", "args": {"alarm_id": 4}}]
    refused = client.post("/alarms/5/acknowledge", headers=headers)
    assert refused.status_code == 409
    assert refused.get_json()["message"] == "alarm 5 is not open: nothing was acknowledged"
    no_token = client.post("/alarms/4/acknowledge", headers={"Accept": "application/json"})
    assert no_token.status_code == 400
    assert len(queued(app)) == 1


def test_one_alarms_sound_is_paused_from_the_live_view_within_the_standards_limit(app):
    client = client_as(app, "nurse", "nurse.jones")
    headers = {"X-CSRF-Token": meta_token(client), "Accept": "application/json"}
    answer = client.post("/alarms/pause-audio", data={"alarm_id": "4", "minutes": "2"}, headers=headers)
    assert (answer.status_code, answer.get_json()["message"]) == (202, "alarm 4's audio paused for 2 min")
    assert queued(app)[0]["args"] == {"duration_s": 120.0, "alarm_id": 4}
    for fields, status, words in (({"alarm_id": "9", "minutes": "2"}, 409, "alarm '9' is not open"),
                                  ({"alarm_id": "four", "minutes": "2"}, 409, "alarm 'four' is not open"),
                                  ({"alarm_id": "4", "minutes": "3"}, 400, "at most 2 minutes")):
        refused = client.post("/alarms/pause-audio", data=fields, headers=headers)
        assert refused.status_code == status and words in refused.get_json()["message"]
    assert len(queued(app)) == 1


def test_the_monitor_pauses_only_the_named_alarms_sound(small_mat_calibration, tmp_path):
    """The per-alarm pause through the running monitor: that alarm goes quiet, the engine's others would not."""
    daemon, events, app, client = nurse_beside_a_monitor(small_mat_calibration, tmp_path)
    daemon.run(8)
    alarm = next(e for e in events if e.kind == "raised" and e.key.startswith("pressure:"))
    headers = {"X-CSRF-Token": meta_token(client), "Accept": "application/json"}
    answer = client.post("/alarms/pause-audio", data={"alarm_id": str(alarm.alarm_id), "minutes": "1"},
                         headers=headers)
    assert answer.status_code == 202
    daemon.run(1)
    daemon.close()
    paused = [e for e in events if e.kind == "audio-paused"]
    assert [(e.alarm_id, e.user) for e in paused] == [(alarm.alarm_id, "nurse.jones")]
