"""The hospital soak: simulated beds raise and clear alarms through the product's own ward link while servers,
links and ward stations are killed on a schedule; what was lost, shown twice and how late, from the beds' and
stations' own records.

    python benchmarks/hospital.py --beds 300 --minutes 30                  # the engine: writes benchmarks/hospital.md
    python benchmarks/hospital.py --beds 300 --minutes 30 --transport mqtt # the same against one Mosquitto

Each bed is a :class:`~appliance.alerts.wardlink.WardLink` with its own durable outbox (a SQLite file) over the
hospital engine (``EngineTransport``, logged in with the bed's password from the generated configuration) or the
ward's Mosquitto (``MqttTransport``); beds are spread over a few worker processes (a worker's engine beds share one
event loop, ``EngineLoop``: a loop and a thread pool per bed would be thousands of threads). Each ward (``--ward-size``
beds) has one ward station, the product's ``EngineStation`` (or the MQTT ``WardStation``), several wards' stations
to a process (``--wards-per-station``) so that crashing a station is a SIGKILL of its process. Alarm changes come
at ``--rate`` a second in all, each to a random bed, which raises a new alarm or ends one it has open.

Faults, on a schedule scaled to the run (:func:`schedule`): every ``--kill-every`` seconds the node leading a ward's
event stream is SIGKILLed and started again ``kill_down_s`` later (against Mosquitto: the broker itself); between
kills, in turn, one ward's beds are cut off (their connections go through relays that drop them), two of the three
nodes are SIGSTOPped and resumed (the engine only), and a station process is SIGKILLed and started again.

What is measured comes from the records: each bed's outbox (``queued_at``, ``confirmed_at``, by whom), the
engine station's journal of applied events (``applied_at``), and a record of every event a station's board took
(:class:`ShownRecord`, written before the station confirms). Lost: numbered at a bed, never applied by a station.
Confirmed then lost: the same, for an event the bed holds as confirmed by a station. Shown twice: an event a
station's board took in two of its lives, or one alarm change taken under two numbers. Latency: queued at the bed
to applied at the station. The technical alarm: each bed of the cut ward polls its link's conditions every
``POLL_CUT_S``; its delay is counted from the cut plus the configured ``confirm_timeout_s``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import signal
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from engine_relay import CuttableLink  # noqa: E402
from report import (cpu_seconds, free_port, listening, machine, mosquitto_binary, percentile, table,  # noqa: E402
                    wait_for)

from appliance.alerts.events import EVENT_TYPES  # noqa: E402
from appliance.hospital.cluster import (LOOPBACK, LocalCluster, loopback_hospital, server_version,  # noqa: E402
                                       stop_process)
from appliance.hospital.description import Ward  # noqa: E402
from appliance.hospital.engine import connect, ensure_ward_streams  # noqa: E402
from appliance.hospital.nodeconfig import ADMIN, read_password  # noqa: E402
from appliance.hospital.subjects import stream_name  # noqa: E402

RATE = 50.0
CONFIRM_TIMEOUT_S = 10.0
"""The ward link's own default: a bed whose confirmations stop for this long raises its technical alarm."""
POLL_CUT_S = 0.1
POLL_OTHERS_S = 1.0
STEADY_AFTER_S = 15.0
"""Events queued this long after the last fault healed (and before the next) count as steady state."""
IN_FLIGHT_S = 2.0
"""Events queued this long before a fault began count as across it: they may be on their way when it strikes."""
DRAIN_LIMIT_S = 300.0
TECHNICAL = ("technical:ward-link", "technical:ward-confirm")
MQTT_PREFIX = "hospital"


# The schedule.

@dataclass(frozen=True)
class Fault:
    """``kind`` from ``at_s`` to ``heal_s`` (seconds after the load starts) on ``target`` (a ward index, or for a
    leader kill the ward whose stream's leader dies)."""

    kind: str
    at_s: float
    heal_s: float
    target: int


@dataclass(frozen=True)
class Timing:
    kill_every_s: float = 120.0
    kill_down_s: float = 30.0
    other_down_s: float = 45.0
    tail_s: float = 90.0
    """Load after the last fault healed: the outboxes drain under load."""


FULL = Timing()
COMPRESSED = Timing(kill_every_s=40.0, kill_down_s=8.0, other_down_s=15.0, tail_s=20.0)


def schedule(duration_s: float, wards: int, kinds: tuple[str, ...], timing: Timing = FULL) -> list[Fault]:
    """Leader (or broker) kills every ``kill_every_s``, and half-way between two kills the next of ``kinds`` in
    turn; nothing after ``duration_s - tail_s``. The cut is always of the last ward, the station crash of the
    first, the kills of each ward's stream in turn."""
    faults, k = [], 0
    at = timing.kill_every_s
    while at + timing.kill_every_s / 2 + timing.other_down_s <= duration_s - timing.tail_s:
        faults.append(Fault("kill", at, at + timing.kill_down_s, k % wards))
        kind = kinds[k % len(kinds)]
        other = at + timing.kill_every_s / 2
        faults.append(Fault(kind, other, other + timing.other_down_s, wards - 1 if kind == "cut" else 0))
        k += 1
        at += timing.kill_every_s
    return faults


# The beds' side: a worker process holding some of the beds.

@dataclass
class BedSpec:
    bed: str
    ward: str
    password: str
    outbox: str
    cut: bool


