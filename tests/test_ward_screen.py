"""The ward station's screen and its configuration: beds from a real Mosquitto through the station to the page,
its JSON and its event stream; the ``appliance ward`` process."""

import json
import shutil
import signal
import subprocess
import sys
import urllib.request

import pytest
from mqtt_broker import free_port, wait_until
from ward_payloads import alarm, summary
from webui_client import client_as

from appliance.errors import ConfigError
from appliance.service.config_sections import MqttSettings
from appliance.ward.config import WardConfig, load_ward_config, ward_config_from_mapping
from webui import create_ward_app


def ward_app(tmp_path, station, **station_options):
    config = WardConfig(MqttSettings("127.0.0.1"), client_id="test-station", **station_options)
    return create_ward_app(tmp_path, station, config, secure_cookies=False, TESTING=True, STREAM_MAX_S=3.0)


def ward(client):
    answer = client.get("/api/ward")
    assert answer.status_code == 200
    return answer.get_json()


def test_the_ward_shows_every_bed_alarming_first_with_its_screen_link(tmp_path, station, beds):
    app = ward_app(tmp_path, station, screen_url="https://{bed_id}.ward3.example/")
    nurse = client_as(app, "nurse")
    quiet, alarming = beds("bed-01"), beds("bed-02")
    quiet.summarise(summary("bed-01"))
    alarming.summarise(summary("bed-02", alarms=[(3, "medium")]))
    # A bed's retained "online" can come before its first summary: wait for both beds' summaries.
    assert wait_until(lambda: all(b["peak_mmhg"] is not None for b in ward(nurse)["beds"][:2])
                      and len(ward(nurse)["beds"]) == 2)
    view = ward(nurse)
    assert view["connected"] and view["counts"] == {"beds": 2, "offline": 0, "alarming": 1}
    first, second = view["beds"]
    assert (first["bed_id"], first["highest_priority"], [a["alarm_id"] for a in first["alarms"]]) == \
        ("bed-02", "medium", [3])
    assert (second["bed_id"], second["highest_priority"], second["alarms"]) == ("bed-01", None, [])
    assert first["screen_url"] == "https://bed-02.ward3.example/"
    assert (first["peak_mmhg"], first["turn_due_in_s"], first["regions"][0]["zone"]) == (41.5, 3600.0, "sacrum")
    page = nurse.get("/ward").get_data(as_text=True)
    assert "ward.js" in page and 'id="beds"' in page
    assert nurse.get("/").headers["Location"].endswith("/ward")


def test_a_new_alarm_is_pushed_to_the_stream_and_an_offline_bed_is_shown(tmp_path, station, beds):
    app = ward_app(tmp_path, station)
    nurse = client_as(app, "nurse")
    bed = beds("bed-07")
    bed.summarise(summary("bed-07"))
    assert wait_until(lambda: ward(nurse)["counts"]["beds"] == 1)
    stream = nurse.get("/api/ward/stream", buffered=False)
    chunks = stream.response
    assert next(chunks).decode().startswith("retry:")
    first = json.loads(next(chunks).decode().removeprefix("data: "))
    assert first["beds"][0]["alarms"] == []
    bed.notify(alarm(alarm_id=9, time_s=200.0))          # its latency is measured in benchmarks/ward_load.md
    for chunk in chunks:
        view = json.loads(chunk.decode().removeprefix("data: "))
        if view["beds"][0]["alarms"]:
            break
    assert view["beds"][0]["alarms"][0]["alarm_id"] == 9
    stream.close()
    bed.close(timeout_s=2.0)                                   # a clean stop says "offline" at once
    assert wait_until(lambda: ward(nurse)["counts"]["offline"] == 1)
    assert ward(nurse)["beds"][0]["status"] == "offline"


def test_the_ward_says_when_it_has_no_broker(tmp_path):
    from appliance.ward.station import WardStation

    with WardStation("127.0.0.1", free_port(), client_id="lonely-station") as station:
        nurse = client_as(ward_app(tmp_path, station), "nurse")
        view = ward(nurse)
        assert view["connected"] is False and view["beds"] == []


