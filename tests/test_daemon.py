"""The monitor daemon: its configuration file, the loop's faults, systemd's notify protocol, the live view,
and a clean stop on SIGTERM of the real process."""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import pytest

from appliance.cli import main
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.errors import ConfigError, TransferFailed
from appliance.service.config import config_from_mapping, load_config
from appliance.service.daemon import NO_DATA_FRAMES, PRUNE_EVERY_S, MonitorDaemon
from appliance.service.live import LiveChannel, read_live
from appliance.service.systemd import SystemdNotifier
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import square_load_scene
from appliance.store import Store
from appliance.store.database import DAY_S

GRID = get_layout("grid-4x4")
INTERVAL = 600.0            # ten minutes a frame: 45 mmHg uses 5 % of the tolerance in a few frames


# The configuration file.

def test_no_configuration_runs_the_virtual_bed_with_the_literature_defaults():
    config = config_from_mapping({})
    assert (config.source, config.layout, config.scenario, config.frame_interval_s) == \
        ("virtual", "grid-16x32", "turn-schedule", 1.0)
    assert config.alerts.threshold_kpa == pytest.approx(32 * 0.133322, rel=1e-4)
    assert (config.alerts.curve, config.alerts.turn_interval_s, config.alerts.escalate_after_s) == \
        ("reswick-rogers", 7200.0, 900.0)
    assert config.mqtt is None and config.webhook is None and config.gpio is None


def test_a_ward_file_is_read_with_paths_relative_to_it(tmp_path):
    (tmp_path / "night.toml").write_text('[scene]\nduration_s = 60\n[[event]]\nat_s = 0\nkind = "lie-down"\n')
    path = tmp_path / "appliance.toml"
    path.write_text('[monitor]\nbed_id = "ward3-bed12"\ndata_dir = "data"\nframe_interval_s = 2\n'
                    '[virtual]\nscenario = "night.toml"\nspeed = 0\n'
                    '[alerts]\nthreshold_mmhg = 40\ncurve_points = [[30, 200], [240, 60], [720, 40]]\n'
                    'turn_interval_min = 180\nrecovery = "decay"\n'
                    '[notify.mqtt]\nhost = "broker.ward"\n[notify.webhook]\nurl = "https://station/alarms"\n')
    config = load_config(path)
    assert config.bed_id == "ward3-bed12" and config.data_dir == tmp_path / "data"
    assert config.scenario == str(tmp_path / "night.toml") and config.speed == 0
    assert config.alerts.curve_points == ((30, 200), (240, 60), (720, 40)) and config.alerts.recovery == "decay"
    assert config.alerts.turn_interval_s == 3 * 3600 and config.mqtt.port == 1883
    assert config.webhook.url == "https://station/alarms"


