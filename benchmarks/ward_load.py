"""Ward station under load: 50 beds at 1 frame/s through a real Mosquitto, watched on the ward view's stream.

    python benchmarks/ward_load.py                # writes benchmarks/ward_load.md and .json (about 11 min)
    python benchmarks/ward_load.py --duration 60  # a shorter run

Four kinds of process, each timed on its own (CPU from /proc/<pid>/stat):

* **Mosquitto**, on a free local port, reporting its counters on ``$SYS`` every second.
* **The ward station**, ``appliance ward --config ward.toml --data-dir DIR --listen 127.0.0.1:PORT
  --plain-http``: the ``WardStation`` and its web view (waitress), with one nurse account made
  beforehand (``appliance.accounts.users.UserStore``), keep-alive 5 s to the broker, summary interval 1 s.
* **The load generator**, one process driving 50 production publishers (``WardLink``, each with its
  outbox and one MQTT connection, with its last will, keep-alive 5 s). Each bed takes a frame a second,
  at its own phase within the second: it sends a summary in ``ward_summary()``'s format (4 to 8 regions with
  zone, peak and dose, the turn countdown, its open alarms, the frame counts) through ``summarise()``,
  and, as the daemon does, notifies its new alarm events (QoS 1) in the same frame before the summary.
  Each bed raises a new alarm every 15 s on average (none in the first 3 s and the last 10 s), which a
  nurse acknowledges 8 to 20 s later (in two of three) and which ends 12 to 40 s after it was raised.
  The wall time of every ``notify()`` is logged. After the frames, the links are given up to 10 s for the
  station's last confirmations; what is still unconfirmed then is counted.
* **Fifteen probe beds, one process each** (the same ward link, summaries only), stopped in turn from 10 %
  to 80 % of the run: five frozen (SIGSTOP, a hung monitor that keeps its connection), five killed
  (SIGKILL: the kernel closes its socket), five closed cleanly (SIGTERM: ``close()`` publishes
  "offline").

The benchmark itself logs in as the nurse over HTTP (the login form and its CSRF token) and reads
``/api/ward/stream`` (server-sent events). An alarm's latency is the time from its ``notify()`` to the
first stream message showing its ``alarm_id`` on its bed: broker, station and web view end to end.
An alarm never shown is lost; an alarm shown twice on one bed in one message is a duplicate; an alarm
still shown more than 3 s after its end is stuck. A stopped bed's offline time runs from the signal
to the first message showing it ``online: false``.

``--stand-in`` runs the ``WardStation`` behind a small stdlib HTTP server of the same routes instead
of ``appliance ward`` (what this benchmark was developed against before the ward command existed); its
view also carries the station's events, so it adds the station's own receipt time of each alarm.
"""

from __future__ import annotations

import argparse
import contextlib
import getpass
import http.client
import http.cookiejar
import json
import os
import random
import re
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from report import (cpu_seconds, free_port, listening, machine, mosquitto_binary, percentile, table,  # noqa: E402
                    wait_for)

BEDS = 50
DURATION_S = 600.0
FRAME_S = 1.0
BED_KEEPALIVE_S = 5              # the least a bed's [notify.mqtt] keepalive_s may be: the strictest case
STATION_KEEPALIVE_S = 5
SUMMARY_INTERVAL_S = 1.0
ALARM_EVERY_S = 15.0             # mean time between a bed's new alarms
FIRST_ALARM_AFTER_S = 3.0
QUIET_END_S = 10.0               # no new alarm in the last seconds, so every one has time to show
ACK_AFTER_S = (8.0, 20.0)
END_AFTER_S = (12.0, 40.0)
STUCK_AFTER_S = 3.0
CONFIRM_WAIT_S = 10.0            # for the last events' confirmations, after the frames
CPU_WINDOW_S = 60.0
PROBES_PER_KIND = 5
STOPPING = (0.1, 0.8)            # the probe beds are stopped in turn across this share of the run
SIGNALS = {"frozen": signal.SIGSTOP, "killed": signal.SIGKILL, "closed": signal.SIGTERM}
NURSE, PASSWORD = "nurse1", "ward load test password"
ZONES = ("occiput", "scapula", "sacrum", "trochanter", "heel", None)
PRIORITY_WEIGHTS = {"low": 0.2, "medium": 0.5, "high": 0.3}