@dataclass
class WorkerSpec:
    transport: str
    beds: list[BedSpec]
    urls: list[str]
    cut_urls: list[str]
    mqtt_port: int
    cut_mqtt_port: int
    rate: float
    confirm_timeout_s: float
    control: str
    seed: int
    index: int


def alarm_change(bed_state: dict, rng: random.Random, elapsed_s: float):
    """A new alarm raised, or one the bed has open ended: each change different from every other of the bed."""
    from appliance.alerts.alarms import AlarmEvent
    from appliance.alerts.events import as_event

    open_alarms = bed_state["open"]
    if open_alarms and (len(open_alarms) >= 3 or rng.random() < 0.5):
        alarm_id = open_alarms.pop(rng.randrange(len(open_alarms)))
        kind = "ended"
    else:
        bed_state["next"] += 1
        alarm_id = bed_state["next"]
        open_alarms.append(alarm_id)
        kind = "raised"
    return as_event(AlarmEvent(time_s=elapsed_s, kind=kind, alarm_id=alarm_id, key="pressure:sacrum",
                               category="clinical", priority="high", message=f"Sacrum dose over limit ({kind})"))


def make_link(spec: WorkerSpec, bed: BedSpec, engine_loop=None):
    from appliance.store.outbox import Outbox

    outbox = Outbox(bed.outbox)
    if spec.transport == "engine":
        from appliance.hospital.bedlink import engine_ward_link

        return engine_ward_link(spec.cut_urls if bed.cut else spec.urls, bed.ward, bed.bed, bed.password, outbox,
                                engine_loop=engine_loop, confirm_timeout_s=spec.confirm_timeout_s)
    from appliance.alerts.ward_mqtt import mqtt_ward_link

    return mqtt_ward_link(LOOPBACK, spec.cut_mqtt_port if bed.cut else spec.mqtt_port, bed.bed, outbox,
                          client_id=bed.bed, topic_prefix=f"{MQTT_PREFIX}/{bed.ward}", username=bed.bed,
                          password=bed.password, confirm_timeout_s=spec.confirm_timeout_s)


def run_worker(spec_path: str) -> None:
    """Start the worker's beds, say when all are connected, drive the load between the times the main process
    writes, report the outboxes' backlog, and close the beds when told to stop."""
    raw = json.loads(Path(spec_path).read_text())
    spec = WorkerSpec(**{**raw, "beds": [BedSpec(**b) for b in raw["beds"]]})
    control = Path(spec.control)
    from appliance.hospital.bedlink import EngineLoop

    engine_loop = EngineLoop() if spec.transport == "engine" else None     # one for the worker's beds
    links = {bed.bed: make_link(spec, bed, engine_loop) for bed in spec.beds}
    cut = {bed.bed for bed in spec.beds if bed.cut}
    wait_for(lambda: all(link.transport.connected() for link in links.values()), 120, "the beds' connections")
    (control / f"ready-{spec.index}").write_text("")
    wait_for(lambda: (control / "go").exists(), 3600, "the start of the load")
    start, end = json.loads((control / "go").read_text())
    stopping = threading.Event()
    with open(control / f"technical-{spec.index}.jsonl", "a", buffering=1) as technical_log:
        watcher = threading.Thread(target=watch_technical, args=(links, cut, technical_log, stopping), daemon=True)
        watcher.start()
        changes = drive(spec, links, start, end)
        while not (control / "stop").exists():
            write_backlog(control, spec.index, links, changes)
            time.sleep(0.5)
        stopping.set()
        watcher.join()
    for link in links.values():
        link.close(timeout_s=2)
    if engine_loop is not None:
        engine_loop.close(timeout_s=5)
    write_backlog(control, spec.index, {}, changes, final={bed: {"published": link.published,
                                                                  "confirmed": link.confirmed}
                                                            for bed, link in links.items()})


def drive(spec: WorkerSpec, links: dict, start: float, end: float) -> int:
    """``spec.rate`` alarm changes a second, each to a random bed of this worker, from ``start`` to ``end``; how
    many were made."""
    control = Path(spec.control)
    rng = random.Random(spec.seed)
    states = {bed: {"open": [], "next": 0} for bed in links}
    names = sorted(links)
    interval = 1.0 / spec.rate if spec.rate > 0 else float("inf")
    due = max(start, time.time())
    changes = 0
    while due < end:
        wait = due - time.time()
        if wait > 0:
            time.sleep(wait)
        bed = rng.choice(names)
        links[bed].notify(alarm_change(states[bed], rng, time.time() - start))
        changes += 1
        due += interval
        if changes % 50 == 0:
            write_backlog(control, spec.index, links, changes)
    return changes


def write_backlog(control: Path, index: int, links: dict, changes: int, final: dict | None = None) -> None:
    """The worker's unconfirmed events now, atomically (the main process reads it while it is rewritten)."""
    pending = sum(len(link.outbox.pending()) for link in links.values())
    path = control / f"backlog-{index}.json"
    path.with_suffix(".tmp").write_text(json.dumps({"pending": pending, "changes": changes, "at": time.time(),
                                                    "final": final}))
    path.with_suffix(".tmp").replace(path)


