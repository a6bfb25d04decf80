"""The admin's Charting page: the HL7 target and its queue, set and read on the screen, checked, audited, taken by
the running monitor; and the FHIR API's tokens made (shown once, kept hashed) and revoked."""

import io
import sqlite3

import pytest
from test_charting_hl7 import Engine, free_port, until
from webui_client import client_as, set_up, token

from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.errors import ConfigError
from appliance.service import settings
from appliance.service.charting_target import CHARTING_FILE, charting_link
from appliance.service.config import config_from_mapping
from appliance.service.daemon import MonitorDaemon
from appliance.service.live import LiveChannel, read_live
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import square_load_scene
from appliance.store import Store
from appliance.store.api_tokens import TOKENS_FILE, digest
from webui import create_app

TARGET = {"host": "engine.hospital", "port": "2575", "enabled": "on", "sending_facility": "WARD3",
          "receiving_application": "EHR"}


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


def post(client, path, **fields):
    return client.post(path, data={"csrf_token": token(client, "/settings"), **fields})


def commands(tmp_path) -> list[dict]:
    with Store.open(tmp_path / "appliance.db") as store:
        return store.commands_since(0)


def audits(app) -> list[tuple[str, str, str]]:
    return [(e["user"], e["action"], e["detail"]) for e in app.extensions["users"].audit_log()]


# Who may.

@pytest.mark.parametrize("role", ["nurse", "engineer"])
def test_only_an_admin_sees_or_changes_charting_and_tokens(app, tmp_path, role):
    client = client_as(app, role)
    before = audits(app)
    assert client.get("/charting").status_code == 403
    assert post(client, "/charting/hl7", **TARGET).status_code == 403
    assert post(client, "/charting/tokens", name="ehr").status_code == 403
    assert post(client, "/charting/tokens/ehr/revoke").status_code == 403
    assert not (tmp_path / "settings.toml").exists() and commands(tmp_path) == [] and audits(app) == before
    assert 'href="/charting"' not in client.get("/settings").get_data(as_text=True)


def test_anonymous_requests_go_to_the_login(app, tmp_path):
    set_up(app.test_client())
    client = app.test_client()
    assert "/login" in client.get("/charting").headers["Location"]
    answer = client.post("/charting/hl7", data={"csrf_token": token(client), **TARGET})
    assert answer.status_code == 302 and not (tmp_path / "settings.toml").exists()


# The target.

def test_an_admin_sets_the_target_which_is_written_whole_queued_and_audited(app, tmp_path):
    admin = client_as(app, "admin")
    assert 'href="/charting"' in admin.get("/settings").get_data(as_text=True)
    assert "Not charting" in admin.get("/charting").get_data(as_text=True)
    answer = post(admin, "/charting/hl7", **TARGET)
    assert answer.status_code == 303
    saved = settings.read_settings(tmp_path / "settings.toml")["charting"]["hl7"]
    assert (saved["host"], saved["port"], saved["enabled"], saved["sending_application"]) == (
        "engine.hospital", 2575, True, "APPLIANCE")
    [command] = commands(tmp_path)
    assert command["kind"] == "apply-settings" and command["args"] == {"charting": {"hl7": saved}}
    user, action, detail = audits(app)[0]
    assert (user, action) == ("admin.test", "changed charting target")
    assert "host None -> engine.hospital" in detail and "port None -> 2575" in detail
    page = admin.get("/charting").get_data(as_text=True)
    assert "charting target changed" in page and 'value="engine.hospital"' in page and "settings file" in page

    assert post(admin, "/charting/hl7", **{**TARGET, "port": "2576", "enabled": ""}).status_code == 303
    saved = settings.read_settings(tmp_path / "settings.toml")["charting"]["hl7"]
    assert (saved["port"], saved["enabled"]) == (2576, False)
    assert audits(app)[0][2].startswith("port 2575 -> 2576, enabled True -> False (command ")
    assert post(admin, "/charting/hl7", **{**TARGET, "port": "2576", "enabled": ""}).status_code == 303
    assert len(commands(tmp_path)) == 2                                 # the same again queues nothing


@pytest.mark.parametrize("field, value, message", [
    ("host", "engine hospital", "host must be a host name (such as engine.hospital) or an IP address, got "
                                "'engine hospital'"),
    ("host", "http://engine", "host must be a host name"),
    ("host", "-engine", "host must be a host name"),
    ("host", "", "host must be non-empty text, got ''"),
    ("port", "70000", "port must be from 1 to 65535, got 70000"),
    ("port", "0", "port must be from 1 to 65535, got 0"),
    ("port", "25.5", "port must be a whole number, got 25.5"),
    ("port", "http", "port must be a number, got 'http'"),
    ("sending_facility", "W|3", "sending_facility must not hold HL7's delimiters"),
    ("ack_timeout_s", "0", "ack_timeout_s must be from 0.5 to 300, got 0"),
    ("colour", "red", "unknown field 'colour'"),
])
def test_a_bad_target_is_refused_naming_the_field_and_nothing_is_saved(app, tmp_path, field, value, message):
    admin = client_as(app, "admin")
    before = audits(app)
    answer = post(admin, "/charting/hl7", **{**TARGET, field: value})
    assert answer.status_code == 400
    assert "charting target not changed: " in answer.get_data(as_text=True)
    assert message in answer.get_data(as_text=True).replace("&#39;", "'")
    assert not (tmp_path / "settings.toml").exists() and commands(tmp_path) == [] and audits(app) == before