@pytest.mark.parametrize("text, message", [
    ('[monitor]\nlayuot = "grid-4x4"\n', "[monitor]: unknown key 'layuot'"),
    ('[alerts]\nthreshold_mmhg = 3\n', "[alerts]: threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 3"),
    ('[alerts]\nturn_interval_min = "2h"\n', "[alerts]: turn_interval_min must be a number, got '2h'"),
    ('[alerts]\ncurve = "braden"\n', "[alerts]: curve must be one of reswick-rogers, linder-ganz, got 'braden'"),
    ('[alerts]\ncurve_points = [[30, 200]]\n', "[alerts] curve_points: tolerance curve 'custom' needs at least 2"),
    ('[alerts]\ncurve_points = [[60, 200], [6000, 100]]\n',
     "[alerts] curve_points: the curve tolerates 60 mmHg for 100 h; a ward's curve may tolerate it for at most 12 h"),
    ('[monitor]\nsource = "serial"\n', "[monitor]: source must be one of virtual, emulated, hardware"),
    ('[monitor]\nbed_id = "bed/7"\n', "[monitor] bed_id must be 1-64 characters without spaces"),
    ('[notify.mqtt]\nport = 1883\n', "[notify.mqtt] is missing 'host'"),
    ('[notify.mqtt]\nhost = "b"\ntopic_prefix = "ward/#"\n', "topic_prefix must not hold wildcards"),
    ('[notify.mqtt]\nconfirm = false\n', "[notify.mqtt] is missing 'host'"),
    ('[notify.mqtt]\nhost = "b"\nconfirm = "yes"\n', "confirm must be true or false"),
    ('[notify.mqtt]\nhost = "b"\nconfirm_timeout_s = 0\n', "confirm_timeout_s"),
    ('[notify.webhook]\nurl = "ftp://x"\n', "url must start with http:// or https://"),
    ('[notify.gpio]\n', "[notify.gpio] needs a board: the virtual bed has no buzzer"),
    ('[notify.engine]\nconfirm_timeout_s = 5\n', "[notify.engine] is missing 'servers'"),
    ('[notify.engine]\nservers = []\nward = "w"\n', "servers must be a non-empty list"),
    ('[notify.engine]\nservers = ["n1:4222"]\nward = "w"\n', "server 'n1:4222' must be nats://HOST:PORT"),
    ('[notify.engine]\nservers = ["nats://bed:pw@n1:4222"]\nward = "w"\n', "without a login"),
    ('[notify.engine]\nservers = ["nats://n1:4222"]\nward = "ward.3"\n', "ward must be the ward's name"),
    ('[notify.engine]\nservers = ["nats://n1:4222"]\nward = "w"\n', "missing 'password_file'"),
    ('[notify.engine]\nservers = ["nats://n1:4222"]\nward = "w"\npassword_file = "none"\n',
     "[notify.engine] password_file: no file"),
    ('[notify.engine]\nservers = ["nats://n1:4222"]\nward = "w"\nconfirm_timeout_s = 0\n', "confirm_timeout_s"),
    ('[notify.mqtt]\nhost = "b"\n[notify.engine]\nservers = ["nats://n1:4222"]\n', "both given"),
    ('[board]\nprofile = "nonesuch"\n', "[board]:"),
    ('[virtual]\nscenario = "no-such-night"\n', "neither a built-in scenario"),
    ('[monitor]\nsource = "hardware"\n[virtual]\nspeed = 0\n', "[virtual] is only for source = \"virtual\""),
    ('[monitor\n', "is not valid TOML"),
])
def test_a_bad_configuration_is_refused_naming_the_section_and_key(tmp_path, text, message):
    path = tmp_path / "appliance.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert message in str(caught.value) and str(path) in str(caught.value)


def test_the_engine_instead_of_the_broker_is_chosen_by_its_own_table(tmp_path):
    (tmp_path / "engine-password").write_text("secret\n")
    path = tmp_path / "appliance.toml"
    path.write_text('[notify.engine]\nservers = ["nats://10.0.0.1:4222", "nats://10.0.0.2:4222"]\nward = "ward3"\n'
                    'password_file = "engine-password"\nconfirm_timeout_s = 4\n')
    config = load_config(path)
    assert config.mqtt is None
    assert config.engine.servers == ("nats://10.0.0.1:4222", "nats://10.0.0.2:4222") and config.engine.ward == "ward3"
    assert config.engine.password() == "secret"
    assert config.confirmation.confirm is True and config.confirmation.timeout_s == 4


def test_run_check_config_prints_the_configuration_and_refuses_a_bad_one(tmp_path, capsys):
    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text('[monitor]\nbed_id = "bed-4"\n')
    bad.write_text('[store]\nhistory_days = -1\n')
    assert main(["run", "--config", str(good), "--check-config", "--layout", "grid-4x4"]) == 0
    out = capsys.readouterr().out
    assert "bed_id='bed-4'" in out and "layout='grid-4x4'" in out
    assert main(["run", "--config", str(bad), "--check-config"]) != 0
    assert "[store]: history_days must be from 0.01 to 3650, got -1" in capsys.readouterr().err


# systemd's notify protocol, on a real datagram socket.

@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(20.0)
    yield path, sock
    sock.close()


def test_readiness_status_watchdog_and_stopping_reach_the_socket(notify_socket):
    path, sock = notify_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "2000000"})
    assert notifier.watchdog_s == 2.0
    notifier.ready("monitoring bed-1")
    assert sock.recv(4096) == b"READY=1\nSTATUS=monitoring bed-1"
    assert notifier.ping(now=100.0) and sock.recv(4096) == b"WATCHDOG=1"
    assert not notifier.ping(now=100.5)                  # not again before half the interval
    assert notifier.ping(now=101.0)
    assert sock.recv(4096) == b"WATCHDOG=1"
    notifier.stopping()
    assert sock.recv(4096) == b"STOPPING=1"


def test_outside_systemd_notify_does_nothing_and_a_watchdog_for_another_pid_is_ignored():
    assert not SystemdNotifier({}).send("READY=1")
    assert SystemdNotifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}).watchdog_s is None
    assert SystemdNotifier({"NOTIFY_SOCKET": "@abstract"}).address == "\0abstract"