def watch_technical(links: dict, cut: set[str], log, stopping: threading.Event) -> None:
    """Each bed's technical alarms as they come and go (wall time), the cut ward's beds polled often."""
    shown: dict[str, frozenset] = {bed: frozenset() for bed in links}
    last_others = 0.0
    while not stopping.is_set():
        now = time.monotonic()
        beds = [bed for bed in links if bed in cut or now - last_others >= POLL_OTHERS_S]
        if len(beds) > len(cut):
            last_others = now
        for bed in beds:
            current = frozenset(c for c in links[bed].conditions() if c in TECHNICAL)
            if current != shown[bed]:
                at = time.time()
                for condition in current - shown[bed]:
                    log.write(json.dumps({"bed": bed, "condition": condition, "raised": at}) + "\n")
                for condition in shown[bed] - current:
                    log.write(json.dumps({"bed": bed, "condition": condition, "cleared": at}) + "\n")
                shown[bed] = current
        stopping.wait(POLL_CUT_S)


# The stations' side: a process holding some wards' stations.

class ShownRecord:
    """Every event a station's board takes, with the life of the station process it was taken in, written before
    the station confirms it (the board takes it first) to a SQLite file that a SIGKILL does not lose."""

    def __init__(self, path: Path, life: str):
        self.life = life
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("CREATE TABLE IF NOT EXISTS shown (bed TEXT, seq INTEGER, kind TEXT, alarm_id INTEGER,"
                         " change TEXT, life TEXT, at REAL)")

    def observe(self, board) -> None:
        take = board.take

        def recording(bed_id, kind, payload, now=None):
            body = take(bed_id, kind, payload, now)
            if kind in EVENT_TYPES and isinstance(body, dict):
                with self._lock:
                    self._db.execute("INSERT INTO shown VALUES (?, ?, ?, ?, ?, ?, ?)",
                                     (bed_id, body["seq"], kind, body.get("alarm_id"), body.get("kind"), self.life,
                                      time.time()))
            return body

        board.take = recording


def run_stations(spec_path: str) -> None:
    """The product's ward stations for some wards, until SIGTERM (a clean stop) or SIGKILL (a crash)."""
    spec = json.loads(Path(spec_path).read_text())
    folder = Path(spec["folder"])
    record = ShownRecord(folder / "shown.db", f"{os.getpid()}-{time.time():.3f}")
    stations = []
    for ward in spec["wards"]:
        if spec["transport"] == "engine":
            from appliance.ward.engine_station import EngineStation
            from appliance.ward.applied import AppliedJournal

            station = EngineStation(spec["urls"], ward["ward"], ward["station"], ward["password"],
                                    AppliedJournal(folder / f"{ward['ward']}-applied.db"))
        else:
            from appliance.ward.station import WardStation

            station = WardStation(LOOPBACK, spec["mqtt_port"], topic_prefix=f"{MQTT_PREFIX}/{ward['ward']}",
                                  client_id=ward["station"], username=ward["station"], password=ward["password"])
        record.observe(station.board)
        stations.append(station)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait()
    for station in stations:
        station.close()
        journal = getattr(station, "journal", None)
        if journal is not None:
            journal.close()


# The main process: servers, processes, faults.

