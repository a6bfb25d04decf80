"""The hospital's history in a real PostgreSQL, fed by a real three-node engine: each event stored once even when
the writer dies between its commit and its acknowledgement, pressure down-sampled to minutes, partitions made
ahead and dropped whole by the retention, and a bad retention policy refused naming its field."""

import asyncio
import dataclasses
import datetime as dt
import json
import re
import signal
import subprocess
import sys
import threading

import nats.errors
import psycopg
import pytest
from hospital_engine import logged_in, make_streams, running_cluster
from mqtt_broker import wait_until

from appliance.errors import ConfigError
from appliance.hospital.description import HistoryPolicy, description_text, hospital_from_mapping, load_hospital
from appliance.hospital.engine import BedPublisher
from appliance.hospital.history.reads import alarm_counts, pressure_trend, recent_events, ward_trends
from appliance.hospital.history.schema import EVENTS, PRESSURE, drop_expired, ensure_ahead, partitions
from appliance.hospital.history.store import StoredEvent, write_events, write_minutes
from appliance.hospital.history.trend import MinuteTrend
from appliance.hospital.history.writer import HistoryWriter
from appliance.hospital.nodeconfig import HISTORY
from appliance.hospital.subjects import bed_subject

UTC = dt.UTC
POLICY = HistoryPolicy(events_days=60, pressure_days=7)


@pytest.fixture
def db(history_dsn):
    """A connection to a new database for each test, with the history's tables."""
    with psycopg.connect(history_dsn) as connection:
        yield connection


def event(ward, bed, seq, at, kind="raised", priority="high"):
    return StoredEvent(at, ward, bed, seq, "alarm", {"type": "alarm", "kind": kind, "priority": priority,
                                                     "alarm_id": seq, "bed_id": bed, "seq": seq})


class Killed(Exception):
    """The writer's process dying: nothing after this point of its code runs."""


class DiesBeforeItsFirstAcknowledgement(HistoryWriter):
    async def acknowledge(self, messages):
        raise Killed


def test_each_event_is_stored_once_when_the_writer_dies_between_commit_and_acknowledgement(tmp_path, db):
    alarms, turns = 30, 10

    async def run(cluster, hospital):
        await make_streams(cluster)
        async with logged_in(cluster, "bed1") as bed1, logged_in(cluster, "bed3") as bed3:
            for seq in range(1, alarms + 1):
                await BedPublisher(bed1, "ward1", "bed1").send("alarm", seq, {"type": "alarm", "kind": "raised",
                                                                              "priority": "high", "alarm_id": seq})
            for seq in range(1, turns + 1):
                await BedPublisher(bed3, "ward2", "bed3").send("turn", seq, {"type": "turn", "kind": "repositioned"})
        async with logged_in(cluster, HISTORY) as connection:
            first = DiesBeforeItsFirstAcknowledgement(db, connection, hospital, ack_wait_s=2.0)
            subscription = await first.subscribe("ward1")
            give_up = asyncio.get_running_loop().time() + 30
            with pytest.raises(Killed):                   # a busy machine may answer the first fetch empty
                while asyncio.get_running_loop().time() < give_up:
                    await first.step(subscription, "ward1")
        committed = db.execute("SELECT count(*) FROM event").fetchone()[0]
        async with logged_in(cluster, HISTORY) as connection:      # started again: the same durable consumers
            second = HistoryWriter(db, connection, hospital, ack_wait_s=2.0)
            subscriptions = {ward: await second.subscribe(ward) for ward in ("ward1", "ward2")}
            give_up = asyncio.get_running_loop().time() + 30
            while second.stored + second.duplicates < alarms + turns and asyncio.get_running_loop().time() < give_up:
                for ward, subscription in subscriptions.items():
                    await second.step(subscription, ward, timeout_s=0.5)
            quiet = [await second.step(s, w, timeout_s=0.5) for w, s in subscriptions.items()]
        return committed, second, quiet

    with running_cluster(tmp_path) as cluster:
        hospital = dataclasses.replace(cluster.hospital, history=POLICY)
        committed, second, quiet = asyncio.run(run(cluster, hospital))
    assert committed == alarms                  # the first writer's batch was committed, then never acknowledged
    assert second.duplicates == alarms          # ... so all of it came again, and was dropped by its keys
    assert second.stored == turns and second.rejected == 0
    assert quiet == [0, 0]                      # everything acknowledged now: nothing more comes
    rows = db.execute("SELECT bed_id, seq, ward, type, count(*) FROM event GROUP BY 1, 2, 3, 4 ORDER BY 1, 2")
    assert rows.fetchall() == [("bed1", seq, "ward1", "alarm", 1) for seq in range(1, alarms + 1)] + \
        [("bed3", seq, "ward2", "turn", 1) for seq in range(1, turns + 1)]
    assert [e["seq"] for e in recent_events(db, dt.datetime.now(UTC) - dt.timedelta(hours=1), ward="ward2")] == \
        list(range(turns, 0, -1))
    assert alarm_counts(db, dt.datetime.now(UTC) - dt.timedelta(hours=1)) == {"ward1": {"high": alarms}}