def python(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


# The emulated beds (in the load generator's process, or one in its own).

class EmulatedBed:
    """One monitor's output: a summary in ``ward_summary()``'s format each frame and, at random, alarm events."""

    def __init__(self, bed_id: str, rng: random.Random, *, alarms: bool):
        self.bed_id, self.rng, self.alarms_on = bed_id, rng, alarms
        self.time_s = rng.uniform(0.0, 80000.0)          # the monitor's own clock: seconds since it started
        self.maps = int(self.time_s)
        self.turn_due_s = rng.uniform(600.0, 7200.0)
        self.regions = [self._region(k) for k in range(rng.randint(4, 8))]
        self.next_alarm_id = rng.randint(1, 50)
        self.open: dict[int, dict] = {}                  # alarm_id -> alarm, with its ack and end times
        self.next_alarm_s = FIRST_ALARM_AFTER_S + rng.expovariate(1.0 / ALARM_EVERY_S)

    def _region(self, region_id: int) -> dict:
        return {"id": region_id, "zone": self.rng.choice(ZONES), "peak_mmhg": self.rng.uniform(15.0, 70.0),
                "dose": self.rng.uniform(0.0, 0.6)}

    def frame(self, elapsed_s: float, raise_alarms: bool) -> list:
        """Advance one frame (``elapsed_s`` since the run began); the alarm events it makes."""
        from appliance.alerts.events import Event

        self.time_s += FRAME_S
        self.maps += 1
        self.turn_due_s -= FRAME_S
        if self.turn_due_s < -300.0:
            self.turn_due_s = 7200.0
        for region in self.regions:
            region["peak_mmhg"] = min(120.0, max(5.0, region["peak_mmhg"] + self.rng.gauss(0.0, 1.5)))
            region["dose"] = min(1.5, region["dose"] + max(0.0, region["peak_mmhg"] - 32.0) * 1e-5)
        events = []
        for alarm in list(self.open.values()):
            if alarm["ack_at"] is not None and elapsed_s >= alarm["ack_at"] and alarm["acknowledged_by"] is None:
                alarm["acknowledged_by"] = NURSE
                events.append(self._event(Event, "acknowledged", alarm, user=NURSE))
            if elapsed_s >= alarm["end_at"]:
                del self.open[alarm["alarm_id"]]
                events.append(self._event(Event, "ended", alarm))
        if self.alarms_on and raise_alarms and elapsed_s >= self.next_alarm_s:
            self.next_alarm_s = elapsed_s + self.rng.expovariate(1.0 / ALARM_EVERY_S)
            region = self.rng.choice(self.regions)
            zone = region["zone"] or "region"
            alarm = {"alarm_id": self.next_alarm_id, "key": f"pressure:{zone}:{region['id']}",
                     "priority": self.rng.choices(list(PRIORITY_WEIGHTS), list(PRIORITY_WEIGHTS.values()))[0],
                     "state": "active", "message": f"{zone.capitalize()} dose over limit", "acknowledged_by": None,
                     "zone": zone, "region_id": region["id"],
                     "ack_at": elapsed_s + self.rng.uniform(*ACK_AFTER_S) if self.rng.random() < 2 / 3 else None,
                     "end_at": elapsed_s + self.rng.uniform(*END_AFTER_S)}
            self.next_alarm_id += 1
            self.open[alarm["alarm_id"]] = alarm
            events.append(self._event(Event, "raised", alarm))
        return events

    def _event(self, Event, kind: str, alarm: dict, user: str | None = None):
        return Event(self.time_s, "alarm", kind, alarm["priority"], "clinical", alarm["key"], site=alarm["zone"],
                     alarm_id=alarm["alarm_id"], message=alarm["message"], user=user)

    def summary(self) -> dict:
        """As ``appliance.service.daemon.ward_summary`` cuts a live snapshot down."""
        return {"bed_id": self.bed_id, "time_s": self.time_s,
                "peak_mmhg": max(r["peak_mmhg"] for r in self.regions),
                "regions": [{"zone": r["zone"], "peak_mmhg": r["peak_mmhg"], "dose": r["dose"]} for r in self.regions],
                "turn": {"due_in_s": self.turn_due_s},
                "alarms": [{k: a[k] for k in ("alarm_id", "key", "priority", "state", "message", "acknowledged_by")}
                           for a in self.open.values()],
                "status": {"maps": self.maps, "faults": 0}}


def ward_link(port: int, bed_id: str, folder: Path):
    from appliance.alerts.ward_mqtt import mqtt_ward_link
    from appliance.store.outbox import Outbox

    return mqtt_ward_link("127.0.0.1", port, bed_id, Outbox(folder / f"{bed_id}-outbox.db"), client_id=f"{bed_id}-monitor",
                    keepalive_s=BED_KEEPALIVE_S, summary_interval_s=SUMMARY_INTERVAL_S)


def generate(port: int, beds: int, duration_s: float, folder: Path, seed: int) -> None:
    """The load generator: ``beds`` ward links at 1 frame/s for ``duration_s``; logs to ``folder``."""
    rng = random.Random(seed)
    names = [f"bed-{k:02d}" for k in range(1, beds + 1)]
    emulated = [EmulatedBed(name, random.Random(rng.random()), alarms=True) for name in names]
    links = [ward_link(port, name, folder) for name in names]
    wait_for(lambda: all(link.status()["connected"] for link in links), 30, "connection of every bed")
    log = (folder / "events.jsonl").open("w", encoding="utf-8")
    print("ready", flush=True)
    start = time.monotonic()
    due = [(k / beds, k) for k in range(beds)]          # each bed at its own phase within the second
    late, frames = [], 0
    while True:
        at, k = min(due)
        if at >= duration_s:
            break
        delay = start + at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            late.append(-delay)
        for event in emulated[k].frame(at, raise_alarms=at < duration_s - QUIET_END_S):
            published_at = time.time()
            links[k].notify(event)
            log.write(json.dumps({"bed_id": names[k], "alarm_id": event.alarm_id, "kind": event.kind,
                                  "time_s": event.time_s, "published_at": published_at}) + "\n")
        links[k].summarise(emulated[k].summary())
        frames += 1
        due[k] = (at + FRAME_S, k)
    log.close()
    print("done", flush=True)
    deadline = time.monotonic() + CONFIRM_WAIT_S
    while any(link.status()["unconfirmed"] for link in links) and time.monotonic() < deadline:
        time.sleep(0.05)
    counts = {"events_published": sum(link.published for link in links),
              "events_confirmed": sum(link.confirmed for link in links),
              "events_unconfirmed": sum(link.status()["unconfirmed"] for link in links),
              "confirm_latencies_s": [t for link in links for t in link.confirm_latencies_s]}
    closing = [threading.Thread(target=link.close, kwargs={"timeout_s": 5.0}) for link in links]   # all at once
    for thread in closing:
        thread.start()
    for thread in closing:
        thread.join()
    (folder / "generator.json").write_text(json.dumps({
        "frames": frames, "late_frames": sum(d > 0.1 for d in late), "worst_lateness_s": max(late, default=0.0),
        "summaries_sent": sum(link.summaries_sent for link in links),
        "summaries_skipped": sum(link.summaries_skipped for link in links), **counts}))


def probe_bed(port: int, bed_id: str, folder: Path) -> None:
    """One bed in its own process, summaries only, until SIGTERM (then a clean close), SIGKILL or SIGSTOP."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    bed, out = EmulatedBed(bed_id, random.Random(bed_id), alarms=False), ward_link(port, bed_id, folder)
    wait_for(lambda: out.status()["connected"], 30, f"connection of {bed_id}")
    print("ready", flush=True)
    start, frames = time.monotonic(), 0
    while not stop.wait(max(0.0, start + frames * FRAME_S - time.monotonic())):
        bed.frame(frames * FRAME_S, raise_alarms=False)
        out.summarise(bed.summary())
        frames += 1
    out.close(timeout_s=5.0)


# The stand-in station: WardStation behind the same routes, for before `appliance ward` existed.

def stand_in(port: int, listen_port: int) -> None:
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    from appliance.ward.station import WardStation

    station = WardStation("127.0.0.1", port, client_id="ward-load-stand-in", keepalive_s=STATION_KEEPALIVE_S,
                          summary_interval_s=SUMMARY_INTERVAL_S)
    station.wait_subscribed(30)

    def view() -> dict:
        now = time.time()
        return {"now": now, "beds": [{"bed_id": b["bed_id"], "online": b["online"], "status": b["status"],
                                      "heard_s_ago": None if b["last_heard_at"] is None
                                      else round(now - b["last_heard_at"], 1),
                                      "highest_priority": b["highest_priority"], "alarms": b["alarms"],
                                      "events": [{k: e[k] for k in ("alarm_id", "kind", "received_at")}
                                                 for e in b["events"]]} for b in station.beds()]}

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            if self.path == "/login":
                self._send(200, "text/html", b'<form method="post"><input type="hidden" name="csrf_token" '
                                             b'value="stand-in"></form>')
            elif self.path == "/api/ward":
                self._send(200, "application/json", json.dumps(view()).encode())
            elif self.path == "/api/ward/stream":
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.end_headers()
                last = None
                try:
                    while True:
                        state = view()
                        key = json.dumps([(b["online"], b["status"], b["alarms"], b["events"][-1:])
                                          for b in state["beds"]])
                        if key != last:
                            last = key
                            self.wfile.write(f"data: {json.dumps(state)}\n\n".encode())
                            self.wfile.flush()
                        time.sleep(0.25)
                except OSError:
                    return
            else:
                self._send(404, "text/plain", b"not here")

        def do_POST(self):
            self.rfile.read(int(self.headers.get("Content-Length", 0)))
            self.send_response(303)
            self.send_header("Location", "/api/ward")
            self.send_header("Set-Cookie", "session=stand-in; Path=/")
            self.end_headers()

        def _send(self, status: int, kind: str, body: bytes):
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    server = ThreadingHTTPServer(("127.0.0.1", listen_port), Handler)
    server.daemon_threads = True
    signal.signal(signal.SIGTERM, lambda *_: threading.Thread(target=server.shutdown).start())
    server.serve_forever()
    station.close()


# The measuring side.

class Broker:
    """Mosquitto on a free local port with its $SYS counters every second; ``counters`` holds their latest."""

    def __init__(self, folder: Path):
        self.port = free_port()
        binary = mosquitto_binary()
        conf = folder / "mosquitto.conf"
        conf.write_text(f"user {getpass.getuser()}\nlistener {self.port} 127.0.0.1\nallow_anonymous true\n"
                        "sys_interval 1\npersistence false\nmax_queued_messages 10000\n")
        self.process = subprocess.Popen([binary, "-c", str(conf)], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL)
        self.counters: dict[str, int] = {}
        self._client = None
        wait_for(lambda: listening(self.port), 10, "mosquitto")

    def watch(self) -> None:
        import paho.mqtt.client as mqtt

        def on_message(client, userdata, message):
            with contextlib.suppress(ValueError):
                self.counters[message.topic.removeprefix("$SYS/broker/")] = int(message.payload)

        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="ward-load-sys")
        self._client.on_message = on_message
        self._client.on_connect = lambda c, *_: c.subscribe([("$SYS/broker/publish/messages/+", 0),
                                                             ("$SYS/broker/messages/+", 0)])
        self._client.connect("127.0.0.1", self.port)
        self._client.loop_start()

    def stop(self) -> None:
        if self._client is not None:
            self._client.disconnect()
            self._client.loop_stop()
        self.process.terminate()
        self.process.wait(10)


class WardView:
    """A nurse's HTTP session on the station, reading ``/api/ward/stream`` in a thread; notes what it sees."""

    def __init__(self, url: str):
        self.url = url
        self.jar = http.cookiejar.CookieJar()
        self.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(self.jar))
        self.first_seen: dict[tuple[str, int], float] = {}       # (bed, alarm) -> first message showing it
        self.last_seen: dict[tuple[str, int], float] = {}
        self.ack_seen: dict[tuple[str, int], float] = {}
        self.event_received: dict[tuple[str, int], float] = {}   # the station's own receipt, if the view has it
        self.online: dict[str, list[tuple[float, bool, str | None]]] = {}   # each change of a bed's flags
        self.heard: dict[str, float] = {}                        # the bed's last message, as the view last said
        self.offline_heard: dict[str, list[tuple[float, float]]] = {}   # (shown offline, its last message then)
        self.duplicates: list[tuple[float, str, int]] = []
        self.bed_repeats = 0
        self.messages = self.bytes = self.reconnects = 0
        self.max_beds = 0
        self.last_message_at = 0.0
        self._stop = threading.Event()
        self.error: str | None = None
        self._thread = None
        self._socket = None

    def log_in(self, name: str, password: str) -> None:
        with self.opener.open(self.url + "/login", timeout=10) as page:
            token = re.search(r'name="csrf_token" value="([^"]+)"', page.read().decode()).group(1)
        form = urllib.parse.urlencode({"name": name, "password": password, "csrf_token": token}).encode()
        with self.opener.open(self.url + "/login", data=form, timeout=10) as answer:
            answer.read()
        with self.opener.open(self.url + "/api/ward", timeout=10) as answer:   # refused unless logged in
            if answer.headers.get_content_type() != "application/json":
                raise RuntimeError(f"not logged in: /api/ward answered {answer.headers.get_content_type()}")
            json.loads(answer.read())

    def start(self) -> None:
        self._thread = threading.Thread(target=self._read, name="ward-view", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop reading: the stream's socket is shut down under the reader, which then sees its end."""
        self._stop.set()
        if self._socket is not None:
            with contextlib.suppress(OSError):
                self._socket.shutdown(socket.SHUT_RDWR)
        self._thread.join(10)

    def _read(self) -> None:
        address = urllib.parse.urlsplit(self.url)
        while not self._stop.is_set():
            connection = http.client.HTTPConnection(address.hostname, address.port, timeout=30)
            try:
                connection.connect()
                self._socket = connection.sock      # the response takes it over from the connection
                connection.request("GET", "/api/ward/stream", headers={
                    "Accept": "text/event-stream", "Cookie": "; ".join(f"{c.name}={c.value}" for c in self.jar)})
                response = connection.getresponse()
                if response.status != 200:
                    self.error = f"/api/ward/stream answered HTTP {response.status}"
                    return
                for line in response:
                    if line.startswith(b"data:"):
                        self._take(time.time(), line)
                    if self._stop.is_set():
                        return
            except (OSError, http.client.HTTPException):
                if self._stop.is_set():
                    return
            finally:
                connection.close()
            if self._stop.is_set():
                return
            self.reconnects += 1               # the server ends a stream after a while; a browser reconnects
            time.sleep(0.5)

    def _take(self, now: float, line: bytes) -> None:
        state = json.loads(line[5:])
        self.messages += 1
        self.bytes += len(line)
        self.last_message_at = now
        beds = state["beds"]
        self.max_beds = max(self.max_beds, len(beds))
        if len({b["bed_id"] for b in beds}) != len(beds):
            self.bed_repeats += 1
        for bed in beds:
            name = bed["bed_id"]
            flags = (bed["online"], bed.get("status"))
            changes = self.online.setdefault(name, [])
            if not changes or changes[-1][1:] != flags:
                if changes and changes[-1][1] and not bed["online"] and name in self.heard:
                    self.offline_heard.setdefault(name, []).append((now, self.heard[name]))
                changes.append((now, *flags))
            if bed.get("heard_s_ago") is not None:
                self.heard[name] = state["now"] - bed["heard_s_ago"]
            ids = [a["alarm_id"] for a in bed["alarms"]]
            if len(set(ids)) != len(ids):
                self.duplicates.append((now, name, len(ids) - len(set(ids))))
            for alarm in bed["alarms"]:
                key = (name, alarm["alarm_id"])
                self.first_seen.setdefault(key, now)
                self.last_seen[key] = now
                if alarm.get("acknowledged_by") is not None:
                    self.ack_seen.setdefault(key, now)
            for event in bed.get("events", ()):
                if event.get("kind") == "raised" and "received_at" in event:
                    self.event_received.setdefault((name, event["alarm_id"]), event["received_at"])

    def offline_after(self, bed_id: str, since: float) -> dict:
        """Seconds from ``since`` to the first message showing ``bed_id`` offline and to its status "offline", and
        from the bed's last message (as the station heard it, to 0.1 s) to the first."""
        changes = [c for c in self.online.get(bed_id, []) if c[0] >= since]
        offline = next((t for t, online, _ in changes if not online), None)
        will = next((t for t, _, status in changes if status == "offline"), None)
        heard = next((h for t, h in self.offline_heard.get(bed_id, []) if t == offline), None)
        return {"offline_s": None if offline is None else offline - since,
                "status_offline_s": None if will is None else will - since,
                "offline_after_last_message_s": None if offline is None or heard is None else offline - heard}


class CpuSampler:
    """Each process's CPU share (of one core) in successive windows of ``window_s``, from a thread."""

    def __init__(self, pids: dict[str, int], window_s: float):
        self.pids, self.window_s = pids, window_s
        self.windows: list[dict] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cpu-sampler", daemon=True)
        self._thread.start()

    def _sample(self) -> tuple[float, dict]:
        return time.time(), {k: cpu_seconds(p) for k, p in self.pids.items()}

    def _run(self) -> None:
        start = last = self._sample()
        while True:
            stopping = self._stop.wait(self.window_s)
            try:
                now = self._sample()
            except OSError:                                 # a process has ended: the run is over
                return
            if now[0] - last[0] > self.window_s / 4:      # the last, shorter window too, unless it is very short
                self.windows.append({"from_s": last[0] - start[0], "to_s": now[0] - start[0],
                                     **{k: (now[1][k] - last[1][k]) / (now[0] - last[0]) for k in self.pids}})
            last = now
            if stopping:
                return

    def stop(self) -> list[dict]:
        self._stop.set()
        self._thread.join(5)
        return self.windows


def ward_command_exists() -> bool:
    answer = subprocess.run([sys.executable, "-m", "appliance", "ward", "--help"], capture_output=True, check=False)
    return answer.returncode == 0


@contextlib.contextmanager
def station_process(folder: Path, broker_port: int, *, use_stand_in: bool):
    """The ward station on a free port: yields (url, process)."""
    port = free_port()
    if use_stand_in:
        command = python("stand-in", "--port", str(broker_port), "--listen-port", str(port))
    else:
        from appliance.accounts.users import UserStore

        data = folder / "ward-data"
        data.mkdir()
        UserStore(data / "webui.db").create(NURSE, PASSWORD, "nurse", by="benchmark")
        config = folder / "ward.toml"
        config.write_text(f'[broker]\nhost = "127.0.0.1"\nport = {broker_port}\nkeepalive_s = {STATION_KEEPALIVE_S}\n'
                          f'\n[station]\nclient_id = "ward-load-station"\nsummary_interval_s = {SUMMARY_INTERVAL_S}\n')
        command = [sys.executable, "-m", "appliance", "ward", "--config", str(config), "--data-dir", str(data),
                   "--listen", f"127.0.0.1:{port}", "--plain-http"]
    log = (folder / "station.log").open("w")
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: listening(port) or process.poll() is not None, 60, "ward station")
        if process.poll() is not None:
            raise RuntimeError(f"the ward station exited: {(folder / 'station.log').read_text()[-2000:]}")
        yield f"http://127.0.0.1:{port}", process
    finally:
        process.terminate()
        try:
            process.wait(15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()


def start(command: list[str], processes: list) -> subprocess.Popen:
    processes.append(subprocess.Popen(command, stdout=subprocess.PIPE, text=True))
    return processes[-1]


def ready(process: subprocess.Popen) -> None:
    line = process.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"{process.args[2:4]} did not start: {line!r}")


