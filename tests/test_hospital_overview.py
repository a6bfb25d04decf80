"""The hospital overview on a real PostgreSQL history: every ward's beds heard and open alarms by priority, the
ward needing help first, every open alarm of the hospital highest first, read-only, behind the login."""

import datetime as dt

import psycopg
import pytest
from webui_client import client_as

from appliance.hospital.description import hospital_from_mapping
from appliance.hospital.history.reads import open_alarms
from appliance.hospital.history.store import StoredEvent, write_events, write_minutes
from appliance.hospital.history.trend import Minute
from webui import create_hospital_app

NOW = dt.datetime(2026, 11, 26, 3, 0, tzinfo=dt.UTC)
HOSPITAL = hospital_from_mapping({
    "hospital": {"cluster": "st-mary", "store_dir": "/var/lib/appliance-hospital"},
    "node": [{"name": f"n{i}", "host": f"10.0.0.{i}"} for i in (1, 2, 3)],
    "ward": [{"name": "ward3", "beds": ["w3-bed01", "w3-bed02", "w3-bed03"], "stations": ["ward3-station"]},
             {"name": "ward4", "beds": ["w4-bed01", "w4-bed02"], "stations": ["ward4-station"]}],
    "history": {"events_days": 3650, "pressure_days": 90}})


def alarm(ward, bed, seq, minutes_ago, alarm_id, kind, priority=None, site="sacrum", now=NOW):
    body = {"type": "alarm", "kind": kind, "priority": priority, "alarm_id": alarm_id, "bed_id": bed, "seq": seq,
            "site": site, "message": f"{site} dose over limit"}
    return StoredEvent(now - dt.timedelta(minutes=minutes_ago), ward, bed, seq, "alarm", body)


@pytest.fixture
def history(history_dsn):
    with psycopg.connect(history_dsn) as db:
        write_events(db, [
            alarm("ward3", "w3-bed01", 1, 50, 1, "raised", "medium"),
            alarm("ward3", "w3-bed01", 2, 20, 1, "escalated", "high"),        # open, high, not acknowledged
            alarm("ward3", "w3-bed02", 1, 90, 7, "raised", "medium", "heel-left"),
            alarm("ward3", "w3-bed02", 2, 80, 7, "acknowledged", site="heel-left"),   # open, medium, acknowledged
            alarm("ward4", "w4-bed01", 1, 30, 3, "raised", "high", "occiput"),
            alarm("ward4", "w4-bed01", 2, 10, 3, "ended"),                    # over
            alarm("ward4", "w4-bed02", 1, 60 * 30, 9, "raised", "high"),      # too old for the overview's reach
        ])
        write_minutes(db, [Minute("ward3", bed, NOW - dt.timedelta(minutes=1), 60, 60, 40.0, 38.0, "supine",
                                  last_at=NOW - dt.timedelta(seconds=30)) for bed in ("w3-bed01", "w3-bed02")]
                      + [Minute("ward4", "w4-bed01", NOW - dt.timedelta(minutes=10), 60, 60, 30.0, 30.0, "supine",
                                last_at=NOW - dt.timedelta(minutes=9))])
    return history_dsn


def test_open_alarms_are_the_unended_ones_highest_priority_first(history):
    with psycopg.connect(history) as db:
        alarms = open_alarms(db, NOW - dt.timedelta(days=1))
    assert [(a["bed_id"], a["alarm_id"], a["priority"], a["kind"]) for a in alarms] == [
        ("w3-bed01", 1, "high", "escalated"), ("w3-bed02", 7, "medium", "acknowledged")]
    assert alarms[0]["raised_at"] == NOW - dt.timedelta(minutes=50) and alarms[1]["site"] == "heel-left"


def test_the_overview_shows_each_ward_the_ward_needing_help_first(history, tmp_path, monkeypatch):
    import webui.hospital

    monkeypatch.setattr(webui.hospital, "hospital_view", _at_now(webui.hospital.hospital_view))
    app = create_hospital_app(tmp_path, HOSPITAL, lambda: psycopg.connect(history), secure_cookies=False,
                              TESTING=True)
    assert app.test_client().get("/hospital").headers["Location"].endswith("/setup")   # behind the login
    client = client_as(app, "nurse")
    view = client.get("/api/hospital").get_json()
    ward3, ward4 = view["wards"]
    assert ward3 == {"name": "ward3", "beds": 3, "heard": 2, "silent": ["w3-bed03"],
                     "open": {"high": 1, "medium": 1, "low": 0}, "unacknowledged": 1,
                     "raised_last_hour": 1, "raised_last_day": 2}
    assert ward4["heard"] == 0 and ward4["open"] == {"high": 0, "medium": 0, "low": 0}
    assert ward4["raised_last_day"] == 1                                         # raised and ended within the day
    assert [a["bed_id"] for a in view["open_alarms"]] == ["w3-bed01", "w3-bed02"]
    page = client.get("/hospital").get_data(as_text=True)
    assert "2 of 3" in page and "w3-bed03" in page and "sacrum dose over limit" in page
    assert client.get("/").headers["Location"].endswith("/hospital")


def test_the_overview_only_reads(history, tmp_path):
    """The connection it is given is put in read-only mode before any query."""
    seen = []

    def connect():
        connection = psycopg.connect(history)
        seen.append(connection)
        return connection

    app = create_hospital_app(tmp_path, HOSPITAL, connect, secure_cookies=False, TESTING=True)
    client_as(app, "nurse").get("/api/hospital")
    assert seen and all(c.read_only for c in seen)
    with psycopg.connect(history) as db, pytest.raises(psycopg.errors.ReadOnlySqlTransaction):
        db.read_only = True
        db.execute("DELETE FROM event")


def _at_now(view):
    return lambda now=None: view(NOW)
