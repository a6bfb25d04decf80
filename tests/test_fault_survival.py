"""Faults around the monitor rather than in the mat: a second monitor on the same folder, damaged files,
wall-clock steps, a background thread that fails and a full disk. Each is a technical alarm or a refusal
naming what is wrong; none kills the monitor with a traceback or loses a record."""

import errno
import os
import signal
import sqlite3
import subprocess

import pytest
from monitor_process import MINUTE, command, start_monitoring
from mqtt_broker import wait_until
from test_daemon import INTERVAL, FlakySource, board_daemon

from appliance.cli import main
from appliance.errors import DataDirInUse
from appliance.service.config import config_from_mapping
from appliance.service.daemon import MonitorDaemon
from appliance.service.datalock import lock_data_dir
from appliance.service.live import LiveChannel, read_live
from appliance.store import Store

# One data folder per monitor.

def test_a_second_lock_on_a_folder_is_refused_naming_it_and_the_holder(tmp_path):
    held = lock_data_dir(tmp_path)
    with pytest.raises(DataDirInUse, match=rf"data folder {tmp_path} is in use by another monitor "
                                           rf"\(pid {os.getpid()}\)"):
        lock_data_dir(tmp_path)
    held.release()
    lock_data_dir(tmp_path).release()           # released: the folder can be taken again


def test_a_second_monitor_on_a_folder_exits_2_and_one_after_a_sigkill_starts(tmp_path, bed_monitoring, model_cache):
    data = tmp_path / "data"
    first = start_monitoring(command(data, model_cache, speed=1.0))
    try:
        second = subprocess.run(command(data, model_cache, speed=0) + ["--frames", "1"], capture_output=True,
                                text=True, timeout=600, check=False)
        assert second.returncode == 2
        assert second.stderr.splitlines()[-1] == (f"appliance: error: data folder {data} is in use by another "
                                                  f"monitor (pid {first.pid}): each monitor needs a folder of "
                                                  f"its own")
        assert "Traceback" not in second.stderr
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
        first.stdout.close()
    after = subprocess.run(command(data, model_cache, speed=0) + ["--frames", "1"], capture_output=True, text=True,
                           timeout=600, check=False)
    assert after.returncode == 0, after.stderr


# Damaged files: a refusal naming the file (exit 2, one line, the file left as found) or a technical alarm.

def run_monitor(data, model_cache, *options, frames=3):
    """``appliance run`` in this process on the virtual bed: (exit status, stderr's lines)."""
    return main(["run", "--scenario", "supine-unturned", "--interval", str(MINUTE), "--speed", "0",
                 "--data-dir", str(data), "--cache-dir", str(model_cache), "--frames", str(frames), *options])