def stop_times(per_kind: int, duration_s: float) -> list[tuple[float, str, int]]:
    """(seconds into the run, kind, number) of each probe bed's stop: the kinds in turn, evenly spread."""
    start, end = STOPPING
    step = (end - start) * duration_s / (per_kind * len(SIGNALS))
    order = [(k, kind) for k in range(per_kind) for kind in SIGNALS]
    return [(start * duration_s + i * step, kind, k) for i, (k, kind) in enumerate(order)]


def run(beds: int = BEDS, duration_s: float = DURATION_S, *, probes_per_kind: int = PROBES_PER_KIND, seed: int = 1,
        use_stand_in: bool | None = None, say=print) -> dict:
    """One load run of ``beds`` for ``duration_s``: the raw figures, which ``report`` writes up."""
    if use_stand_in is None:
        use_stand_in = not ward_command_exists()
    processes: list[subprocess.Popen] = []
    begun = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        broker = Broker(folder)
        view = sampler = None
        try:
            broker.watch()
            with station_process(folder, broker.port, use_stand_in=use_stand_in) as (url, station):
                say(f"{time.time() - begun:.1f} s: station listening")
                view = WardView(url)
                view.log_in(NURSE, PASSWORD)
                view.start()
                probes = {(kind, k): start(python("bed", "--port", str(broker.port), "--bed-id",
                                                  f"probe-{kind}-{k}", "--folder", tmp), processes)
                          for kind in SIGNALS for k in range(probes_per_kind)}
                generator = start(python("generate", "--port", str(broker.port), "--beds", str(beds),
                                         "--duration", str(duration_s), "--folder", tmp, "--seed", str(seed)),
                                  processes)
                for process in processes:
                    ready(process)
                say(f"{time.time() - begun:.1f} s: {beds} beds and {len(probes)} probe beds running for "
                    f"{duration_s:.0f} s ({'stand-in' if use_stand_in else 'appliance ward'})")
                pids = {"broker": broker.process.pid, "station": station.pid, "generator": generator.pid,
                        "client": os.getpid()}
                cpu0, counters0, t0 = {k: cpu_seconds(p) for k, p in pids.items()}, dict(broker.counters), time.time()
                sampler = CpuSampler(pids, min(CPU_WINDOW_S, duration_s / 4))
                stopped = {}
                for at, kind, k in stop_times(probes_per_kind, duration_s):
                    time.sleep(max(0.0, t0 + at - time.time()))
                    stopped[f"probe-{kind}-{k}"] = kind, time.time()
                    probes[kind, k].send_signal(SIGNALS[kind])
                if generator.stdout.readline().strip() != "done":
                    raise RuntimeError("the load generator did not finish its frames")
                done_at = time.time()
                elapsed = done_at - t0
                cpu = {k: (cpu_seconds(p) - cpu0[k]) / elapsed for k, p in pids.items()}
                cpu_windows = sampler.stop()
                counters1 = dict(broker.counters)
                say(f"{time.time() - begun:.1f} s: frames done")
                generator.wait(60)
                time.sleep(2.0)       # the last messages of the stream
                view.stop()
                if view.error is not None:
                    raise RuntimeError(view.error)
                say(f"{time.time() - begun:.1f} s: beds closed")
        finally:
            for process in processes:
                if process.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        process.send_signal(signal.SIGCONT)
                        process.kill()
                process.wait(10)
                if process.stdout is not None:
                    process.stdout.close()
            if sampler is not None:
                sampler.stop()
            if view is not None and view._thread is not None and view._thread.is_alive():
                view.stop()
            broker.stop()
        events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
        generated = json.loads((folder / "generator.json").read_text())
    out = figures(beds, duration_s, use_stand_in, view, events, generated, cpu, counters0, counters1, elapsed,
                  stopped)
    out["cpu_windows"] = cpu_windows
    out["load_beds_shown_offline"] = sorted(bed for bed, changes in view.online.items() if not bed.startswith("probe-")
                                            and any(not online for t, online, _ in changes if t < done_at))
    return out