@pytest.mark.parametrize("table, message", [
    ({}, "[broker] is missing"),
    ({"broker": {"port": 1883}}, "[broker] is missing 'host'"),
    ({"broker": {"host": "b"}, "beds": {}}, "unknown key 'beds'"),
    ({"broker": {"host": "b"}, "station": {"screen": "x"}}, "[station]: unknown key 'screen'"),
    ({"broker": {"host": "b"}, "station": {"screen_url": "ftp://{bed_id}"}}, "must start with http"),
    ({"broker": {"host": "b"}, "station": {"screen_url": "https://{bed}/"}}, "may hold only {bed_id}"),
    ({"broker": {"host": "b"}, "station": {"client_id": "ward/3"}}, "client_id must be"),
    ({"broker": {"host": "b"}, "station": {"summary_interval_s": 0}}, "summary_interval_s must be from 0.1"),
    ({"broker": {"host": "b", "password_file": "pw"}}, "[broker]: password_file needs a username"),
    ({"broker": {"host": "b"}, "station": {"command_expiry_s": 1}}, "command_expiry_s must be from 5 to 3600"),
    ({"engine": {"servers": ["nats://n1:4222"]}}, "[engine] is missing 'ward'"),
    ({"engine": {"servers": ["n1"], "ward": "w"}}, "[engine]: server 'n1' must be nats://HOST:PORT"),
    ({"broker": {"host": "b"}, "engine": {"servers": ["nats://n1:4222"], "ward": "w", "password_file": "pw"}},
     "[engine] password_file: no file"),
])
def test_a_bad_station_configuration_names_the_key(table, message):
    with pytest.raises(ConfigError) as caught:
        ward_config_from_mapping(table)
    assert message in str(caught.value)


def test_the_configuration_file_and_screen_links(tmp_path, ca_certificate):
    path = tmp_path / "ward.toml"
    path.write_text('[broker]\nhost = "broker.ward3"\nport = 8883\nusername = "station"\npassword_file = "pw"\n'
                    'ca_file = "ca.crt"\n[station]\nscreen_url = "https://{bed_id}.ward3.example:8443/"\n')
    with pytest.raises(ConfigError, match=r"ward.toml: \[broker\] password_file: no file"):
        load_ward_config(path)
    (tmp_path / "pw").write_text("secret\n")
    shutil.copy(ca_certificate, tmp_path / "ca.crt")
    config = load_ward_config(path)
    assert (config.broker.host, config.broker.port, config.broker.password()) == ("broker.ward3", 8883, "secret")
    assert config.broker.ca_file == tmp_path / "ca.crt"
    assert config.screen_of("bed 1/a") == "https://bed%201%2Fa.ward3.example:8443/"     # a bed id cannot escape
    assert WardConfig(config.broker).screen_of("bed-1") is None
    assert config.command_expiry_s == 120.0                   # a nurse's command waits two minutes by default


def test_appliance_ward_serves_the_screen_and_stops_on_sigterm(tmp_path, broker, beds):
    (tmp_path / "ward.toml").write_text(f'[broker]\nhost = "127.0.0.1"\nport = {broker.port}\n'
                                        '[station]\nclient_id = "process-station"\n')
    port = free_port()
    process = subprocess.Popen([sys.executable, "-m", "appliance", "ward", "--config", str(tmp_path / "ward.toml"),
                                "--data-dir", str(tmp_path / "station"), "--listen", f"127.0.0.1:{port}"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: _answers(f"http://127.0.0.1:{port}/login"), timeout_s=20)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/setup") as answer:    # a fresh station: set up
            assert "admin" in answer.read().decode()
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=10)
    finally:
        process.kill()
    assert process.returncode == 0, err
    assert f"the screen on http://127.0.0.1:{port}/" in out and (tmp_path / "station" / "webui.db").exists()


def test_appliance_ward_refuses_a_bad_configuration_with_its_name(tmp_path):
    (tmp_path / "ward.toml").write_text('[broker]\nhost = "b"\n[station]\nscreen_url = "x"\n')
    done = subprocess.run([sys.executable, "-m", "appliance", "ward", "--config", str(tmp_path / "ward.toml"),
                           "--check-config"], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode != 0 and "ward.toml: [station]: screen_url must start with http" in done.stderr


def _answers(url):
    try:
        with urllib.request.urlopen(url, timeout=1):
            return True
    except OSError:
        return False


def test_the_example_configuration_in_docs_is_valid(tmp_path, ca_certificate):
    """docs/ward.example.toml as the README's server installation uses it, with its secrets' paths made here."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "ward.example.toml").read_text()
    for server_path, name in (("/run/credentials/appliance-ward.service/mqtt-password", "password"),
                              ("/etc/appliance/ward-ca.crt", "ca.crt")):
        assert server_path in text
        text = text.replace(server_path, str(tmp_path / name))
    (tmp_path / "password").write_text("secret\n")
    shutil.copy(ca_certificate, tmp_path / "ca.crt")
    (tmp_path / "ward.toml").write_text(text)
    config = load_ward_config(tmp_path / "ward.toml")
    assert (config.broker.port, config.broker.username, config.client_id) == (8883, "ward3-station", "ward3-station")
    assert config.screen_of("ward3-bed12") == "https://ward3-bed12.ward3.example/"
