"""The ward screen reading the hospital history: each bed's peak pressure per minute and the ward's events over
the look-back, from a real PostgreSQL written with the history's own store; only this ward's, read at most once
a period, and the live board answering when the database is gone. The ``[history]`` table of the station's
configuration."""

import datetime as dt
import time

import psycopg
import pytest
from mqtt_broker import free_port, wait_until
from postgres_server import running_postgres
from ward_payloads import summary
from webui_client import client_as

from appliance.errors import ConfigError
from appliance.hospital.history.schema import create_schema
from appliance.hospital.history.store import StoredEvent, write_events, write_minutes
from appliance.hospital.history.trend import Minute
from appliance.service.config_sections import MqttSettings
from appliance.ward.config import HistorySource, WardConfig, ward_config_from_mapping
from webui import create_ward_app

MINUTE = dt.timedelta(minutes=1)
HOUR = dt.timedelta(hours=1)


def this_minute() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(second=0, microsecond=0)


def event(ward, bed, seq, at, type_, kind, priority=None, message="Sacrum dose over limit"):
    return StoredEvent(at, ward, bed, seq, type_, {"type": type_, "kind": kind, "priority": priority,
                                                   "alarm_id": seq if type_ == "alarm" else None, "bed_id": bed,
                                                   "seq": seq, "message": message})


def minute(ward, bed, at, peak):
    return Minute(ward, bed, at, 60, 0 if peak is None else 60, peak, peak, "supine", last_at=at + MINUTE)


def ward_app(tmp_path, station, dsn, **config):
    ward_config = WardConfig(MqttSettings("127.0.0.1"), client_id="test-station",
                             history=HistorySource(dsn, "ward3", look_back_h=12.0))
    return create_ward_app(tmp_path, station, ward_config, secure_cookies=False, TESTING=True, **config)


def get(client, path):
    answer = client.get(path)
    assert answer.status_code == 200, answer.get_data(as_text=True)
    return answer.get_json()


def test_the_screen_shows_each_beds_trend_and_the_wards_events_of_the_look_back(tmp_path, station, beds,
                                                                                 history_dsn):
    now = this_minute()
    with psycopg.connect(history_dsn) as db:
        write_events(db, [
            event("ward3", "w3-bed01", 4, now - 10 * MINUTE, "alarm", "raised", "high"),
            event("ward3", "w3-bed02", 9, now - 11 * HOUR, "turn", "recorded", message="turn recorded by n.lee"),
            event("ward3", "w3-bed02", 8, now - 13 * HOUR, "alarm", "raised", "medium"),     # before the shift
            event("ward4", "w4-bed01", 1, now - 5 * MINUTE, "alarm", "raised", "high"),      # another ward's
        ])
        write_minutes(db, [
            minute("ward3", "w3-bed01", now - 3 * MINUTE, 38.5),
            minute("ward3", "w3-bed01", now - 2 * MINUTE, None),                            # a minute of faults
            minute("ward3", "w3-bed01", now - 1 * MINUTE, 41.3),          # float4: sent as 41.3, not 41.2999992
            minute("ward3", "w3-bed02", now - 11 * HOUR, 22.0),
            minute("ward3", "w3-bed02", now - 13 * HOUR, 99.0),                              # before the shift
            minute("ward4", "w4-bed01", now - 1 * MINUTE, 60.0),                             # another ward's
        ])
    app = ward_app(tmp_path, station, history_dsn)
    nurse = client_as(app, "nurse")
    beds("w3-bed01").summarise(summary("w3-bed01"))
    assert wait_until(lambda: [b["peak_mmhg"] for b in get(nurse, "/api/ward")["beds"]] == [41.5])

    history = get(nurse, "/api/ward/history")
    assert history["available"] is True and history["look_back_h"] == 12.0
    assert history["read_at"] - history["since"] == pytest.approx(12 * 3600.0)
    assert history["trends"] == {
        "w3-bed01": [[(now - 3 * MINUTE).timestamp(), 38.5], [(now - 2 * MINUTE).timestamp(), None],
                     [(now - MINUTE).timestamp(), 41.3]],
        "w3-bed02": [[(now - 11 * HOUR).timestamp(), 22.0]]}
    assert [(e["bed_id"], e["seq"], e["type"], e["kind"], e["priority"], e["message"]) for e in history["events"]] == [
        ("w3-bed01", 4, "alarm", "raised", "high", "Sacrum dose over limit"),
        ("w3-bed02", 9, "turn", "recorded", None, "turn recorded by n.lee")]
    assert history["events"][0]["stored_at"] == (now - 10 * MINUTE).timestamp()
    assert history["events_cut"] is False

    assert "trends" not in get(nurse, "/api/ward")                  # the live board and its stream stay small
    page = nurse.get("/ward").get_data(as_text=True)
    assert 'id="history"' in page and "Ward history, last 12 h" in page and 'data-refresh-s="30.0"' in page


def test_a_look_back_with_more_events_than_listed_lists_the_newest_and_says_older_ones_are_left_out(
        tmp_path, station, history_dsn):
    from webui.ward_history import EVENTS_SHOWN

    now = this_minute()
    with psycopg.connect(history_dsn) as db:
        write_events(db, [event("ward3", "w3-bed01", seq, now - (EVENTS_SHOWN + 1 - seq) * dt.timedelta(seconds=10),
                                "alarm", "raised", "medium") for seq in range(EVENTS_SHOWN + 1)])
    history = get(client_as(ward_app(tmp_path, station, history_dsn), "nurse"), "/api/ward/history")
    assert history["events_cut"] is True
    assert [e["seq"] for e in history["events"]] == list(range(EVENTS_SHOWN, 0, -1))     # seq 0, the oldest, left out