@dataclass
class Plan:
    beds: int
    ward_size: int
    duration_s: float
    transport: str
    rate: float = RATE
    workers: int = 0
    wards_per_station: int = 1
    confirm_timeout_s: float = CONFIRM_TIMEOUT_S
    timing: Timing = FULL
    seed: int = 1

    def __post_init__(self):
        if self.beds < 1 or self.ward_size < 1 or self.duration_s <= 0 or self.rate <= 0:
            raise ValueError(f"beds ({self.beds}), ward size ({self.ward_size}), duration ({self.duration_s}) and "
                             f"rate ({self.rate}) must be positive")
        if self.transport not in ("engine", "mqtt"):
            raise ValueError(f"transport must be 'engine' or 'mqtt', got {self.transport!r}")

    @property
    def wards(self) -> list[Ward]:
        count = -(-self.beds // self.ward_size)
        return [Ward(f"ward{w + 1}", tuple(f"w{w + 1}-bed{b + 1:03d}" for b in range(self.beds)
                                           if b // self.ward_size == w),
                     (f"station{w + 1}",)) for w in range(count)]

    @property
    def fault_kinds(self) -> tuple[str, ...]:
        return ("cut", "pause", "station") if self.transport == "engine" else ("cut", "station")


@dataclass
class Run:
    """What the main process saw happen, in wall time."""

    load_start: float = 0.0
    load_end: float = 0.0
    faults: list[dict] = field(default_factory=list)
    drained_at: float | None = None
    server: str = ""
    notes: list[str] = field(default_factory=list)


class Servers:
    """The engine's three nodes, or one Mosquitto, with the beds' passwords and the relays of the cut ward."""

    def __init__(self, plan: Plan, folder: Path):
        self.plan, self.folder = plan, folder
        self.cluster: LocalCluster | None = None
        self.mosquitto: subprocess.Popen | None = None
        self.relay: CuttableLink | None = None
        self.mqtt_port = 0
        self.killed: str | None = None
        """The node SIGKILLed last, to start again."""

    def __enter__(self) -> Servers:
        if self.plan.transport == "engine":
            hospital = loopback_hospital(self.folder / "store", self.plan.wards, mqtt=False)
            self.cluster = LocalCluster(hospital, self.folder / "config").__enter__()
            asyncio.run(self._streams())
            self.relay = CuttableLink.to_cluster(self.cluster)
        else:
            self._write_broker()
            self.start_broker()
            self.relay = CuttableLink([(LOOPBACK, self.mqtt_port)])
        return self

    def __exit__(self, *exc) -> None:
        if self.relay is not None:
            self.relay.close()
        if self.cluster is not None:
            self.cluster.__exit__(*exc)
        if self.mosquitto is not None and self.mosquitto.poll() is None:
            stop_process(self.mosquitto, 10.0)

    def password(self, user: str) -> str:
        if self.cluster is not None:
            return read_password(self.cluster.configs.secrets_folder, user)
        return (self.folder / "broker" / "secrets" / f"{user}.password").read_text().strip()

    @property
    def name(self) -> str:
        if self.cluster is not None:
            return f"nats-server {server_version(self.cluster.binary)}, three nodes"
        version = subprocess.run([self._mosquitto_binary(), "-h"], capture_output=True, text=True,
                                 check=False).stdout
        return (version.splitlines() or ["mosquitto"])[0].strip()

    async def _streams(self) -> None:
        assert self.cluster is not None
        admin = await connect(self.cluster.urls, ADMIN, self.password(ADMIN))
        try:
            await ensure_ward_streams(admin, self.cluster.hospital)
        finally:
            await admin.close()

    async def _leader(self, ward: str) -> str | None:
        assert self.cluster is not None
        admin = await connect(self.cluster.urls, ADMIN, self.password(ADMIN), attempts=3)
        try:
            info = await admin.jetstream().stream_info(stream_name(ward))
            return info.cluster.leader if info.cluster is not None else None
        finally:
            await admin.close()

    def leader(self, ward: str) -> str | None:
        """The node leading ``ward``'s event stream now, or None when no one answers within a few seconds."""
        for _ in range(10):
            try:
                return asyncio.run(asyncio.wait_for(self._leader(ward), 5))
            except Exception:  # noqa: BLE001  an election under way: ask again
                time.sleep(0.5)
        return None

    def _write_broker(self) -> None:
        """The ward broker as ``appliance ward-broker`` writes it (passwords, ACL, persistence), one topic prefix
        per ward so each station reads its own ward."""
        import getpass

        from appliance.ward.broker import Listener, acl_text, write_ward_broker

        self.mqtt_port = free_port()
        folder = self.folder / "broker"
        wards = self.plan.wards
        files = write_ward_broker(folder, [b for w in wards for b in w.beds], [s for w in wards for s in w.stations],
                                  listener=Listener(self.mqtt_port), persistence_location=folder / "persist")
        (folder / "persist").mkdir(exist_ok=True)
        files.acl_file.write_text("".join(acl_text(w.stations, f"{MQTT_PREFIX}/{w.name}") for w in wards))
        config = files.config_file.read_text().replace(f"listener {self.mqtt_port}",
                                                       f"listener {self.mqtt_port} {LOOPBACK}")
        files.config_file.write_text(f"user {getpass.getuser()}\n{config}")

    def start_broker(self) -> None:
        with open(self.folder / "mosquitto.log", "ab") as log:
            self.mosquitto = subprocess.Popen([mosquitto_binary(), "-c",
                                               str(self.folder / "broker" / "ward-broker.conf")],
                                              stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        wait_for(lambda: listening(self.mqtt_port), 20, "mosquitto")

    def kill_broker(self) -> None:
        assert self.mosquitto is not None
        self.mosquitto.send_signal(signal.SIGKILL)
        self.mosquitto.wait(10)


class Processes:
    """The worker and station processes."""

    def __init__(self, plan: Plan, servers: Servers, folder: Path):
        self.plan, self.servers, self.folder = plan, servers, folder
        self.control = folder / "control"
        self.control.mkdir(parents=True, exist_ok=True)
        self.workers: list[subprocess.Popen] = []
        self.stations: dict[int, subprocess.Popen] = {}
        self.station_specs: list[Path] = []
        self.script = str(Path(__file__).resolve())

    def start(self) -> None:
        wards = self.plan.wards
        urls = self.servers.cluster.urls if self.servers.cluster is not None else []
        groups = [wards[i:i + self.plan.wards_per_station] for i in range(0, len(wards), self.plan.wards_per_station)]
        for g, group in enumerate(groups):
            folder = self.folder / "stations" / f"group{g + 1}"
            folder.mkdir(parents=True, exist_ok=True)
            spec = folder / "spec.json"
            spec.write_text(json.dumps({
                "transport": self.plan.transport, "folder": str(folder), "urls": urls,
                "mqtt_port": self.servers.mqtt_port,
                "wards": [{"ward": w.name, "station": w.stations[0], "password": self.servers.password(w.stations[0])}
                          for w in group]}))
            self.station_specs.append(spec)
            self.start_station(g)
        beds = [BedSpec(bed, w.name, self.servers.password(bed), str(self.folder / "beds" / f"{bed}.db"),
                        w is wards[-1] and len(wards) > 1)
                for w in wards for bed in w.beds]
        (self.folder / "beds").mkdir(exist_ok=True)
        workers = self.plan.workers or max(1, -(-len(beds) // 150))
        relay = self.servers.relay
        assert relay is not None
        for i in range(workers):
            mine = beds[i::workers]
            spec = WorkerSpec(self.plan.transport, mine, urls, relay.urls, self.servers.mqtt_port,
                              relay.ports[0], self.plan.rate * len(mine) / len(beds), self.plan.confirm_timeout_s,
                              str(self.control), self.plan.seed * 1000 + i, i)
            path = self.control / f"worker-{i}.json"
            path.write_text(json.dumps(asdict(spec)))
            self.workers.append(self._spawn("worker", path, self.control / f"worker-{i}.log"))
        wait_for(lambda: all((self.control / f"ready-{i}").exists() for i in range(workers)) or self._dead_worker(),
                 300, "the beds to connect")
        if self._dead_worker():
            raise RuntimeError(f"a bed worker exited while starting: see {self.control}/worker-*.log")
        for group, process in self.stations.items():
            if process.poll() is not None:
                raise RuntimeError(f"station process {group + 1} exited: see {self.station_specs[group].parent}")

    def _dead_worker(self) -> bool:
        return any(worker.poll() is not None for worker in self.workers)

    def _spawn(self, role: str, spec: Path, log_path: Path) -> subprocess.Popen:
        with open(log_path, "ab") as log:
            return subprocess.Popen([sys.executable, self.script, role, str(spec)], stdout=log,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)

    def start_station(self, group: int) -> None:
        spec = self.station_specs[group]
        self.stations[group] = self._spawn("stations", spec, spec.parent / "stations.log")

    def kill_station(self, group: int) -> None:
        process = self.stations.pop(group)
        process.send_signal(signal.SIGKILL)
        process.wait(10)

    def backlog(self) -> tuple[int, int, list]:
        """Unconfirmed events at the beds and alarm changes made so far, as the workers last wrote them."""
        pending = changes = 0
        finals = []
        for i in range(len(self.workers)):
            path = self.control / f"backlog-{i}.json"
            if not path.exists():
                return -1, 0, []
            data = json.loads(path.read_text())
            pending += data["pending"]
            changes += data["changes"]
            finals.append(data["final"])
        return pending, changes, finals

    def stop(self) -> None:
        (self.control / "stop").write_text("")
        for worker in self.workers:
            try:
                worker.wait(120)
            except subprocess.TimeoutExpired:
                worker.kill()
                worker.wait(10)
        for process in self.stations.values():
            stop_process(process, 30.0)


def soak(plan: Plan, folder: Path, progress=print) -> tuple[Run, list[Fault]]:
    """Run ``plan`` in ``folder``: servers, stations, beds, the load and the faults; the records stay in
    ``folder`` for :func:`measure`."""
    run = Run()
    faults = schedule(plan.duration_s, len(plan.wards), plan.fault_kinds, plan.timing)
    with Servers(plan, folder) as servers:
        run.server = servers.name
        processes = Processes(plan, servers, folder)
        try:
            processes.start()
            progress(f"{plan.beds} beds connected; load for {plan.duration_s:.0f} s, {len(faults)} faults")
            run.load_start = time.time() + 1.0
            run.load_end = run.load_start + plan.duration_s
            (processes.control / "go").write_text(json.dumps([run.load_start, run.load_end]))
            actions = sorted([(f.at_s, "start", f) for f in faults] + [(f.heal_s, "heal", f) for f in faults],
                             key=lambda a: a[0])
            for at_s, step, fault in actions:
                delay = run.load_start + at_s - time.time()
                if delay > 0:
                    time.sleep(delay)
                note = apply(step, fault, plan, servers, processes)
                run.faults.append({"kind": fault.kind, "step": step, "at": time.time(), "target": fault.target,
                                   "note": note})
                progress(f"{time.time() - run.load_start:7.1f} s: {fault.kind} {step} {note}")
            time.sleep(max(0.0, run.load_end - time.time()))
            deadline = time.time() + DRAIN_LIMIT_S
            while time.time() < deadline:
                pending, _, _ = processes.backlog()
                if pending == 0:
                    run.drained_at = time.time()
                    break
                time.sleep(0.5)
            empty = "never" if run.drained_at is None else f"after {run.drained_at - run.load_end:.1f} s"
            progress(f"load ended; outboxes empty {empty}")
            run.notes.append(cpu_note(plan, servers, processes, time.time() - run.load_start))
        finally:
            processes.stop()
        _, run_changes, finals = processes.backlog()
        run.notes.append(f"alarm changes made: {run_changes}")
        (folder / "run.json").write_text(json.dumps({"run": asdict(run), "finals": finals}))
    return run, faults


def cpu_note(plan: Plan, servers: Servers, processes: Processes, elapsed_s: float) -> str:
    """The CPU the beds, the stations and the servers used over the load, as shares of one core (the processes
    started again after a kill count from their restart)."""
    def share(pids: list[int]) -> float:
        return sum(cpu_seconds(pid) for pid in pids) / elapsed_s

    beds = share([worker.pid for worker in processes.workers])
    stations = share([process.pid for process in processes.stations.values()])
    if servers.cluster is not None:
        server_pids = [process.pid for process in servers.cluster.processes.values()]
    else:
        server_pids = [] if servers.mosquitto is None else [servers.mosquitto.pid]
    return (f"CPU over the load, in cores: the beds' workers {beds:.2f} ({1000 * beds / plan.beds:.2f} thousandths "
            f"of a core a bed), the stations {stations:.2f}, the servers {share(server_pids):.2f}")


def apply(step: str, fault: Fault, plan: Plan, servers: Servers, processes: Processes) -> str:
    """Do (``start``) or undo (``heal``) ``fault``; what was done, for the record."""
    wards = plan.wards
    cluster = servers.cluster
    if fault.kind == "kill":
        if cluster is None:
            if step == "start":
                servers.kill_broker()
                return "mosquitto SIGKILLed"
            servers.start_broker()
            return "mosquitto started"
        if step == "start":
            leader = servers.leader(wards[fault.target].name)
            if leader is None or not cluster.running(leader):
                leader = next(n.name for n in cluster.hospital.nodes if cluster.running(n.name))
            cluster.kill(leader)
            servers.killed = leader
            return f"{leader} (leading {stream_name(wards[fault.target].name)}) SIGKILLed"
        name = servers.killed
        assert name is not None
        cluster.start(name)
        cluster.wait_ready([name], timeout_s=60)
        return f"{name} started"
    if fault.kind == "cut":
        assert servers.relay is not None
        if step == "start":
            servers.relay.cut()
            return f"{wards[fault.target].name}'s beds cut off"
        servers.relay.mend()
        return f"{wards[fault.target].name}'s link mended"
    if fault.kind == "pause":
        assert cluster is not None
        names = [n.name for n in cluster.hospital.nodes][1:]
        for name in names:
            (cluster.pause if step == "start" else cluster.resume)(name)
        return f"{' and '.join(names)} {'SIGSTOPped' if step == 'start' else 'resumed'}"
    group = fault.target // plan.wards_per_station
    if step == "start":
        processes.kill_station(group)
        return f"station process {group + 1} SIGKILLed"
    processes.start_station(group)
    return f"station process {group + 1} started"


# Measuring from the records.

@dataclass
class Measured:
    events: int = 0
    confirmed: int = 0
    lost: int = 0
    confirmed_lost: int = 0
    shown_twice_lives: int = 0
    shown_twice_content: int = 0
    unconfirmed_at_end: int = 0
    latency_steady: list[float] = field(default_factory=list)
    confirm_steady: list[float] = field(default_factory=list)
    latency_windows: list[dict] = field(default_factory=list)
    drain_after_faults_s: float | None = None
    empty_after_load_s: float | None = None
    technical: list[dict] = field(default_factory=list)
    technical_elsewhere: dict = field(default_factory=dict)
    lost_examples: list = field(default_factory=list)
    sends: int = 0


def read_outboxes(folder: Path, plan: Plan) -> dict[tuple[str, int], dict]:
    """Every event every bed numbered: (bed, seq) -> queued_at, confirmed_at, confirmed_by, alarm_id, kind."""
    events = {}
    for ward in plan.wards:
        for bed in ward.beds:
            db = sqlite3.connect(f"file:{folder / 'beds' / f'{bed}.db'}?mode=ro", uri=True)
            try:
                rows = db.execute("SELECT seq, event, queued_at, confirmed_at, confirmed_by FROM outbox").fetchall()
            finally:
                db.close()
            for seq, text, queued, confirmed, by in rows:
                event = json.loads(text)
                events[bed, seq] = {"ward": ward.name, "queued": queued, "confirmed": confirmed, "by": by,
                                    "alarm_id": event.get("alarm_id"), "kind": event.get("kind")}
            top = max((seq for seq, *_ in rows), default=0)
            if len(rows) != top:
                raise RuntimeError(f"{bed}'s outbox holds {len(rows)} events numbered up to {top}: confirmed "
                                   f"entries were forgotten, so this soak cannot account for them")
    return events


def read_stations(folder: Path, plan: Plan) -> tuple[dict, list]:
    """What the stations applied, (bed, seq) -> first applied_at (the engine's journals; over MQTT the first time a
    board took it), and every take the boards recorded."""
    applied: dict[tuple[str, int], float] = {}
    shown = []
    for group in sorted((folder / "stations").iterdir()):
        for journal in group.glob("*-applied.db"):
            db = sqlite3.connect(f"file:{journal}?mode=ro", uri=True)
            try:
                for bed, seq, at in db.execute("SELECT bed_id, seq, applied_at FROM applied"):
                    applied[bed, seq] = min(at, applied.get((bed, seq), at))
            finally:
                db.close()
        db = sqlite3.connect(f"file:{group / 'shown.db'}?mode=ro", uri=True)
        try:
            shown += db.execute("SELECT bed, seq, kind, alarm_id, change, life, at FROM shown").fetchall()
        finally:
            db.close()
    if plan.transport == "mqtt":
        for bed, seq, _, _, _, _, at in shown:
            applied[bed, seq] = min(at, applied.get((bed, seq), at))
    return applied, shown


def windows(run: Run) -> list[dict]:
    """Each fault from its start to its heal, in wall time."""
    starts: dict[tuple[str, int], dict] = {}
    found = []
    for entry in run.faults:
        key = (entry["kind"], entry["target"])
        if entry["step"] == "start":
            starts[key] = entry
        else:
            begun = starts.pop(key)
            found.append({"kind": entry["kind"], "target": entry["target"], "start": begun["at"], "heal": entry["at"],
                          "note": begun["note"]})
    return found


def measure(folder: Path, plan: Plan, run: Run) -> Measured:
    m = Measured()
    events = read_outboxes(folder, plan)
    applied, shown = read_stations(folder, plan)
    m.events = len(events)
    for key, event in events.items():
        if event["confirmed"] is not None:
            m.confirmed += 1
        else:
            m.unconfirmed_at_end += 1
        if key not in applied:
            m.lost += 1
            if len(m.lost_examples) < 5:
                m.lost_examples.append([*key, event["kind"], event["by"]])
            if event["confirmed"] is not None and event["by"] != "broker":
                m.confirmed_lost += 1
    lives = defaultdict(set)
    seqs_of_change = defaultdict(set)
    for bed, seq, _, alarm_id, change, life, _ in shown:
        lives[bed, seq].add(life)
        seqs_of_change[bed, alarm_id, change].add(seq)
    m.shown_twice_lives = sum(1 for found in lives.values() if len(found) > 1)
    m.shown_twice_content = sum(1 for found in seqs_of_change.values() if len(found) > 1)
    spans = windows(run)
    latency = {key: applied[key] - event["queued"] for key, event in events.items() if key in applied}
    for span in spans:
        hit = [(key, event) for key, event in events.items() if key in latency and
                    span["start"] - IN_FLIGHT_S <= event["queued"] <= span["heal"] and
               (span["kind"] not in ("cut", "station") or event["ward"] in wards_hit(span, plan))]
        m.latency_windows.append({**span, "latencies": [latency[key] for key, _ in hit],
                                  "confirms": [event["confirmed"] - event["queued"] for _, event in hit
                                               if event["confirmed"] is not None]})
    for key, event in events.items():
        if key in latency and steady(event["queued"], spans, run):
            m.latency_steady.append(latency[key])
            if event["confirmed"] is not None:
                m.confirm_steady.append(event["confirmed"] - event["queued"])
    if spans:
        last_heal = max(span["heal"] for span in spans)
        before = [event["confirmed"] for event in events.values() if event["queued"] <= last_heal]
        if all(c is not None for c in before):
            m.drain_after_faults_s = max(0.0, max(before, default=last_heal) - last_heal)
    if run.drained_at is not None:
        m.empty_after_load_s = run.drained_at - run.load_end
    m.technical, m.technical_elsewhere = technical_alarms(folder, plan, spans)
    finals = json.loads((folder / "run.json").read_text())["finals"]
    m.sends = sum(bed["published"] for final in finals if final for bed in final.values())
    return m


def wards_hit(span: dict, plan: Plan) -> set[str]:
    wards = plan.wards
    if span["kind"] == "cut":
        return {wards[span["target"]].name}
    group = span["target"] // plan.wards_per_station
    return {w.name for w in wards[group * plan.wards_per_station:(group + 1) * plan.wards_per_station]}


def steady(queued: float, spans: list[dict], run: Run) -> bool:
    """Queued with no fault under way and ``STEADY_AFTER_S`` after the last one healed (and after the start)."""
    if queued < run.load_start + STEADY_AFTER_S:
        return False
    return all(not (span["start"] - IN_FLIGHT_S <= queued <= span["heal"] + STEADY_AFTER_S) for span in spans)


def technical_alarms(folder: Path, plan: Plan, spans: list[dict]) -> tuple[list[dict], dict]:
    """For each cut: every bed of the cut ward, when (after the cut plus the configured time) it raised its
    technical alarm and whether it cleared after the mend. And how many beds raised one during each other
    kind of fault."""
    transitions = []
    for path in (folder / "control").glob("technical-*.jsonl"):
        transitions += [json.loads(line) for line in path.read_text().splitlines() if line]
    cut_ward = plan.wards[-1]
    results = []
    for span in (s for s in spans if s["kind"] == "cut"):
        delays, cleared = [], 0
        for bed in cut_ward.beds:
            raised = [t["raised"] for t in transitions if t["bed"] == bed and "raised" in t
                      and span["start"] <= t["raised"] <= span["heal"]]
            if raised:
                delays.append(min(raised) - span["start"] - plan.confirm_timeout_s)
            if any(t["bed"] == bed and "cleared" in t and t["cleared"] >= span["heal"] for t in transitions) and \
                    not still_raised(transitions, bed):
                cleared += 1
        results.append({"start": span["start"], "beds": len(cut_ward.beds), "raised": len(delays),
                        "cleared": cleared, "delays": delays})
    elsewhere: dict[str, int] = Counter()
    for span in (s for s in spans if s["kind"] != "cut"):
        beds = {t["bed"] for t in transitions if "raised" in t and span["start"] <= t["raised"] <= span["heal"] + 5}
        elsewhere[span["kind"]] = max(elsewhere[span["kind"]], len(beds))
    return results, dict(elsewhere)


def still_raised(transitions: list[dict], bed: str) -> bool:
    """Whether the bed's last transition of any technical alarm left it raised."""
    state: dict[str, bool] = {}
    for t in sorted((t for t in transitions if t["bed"] == bed), key=lambda t: t.get("raised", t.get("cleared"))):
        state[t["condition"]] = "raised" in t
    return any(state.values())


# The report.

HEADER = """# The hospital soak: alarms through killed servers, a cut link and a crashed station

Written by `benchmarks/hospital.py` (how it works: its docstring). Every bed is the product's ward link with its
own durable outbox and its own login; every ward station is the product's (`EngineStation` with its journal of
applied events on the engine, the MQTT `WardStation` on Mosquitto). Lost, shown twice and latencies are read
from the beds' outboxes and the stations' journals and boards after the run, not from the harness's own
counting. Beds send no summaries in the soak: only alarm changes, which are what a confirmation is for.

"""

def measured_record(plan: Plan, run: Run, m: Measured) -> dict:
    """The run's counts, faults and technical alarms, without the per-event latencies (the report has those)."""
    counts = {k: v for k, v in asdict(m).items() if k not in ("latency_steady", "confirm_steady", "latency_windows")}
    return {"beds": plan.beds, "wards": len(plan.wards), "ward_size": plan.ward_size, "faults": run.faults,
            "fault_windows": len(m.latency_windows), **counts}


def ms(values: list[float], q: float) -> str:
    return f"{1000 * percentile(values, q):.0f}" if values else "-"


def report(plan: Plan, run: Run, m: Measured, command: str, elapsed_s: float) -> str:
    kind = "the hospital engine" if plan.transport == "engine" else "one Mosquitto (the baseline)"
    lines = [f"## {plan.beds} beds on {kind}, {plan.duration_s / 60:.0f} minutes", "",
             f"`{command}` on {machine()}; {run.server}; {elapsed_s / 60:.0f} min in all.", "",
             f"{plan.beds} beds in {len(plan.wards)} wards of up to {plan.ward_size}, {plan.rate:.0f} alarm changes a "
             f"second in all, the ward link's technical alarm after {plan.confirm_timeout_s:.0f} s without "
             f"confirmations. {'; '.join(run.notes)}.", "",
             table(["", "count"], [["alarm changes numbered at the beds", m.events],
                                   ["sent by the beds, resends included", m.sends],
                                   ["confirmed at the bed by a station", m.confirmed],
                                   ["never applied by a station (lost)", m.lost],
                                   ["confirmed at the bed, then lost", m.confirmed_lost],
                                   ["shown twice: taken in two lives of a station", m.shown_twice_lives],
                                   ["shown twice: one alarm change under two numbers", m.shown_twice_content],
                                   ["unconfirmed at the end", m.unconfirmed_at_end]]), ""]
    if m.lost_examples:
        lines += [f"Lost, for example (bed, number, change, confirmed by): {m.lost_examples}.", ""]
    lines += ["Bed-to-station latency (queued at the bed to applied at the station), ms:", "",
              table(["when", "events", "p50", "p99", "max", "p99 to the bed's confirmation"],
                    [["steady state", len(m.latency_steady), ms(m.latency_steady, 0.5), ms(m.latency_steady, 0.99),
                      ms(m.latency_steady, 1.0), ms(m.confirm_steady, 0.99)]] +
                    [[f"{w['kind']} at {w['start'] - run.load_start:.0f} s ({w['note']}), queued from "
                      f"{IN_FLIGHT_S:.0f} s before until healed {w['heal'] - w['start']:.0f} s later",
                      len(w["latencies"]), ms(w["latencies"], 0.5), ms(w["latencies"], 0.99), ms(w["latencies"], 1.0),
                      ms(w["confirms"], 0.99)] for w in m.latency_windows]), ""]
    drain = "never" if m.drain_after_faults_s is None else f"{m.drain_after_faults_s:.1f} s"
    empty = "never" if m.empty_after_load_s is None else f"{m.empty_after_load_s:.1f} s"
    lines += [f"Every event queued before the last fault healed was confirmed {drain} after it healed (under load); "
              f"once the load stopped, every bed's outbox was empty after {empty}.", ""]
    if m.technical:
        rows = [[f"{t['start'] - run.load_start:.0f} s", f"{t['raised']} of {t['beds']}",
                 f"{t['cleared']} of {t['beds']}",
                 *(f"{value:.2f}" for value in ((min(t["delays"]), statistics.median(t["delays"]), max(t["delays"]))
                                                if t["delays"] else (float("nan"),) * 3))] for t in m.technical]
        lines += [f"The cut ward's technical alarm, delay after the cut plus {plan.confirm_timeout_s:.0f} s, in s "
                  f"(polled every {POLL_CUT_S} s; an alarm change left unconfirmed just before the cut can bring it "
                  f"forward by that change's age):", "",
                  table(["cut at", "raised", "cleared after the mend", "min", "median", "max"], rows), ""]
    if m.technical_elsewhere:
        lines += ["Beds that raised a technical alarm during the other faults (most in one fault): " +
                  ", ".join(f"{kind} {count}" for kind, count in sorted(m.technical_elsewhere.items())) + ".", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "worker":
        run_worker(argv[1])
        return 0
    if argv and argv[0] == "stations":
        run_stations(argv[1])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--beds", type=int, default=300)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--ward-size", type=int, default=30)
    parser.add_argument("--rate", type=float, default=RATE, help="alarm changes a second over all beds")
    parser.add_argument("--transport", choices=("engine", "mqtt"), default="engine")
    parser.add_argument("--workers", type=int, default=0, help="bed processes (default: one per 150 beds)")
    parser.add_argument("--wards-per-station", type=int, default=1)
    parser.add_argument("--compressed", action="store_true", help="the test's short fault schedule")
    parser.add_argument("--keep", type=Path, help="keep the records in this folder")
    parser.add_argument("--out", type=Path, default=HERE / "hospital.md")
    parser.add_argument("--append", action="store_true", help="add the section to --out instead of replacing it")
    parser.add_argument("--json", type=Path, help="also write the counts and the faults as JSON here (for a test)")
    args = parser.parse_args(argv)
    plan = Plan(args.beds, args.ward_size, args.minutes * 60, args.transport, rate=args.rate, workers=args.workers,
                wards_per_station=args.wards_per_station, timing=COMPRESSED if args.compressed else FULL)
    began = time.time()
    with contextlib.ExitStack() as stack:
        folder = args.keep or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="hospital-soak-")))
        folder.mkdir(parents=True, exist_ok=True)
        run, _ = soak(plan, folder)
        measured = measure(folder, plan, run)
    shown = [a for i, a in enumerate(argv) if a != "--keep" and (i == 0 or argv[i - 1] != "--keep")]
    command = "python benchmarks/hospital.py " + " ".join(shown)             # where records were kept is no figure
    section = report(plan, run, measured, command, time.time() - began)
    print(section)
    if args.json:
        args.json.write_text(json.dumps(measured_record(plan, run, measured)))
    text = HEADER + section if not args.append or not args.out.exists() else \
        args.out.read_text().rstrip() + "\n\n" + section
    args.out.write_text(text if text.endswith("\n") else text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