# The live view.

def test_the_live_view_is_always_a_whole_snapshot_and_publishing_never_waits(tmp_path):
    live = LiveChannel(tmp_path / "live.json")
    seen, stop = [], threading.Event()

    def reader():
        while not stop.is_set():
            snapshot = read_live(tmp_path / "live.json")
            if snapshot is not None:
                seen.append(snapshot["sequence"])

    thread = threading.Thread(target=reader)
    thread.start()
    big = [[1.5] * 34] * 16
    for n in range(300):
        live.publish({"sequence": n, "map": {"mmhg": big}})
        time.sleep(0.002)
    disk, writing = threading.Event(), threading.Event()       # now the disk hangs in the middle of a write
    write = live._write

    def hanging_write(snapshot):
        writing.set()
        disk.wait()
        write(snapshot)
    live._write = hanging_write
    live.publish({"sequence": 300, "map": {"mmhg": big}})
    assert writing.wait(10)
    skipped = live.skipped
    for n in range(301, 310):                                   # each returns with the writer stuck
        live.publish({"sequence": n, "map": {"mmhg": big}})
    assert live.skipped == skipped + 8                          # all but the newest replaced, not queued
    disk.set()
    live.close()
    stop.set()
    thread.join()
    assert read_live(tmp_path / "live.json")["sequence"] == 309      # the newest one is always written
    assert seen == sorted(seen) and len(seen) > 10                     # whole files, in order
    assert live.written + live.skipped == 310


# The loop on a small mat.

class FlakySource(VirtualBedSource):
    """The virtual mat, failing on the frames numbered in ``failing`` (counted from 0)."""

    def __init__(self, failing, **kwargs):
        super().__init__(GRID, square_load_scene(100, 100, 30, 70, 40, 6.0), default_protocol(GRID),
                         frame_interval_s=INTERVAL, **kwargs)
        self.failing, self.calls = set(failing), -1

    def acquire(self):
        self.calls += 1
        if self.calls in self.failing:
            self.front_end.time_s += self.front_end.frame_interval_s
            raise TransferFailed("I2C NACK from 0x48")
        return super().acquire()


def small_daemon(small_mat_calibration, tmp_path, source, **alerts):
    model, calibration = small_mat_calibration
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": INTERVAL},
                                  "alerts": alerts})
    events = []
    daemon = MonitorDaemon(config, source, model, calibration, Store.open(tmp_path / "appliance.db"),
                           live=LiveChannel(tmp_path / "live.json"), on_event=events.append, say=lambda text: None)
    daemon.start()
    return daemon, events


def test_a_bus_fault_is_a_technical_alarm_at_once_and_no_data_after_three(small_mat_calibration, tmp_path):
    source = FlakySource(failing={3, 4, 5, 6})
    daemon, events = small_daemon(small_mat_calibration, tmp_path, source, alarm_dose=0.05)
    assert daemon.run(10) == 10
    daemon.close()
    raised = {e.key: e.time_s for e in events if e.kind == "raised"}
    ended = {e.key: e.time_s for e in events if e.kind == "ended"}
    assert raised["technical:front-end"] == 3 * INTERVAL                      # the first frame that failed
    assert raised["technical:no-data"] == (3 + NO_DATA_FRAMES - 1) * INTERVAL
    assert ended["technical:front-end"] == ended["technical:no-data"] == 7 * INTERVAL   # the first map again
    clinical = [k for k in raised if k.startswith("pressure:")]
    assert clinical and all(k not in ended for k in clinical)      # no clinical alarm ends for want of data
    assert (daemon.maps, daemon.faults) == (6, 4)
    with Store.open(tmp_path / "appliance.db") as store:
        assert [e["key"] for e in store.events_since(0) if e["kind"] == "raised"] == list(raised)
    live = read_live(tmp_path / "live.json")
    assert live["status"]["faults"] == 4 and live["alarms"] and live["regions"][0]["dose"] > 0


