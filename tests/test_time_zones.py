"""The configured time zone: checked by name, the system's by default, set by an admin on the screen, and
daylight-saving changes read right on the pages, in the shift report and from the command line."""

import csv
import io
import re
from datetime import UTC, datetime

import numpy as np
import pytest
from pypdf import PdfReader
from webui_client import client_as, token

from appliance import time_zones
from appliance.alerts.events import Event
from appliance.cli import main
from appliance.errors import ConfigError
from appliance.service.config import config_from_mapping
from appliance.service.live import LiveChannel
from appliance.service import settings
from appliance.service.settings import check_settings, read_settings
from appliance.store import Store
from appliance.time_zones import clock_text, system_zone, time_zone
from webui import create_app

LONDON = time_zone("Europe/London")


def utc(*fields) -> float:
    return datetime(*fields, tzinfo=UTC).timestamp()


def test_the_spring_change_skips_an_hour_and_the_autumn_change_repeats_one_told_apart_by_the_zone():
    # Europe/London: 29 March 2026 01:00 UTC clocks go forward to 02:00 BST; 25 October 2026 01:00 UTC back to GMT.
    assert [clock_text(utc(2026, 3, 29, h, 30), LONDON) for h in (0, 1, 2)] == [
        "2026-03-29 00:30:00 GMT", "2026-03-29 02:30:00 BST", "2026-03-29 03:30:00 BST"]
    assert [clock_text(utc(2026, 10, 25, h, 30), LONDON) for h in (0, 1, 2)] == [
        "2026-10-25 01:30:00 BST", "2026-10-25 01:30:00 GMT", "2026-10-25 02:30:00 GMT"]
    new_york = time_zone("America/New_York")          # its own change, a week later: 1 November 2026, 06:00 UTC
    assert clock_text(utc(2026, 10, 25, 12, 0), new_york) == "2026-10-25 08:00:00 EDT"
    assert clock_text(utc(2026, 11, 1, 12, 0), new_york) == "2026-11-01 07:00:00 EST"


def test_a_simulated_beds_seconds_stay_seconds_since_its_start():
    assert clock_text(3725.0, LONDON) == "1:02:05"


@pytest.mark.parametrize("name", ["Mars/Base", "Europe/Londn", "../etc/passwd", "/usr/share/zoneinfo/UTC", "", 5])
def test_an_unknown_zone_is_refused_by_name_in_the_configuration_and_the_settings(name):
    with pytest.raises(ConfigError, match=r"\[monitor\] time_zone: (unknown time zone|a time zone is named)") as made:
        config_from_mapping({"monitor": {"time_zone": name}})
    assert repr(name) in str(made.value)
    with pytest.raises(ConfigError, match=r"\[monitor\] time_zone"):
        check_settings({"monitor": {"time_zone": name}})


def test_the_configured_zone_is_kept_and_the_default_is_the_systems(monkeypatch):
    assert config_from_mapping({"monitor": {"time_zone": "Europe/London"}}).time_zone == "Europe/London"
    monkeypatch.setenv("TZ", ":Australia/Adelaide")
    assert config_from_mapping({}).time_zone == system_zone() == "Australia/Adelaide"


def test_the_system_zone_is_read_from_the_localtime_link_then_debians_file_then_utc(monkeypatch, tmp_path):
    monkeypatch.delenv("TZ", raising=False)
    link, named = tmp_path / "localtime", tmp_path / "timezone"
    link.symlink_to("/usr/share/zoneinfo/Asia/Kolkata")
    monkeypatch.setattr(time_zones, "LOCALTIME", link)
    monkeypatch.setattr(time_zones, "TIMEZONE_FILE", named)
    assert system_zone() == "Asia/Kolkata"
    link.unlink()
    link.write_bytes(b"TZif")                              # a copied file names no zone
    named.write_text("Europe/Berlin\n")
    assert system_zone() == "Europe/Berlin"
    named.write_text("Not/AZone\n")
    assert system_zone() == "UTC"