def test_a_saved_target_replaces_the_configurations_at_the_next_start_and_outlives_an_engineers_file(app,
                                                                                                     tmp_path):
    assert post(client_as(app, "admin"), "/charting/hl7", **TARGET).status_code == 303
    engineer = client_as(app, "engineer")
    answer = engineer.post("/settings/file", data={"csrf_token": token(engineer, "/settings"), "file": (
        io.BytesIO(b'[monitor]\nbed_id = "ward3-bed7"\n'), "bed.toml")}, content_type="multipart/form-data")
    assert answer.status_code == 303
    saved = settings.read_settings(tmp_path / "settings.toml")
    assert saved["monitor"] == {"bed_id": "ward3-bed7"} and saved["charting"]["hl7"]["host"] == "engine.hospital"
    configured = config_from_mapping({"charting": {"hl7": {"host": "old.engine", "port": 7, "sending_facility": "W",
                                                           "receiving_application": "E", "ack_timeout_s": 30}}})
    started = settings.load_overlaid(configured, tmp_path)
    assert (started.hl7.host, started.hl7.port, started.hl7.ack_timeout_s, started.bed_id) == (
        "engine.hospital", 2575, 10.0, "ward3-bed7")                       # the whole table, not a mix
    refused = engineer.post("/settings/file", data={"csrf_token": token(engineer, "/settings"), "file": (
        io.BytesIO(b'[charting.hl7]\nhost = "x"\nport = 1\nsending_facility = "W"\nreceiving_application = "E"\n'),
        "c.toml")}, content_type="multipart/form-data")
    assert refused.status_code == 400 and "c.toml holds a [charting.hl7]" in refused.get_data(as_text=True)


def test_the_configuration_checks_the_host_and_the_enabled_switch_too():
    table = {"host": "10.0.0.7", "port": 2575, "sending_facility": "W", "receiving_application": "E"}
    assert config_from_mapping({"charting": {"hl7": table}}).hl7.host == "10.0.0.7"
    assert config_from_mapping({"charting": {"hl7": {**table, "host": "fd00::7"}}}).hl7.host == "fd00::7"
    assert config_from_mapping({"charting": {"hl7": {**table, "enabled": False}}}).hl7.enabled is False
    with pytest.raises(ConfigError, match=r"\[charting.hl7\]: enabled must be true or false, got 'no'"):
        config_from_mapping({"charting": {"hl7": {**table, "enabled": "no"}}})
    with pytest.raises(ConfigError, match=r"\[charting.hl7\]: host must be a host name"):
        config_from_mapping({"charting": {"hl7": {**table, "host": "engine:2575"}}})


def test_a_switched_off_target_makes_no_link_and_keeps_the_queue(tmp_path):
    table = {"host": "127.0.0.1", "port": 2575, "sending_facility": "W", "receiving_application": "E"}
    assert charting_link(config_from_mapping({"charting": {"hl7": {**table, "enabled": False}}}), tmp_path) is None
    assert not (tmp_path / CHARTING_FILE).exists()


# The running monitor.

def charting_monitor(small_mat_calibration, tmp_path, port: int):
    """A monitor charting to ``port`` on loopback, taking settings commands, with its data folder in ``tmp_path``."""
    model, calibration = small_mat_calibration
    grid = get_layout("grid-4x4")
    source = VirtualBedSource(grid, square_load_scene(100, 100, 30, 70, 40, 6.0), default_protocol(grid),
                              frame_interval_s=600.0)
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": 600.0,
                                              "data_dir": str(tmp_path)},
                                  "alerts": {"alarm_dose": 0.05},
                                  "charting": {"hl7": {"host": "127.0.0.1", "port": port, "sending_facility": "WARD3",
                                                       "receiving_application": "EHR"}}})
    daemon = MonitorDaemon(config, source, model, calibration, Store.open(tmp_path / "appliance.db"),
                           notifiers=[charting_link(config, tmp_path)], live=LiveChannel(tmp_path / "live.json"),
                           say=lambda text: None)
    settings.attach(daemon)
    daemon.start()
    return daemon