def test_acknowledgement_is_applied_at_the_next_frame_and_recorded(small_mat_calibration, tmp_path):
    daemon, events = small_daemon(small_mat_calibration, tmp_path, FlakySource(failing=()), alarm_dose=0.05)
    daemon.run(8)
    alarm = next(e for e in events if e.kind == "raised")
    next_frame_s = daemon.source.now()
    with Store.open(tmp_path / "appliance.db") as screen:        # the web screen: another connection, own process
        good = screen.queue_command("acknowledge", {"alarm_id": alarm.alarm_id}, "nurse.jones")
        bad = screen.queue_command("acknowledge", {"alarm_id": 999}, "nurse.jones")   # refused; the loop goes on
    daemon.run(2)
    daemon.close()
    acked = [e for e in events if e.kind == "acknowledged"]
    assert [(e.alarm_id, e.user, e.time_s) for e in acked] == [(alarm.alarm_id, "nurse.jones", next_frame_s)]
    with Store.open(tmp_path / "appliance.db") as store:
        assert store.command(good)["state"] == "done" and store.command(bad)["state"] == "refused"
        assert "alarm 999 is unknown" in store.command(bad)["result"]
        assert [e["user"] for e in store.events_since(0) if e["kind"] == "acknowledged"] == ["nurse.jones"]


def test_retention_runs_at_the_first_frame_and_every_hour_of_monitoring(small_mat_calibration, tmp_path):
    model, calibration = small_mat_calibration
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": INTERVAL}})
    store = Store.open(tmp_path / "appliance.db", history_interval_s=0.0, history_days=1800.0 / DAY_S)
    said = []
    daemon = MonitorDaemon(config, FlakySource(failing=()), model, calibration, store, say=said.append)
    daemon.start()
    daemon.run(14)                                   # 14 maps ten minutes apart, from 0 to 2 h 10 min
    kept = [t for t, _ in store.history_between(0.0, 1e9)]
    daemon.close()
    assert daemon.last_prune_s == 2 * PRUNE_EVERY_S                  # pruned at 0, 1 h and 2 h
    assert kept == [k * INTERVAL for k in range(14) if k * INTERVAL >= 2 * PRUNE_EVERY_S - 1800.0]  # the last 30 min
    assert any(line.startswith("retention: ") for line in said)


# The real process: systemd readiness and a clean SIGTERM.

def test_sigterm_stops_the_real_process_cleanly_after_telling_systemd(notify_socket, tmp_path, bed_monitoring,
                                                                     model_cache):
    """With ``--screen``, the nurse's screen is served while the monitor runs and stops with it."""
    path, sock = notify_socket
    env = {**os.environ, "NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "10000000"}
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        screen = f"http://127.0.0.1:{s.getsockname()[1]}/setup"
        port = str(s.getsockname()[1])
    process = subprocess.Popen([sys.executable, "-m", "appliance", "run", "--scenario", "supine-still",
                                "--interval", "1", "--speed", "4", "--data-dir", str(tmp_path / "data"),
                                "--cache-dir", str(model_cache), "--screen", port], env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        messages = []
        while not any(m.startswith(b"READY=1") for m in messages):
            messages.append(sock.recv(4096))
        assert b"WATCHDOG=1" in [sock.recv(4096) for _ in range(2)]          # pinged as frames go by
        assert "First start: the administrator" in _page(screen, within_s=20)
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=30)
    finally:
        process.kill()
    assert process.returncode == 0, err
    with pytest.raises(OSError):
        urllib.request.urlopen(screen, timeout=2)
    tail = []
    sock.settimeout(1.0)
    try:
        while True:
            tail.append(sock.recv(4096))
    except TimeoutError:
        pass
    assert b"STOPPING=1" in tail
    assert "stopped after" in err
    with Store.open(tmp_path / "data" / "appliance.db") as store:
        assert store.load_state("alerts")["last_time_s"] > 0
    assert json.loads((tmp_path / "data" / "live.json").read_text())["bed_id"]


def _page(url: str, within_s: float) -> str:
    """The page at ``url`` once the server answers (within ``within_s``)."""
    deadline = time.monotonic() + within_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as answer:
                return answer.read().decode()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_a_bad_screen_address_is_refused_before_anything_starts(tmp_path, capsys):
    assert main(["run", "--screen", "localhost:http", "--data-dir", str(tmp_path)]) != 0
    assert "--screen takes [HOST:]PORT with a port from 1 to 65535, got 'localhost:http'" in capsys.readouterr().err
    assert not (tmp_path / "appliance.db").exists()


def board_daemon(calibration, tmp_path, on_map):
    """The daemon ``appliance run`` assembles on grid-4x4's emulated board (the real scan path), with
    ``calibration`` saved beside its data folder."""
    from appliance.core.pressure import save_pressure_calibration
    from appliance.service.assemble import assemble

    save_pressure_calibration(tmp_path / "pressure.json", calibration)
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "source": "hardware", "frame_interval_s": 0.05,
                                              "calibration": str(tmp_path / "pressure.json"),
                                              "data_dir": str(tmp_path / "data"),
                                              "cache_dir": str(tmp_path / "models")},
                                  "board": {"backend": "emulated"}})
    return assemble(config, say=lambda text: None, on_map=on_map)