def figures(beds, duration_s, use_stand_in, view: WardView, events, generated, cpu, counters0, counters1, elapsed,
            stopped) -> dict:
    raised = {(e["bed_id"], e["alarm_id"]): e["published_at"] for e in events if e["kind"] == "raised"}
    ended = {(e["bed_id"], e["alarm_id"]): e["published_at"] for e in events if e["kind"] == "ended"}
    acked = {(e["bed_id"], e["alarm_id"]): e["published_at"] for e in events if e["kind"] == "acknowledged"}
    latencies = {f"{b}/{a}": view.first_seen[b, a] - t for (b, a), t in raised.items() if (b, a) in view.first_seen}
    station = [view.event_received[k] - t for k, t in raised.items() if k in view.event_received]
    ack = [view.ack_seen[k] - t for k, t in acked.items() if k in view.ack_seen]
    stuck = [f"{b}/{a}" for (b, a), t in ended.items() if view.last_seen.get((b, a), 0.0) > t + STUCK_AFTER_S]
    rates = {key: (counters1[key] - counters0[key]) / elapsed for key in
             ("messages/received", "messages/sent", "publish/messages/sent") if key in counters0 and key in counters1}
    # Mosquitto 2.0.11 leaves retained QoS 0 messages (the summaries) out of publish/messages/received: count
    # what the beds sent instead (every summary and event; the probes' summaries and the statuses are few).
    rates["publish/in (beds' own counts)"] = (generated["summaries_sent"] + generated["events_published"]) / elapsed
    offline = {bed: {"kind": kind, **view.offline_after(bed, at)} for bed, (kind, at) in stopped.items()}
    return {"beds": beds, "duration_s": duration_s, "station": "stand-in" if use_stand_in else "appliance ward",
            "bed_keepalive_s": BED_KEEPALIVE_S, "window_s": elapsed,
            "alarms_raised": len(raised),
            "alarms_lost": sorted(f"{b}/{a}" for b, a in set(raised) - set(view.first_seen)),
            "unexpected_alarms": sorted(f"{b}/{a}" for b, a in set(view.first_seen) - set(raised)
                                        if not b.startswith("probe-")),
            "duplicates_shown": len(view.duplicates), "bed_repeats": view.bed_repeats, "stuck_alarms": stuck,
            "acks": len(acked), "ack_latencies_s": ack, "latencies_s": latencies, "station_latencies_s": station,
            "stream": {"messages": view.messages, "bytes": view.bytes, "reconnects": view.reconnects,
                       "most_beds_shown": view.max_beds},
            "offline": offline, "cpu": cpu, "broker_per_s": rates, "generator": generated}


