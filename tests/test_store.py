"""The SQLite store: schema, atomic frames, down-sampled history, retention and refusal of bad files."""

import sqlite3
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.turns import TurnEvent
from appliance.store import SchemaTooNew, Store, StoreClosed, StoreCorrupt, StoreError
from appliance.store.database import DAY_S, SCHEMA_VERSION, STATE_SYNC_S


def raw(path, sql):
    """Ask the file directly, on a connection of its own, what is really on disk."""
    db = sqlite3.connect(path)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


def alarm_event(t, kind="raised", alarm_id=1):
    return AlarmEvent(time_s=t, kind=kind, alarm_id=alarm_id, key="sacrum", category="clinical",
                      priority="high", message="Sacrum pressure", user=None, channel=None)


def test_schema_created_with_wal_and_incremental_vacuum(tmp_path):
    path = tmp_path / "store.db"
    with Store.open(path):
        pass
    assert raw(path, "SELECT version FROM schema_version") == [(SCHEMA_VERSION,)]
    assert raw(path, "PRAGMA journal_mode") == [("wal",)]
    assert raw(path, "PRAGMA auto_vacuum") == [(2,)]
    tables = {name for (name,) in raw(path, "SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"schema_version", "events", "state", "pressure_history"} <= tables
    with Store.open(path) as store:  # reopening migrates nothing and keeps the version
        assert store.last_time() is None
    assert raw(path, "SELECT version FROM schema_version") == [(SCHEMA_VERSION,)]


def test_a_read_only_store_reads_beside_a_writer_and_takes_no_writes(tmp_path):
    path = tmp_path / "store.db"
    with Store.open(path) as store:
        store.save_state("alerts", {"dose": 0.5}, 10.0)
    writer = sqlite3.connect(path, isolation_level=None)
    writer.execute("BEGIN IMMEDIATE")                     # the monitor inside a frame's commit
    writer.execute("INSERT INTO state (name, saved_at_s, value) VALUES ('late', 11.0, '{}')")
    try:
        with Store.open_read_only(path) as reader:
            assert reader.load_state("alerts") == {"dose": 0.5} and reader.load_state("late") is None
            with pytest.raises(StoreError, match="is open read-only: it takes no writes"):
                reader.save_state("alerts", {"dose": 0.0}, 12.0)
            with pytest.raises(sqlite3.OperationalError, match="readonly database"):
                reader._conn().execute("DELETE FROM state")
    finally:
        writer.execute("ROLLBACK")
        writer.close()
    assert raw(path, "SELECT name FROM state") == [("alerts",)]


def test_a_read_only_store_needs_the_file_made_and_migrated_by_a_writer(tmp_path):
    with pytest.raises(StoreError, match="cannot open store .*missing.db to read"):
        Store.open_read_only(tmp_path / "missing.db")
    old = tmp_path / "old.db"
    with Store.open(old):
        pass
    db = sqlite3.connect(old)
    db.execute("UPDATE schema_version SET version = 1")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match=f"schema version 1, not {SCHEMA_VERSION}: the monitor brings it up"):
        Store.open_read_only(old)
    assert raw(old, "SELECT version FROM schema_version") == [(1,)]


def test_events_of_both_engines_round_trip_with_extra_fields_in_detail(tmp_path):
    with Store.open(tmp_path / "store.db") as store:
        store.record_events([alarm_event(10.0),
                             AlarmEvent(12.0, "acknowledged", 1, "sacrum", "clinical", "high", "Sacrum pressure",
                                        user="nurse A", channel="bedside"),
                             TurnEvent(time_s=15.0, kind="repositioned", posture="left-30", previous="supine",
                                       how="posture")])
        events = store.events_since(11.0)
        assert store.last_time() == 15.0
    assert events[0]["kind"] == "acknowledged" and events[0]["user"] == "nurse A"
    assert events[0]["channel"] == "bedside"
    assert events[1] == {"time_s": 15.0, "kind": "repositioned", "alarm_id": None, "key": None, "category": None,
                         "priority": None, "user": None, "channel": None, "message": None,
                         "posture": "left-30", "previous": "supine", "how": "posture", "site": None}


def test_state_json_round_trip(tmp_path):
    state = {"version": 1, "alarms": [{"id": 3, "key": "heel", "paused_until_s": None, "priority": "medium"}],
             "next_id": 4, "ratio": 0.125}
    with Store.open(tmp_path / "store.db") as store:
        assert store.load_state("alarms") is None
        store.save_state("alarms", state, now_s=100.0)
        store.save_state("alarms", {**state, "next_id": 5}, now_s=101.0)
    with Store.open(tmp_path / "store.db") as store:
        assert store.load_state("alarms") == {**state, "next_id": 5}
        assert store.last_time() == 101.0


def test_a_failed_frame_leaves_neither_state_nor_events(tmp_path):
    with Store.open(tmp_path / "store.db") as store:
        store.commit_frame(1.0, [alarm_event(1.0)], {"alarms": {"n": 1}})
        with pytest.raises(ValueError, match="time_s and kind"):
            store.commit_frame(2.0, [alarm_event(2.0), {"kind": "no time"}], {"alarms": {"n": 2}})
        assert store.load_state("alarms") == {"n": 1}
        assert [e["time_s"] for e in store.events_since(0.0)] == [1.0]


class CountingStore(Store):
    """A store that notes the synchronous level of every write it makes."""

    def _transaction(self, synchronous):
        self.levels.append(synchronous)
        return super()._transaction(synchronous)


def test_quiet_frames_are_synced_once_a_state_sync_period_and_events_and_commands_at_once(tmp_path):
    store = CountingStore.open(tmp_path / "store.db")
    store.levels = []
    try:
        for t in range(60):                                      # a quiet minute at the bed's 1 s
            store.commit_frame(float(t), [], {"alerts": {"t": t}})
        assert [t for t, level in enumerate(store.levels) if level == "FULL"] == \
            list(range(0, 60, int(STATE_SYNC_S)))
        assert store.load_state("alerts") == {"t": 59}          # NORMAL commits are committed all the same
        store.levels.clear()
        store.commit_frame(60.0, [alarm_event(60.0)], {"alerts": {"t": 60}})       # an event: at once
        command = store.queue_command("acknowledge", {"alarm_id": 1}, "nurse.a")
        store.commit_frame(61.0, [], {"alerts": {"t": 61}}, [(command, True, "1 event(s)")])
        store.commit_frame(62.0, [], {"alerts": {"t": 62}})                        # 2 s after the last: NORMAL
        store.commit_frame(30.0, [], {"alerts": {"t": 30}})                        # the clock stepped back
        assert store.levels == ["FULL", "FULL", "FULL", "NORMAL", "FULL"]
    finally:
        store.close()


def test_a_process_killed_inside_a_frame_keeps_every_committed_frame_and_nothing_partial(tmp_path):
    path = tmp_path / "store.db"
    child = textwrap.dedent(f"""
        import os
        from appliance.store import Store
        store = Store.open({str(path)!r})
        for i in range(5):
            store.commit_frame(float(i), [{{"time_s": float(i), "kind": "raised", "alarm_id": i}},
                                          {{"time_s": float(i), "kind": "escalated", "alarm_id": i}}],
                               {{"alarms": {{"frame": i}}, "turns": {{"frame": i}}}})

        def dying_events():
            yield {{"time_s": 5.0, "kind": "raised", "alarm_id": 5}}
            os._exit(0)  # power cut: the state and one event of frame 5 are written, not committed

        store.commit_frame(5.0, dying_events(), {{"alarms": {{"frame": 5}}, "turns": {{"frame": 5}}}})
    """)
    subprocess.run([sys.executable, "-c", child], check=True, timeout=60)
    with Store.open(path) as store:
        events = store.events_since(0.0)
        assert [(e["time_s"], e["kind"]) for e in events] == [
            (float(i), kind) for i in range(5) for kind in ("raised", "escalated")]
        assert store.load_state("alarms") == {"frame": 4}
        assert store.load_state("turns") == {"frame": 4}
        assert store.last_time() == 4.0


def test_history_is_down_sampled_to_the_interval(tmp_path):
    with Store.open(tmp_path / "store.db", history_interval_s=60.0) as store:
        kept = [t for t in np.arange(0.0, 300.0, 7.0) if store.record_map(t, np.full((2, 3), t))]
        assert store.record_map(10.0, np.ones((2, 3))) is False  # a clock stepping back stores nothing
    assert kept == [0.0, 63.0, 126.0, 189.0, 252.0]
    with Store.open(tmp_path / "store.db", history_interval_s=60.0) as store:
        assert store.record_map(300.0, np.ones((2, 3))) is False  # the last kept time survives a restart
        assert store.record_map(312.0, np.ones((2, 3))) is True
        assert [t for t, _ in store.history_between(60.0, 200.0)] == [63.0, 126.0, 189.0]


def test_float32_maps_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pressure = rng.uniform(0.0, 20.0, size=(16, 24)).astype(np.float32)
    with Store.open(tmp_path / "store.db") as store:
        store.record_map(5.0, pressure)
        [(t, back)] = store.history_between(0.0, 10.0)
        with pytest.raises(ValueError, match="2-D"):
            store.record_map(500.0, np.ones(4))
        with pytest.raises(ValueError, match="non-finite"):
            store.record_map(500.0, np.full((2, 2), np.nan))
    assert t == 5.0 and back.dtype == np.float32 and back.shape == (16, 24)
    np.testing.assert_array_equal(back, pressure)
    assert raw(tmp_path / "store.db", "SELECT rows, cols, length(data), peak_kpa FROM pressure_history") == [
        (16, 24, 16 * 24 * 4, pytest.approx(float(pressure.max())))]


def test_prune_by_age(tmp_path):
    with Store.open(tmp_path / "store.db", history_days=30, event_days=365) as store:
        for day in range(41):
            store.record_map(day * DAY_S, np.full((4, 4), float(day)))
        store.record_events([alarm_event(day * DAY_S) for day in range(0, 400, 10)])
        deleted = store.prune(now_s=400 * DAY_S)
        assert deleted == {"history": 41, "events": 4}  # days 0..40 < day 370; days 0, 10, 20, 30 < day 35
        assert store.history_between(0.0, 1e12) == []
        assert store.events_since(0.0)[0]["time_s"] == 40 * DAY_S
        store.record_map(401 * DAY_S, np.ones((4, 4)))
        deleted = store.prune(now_s=431 * DAY_S - 1.0)
        assert deleted == {"history": 0, "events": 3}  # day 401 is just under 30 days old; events 40, 50, 60 go


def test_prune_to_the_size_cap_drops_the_oldest_history_and_shrinks_the_file(tmp_path):
    path = tmp_path / "store.db"
    map_bytes = 64 * 64 * 4
    with Store.open(path, history_interval_s=60.0, max_bytes=600_000) as store:
        for i in range(100):
            store.record_map(i * 60.0, np.full((64, 64), float(i)), [{"id": 1, "peak_mmhg": 40.0, "area_cm2": 9.0}])
        store.record_events([alarm_event(0.0)])
        assert store.size_bytes() > 100 * map_bytes
        deleted = store.prune(now_s=100 * 60.0)
        kept = [t for t, _ in store.history_between(0.0, 1e12)]
        assert [r["time_s"] for r in store.regions_between(0.0, 1e12)] == kept     # regions go with their maps
        assert store.size_bytes() <= 600_000
    assert path.stat().st_size <= 600_000
    assert deleted["events"] == 0 and deleted["history"] == 100 - len(kept)
    assert 25 <= len(kept) <= 600_000 // map_bytes  # most of the cap is used, by the newest maps
    assert kept == [i * 60.0 for i in range(100 - len(kept), 100)]


def test_the_size_cap_cuts_the_oldest_events_only_once_history_is_gone(tmp_path):
    with Store.open(tmp_path / "store.db", max_bytes=100_000) as store:
        store.record_map(0.0, np.ones((64, 64)))
        store.record_events([{"time_s": float(i), "kind": "raised", "message": "x" * 200} for i in range(2000)])
        deleted = store.prune(now_s=2000.0)
        times = [e["time_s"] for e in store.events_since(0.0)]
        assert store.size_bytes() <= 100_000
    assert deleted == {"history": 1, "events": 2000 - len(times)}
    # About 400 bytes an event: most of the cap is kept, and the newest; every table and index, however empty,
    # takes a 4 KiB page of the cap.
    assert 140 <= len(times) < 250
    assert times == [float(i) for i in range(2000 - len(times), 2000)]


def test_a_newer_schema_is_refused(tmp_path):
    path = tmp_path / "store.db"
    with Store.open(path):
        pass
    db = sqlite3.connect(path)
    with db:
        db.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    db.close()
    with pytest.raises(SchemaTooNew, match=f"{path}.*version {SCHEMA_VERSION + 1}"):
        Store.open(path)


def test_a_file_that_is_not_a_database_is_refused_by_name_and_left_untouched(tmp_path):
    path = tmp_path / "notes.db"
    content = b"this is a nurse's shift note, not a database\n" * 200
    path.write_bytes(content)
    with pytest.raises(StoreCorrupt, match="notes.db"):
        Store.open(path)
    assert path.read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.db"]


def test_writes_after_close_raise(tmp_path):
    store = Store.open(tmp_path / "store.db")
    store.close()
    store.close()  # closing twice is harmless
    with pytest.raises(StoreClosed, match="store.db"):
        store.commit_frame(1.0, [], {"alarms": {}})
    with pytest.raises(StoreClosed):
        store.record_map(1.0, np.ones((2, 2)))
    with pytest.raises(StoreClosed):
        store.record_events([alarm_event(1.0)])


def test_a_version_1_file_gains_the_command_queue_and_keeps_its_data(tmp_path):
    from appliance.store.database import MIGRATIONS

    path = tmp_path / "old.db"
    db = sqlite3.connect(path)
    for statement in MIGRATIONS[1]:
        db.execute(statement)
    db.execute("INSERT INTO schema_version (version) VALUES (1)")
    db.execute("INSERT INTO events (time_s, kind) VALUES (5.0, 'raised')")
    db.commit()
    db.close()
    with Store.open(path) as store:
        assert [e["kind"] for e in store.events_since(0)] == ["raised"]
        first = store.queue_command("acknowledge", {"alarm_id": 3}, "nurse.jones")
        second = store.queue_command("pause-audio", {"duration_s": 60}, "nurse.jones")
        assert [c["id"] for c in store.pending_commands()] == [first, second]
        store.commit_frame(10.0, [], {}, [(first, True, "1 event(s)")])
        assert [c["id"] for c in store.pending_commands()] == [second]
        assert store.command(first)["state"] == "done" and store.command(first)["args"] == {"alarm_id": 3}
    assert raw(path, "SELECT version FROM schema_version") == [(SCHEMA_VERSION,)]


def test_regions_are_kept_with_their_map_and_pruned_with_it(tmp_path):
    regions = [{"id": 4, "zone": "sacrum", "peak_mmhg": 61.5, "area_cm2": 120.0, "dose": 0.25},
               {"id": 7, "zone": None, "peak_mmhg": 35.0, "area_cm2": 30.0, "dose": None}]
    with Store.open(tmp_path / "s.db", history_interval_s=60.0, history_days=1.0) as store:
        assert store.record_map(0.0, np.ones((2, 2)), regions)
        assert not store.record_map(30.0, np.ones((2, 2)), regions)       # between kept maps: neither is kept
        assert store.record_map(60.0, np.ones((2, 2)), regions[:1])
        kept = store.regions_between(0.0, 60.0)
        assert [(r["time_s"], r["region_id"], r["zone"], r["dose"]) for r in kept] == [
            (0.0, 4, "sacrum", 0.25), (0.0, 7, None, None), (60.0, 4, "sacrum", 0.25)]
        store.prune(DAY_S + 30.0)
        assert [r["time_s"] for r in store.regions_between(0.0, DAY_S)] == [60.0]


def test_a_long_command_reports_its_progress(tmp_path):
    with Store.open(tmp_path / "s.db") as store:
        command = store.queue_command("calibrate", {}, "eng.smith")
        assert store.command(command)["progress"] is None
        store.set_progress(command, 0.4, "load 12 of 30")
        assert (store.command(command)["progress"], store.command(command)["progress_note"]) == (0.4, "load 12 of 30")
        store.set_progress(command, 7.0)
        assert store.command(command)["progress"] == 1.0
        assert [c["id"] for c in store.commands_since(0.0, kinds=["calibrate"])] == [command]
        assert store.commands_since(0.0, kinds=["acquire"]) == []


def test_a_reader_leaves_the_files_alone_and_a_writer_checkpoints_on_close(tmp_path):
    """The screen opens the store per request: reading must write nothing (no checkpoint of the monitor's WAL),
    so a page view costs the SD card nothing."""
    path = tmp_path / "appliance.db"
    monitor = Store.open(path)
    monitor.save_state("alarms", {"next_id": 5}, now_s=5.0)
    wal = tmp_path / "appliance.db-wal"
    before = (path.stat().st_mtime_ns, path.stat().st_size, wal.stat().st_size)
    assert before[2] > 0                                        # the monitor's frame is still in the WAL
    for _ in range(3):
        with Store.open(path) as reader:
            assert reader.load_state("alarms") == {"next_id": 5}
    assert (path.stat().st_mtime_ns, path.stat().st_size, wal.stat().st_size) == before
    with Store.open(path) as writer:
        writer.save_state("alarms", {"next_id": 6}, now_s=6.0)
    assert wal.stat().st_size == 0                              # a writer checkpoints and truncates on close
    monitor.close()