def written(daemon) -> None:
    """Wait until the live view holds the monitor's last snapshot: a thread of its own writes it."""
    until(lambda: daemon.live.written + daemon.live.skipped == daemon.maps + daemon.faults)


def test_the_monitor_takes_a_new_target_at_its_next_frame_and_sends_it_what_waited(small_mat_calibration, tmp_path):
    down = free_port()                                          # no engine listens here
    daemon = charting_monitor(small_mat_calibration, tmp_path, down)
    engine = Engine()
    try:
        daemon.run(3)
        [old] = daemon.notifiers
        until(lambda: old.status()["last_error"] is not None and old.status()["waiting"] > 0)
        daemon.run(1)                                           # the live view shows the failing link
        written(daemon)
        app = create_app(tmp_path, secure_cookies=False, TESTING=True)
        admin = client_as(app, "admin")
        page = admin.get("/charting").get_data(as_text=True)
        waiting = read_live(tmp_path / "live.json")["charting"]["waiting"]
        assert waiting > 0 and f"<th>Messages waiting</th><td>{waiting}</td>" in page
        assert f"127.0.0.1:{down} (not connected)" in page and "ConnectionRefusedError" in page
        answer = post(admin, "/charting/hl7", host="127.0.0.1", port=str(engine.port), enabled="on",
                      sending_facility="WARD3", receiving_application="EHR")
        assert answer.status_code == 303
        assert daemon.notifiers == [old]                        # not before the next frame
        daemon.run(1)
        [new] = daemon.notifiers
        assert new is not old and (new.host, new.port) == ("127.0.0.1", engine.port)
        until(lambda: new.status()["waiting"] == 0)
        [command] = commands(tmp_path)
        assert command["state"] == "done"
        assert command["result"] == f"charting target 127.0.0.1:{down} -> 127.0.0.1:{engine.port}"
        sequence = [int(cid.rsplit("-", 1)[1]) for cid in engine.control_ids()]
        answer = admin.post("/settings/clock", data={"csrf_token": token(admin, "/settings"),
                                                     "time_zone": "Europe/London"})
        assert answer.status_code == 303 and read_live(tmp_path / "live.json")["time_zone"] != "Europe/London"
        daemon.run(1)                                           # the time zone, like the bed id, at once
        written(daemon)
        assert read_live(tmp_path / "live.json")["time_zone"] == daemon.config.time_zone == "Europe/London"
        assert len(sequence) >= waiting and sequence == list(range(1, len(sequence) + 1))    # all, once, in order
    finally:
        daemon.close()
        engine.close()
    with sqlite3.connect(tmp_path / CHARTING_FILE) as db:       # the one queue, carried over
        assert db.execute("SELECT COUNT(*) FROM messages WHERE state = 'pending'").fetchone()[0] == 0


# FHIR API tokens.

def test_an_admin_makes_a_token_shown_once_and_kept_hashed_and_revokes_it(app, tmp_path):
    admin = client_as(app, "admin")
    answer = post(admin, "/charting/tokens", name="ehr-gateway")
    assert answer.status_code == 201 and answer.headers["Cache-Control"] == "no-store"
    page = answer.get_data(as_text=True)
    made = page.split("<code>")[1].split("</code>")[0]
    assert len(made) >= 43                                      # 32 random bytes, base64url
    assert made not in admin.get("/charting").get_data(as_text=True)          # shown only then
    with sqlite3.connect(tmp_path / TOKENS_FILE) as db:
        assert db.execute("SELECT name, hash FROM tokens").fetchall() == [("ehr-gateway", digest(made))]
    fhir = app.test_client()
    assert fhir.get("/fhir/Patient", headers={"Authorization": f"Bearer {made}"}).status_code == 200
    assert audits(app)[0] == ("admin.test", "made FHIR API token", "ehr-gateway")
    assert all(made not in detail for _, _, detail in audits(app))
    again = post(admin, "/charting/tokens", name="ehr-gateway")
    assert again.status_code == 400 and "a token named &#39;ehr-gateway&#39; exists" in again.get_data(as_text=True)
    bad = post(admin, "/charting/tokens", name="no spaces")
    assert bad.status_code == 400 and "a token&#39;s name is 1-64 letters" in bad.get_data(as_text=True)

    assert post(admin, "/charting/tokens/ehr-gateway/revoke").status_code == 303
    assert fhir.get("/fhir/Patient", headers={"Authorization": f"Bearer {made}"}).status_code == 401
    assert audits(app)[0] == ("admin.test", "revoked FHIR API token", "ehr-gateway")
    missing = post(admin, "/charting/tokens/ehr-gateway/revoke")
    assert missing.status_code == 404 and "no token is named" in missing.get_data(as_text=True)
    assert audits(app)[0] == ("admin.test", "revoked FHIR API token", "ehr-gateway")