# The report.

def stats_ms(values) -> str:
    values = list(values)
    if not values:
        return "- | - | - | 0"
    return (f"{1000 * statistics.median(values):.0f} | {1000 * percentile(values, 0.95):.0f} | "
            f"{1000 * max(values):.0f} | {len(values)}")


def seconds(value) -> str:
    return "never" if value is None else f"{value:.2f}"


def offline_by_kind(result: dict) -> dict:
    """For each kind of stop: the probe beds' offline times (seconds), None where never shown in the run."""
    out = {}
    for bed in result["offline"].values():
        kind = out.setdefault(bed["kind"], {key: [] for key in ("offline_s", "status_offline_s",
                                                                "offline_after_last_message_s")})
        for key, values in kind.items():
            values.append(bed[key])
    return out


def spread_s(values) -> str:
    """median / max of the values shown, and how many were never shown."""
    shown = [v for v in values if v is not None]
    text = f"{statistics.median(shown):.2f} / {max(shown):.2f}" if shown else "-"
    return text + (f" ({len(values) - len(shown)} never)" if len(shown) < len(values) else "")


STOP_NAMES = {"frozen": "SIGSTOP: hung monitor, connection held", "killed": "SIGKILL: killed monitor, socket closed",
              "closed": "SIGTERM: clean close()"}