def garble(path, offset, length=3 * 4096):
    with open(path, "r+b") as f:
        f.seek(offset)
        f.write(bytes(range(256)) * (length // 256))


@pytest.mark.parametrize("damage", ["pages", "header"])
def test_a_damaged_store_is_refused_naming_it_and_left_as_found(tmp_path, bed_monitoring, model_cache, capsys,
                                                                damage):
    data = tmp_path / "data"
    assert run_monitor(data, model_cache, frames=8) == 0
    store = data / "appliance.db"
    garble(store, 2 * 4096 if damage == "pages" else 0)
    before = store.read_bytes()
    capsys.readouterr()
    assert run_monitor(data, model_cache) == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith(f"appliance: error: store {store} is damaged (") and "move it aside" in last
    assert store.read_bytes() == before


@pytest.mark.parametrize("name, what", [("monitor.toml", "configuration file"), ("settings.toml", "settings file"),
                                        ("pressure.json", "pressure calibration")])
def test_a_damaged_configuration_settings_or_calibration_file_is_refused_naming_it(tmp_path, bed_monitoring,
                                                                                  model_cache, capsys, name, what):
    data = tmp_path / "data"
    data.mkdir()
    path = (data if name == "settings.toml" else tmp_path) / name
    path.write_bytes(b"\x00\xff[monitor\n\x89PNG")
    option = {"monitor.toml": ["--config", str(path)], "pressure.json": ["--calibration", str(path)]}.get(name, [])
    assert run_monitor(data, model_cache, *option) == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith(f"appliance: error: {what} {path} is not valid ")
    assert not (data / "appliance.db").exists() or name == "settings.toml"


def test_a_damaged_saved_alert_state_starts_afresh_under_a_technical_alarm(tmp_path, bed_monitoring, model_cache,
                                                                         capsys):
    data = tmp_path / "data"
    assert run_monitor(data, model_cache) == 0
    with sqlite3.connect(data / "appliance.db") as db:
        db.execute("UPDATE state SET value = '{\"alarms\": [' WHERE name = 'alerts'")
    db.close()
    assert run_monitor(data, model_cache) == 0
    out = capsys.readouterr()
    assert f"store {data / 'appliance.db'}: the saved state 'alerts' is not valid JSON" in out.err
    with Store.open(data / "appliance.db") as store:
        raised = [e for e in store.events_since(0) if e["kind"] == "raised" and e["key"] == "technical:saved-state"]
    assert len(raised) == 1 and "started afresh" in raised[0]["message"] and "appliance.db" in raised[0]["message"]


def test_a_damaged_live_view_shows_the_screen_stale_and_logs_the_file(tmp_path, caplog):
    from webui import create_app
    from webui.live import snapshot

    (tmp_path / "live.json").write_bytes(b'{"format": "appliance-live/1", "seq')
    app = create_app(tmp_path, secure_cookies=False)
    with app.app_context():
        shown = snapshot()
    assert shown["stale"] and "cannot be read" in shown["message"]
    assert str(tmp_path) not in shown["message"]                  # no server path on a nurse's screen...
    assert str(tmp_path / "live.json") in caplog.text             # ...but in the screen's log for the engineer


# Supervised helper threads.

class FailingLive(LiveChannel):
    """The live view on a disk whose first ``failing`` writes fail."""

    def __init__(self, path, failing):
        self.failing = failing
        super().__init__(path, backoff_s=0.01)

    def _write(self, snapshot):
        if self.failing > 0:
            self.failing -= 1
            raise OSError(errno.EIO, "Input/output error", str(self.path))
        super()._write(snapshot)


def test_a_failing_helper_thread_is_a_technical_alarm_and_is_restarted(small_mat_calibration, tmp_path):
    model, calibration = small_mat_calibration
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": INTERVAL}})
    live = FailingLive(tmp_path / "live.json", failing=3)
    events = []
    daemon = MonitorDaemon(config, FlakySource(failing=()), model, calibration, Store.open(tmp_path / "a.db"),
                           live=live, on_event=events.append, say=lambda text: None)
    daemon.start()
    daemon.step()
    assert wait_until(lambda: live.fault is not None)
    daemon.step()
    raised = [e for e in events if e.key == "technical:live-view" and e.kind == "raised"]
    assert len(raised) == 1 and "Input/output error" in raised[0].message
    frames = 2
    while live.fault is not None or live.written == 0:      # restarted: the next snapshots are written
        assert frames < 30 and live._worker.is_alive()
        daemon.step()
        frames += 1
        wait_until(lambda: live.written > 0, timeout_s=1.0)
    daemon.step()
    daemon.close()
    assert [e.kind for e in events if e.key == "technical:live-view"] == ["raised", "ended"]
    assert read_live(tmp_path / "live.json")["sequence"] == frames + 1
    assert daemon.maps == frames + 1                          # every frame made its map throughout


# A full disk.

class FillingStore(Store):
    """A store on a disk that fills while ``full`` is set: every write fails as SQLite reports it."""

    full = False

    def _transaction(self, synchronous):
        if self.full:
            raise sqlite3.OperationalError("database or disk is full")
        return super()._transaction(synchronous)


def fill(store, full):
    """Fill the disk under ``store`` (or free it): ``FillingStore``'s switch, or SQLite's own page limit, which
    fails a write that would grow the file with SQLITE_FULL, as a full file system does."""
    if isinstance(store, FillingStore):
        store.full = full
    else:
        pages = store._db.execute("PRAGMA page_count").fetchone()[0]
        store._db.execute(f"PRAGMA max_page_count = {pages if full else 2 ** 30}")


@pytest.mark.parametrize("disk", ["injected", "page-limit"])
def test_a_full_disk_is_a_technical_alarm_and_every_record_is_written_once_it_has_room(small_mat_calibration,
                                                                                        tmp_path, disk):
    model, calibration = small_mat_calibration
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": INTERVAL},
                                  "alerts": {"alarm_dose": 0.05}, "store": {"history_interval_s": 0}})
    path = tmp_path / "appliance.db"
    store = (FillingStore if disk == "injected" else Store).open(path, history_interval_s=0)
    events = []
    daemon = MonitorDaemon(config, FlakySource(failing=()), model, calibration, store, on_event=events.append,
                           say=lambda text: None)
    daemon.start()
    daemon.run(2)
    fill(store, True)
    while not any(e.kind == "raised" and e.key.startswith("pressure:") for e in events):
        assert daemon.step() is not None and daemon.maps < 20         # clinical alarms go on from memory
    alarm = next(e for e in events if e.kind == "raised" and e.key.startswith("pressure:"))
    with Store.open(path) as screen:                                   # the screen's own connection
        acknowledge = screen.queue_command("acknowledge", {"alarm_id": alarm.alarm_id}, "nurse.jones")
    daemon.run(3)
    storage = [e for e in events if e.key == "technical:storage"]
    assert [e.kind for e in storage] == ["raised"]
    assert storage[0].message.startswith("storage full: records kept in memory (")
    assert daemon.writes.held > 0
    fill(store, False)
    daemon.run(2)
    assert [e.kind for e in events if e.key == "technical:storage"] == ["raised", "ended"]
    maps = daemon.maps
    daemon.close()
    with Store.open(path) as kept:
        logged = [(e["kind"], e["key"], e["time_s"]) for e in kept.events_since(0)]
        assert logged == [(e.kind, e.key, e.time_s) for e in events]            # all of them, in order
        assert [e.kind for e in events].count("acknowledged") == 1
        assert kept.command(acknowledge)["state"] == "done"
        assert len(kept.history_between(0, 1e9)) == maps
        assert kept.load_state("alerts")["last_time_s"] == daemon.pipeline.last_time_s