def test_the_history_is_read_at_most_once_a_period_and_again_after_a_failure(tmp_path, history_dsn):
    from appliance.ward.station import WardStation

    clock, connections, refusing = [time.time()], [], [True]

    def connect():
        connections.append(clock[0])
        if refusing[0]:
            raise psycopg.OperationalError("connection refused")
        return psycopg.connect(history_dsn)

    with WardStation("127.0.0.1", free_port(), client_id="lonely-station") as station:
        app = ward_app(tmp_path, station, history_dsn)
        history = app.extensions["ward_history"]
        history.connect, history.clock = connect, lambda: clock[0]
        nurses = [client_as(app, "nurse", f"nurse.{n}") for n in range(3)]      # three screens
        assert get(nurses[0], "/api/ward/history")["available"] is False
        refusing[0] = False
        clock[0] += 29.0
        assert get(nurses[1], "/api/ward/history")["available"] is False   # the failure is kept for the period
        assert len(connections) == 1
        clock[0] += 1.0
        assert get(nurses[2], "/api/ward/history")["available"] is True    # the first poll after it tries again
        for nurse in nurses:
            assert get(nurse, "/api/ward/history")["available"] is True
        assert len(connections) == 2                                       # however many screens ask


def test_with_the_database_stopped_the_board_still_answers_and_says_the_history_is_unavailable(
        tmp_path, station, beds):
    with running_postgres() as postgres:
        postgres.psql("CREATE DATABASE stopping")
        dsn = postgres.dsn("stopping")
        with psycopg.connect(dsn) as db:
            create_schema(db)
            write_minutes(db, [minute("ward3", "w3-bed05", this_minute() - MINUTE, 30.0)])
        app = ward_app(tmp_path, station, dsn, HISTORY_REFRESH_S=0.0)
        nurse = client_as(app, "nurse")
        assert list(get(nurse, "/api/ward/history")["trends"]) == ["w3-bed05"]
    history = get(nurse, "/api/ward/history")                           # the server is stopped and gone
    assert (history["available"], history["trends"], history["events"], history["events_cut"]) == (False, {}, [], False)
    beds("w3-bed05").summarise(summary("w3-bed05"))
    assert wait_until(lambda: [b["bed_id"] for b in get(nurse, "/api/ward")["beds"]] == ["w3-bed05"])
    page = nurse.get("/ward")
    assert page.status_code == 200 and 'id="history"' in page.get_data(as_text=True)


def test_a_station_without_history_shows_none_and_has_no_history_endpoint(tmp_path):
    from appliance.ward.station import WardStation

    with WardStation("127.0.0.1", free_port(), client_id="lonely-station") as station:
        app = create_ward_app(tmp_path, station, WardConfig(MqttSettings("127.0.0.1")), secure_cookies=False,
                              TESTING=True)
        nurse = client_as(app, "nurse")
        assert 'id="history"' not in nurse.get("/ward").get_data(as_text=True)
        assert nurse.get("/api/ward/history").status_code == 404


BROKER = {"host": "broker.ward3"}


@pytest.mark.parametrize("history, message", [
    ({"dsn": "host=db"}, "[history] is missing 'ward'"),
    ({"ward": "ward3"}, "[history] is missing 'dsn'"),
    ({"dsn": "", "ward": "ward3"}, "[history]: dsn must be non-empty text"),
    ({"dsn": "history.hospital", "ward": "ward3"}, "[history]: dsn is not a PostgreSQL connection string"),
    ({"dsn": "host=db colour=blue", "ward": "ward3"}, "[history]: dsn is not a PostgreSQL connection string"),
    ({"dsn": "postgresql://station:secret@db/appliance_history", "ward": "ward3"},
     "[history]: dsn must not hold the password"),
    ({"dsn": "host=db", "ward": "ward 3"}, "[history] ward 'ward 3': must be 1-64 characters"),
    ({"dsn": "host=db", "ward": "ward3", "look_back_h": 0.5}, "[history]: look_back_h must be from 1 to 24"),
    ({"dsn": "host=db", "ward": "ward3", "look_back_h": 36}, "[history]: look_back_h must be from 1 to 24"),
    ({"dsn": "host=db", "ward": "ward3", "look_back_h": "12"}, "[history]: look_back_h must be a number"),
    ({"dsn": "host=db", "ward": "ward3", "since_h": 12}, "[history]: unknown key 'since_h'"),
    ("host=db", "[history] must be a table"),
])
def test_a_bad_history_table_is_refused_naming_the_key(history, message):
    with pytest.raises(ConfigError) as caught:
        ward_config_from_mapping({"broker": BROKER, "history": history})
    assert message in str(caught.value)


def test_the_history_table_reads_a_shift_of_the_engines_ward_by_default(tmp_path):
    (tmp_path / "pw").write_text("secret\n")
    engine = {"servers": ["nats://n1:4222"], "ward": "ward3", "password_file": "pw"}
    config = ward_config_from_mapping({"engine": engine, "history": {"dsn": "host=db dbname=h"}}, tmp_path)
    assert config.history == HistorySource("host=db dbname=h", "ward3", 12.0)
    config = ward_config_from_mapping({"broker": BROKER, "history": {"dsn": "host=db passfile=/x", "ward": "w7",
                                                                     "look_back_h": 8}})
    assert config.history == HistorySource("host=db passfile=/x", "w7", 8.0)
    assert ward_config_from_mapping({"broker": BROKER}).history is None