def report(result: dict, command: str) -> str:
    from appliance.ward.board import STALE_MARGIN_S

    rows = [["new alarm: notify() to the ward view's stream", stats_ms(result["latencies_s"].values())],
            ["acknowledgement: notify() to the ward view's stream", stats_ms(result["ack_latencies_s"])]]
    if result["station_latencies_s"]:
        rows.append(["new alarm: notify() to the station's receipt", stats_ms(result["station_latencies_s"])])
    rows.append(["any alarm change: notify() to the station's confirmation at the bed",
                 stats_ms(result["generator"]["confirm_latencies_s"])])
    latency_table = "\n".join(["| path | median ms | p95 ms | max ms | n |", "|---|---|---|---|---|"]
                              + [f"| {path} | {cells} |" for path, cells in rows])
    stream = result["stream"]
    alarm_table = table(["alarms raised", "lost (never shown)", "duplicated in one message", "stuck (> 3 s after end)",
                         "shown but never raised", "acknowledgements", "running beds shown offline",
                         "stream messages /s", "stream kB/s", "stream reconnects", "most beds shown"],
                        [[result["alarms_raised"], len(result["alarms_lost"]), result["duplicates_shown"],
                          len(result["stuck_alarms"]), len(result["unexpected_alarms"]), result["acks"],
                          len(result["load_beds_shown_offline"]),
                          f"{stream['messages'] / result['window_s']:.1f}",
                          f"{stream['bytes'] / result['window_s'] / 1000:.0f}", stream["reconnects"],
                          stream["most_beds_shown"]]])
    kinds = offline_by_kind(result)
    offline_table = table(["probe beds stopped by", "n", "shown offline after the stop s (median / max)",
                           "after the bed's last message s", "status \"offline\" after the stop s", "bed keep-alive s"],
                          [[STOP_NAMES[kind], len(v["offline_s"]), spread_s(v["offline_s"]),
                            spread_s(v["offline_after_last_message_s"]), spread_s(v["status_offline_s"]),
                            result["bed_keepalive_s"]] for kind, v in kinds.items()])
    cpu, rates, gen = result["cpu"], result["broker_per_s"], result["generator"]

    def rate(key):
        return f"{rates[key]:.1f}" if key in rates else "-"
    load_table = table(["broker CPU %", "station CPU %", "generator CPU %", "benchmark client CPU %",
                        "PUBLISH in /s", "PUBLISH out /s", "MQTT packets in /s", "MQTT packets out /s"],
                       [[f"{100 * cpu['broker']:.1f}", f"{100 * cpu['station']:.1f}", f"{100 * cpu['generator']:.1f}",
                         f"{100 * cpu['client']:.1f}", rate("publish/in (beds' own counts)"),
                         rate("publish/messages/sent"), rate("messages/received"), rate("messages/sent")]])
    generator_table = table(["frames", "frames > 100 ms late", "worst lateness ms", "summaries sent",
                             "summaries skipped", "events published (resends too)", "confirmed by the station",
                             "unconfirmed at the end"],
                            [[gen["frames"], gen["late_frames"], f"{1000 * gen['worst_lateness_s']:.0f}",
                              gen["summaries_sent"], gen["summaries_skipped"], gen["events_published"],
                              gen["events_confirmed"], gen["events_unconfirmed"]]])
    windows = result.get("cpu_windows", [])
    station_trend = (f"The station's CPU went from {100 * windows[0]['station']:.1f} % in the first window to "
                     f"{100 * max(w['station'] for w in windows):.1f} % at most, by window of the run:"
                     if len(windows) > 1 else "By window of the run:")
    windows_table = table(["window s", "broker CPU %", "station CPU %", "generator CPU %"],
                          [[f"{w['from_s']:.0f}-{w['to_s']:.0f}", f"{100 * w['broker']:.1f}",
                            f"{100 * w['station']:.1f}", f"{100 * w['generator']:.1f}"]
                           for w in result.get("cpu_windows", [])])
    latencies = list(result["latencies_s"].values())
    frozen = kinds.get("frozen", {}).get("offline_s", [])
    doc = __doc__.split("\n\n", 2)[2].strip()
    return f"""# Ward station under load

`{command}` on {machine()}; 2 shared vCPUs, nothing pinned, so timings are noisy: medians,
95th percentiles and counts. Station: {result['station']}. {result['beds']} beds and
{len(result['offline'])} probe beds for {result['duration_s']:.0f} s (measured window {result['window_s']:.0f} s).

{doc}

## Alarm latency

{latency_table}

A new alarm is on the ward view {ms(statistics.median(latencies) if latencies else None)} ms after the monitor
notifies it (median; p95 {ms(percentile(latencies, 0.95) if latencies else None)} ms, against the 2 s required);
{len(result['alarms_lost'])} of {result['alarms_raised']} alarms never showed.

## Alarms

{alarm_table}

## Offline

{offline_table}

A monitor that is killed or closed shows offline at once. A hung one (its connection still open) shows offline
when it has been silent for the station's `stale_after_s` (3 summary intervals + {STALE_MARGIN_S:g} s =
{3 + STALE_MARGIN_S:g} s), seen within the stream's 0.25 s poll: {spread_s(frozen)} s after the stop here (median /
max), against a keep-alive of {result['bed_keepalive_s']} s, the least a bed may set. The broker's last will comes
1.5 to 2.6 keep-alives after the stop (Mosquitto 2.0.11).

## Load

CPU as % of one core over the measured window. PUBLISH out and MQTT packets from Mosquitto's `$SYS`
counters; PUBLISH in from the beds' own counts (summaries and events sent, resends too), since Mosquitto
2.0.11 leaves retained QoS 0 messages out of its received count.

{load_table}

{station_trend}

{windows_table}

The load generator's own account of its frames:

{generator_table}
"""