# Wall-clock steps.

class Clocks:
    """A wall clock a test can step and a monotonic clock it moves on by hand."""

    def __init__(self, wall=1_780_000_000.0):
        self.shift, self.steady, self.start = 0.0, 0.0, wall

    def wall(self):
        return self.start + self.steady + self.shift

    def monotonic(self):
        return self.steady


def test_frame_times_follow_the_monotonic_clock_and_a_step_is_reported_once():
    from appliance.service.clock import FrameClock

    clocks = Clocks()
    clock = FrameClock(wall=clocks.wall, monotonic=clocks.monotonic)
    times = [clock.now()]
    clocks.steady += 1.0
    assert clock.step() is None                    # no step: nothing to report
    clocks.shift -= 3600.0
    clocks.steady += 1.0
    times.append(clock.now())
    assert clock.step() == pytest.approx(-3600.0) and clock.step() is None
    clocks.steady += 1.0
    clocks.shift += 3.0                            # a few seconds of drift correction: not a step
    times.append(clock.now())
    assert clock.step() is None
    assert times == [clocks.start, clocks.start + 2.0, clocks.start + 3.0]
    clock.not_before(clocks.start + 100.0)         # a restart after records later than the wall clock
    assert clock.now() > clocks.start + 100.0


def test_the_board_monitor_carries_on_over_a_wall_clock_step_back_and_logs_it(small_mat_calibration, tmp_path):
    from appliance.service.clock import FrameClock

    maps = []
    daemon = board_daemon(small_mat_calibration[1], tmp_path, maps.append)
    clocks = Clocks(wall=daemon.source.now() + 1.0)
    daemon.source.clock = FrameClock(wall=clocks.wall, monotonic=clocks.monotonic)
    try:
        for n in range(4):
            clocks.steady += 60.0
            if n == 2:
                clocks.shift = -3600.0             # the wall clock is set back an hour
            daemon.step()
    finally:
        daemon.close()
    times = [m.time_s for m in maps]
    assert len(times) == 4 and times == sorted(times) and times[-1] - times[0] == pytest.approx(180.0)
    with Store.open(tmp_path / "data" / "appliance.db") as store:
        steps = [e for e in store.events_since(0) if e["kind"] == "clock-step"]
    assert len(steps) == 1 and "stepped back 3600 s" in steps[0]["message"]