def test_the_daemon_runs_the_scan_engine_on_a_board_with_wall_clock_times(small_mat_calibration, tmp_path):
    """``source = "hardware"`` with the emulated board: the real scan path, frames on the wall clock."""
    maps = []
    started = time.time()
    daemon = board_daemon(small_mat_calibration[1], tmp_path, maps.append)
    try:
        assert daemon.run(2) == 2
    finally:
        daemon.close()
    assert len(maps) == 2 and all(started <= m.time_s <= time.time() for m in maps)
    assert not maps[-1].regions                            # the emulated mat is empty: nothing loaded
    assert read_live(tmp_path / "data" / "live.json")["status"]["source"] == "hardware"


def test_a_board_needs_a_calibration_of_its_own(tmp_path):
    from appliance.service.assemble import assemble

    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "source": "hardware",
                                              "data_dir": str(tmp_path), "cache_dir": str(tmp_path)},
                                  "board": {"backend": "emulated"}})
    with pytest.raises(ConfigError, match="calibration is needed with a board"):
        assemble(config, say=lambda text: None)


def test_a_stale_calibration_is_a_technical_alarm(small_mat_calibration, tmp_path):
    """A year-old calibration, or a liquid far from the calibration's temperature, is equipment, not patient."""
    import dataclasses

    from appliance.service.monitor import stale_calibration

    model, calibration = small_mat_calibration
    old = dataclasses.replace(calibration, notes={**calibration.notes, "made_at": time.time() - 400 * 86400})
    daemon, events = small_daemon((model, old), tmp_path, FlakySource(failing=()))
    daemon.run(2)
    daemon.close()
    raised = [(e.key, e.category, e.time_s) for e in events if e.kind == "raised"]
    assert ("technical:calibration", "technical", 0.0) in raised
    assert "400 days ago" in next(e.message for e in events if e.key == "technical:calibration")
    assert stale_calibration(calibration, calibration.reference_temperature_c + 2.0) is None
    warm = stale_calibration(calibration, calibration.reference_temperature_c + 6.0)
    assert warm is not None and "pressures are not trusted" in warm.message


class Recorder:
    """A notifier that keeps what it is given."""

    def __init__(self):
        self.events = []

    def notify(self, event):
        self.events.append(event)

    def close(self):
        pass


def test_after_a_crash_the_last_frames_events_are_notified_again(small_mat_calibration, tmp_path):
    model, calibration = small_mat_calibration
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": INTERVAL},
                                  "alerts": {"alarm_dose": 0.05}})
    first = Recorder()
    daemon = MonitorDaemon(config, FlakySource(failing=()), model, calibration, Store.open(tmp_path / "a.db"),
                           notifiers=[first], say=lambda text: None)
    daemon.start()
    while not any(e.kind == "raised" and e.key.startswith("pressure:") for e in first.events):
        before = len(first.events)
        daemon.step()
    last_frame = first.events[before:]                          # the crash comes now, before any close
    again = Recorder()
    restarted = MonitorDaemon(config, FlakySource(failing=()), model, calibration, Store.open(tmp_path / "a.db"),
                              notifiers=[again], say=lambda text: None)
    restarted.start()
    assert again.events == last_frame and restarted.resumed_from_s == daemon.pipeline.last_time_s
    restarted.close()


def test_the_live_view_names_each_setting_that_is_not_the_default(small_mat_calibration, tmp_path):
    (tmp_path / "a").mkdir()
    plain, _ = small_daemon(small_mat_calibration, tmp_path / "a", FlakySource(failing=()))
    plain.run(1)
    plain.close()
    assert read_live(tmp_path / "a" / "live.json")["settings_changed"] == []
    daemon, _ = small_daemon(small_mat_calibration, tmp_path, FlakySource(failing=()), threshold_mmhg=40,
                             turn_interval_min=90)
    daemon.run(1)
    daemon.close()
    changed = read_live(tmp_path / "live.json")["settings_changed"]
    assert [c["text"] for c in changed] == ["threshold 40 mmHg (default 32)", "turn interval 90 min (default 120)"]
    assert (changed[0]["key"], changed[0]["value"], changed[0]["default"]) == ("threshold_mmhg", 40, 32)