def test_the_history_user_reads_but_cannot_publish_events_or_change_a_stream(tmp_path):
    async def run(cluster):
        await make_streams(cluster)
        errors = []

        async def on_error(error):
            errors.append(str(error))

        async with logged_in(cluster, HISTORY, on_error=on_error) as connection:
            with pytest.raises(TimeoutError, match="not acknowledged"):
                await BedPublisher(connection, "ward1", "bed1").send("alarm", 1, {"kind": "forged"}, deadline_s=1)
            with pytest.raises(nats.errors.Error):
                await connection.jetstream(timeout=1).delete_stream("ALARMS_ward1")
        async with logged_in(cluster, "hospital-admin") as admin:
            info = await admin.jetstream().stream_info("ALARMS_ward1")
        return errors, info.state.messages

    with running_cluster(tmp_path) as cluster:
        errors, stored = asyncio.run(run(cluster))
    assert stored == 0
    assert any('publish to "hospital.ward1.bed1.alarm"' in error for error in errors)
    assert any('publish to "$js.api.stream.delete.alarms_ward1"' in error.lower() for error in errors), errors


def test_a_resend_stored_again_by_the_engine_on_another_month_is_kept_once(db):
    first = dt.datetime(2026, 10, 31, 23, 59, tzinfo=UTC)
    again = dt.datetime(2026, 11, 1, 0, 20, tzinfo=UTC)         # outside the stream's window, in the next month
    assert write_events(db, [event("w", "b", 7, first), event("w", "b", 8, first)]) == 2
    assert write_events(db, [event("w", "b", 7, again), event("w", "b", 9, again)]) == 1
    assert db.execute("SELECT seq, stored_at FROM event ORDER BY seq").fetchall() == [(7, first), (8, first),
                                                                                       (9, again)]
    assert partitions(db, EVENTS) == ["event_20261001", "event_20261101"]


def test_partitions_are_made_ahead_and_retention_drops_whole_ones_past_the_policy(db):
    now = dt.datetime(2026, 11, 26, 12, 0, tzinfo=UTC)
    assert ensure_ahead(db, now) == ["event_20261101", "pressure_minute_20261126", "pressure_minute_20261127",
                                     "pressure_minute_20261128"]
    assert ensure_ahead(db, now + dt.timedelta(days=4))[0:2] == ["event_20261101", "event_20261201"]
    old_events = [event("w", "b", seq, now - dt.timedelta(days=days)) for seq, days in ((1, 90), (2, 61), (3, 20))]
    write_events(db, old_events)
    trend = MinuteTrend()
    for days in (9, 8, 7, 6):
        trend.add("w", "b", (now - dt.timedelta(days=days)).timestamp(), {"peak_mmhg": 30.0, "regions": []})
    write_minutes(db, trend.take())
    assert partitions(db, EVENTS) == ["event_20260801", "event_20260901", "event_20261101", "event_20261201"]
    before = partitions(db, PRESSURE)
    assert before == ["pressure_minute_20261117", "pressure_minute_20261118", "pressure_minute_20261119",
                      "pressure_minute_20261120", "pressure_minute_20261126", "pressure_minute_20261127",
                      "pressure_minute_20261128", "pressure_minute_20261130",
                      "pressure_minute_20261201", "pressure_minute_20261202"]

    dropped = drop_expired(db, now, POLICY.events_days, POLICY.pressure_days)
    # events: 60 days before is 27 September, so August's month (ending 1 September) goes and September's stays,
    # with the event of 26 September in it: data is kept for the policy's days and at most one partition more;
    # pressure: 7 days before is 19 November noon, so the 17th and 18th go and the 19th, partly younger, stays
    assert dropped == ["event_20260801", "pressure_minute_20261117", "pressure_minute_20261118"]
    assert db.execute("SELECT seq FROM event ORDER BY seq").fetchall() == [(2,), (3,)]
    assert db.execute("SELECT seq FROM event_key ORDER BY seq").fetchall() == [(2,), (3,)]
    assert db.execute("SELECT count(*) FROM pressure_minute").fetchone()[0] == 2
    assert drop_expired(db, now, POLICY.events_days, POLICY.pressure_days) == []