def test_the_screen_goes_stale_when_the_monitor_stops_even_if_the_clock_was_set_back(tmp_path, monkeypatch):
    import json

    import webui.live
    from webui import create_app

    clocks = Clocks()
    monkeypatch.setattr(webui.live, "wall", clocks.wall)
    monkeypatch.setattr(webui.live, "monotonic", clocks.monotonic)
    (tmp_path / "live.json").write_text(json.dumps({"format": "appliance-live/1", "sequence": 7,
                                                    "wall_interval_s": 1.0, "written_at": clocks.wall()}))
    clocks.shift = -3600.0                      # then the monitor stops and the clock is set back an hour
    app = create_app(tmp_path, secure_cookies=False)
    with app.app_context():
        assert not webui.live.snapshot()["stale"]
        clocks.steady += 10 * webui.live.STALE_AFTER_FRAMES
        assert webui.live.snapshot()["stale"]


def test_the_ward_station_judges_a_bed_silent_on_the_monotonic_clock():
    from appliance.ward.board import BedState

    bed = BedState("bed7", status="online", last_heard_at=1_780_000_000.0, last_heard_steady=100.0)
    assert bed.online(101.0, stale_after_s=5.0)
    assert not bed.online(106.0, stale_after_s=5.0)      # silent for 6 s, whatever the wall clock says now


def test_a_supervised_thread_is_restarted_after_each_failure_until_its_work_is_done():
    from appliance.supervise import Supervised

    runs = []

    def work():
        runs.append(len(runs))
        if len(runs) <= 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        worker.ok()

    worker = Supervised("writer", work, backoff_s=0.001)
    worker.start().join(10)
    assert not worker.is_alive() and runs == [0, 1, 2]
    assert worker.failures == 2 and worker.fault is None         # the fault ended with the first success


def test_what_a_full_disk_holds_is_bounded_and_what_is_dropped_is_counted(tmp_path):
    import numpy as np

    from appliance.store.holding import HeldWrites

    store = FillingStore.open(tmp_path / "a.db", history_interval_s=0)
    writes = HeldWrites(store, max_events=5, max_maps=3)
    store.full = True
    for t in range(8):
        writes.record_map(float(t), np.full((2, 2), float(t)))
        writes.commit_frame(float(t), [{"time_s": float(t), "kind": "raised", "key": f"k{t}"}], {"alerts": {"t": t}})
    assert writes.condition() == {"technical:storage": "storage full: records kept in memory (8 held; 3 event(s) "
                                                       "and 5 map(s) dropped)"}
    store.full = False
    assert writes.flush() and writes.condition() == {}
    assert [e["key"] for e in store.events_since(0)] == ["k3", "k4", "k5", "k6", "k7"]       # the newest, in order
    assert [t for t, _ in store.history_between(0, 10)] == [5.0, 6.0, 7.0]
    assert store.load_state("alerts") == {"t": 7}
    store.close()


def test_a_ward_command_applied_while_the_disk_is_full_is_known_until_written_and_then_kept(tmp_path):
    """A repeat of the ward station's command must find it applied whether its record is still held in memory
    or already in the store, or the bed would apply it twice."""
    from appliance.store.holding import HeldWrites

    store = FillingStore.open(tmp_path / "a.db")
    writes = HeldWrites(store)
    done = {"ward_id": "c" * 32, "kind": "record-turn", "args": {}, "user": "ward:nurse.smith", "queued_at": 5.0,
            "applied": True, "result": "turn recorded"}
    store.full = True
    writes.commit_frame(6.0, [{"time_s": 6.0, "kind": "recorded", "user": "ward:nurse.smith"}], {}, [], [done])
    assert writes.held_ward_command("c" * 32) == done and store.ward_command("c" * 32) is None
    assert writes.held == 2
    store.full = False
    assert writes.flush() and writes.held_ward_command("c" * 32) is None
    kept = store.ward_command("c" * 32)
    assert (kept["state"], kept["user"], kept["kind"], kept["result"]) == \
        ("done", "ward:nurse.smith", "record-turn", "turn recorded")
    store.commit_frame(7.0, [], {}, [], [done])                    # written twice by mistake: still once
    assert len(store.commands_since(0.0)) == 1
    store.close()