# On the screen and in the shift report.

CHANGE = utc(2026, 10, 25, 1, 0)                           # Europe/London: BST ends, GMT begins


@pytest.fixture
def autumn(tmp_path):
    """A bed's store across the autumn change: a turn at 01:30 BST, an alarm at 01:30 GMT an hour later."""
    with Store.open(tmp_path / "appliance.db", history_interval_s=0) as store:
        for n in range(5):
            store.record_map(CHANGE - 3600 + n * 1800, np.full((2, 3), 1.0),
                             [{"id": 1, "zone": "sacrum", "peak_mmhg": 40.0, "area_cm2": 12.0, "dose": 0.1}])
        store.record_events([
            Event(CHANGE - 1800, "turn", "recorded", posture="left-30", user="nurse.kim", message="turned left"),
            Event(CHANGE + 1800, "alarm", "raised", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1,
                  message="sustained pressure at the sacrum"),
        ])
        running = config_from_mapping({"monitor": {"time_zone": "America/New_York"}})   # the monitor's own zone
        store.save_state(settings.STATE, settings.published(running), CHANGE)
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "ward3-bed12", "time_s": CHANGE + 3600, "sequence": 1, "time_zone": "America/New_York"})
    live.close()
    return tmp_path


def csv_rows(text: str) -> list[dict]:
    return list(csv.DictReader(io.StringIO(text)))


def test_an_admin_sets_the_zone_and_every_page_and_report_reads_the_change_right(autumn):
    app = create_app(autumn, secure_cookies=False, TESTING=True)
    admin, nurse = client_as(app, "admin"), client_as(app, "nurse")
    # No zone in the settings file: the monitor's (its live view) until the admin sets one.
    assert "2026-10-24 21:30:00 EDT" in nurse.get("/alarms").get_data(as_text=True)
    answer = admin.post("/settings/clock", data={"csrf_token": token(admin, "/settings"), "time_zone": "Europe/London"})
    assert answer.status_code == 303
    assert read_settings(autumn / "settings.toml") == {"monitor": {"time_zone": "Europe/London"}}
    with Store.open(autumn / "appliance.db") as store:
        [command] = store.commands_since(0)
    assert command["args"] == {"monitor": {"time_zone": "Europe/London"}}
    assert app.extensions["users"].audit_log()[0]["detail"].startswith(
        "time_zone America/New_York -> Europe/London (command ")

    alarms = nurse.get("/alarms").get_data(as_text=True)
    assert "2026-10-25 01:30:00 GMT" in alarms and "2026-10-25 01:30:00 BST" in alarms
    summary = nurse.get("/history/summary?hours=12").get_data(as_text=True)
    assert "2026-10-25 01:30:00 GMT" in summary
    assert 'data-time-zone="Europe/London"' in nurse.get("/").get_data(as_text=True)
    rows = csv_rows(nurse.get("/history/report.csv?hours=12").get_data(as_text=True))
    assert [(r["time_utc"], r["time_local"]) for r in rows] == [
        ("2026-10-25T00:30:00+00:00", "2026-10-25T01:30:00+01:00"),
        ("2026-10-25T01:30:00+00:00", "2026-10-25T01:30:00+00:00")]
    pdf = " ".join(" ".join(page.extract_text().split()) for page in PdfReader(io.BytesIO(
        nurse.get("/history/report.pdf?hours=12").data)).pages)
    assert "2026-10-25 01:30:00 BST" in pdf and "2026-10-25 01:30:00 GMT" in pdf