def test_a_minute_written_in_two_parts_keeps_each_zones_highest_and_the_latest_state(db):
    start = dt.datetime(2026, 11, 26, 3, 15, tzinfo=UTC).timestamp()
    parts = []
    for seconds, summaries in ((range(20), [(40.0, "supine", 50.0, 0.2)]),
                               (range(30, 40), [(60.0, "left", 45.0, 0.3), (None, "left", None, None)])):
        trend = MinuteTrend()
        for second in seconds:
            for peak, posture, sacrum, dose in summaries:
                regions = [] if sacrum is None else [{"zone": "sacrum", "peak_mmhg": sacrum, "dose": dose},
                                                     {"zone": None, "peak_mmhg": peak, "dose": 0.0}]
                trend.add("ward3", "bed1", start + second, {"peak_mmhg": peak, "posture": posture, "regions": regions})
        parts += trend.take()
    for part in parts:
        write_minutes(db, [part])
    [minute] = pressure_trend(db, "bed1", dt.datetime.fromtimestamp(start, UTC))
    assert (minute["samples"], minute["maps"]) == (40, 30)
    assert minute["peak_max_mmhg"] == 60.0 and minute["peak_last_mmhg"] is None and minute["posture"] == "left"
    assert minute["region_max_mmhg"] == {"sacrum": 50.0, "unidentified": 60.0}
    assert minute["region_dose"] == {"sacrum": 0.3, "unidentified": 0.0}


async def until(condition, timeout_s=10.0):
    give_up = asyncio.get_running_loop().time() + timeout_s
    while not condition():
        assert asyncio.get_running_loop().time() < give_up, "not within the time"
        await asyncio.sleep(0.02)


def test_the_writer_turns_summaries_heard_on_the_engine_into_minutes(tmp_path, db):
    clock = [dt.datetime(2026, 11, 26, 8, 0, 5, tzinfo=UTC).timestamp()]

    async def run(cluster, hospital):
        await make_streams(cluster)
        async with logged_in(cluster, HISTORY) as connection, logged_in(cluster, "bed2") as bed:
            writer = HistoryWriter(db, connection, hospital, flush_every_s=0.1, clock=lambda: clock[0])
            running = asyncio.create_task(writer.run())
            start, clock[0] = clock[0], clock[0] - 3600        # an hour before: probes until the writer hears them
            while writer.heard == 0:                           # (its subscription has reached the bed's node)
                await bed.publish(bed_subject("ward1", "bed2", "summary"), json.dumps(
                    {"bed_id": "bed2", "peak_mmhg": 1.0, "posture": "supine", "regions": []}).encode())
                await asyncio.sleep(0.2)
            await bed.flush()                                  # every probe sent is at the server, and the server
            await connection.flush()                           # has handed the writer's connection what it routed
            await asyncio.sleep(0.5)                           # to it: the writer's callbacks have had their turn
            clock[0], probes = start, writer.heard
            for second in range(12):
                clock[0] += 5                                  # 08:00:10 ... 08:00:55, then 08:01:00 and 08:01:05
                await bed.publish(bed_subject("ward1", "bed2", "summary"), json.dumps(
                    {"bed_id": "bed2", "peak_mmhg": 20.0 + second, "posture": "supine",
                     "regions": [{"zone": "heel-left", "peak_mmhg": 10.0 + second, "dose": 0.01}]}).encode())
                await until(lambda second=second: writer.heard == probes + second + 1)
            await until(lambda: db_minutes() == 1)             # the finished minute, written while running
            writer.stop()
            await running
        return writer

    def db_minutes():
        with psycopg.connect(db.info.dsn) as other:
            return other.execute("SELECT count(*) FROM pressure_minute WHERE minute >= %s",
                                 (dt.datetime(2026, 11, 26, 8, tzinfo=UTC),)).fetchone()[0]

    with running_cluster(tmp_path) as cluster:
        writer = asyncio.run(run(cluster, dataclasses.replace(cluster.hospital, history=POLICY)))
    rows = pressure_trend(db, "bed2", dt.datetime(2026, 11, 26, 8, tzinfo=UTC))
    assert [(r["minute"].minute, r["samples"], r["maps"], r["peak_max_mmhg"], r["peak_last_mmhg"]) for r in rows] == \
        [(0, 10, 10, 29.0, 29.0), (1, 2, 2, 31.0, 31.0)]
    assert [r["region_max_mmhg"] for r in rows] == [{"heel-left": 19.0}, {"heel-left": 21.0}]
    assert writer.rejected == 0
    eight = dt.datetime(2026, 11, 26, 8, tzinfo=UTC)
    assert ward_trends(db, "ward1", eight) == {"bed2": [(eight, 29.0), (eight + dt.timedelta(minutes=1), 31.0)]}
    assert ward_trends(db, "ward2", dt.datetime(2026, 11, 26, 8, tzinfo=UTC)) == {}


def description(history):
    return {"hospital": {"cluster": "st-mary", "store_dir": "/var/lib/h"},
            "node": [{"name": "n1", "host": "127.0.0.1"}], "ward": [{"name": "w", "beds": ["b"], "stations": ["s"]}],
            "history": history}