def ms(value) -> str:
    return "-" if value is None else f"{1000 * value:.0f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="role")
    for role in ("generate", "bed", "stand-in"):
        p = sub.add_parser(role)
        p.add_argument("--port", type=int, required=True)
        if role == "generate":
            p.add_argument("--beds", type=int, default=BEDS)
            p.add_argument("--duration", type=float, default=DURATION_S)
            p.add_argument("--seed", type=int, default=1)
        if role == "bed":
            p.add_argument("--bed-id", required=True)
        if role == "stand-in":
            p.add_argument("--listen-port", type=int, required=True)
        else:
            p.add_argument("--folder", type=Path, required=True)
    parser.add_argument("--beds", type=int, default=BEDS)
    parser.add_argument("--duration", type=float, default=DURATION_S)
    parser.add_argument("--stand-in", action="store_true", help="the stdlib stand-in instead of `appliance ward`")
    args = parser.parse_args(argv)
    if args.role == "generate":
        generate(args.port, args.beds, args.duration, args.folder, args.seed)
    elif args.role == "bed":
        probe_bed(args.port, args.bed_id, args.folder)
    elif args.role == "stand-in":
        stand_in(args.port, args.listen_port)
    else:
        command = " ".join(["python benchmarks/ward_load.py", *(argv if argv is not None else sys.argv[1:])])
        result = run(args.beds, args.duration, use_stand_in=args.stand_in or None)
        (HERE / "ward_load.json").write_text(json.dumps(result, indent=1))
        text = report(result, command)
        (HERE / "ward_load.md").write_text(text)
        print(text)


if __name__ == "__main__":
    main()