def test_the_history_charts_ticks_read_local_hours_across_the_change(autumn):
    app = create_app(autumn, secure_cookies=False, TESTING=True)
    admin = client_as(app, "admin")
    admin.post("/settings/clock", data={"csrf_token": token(admin, "/settings"), "time_zone": "Europe/London"})
    page = admin.get("/history?hours=3").get_data(as_text=True)
    # Ticks every quarter hour from 00:00 UTC: 01:00 to 01:45 BST, then 01:00 GMT again.
    ticks = re.findall(r">(\d\d:\d\d)</text>", page)
    assert ticks[:6] == ["01:00", "01:15", "01:30", "01:45", "01:00", "01:15"]


@pytest.mark.parametrize("role", ["nurse", "engineer"])
def test_only_an_admin_sets_the_zone(autumn, role):
    app = create_app(autumn, secure_cookies=False, TESTING=True)
    client = client_as(app, role)
    answer = client.post("/settings/clock", data={"csrf_token": token(client, "/settings"), "time_zone": "UTC"})
    assert answer.status_code == 403 and not (autumn / "settings.toml").exists()
    if role == "engineer":                                    # nor through the bed's form or a settings file
        answer = client.post("/settings/bed", data={"csrf_token": token(client, "/settings"), "time_zone": "UTC"})
        assert answer.status_code == 400 and "unknown field &#39;time_zone&#39;" in answer.get_data(as_text=True)
        answer = client.post("/settings/file", data={"csrf_token": token(client, "/settings"), "file": (
            io.BytesIO(b'[monitor]\ntime_zone = "UTC"\n'), "s.toml")}, content_type="multipart/form-data")
        assert answer.status_code == 400 and "s.toml sets time_zone" in answer.get_data(as_text=True)
        assert not (autumn / "settings.toml").exists()


def test_an_unknown_zone_is_refused_on_the_page_naming_it_and_nothing_changes(autumn):
    app = create_app(autumn, secure_cookies=False, TESTING=True)
    admin = client_as(app, "admin")
    before = app.extensions["users"].audit_log()
    answer = admin.post("/settings/clock", data={"csrf_token": token(admin, "/settings"), "time_zone": "Europe/Londn"})
    assert answer.status_code == 400
    assert ("clock settings not changed: [monitor] time_zone: unknown time zone &#39;Europe/Londn&#39;"
            in answer.get_data(as_text=True))
    assert not (autumn / "settings.toml").exists() and app.extensions["users"].audit_log() == before


def test_the_command_line_report_takes_the_beds_zone_or_one_given_and_refuses_an_unknown_one(autumn, capsys):
    out = autumn / "s.csv"
    assert main(["report", "--data-dir", str(autumn), "--out", str(out)]) == 0
    assert csv_rows(out.read_text())[0]["time_local"] == "2026-10-24T20:30:00-04:00"      # the monitor's zone
    assert "times in America/New_York" in capsys.readouterr().err
    assert main(["report", "--data-dir", str(autumn), "--out", str(out), "--time-zone", "Europe/London"]) == 0
    assert [r["time_local"] for r in csv_rows(out.read_text())] == ["2026-10-25T01:30:00+01:00",
                                                                    "2026-10-25T01:30:00+00:00"]
    with pytest.raises(SystemExit) as exited:
        main(["report", "--data-dir", str(autumn), "--out", str(out), "--time-zone", "Mars/Base"])
    assert exited.value.code == 2
    assert "argument --time-zone: unknown time zone 'Mars/Base'" in capsys.readouterr().err


def test_chart_ticks_fall_on_the_local_hour_in_a_zone_half_an_hour_off_utc():
    from webui.history import time_ticks

    start = utc(2026, 10, 25, 0, 10)                        # 05:40 in India (UTC+5:30)
    ticks = time_ticks(start, start + 6 * 3600, offset_s=5.5 * 3600)
    kolkata = time_zone("Asia/Kolkata")
    assert [clock_text(t, kolkata, "%H:%M") for t in ticks] == ["06:00", "07:00", "08:00", "09:00", "10:00",
                                                                "11:00"]
    assert {clock_text(t, kolkata, "%M") for t in time_ticks(start, start + 6 * 3600)} == {"30"}   # UTC's hours