@pytest.mark.parametrize("history, message", [
    ({"pressure_days": 7}, "[history] events_days is missing: how many days the hospital keeps them is its policy"),
    ({"events_days": 60}, "[history] pressure_days is missing"),
    ({"events_days": 0, "pressure_days": 7}, "[history] events_days must be a whole number of days from 1 to 36525, "
                                             "got 0"),
    ({"events_days": 60, "pressure_days": 7.5}, "[history] pressure_days must be a whole number of days from 1 to "
                                                "36525, got 7.5"),
    ({"events_days": True, "pressure_days": 7}, "[history] events_days must be a whole number of days"),
    ({"events_days": 60, "pressure_days": 40000}, "pressure_days must be a whole number of days from 1 to 36525, "
                                                  "got 40000"),
    ({"events_days": 60, "pressure_days": 7, "database": "History"}, "[history] database 'History': must be 1-63 "
                                                                     "lower-case letters"),
    ({"events_days": 60, "pressure_days": 7, "database": "a;drop"}, "[history] database 'a;drop'"),
    ({"events_days": 60, "pressure_days": 7, "keep": 1}, "unknown key 'keep'"),
    ([], "[history] is missing or not a table"),
])
def test_a_bad_retention_policy_is_refused_naming_its_field(history, message):
    data = description(history)
    data["hospital"]["replicas"] = 1
    with pytest.raises(ConfigError) as raised:
        hospital_from_mapping(data)
    assert message in str(raised.value)


def test_a_good_policy_is_read_written_back_and_the_writer_refuses_to_start_without_one(db, tmp_path):
    data = description({"events_days": 3650, "pressure_days": 90})
    data["hospital"]["replicas"] = 1
    hospital = hospital_from_mapping(data)
    assert hospital.history == HistoryPolicy(3650, 90, "appliance_history")
    (tmp_path / "h.toml").write_text(description_text(hospital))
    assert load_hospital(tmp_path / "h.toml") == hospital
    with pytest.raises(ValueError, match=r"no \[history\] table: the history writer needs its retention policy"):
        HistoryWriter(db, object(), dataclasses.replace(hospital, history=None))


def test_the_history_command_sigkilled_and_started_again_stores_every_event_once(tmp_path, postgres):
    """The writer as systemd runs it, SIGKILLed while a bed publishes and started again: every acknowledged
    event in the table once; SIGTERM then stops it cleanly with its counts."""
    postgres.psql("CREATE DATABASE killed_writer")
    dsn = postgres.dsn("killed_writer")
    total = 200

    def count():
        with psycopg.connect(dsn) as db:
            exists = db.execute("SELECT to_regclass('event')").fetchone()[0]
            return db.execute("SELECT count(*) FROM event").fetchone()[0] if exists else 0

    async def publish(cluster, seqs):
        async with logged_in(cluster, "bed2") as bed:
            for seq in seqs:
                await BedPublisher(bed, "ward1", "bed2").send("alarm", seq, {"type": "alarm", "kind": "raised",
                                                                             "priority": "medium"})
                await asyncio.sleep(0.025)                 # 5 s in all: the kill falls while it publishes

    with running_cluster(tmp_path) as cluster:
        asyncio.run(make_streams(cluster))
        path = tmp_path / "hospital.toml"
        path.write_text(description_text(dataclasses.replace(cluster.hospital, history=POLICY)))
        command = [sys.executable, "-m", "appliance", "hospital", "history", "--description", str(path), "--secrets",
                   str(cluster.configs.secrets_folder), "--dsn", dsn]
        writer = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            publisher = threading.Thread(target=lambda: asyncio.run(publish(cluster, range(1, total + 1))))
            publisher.start()
            assert wait_until(lambda: count() >= 1, timeout_s=30)
            writer.send_signal(signal.SIGKILL)
            writer.communicate(timeout=10)
            killed_at = count()
            writer = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            assert writer.stdout.readline().startswith("history writer: 2 ward stream(s)")   # SIGTERM handled now
            publisher.join(60)
            assert wait_until(lambda: count() == total, timeout_s=40), count()
            writer.send_signal(signal.SIGTERM)
            output = writer.communicate(timeout=30)[0]
        finally:
            if writer.poll() is None:
                writer.kill()
                writer.communicate(timeout=10)
    assert writer.returncode == 0, output
    assert 0 < killed_at < total
    with psycopg.connect(dsn) as db:
        assert db.execute("SELECT seq, count(*) FROM event WHERE bed_id = 'bed2' GROUP BY seq ORDER BY seq") \
            .fetchall() == [(seq, 1) for seq in range(1, total + 1)]
    stored = int(re.search(r"stopped: (\d+) event\(s\) stored", output).group(1))
    assert stored == total - killed_at          # the second writer stored exactly what the first had not
