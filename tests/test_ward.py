"""The ward station against a real Mosquitto broker (tests/mqtt_broker.py), with beds as ward links, raw paho
clients, a separate process and a small monitor daemon."""

import json
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import paho.mqtt.client as mqtt
import pytest
from mqtt_broker import free_port, subscribed_station, wait_until
from ward_payloads import alarm, as_sent, summary

from appliance.alerts.ward_mqtt import mqtt_ward_link, release
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.service.config import config_from_mapping
from appliance.service.daemon import MonitorDaemon
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import square_load_scene
from appliance.store import Store
from appliance.store.outbox import Outbox
from appliance.ward.board import BedState
from appliance.ward.station import WardStation


class Publisher:
    """A raw paho client, to publish what no ward link would (resends out of order, garbage, other beds'
    summaries)."""

    def __init__(self, port):
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-publisher")
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def send(self, topic, payload, qos=1, retain=False):
        info = self.client.publish(topic, payload if isinstance(payload, (str, bytes)) else json.dumps(payload),
                                   qos=qos, retain=retain)
        info.wait_for_publish(5)

    def event(self, bed_id, event, seq=None):
        """``event`` on ``bed_id``'s topic as its ward link would send it, numbered ``seq`` (``as_sent``)."""
        self.send(f"appliance/{bed_id}/{event.type}", as_sent(event, bed_id, seq))

    def close(self):
        release(self.client)


@pytest.fixture
def publisher(broker):
    p = Publisher(broker.port)
    yield p
    p.close()


class Confirmations:
    """Every bed's confirm topic, as the beds hear it: each confirmation as (bed_id, payload, what ``look()``
    returned as it came, if a test set ``look``)."""

    def __init__(self, port):
        self.received, self.look = [], None
        subscribed = threading.Event()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-confirmations")
        self.client.on_subscribe = lambda *args: subscribed.set()
        self.client.on_message = self._take
        self.client.connect("127.0.0.1", port)
        self.client.subscribe("appliance/+/confirm", qos=1)
        self.client.loop_start()
        assert subscribed.wait(5), "no subscription to the confirmations"

    def _take(self, client, userdata, message):
        self.received.append((message.topic.split("/")[1], json.loads(message.payload),
                              None if self.look is None else self.look()))

    def seqs(self, bed_id):
        return [body["seq"] for bed_id_, body, _ in self.received if bed_id_ == bed_id]

    def close(self):
        release(self.client)


@pytest.fixture
def confirmations(broker):
    c = Confirmations(broker.port)
    yield c
    c.close()


def bed(station, bed_id):
    """The station's view of ``bed_id``, or None while it knows nothing of it."""
    return next((b for b in station.beds() if b["bed_id"] == bed_id), None)


def open_alarms(station, bed_id):
    return {a["alarm_id"]: a for a in (bed(station, bed_id) or {}).get("alarms", [])}


# What reaches the station.

def test_a_beds_summary_and_alarms_reach_the_station_in_order(station, beds):
    """Every alarm reaches the station, in order of priority; how fast is benchmarks/ward_load.py's (median
    137 ms against the 2 s required), not a test's, which a busy machine would fail."""
    bed7 = beds("bed7")
    bed7.summarise(summary("bed7", alarms=[(1, "medium")]))
    assert wait_until(lambda: (bed(station, "bed7") or {}).get("summary") is not None, 5)
    seen = bed(station, "bed7")
    assert seen["online"] and seen["status"] == "online"
    assert seen["summary"]["peak_mmhg"] == 41.5 and seen["summary"]["status"] == {"maps": 7, "faults": 0,
                                                                                          "source": "hardware"}
    assert isinstance(seen["summary"]["written_at"], float)                  # stamped when it was written
    assert [(a["alarm_id"], a["priority"]) for a in seen["alarms"]] == [(1, "medium")]

    for i in range(2, 22):  # each alarm after the last summary: the event alone makes it open
        bed7.notify(alarm(i, time_s=100.0 + i))
        assert wait_until(lambda i=i: any(e["alarm_id"] == i for e in bed(station, "bed7")["events"]), 30)
        [event] = [e for e in bed(station, "bed7")["events"] if e["alarm_id"] == i]
        assert isinstance(event["received_at"], float)          # stamped by the station when it came
    seen = bed(station, "bed7")
    assert [a["alarm_id"] for a in seen["alarms"]] == list(range(2, 22)) + [1]   # high first, then by id
    assert seen["highest_priority"] == "high"
    assert wait_until(lambda: bed7.confirmed == 20, 5)                        # and the bed heard each confirmed


def test_two_beds_are_kept_apart(station, beds):
    bed1, bed2 = beds("bed1"), beds("bed2")
    bed1.notify(alarm(1, priority="low"))
    bed2.notify(alarm(1, priority="high", key="pressure:heel-left"))
    bed2.notify(alarm(2, priority="medium"))
    assert wait_until(lambda: [len(b["events"]) for b in sorted(station.beds(), key=lambda b: b["bed_id"])]
                      == [1, 2], 5)
    one, two = bed(station, "bed1"), bed(station, "bed2")
    assert [(a["alarm_id"], a["priority"]) for a in one["alarms"]] == [(1, "low")]
    assert [(a["alarm_id"], a["priority"], a["key"]) for a in two["alarms"]] == [
        (1, "high", "pressure:heel-left"), (2, "medium", "pressure:sacrum")]


def test_a_repeated_seq_is_applied_once_and_confirmed_each_time(station, publisher, confirmations):
    for _ in range(4):     # resent while unconfirmed, again after the bed's restart, and redelivered by the broker
        publisher.event("bed7", alarm(3), seq=1)
    assert wait_until(lambda: confirmations.seqs("bed7") == [1, 1, 1, 1], 5)
    seen = bed(station, "bed7")
    assert seen["duplicates"] == 3 and [e["seq"] for e in seen["events"]] == [1]
    assert list(open_alarms(station, "bed7")) == [3]
    publisher.event("bed7", alarm(3, kind="acknowledged"), seq=2)
    assert wait_until(lambda: confirmations.seqs("bed7")[-1:] == [2], 5)
    assert [e["seq"] for e in bed(station, "bed7")["events"]] == [1, 2] and bed(station, "bed7")["duplicates"] == 3
    assert {(bed_id, body["station"]) for bed_id, body, _ in confirmations.received} == {("bed7", "test-station")}
    assert wait_until(lambda: station.confirmations_sent == 5, 5)


def test_a_confirmation_comes_only_once_the_station_shows_the_event(station, publisher, confirmations):
    confirmations.look = lambda: open_alarms(station, "bed7")
    for i in range(1, 21):
        publisher.event("bed7", alarm(i))
    assert wait_until(lambda: confirmations.seqs("bed7") == list(range(1, 21)), 5)
    assert all(body["seq"] in shown for _, body, shown in confirmations.received)     # alarm i is seq i
    assert all(isinstance(body["confirmed_at"], float) for _, body, _ in confirmations.received)


def test_an_older_event_never_undoes_a_newer_state_of_its_alarm(station, publisher, confirmations):
    publisher.event("bed7", alarm(1, priority="low"), seq=1)
    publisher.event("bed7", alarm(1, kind="escalated", priority="high"), seq=3)
    publisher.event("bed7", alarm(1, kind="escalated", priority="medium"), seq=2)   # resent, late: not back to it
    publisher.event("bed7", alarm(2, kind="ended"), seq=6)                           # alarm 2 ended...
    publisher.event("bed7", alarm(2), seq=5)                                         # ...before its raise came
    publisher.event("bed7", alarm(4), seq=7)                                         # positive control
    assert wait_until(lambda: confirmations.seqs("bed7") == [1, 3, 2, 6, 5, 7], 5)
    assert {i: a["priority"] for i, a in open_alarms(station, "bed7").items()} == {1: "high", 4: "high"}


def test_an_event_the_summary_already_holds_is_not_applied_over_it(station, publisher, confirmations):
    publisher.send("appliance/bed7/summary", summary("bed7", time_s=100.0, seq=10, alarms=[(2, "low")]), qos=0)
    assert wait_until(lambda: (bed(station, "bed7") or {}).get("summary") is not None, 5)
    publisher.event("bed7", alarm(7, time_s=500.0), seq=8)    # over by seq 10: a clock step made its time look later
    publisher.event("bed7", alarm(3, time_s=50.0), seq=11)    # after the summary though the clock was set back
    assert wait_until(lambda: confirmations.seqs("bed7") == [8, 11], 5)
    assert sorted(open_alarms(station, "bed7")) == [2, 3]
    assert [e["seq"] for e in bed(station, "bed7")["events"]] == [8, 11]                # both on the event list


def test_events_sent_while_the_station_was_away_are_confirmed_when_it_is_back(broker, publisher, confirmations):
    """The broker holds them for the station's persistent session; a ward link would resend them too."""
    with WardStation("127.0.0.1", broker.port, client_id="returning-station") as first:
        assert first.wait_subscribed(10)
        publisher.event("bed7", alarm(1))
        assert wait_until(lambda: confirmations.seqs("bed7") == [1], 5)
    for i in range(2, 6):
        publisher.event("bed7", alarm(i))
    with WardStation("127.0.0.1", broker.port, client_id="returning-station") as again:
        assert wait_until(lambda: confirmations.seqs("bed7") == [1, 2, 3, 4, 5], 5)
        assert sorted(open_alarms(again, "bed7")) == [2, 3, 4, 5]
        assert {body["station"] for _, body, _ in confirmations.received} == {"returning-station"}


# Offline.

BED_PROCESS = textwrap.dedent("""
    import json, sys, time
    import paho.mqtt.client as mqtt
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="bed-process")
    client.will_set("appliance/bed9/status", "offline", qos=1, retain=True)
    client.connect("127.0.0.1", int(sys.argv[1]), keepalive=int(sys.argv[2]))
    client.loop_start()
    client.publish("appliance/bed9/status", "online", qos=1, retain=True).wait_for_publish(5)
    print("online", flush=True)
    while True:   # a summary every 0.3 s, as a monitor's loop would send them
        summary = {"bed_id": "bed9", "time_s": time.time(), "seq": 0, "peak_mmhg": None, "regions": [], "alarms": []}
        client.publish("appliance/bed9/summary", json.dumps(summary), qos=0, retain=True)
        time.sleep(0.3)
""")


def bed_process(port, keepalive_s):
    process = subprocess.Popen([sys.executable, "-c", BED_PROCESS, str(port), str(keepalive_s)],
                               stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "online"
    return process


def end(process):
    process.kill()
    process.wait()
    process.stdout.close()


GENEROUS_S = 30.0
"""How long a test waits for a bed to show offline: a deadline that only a broken link misses, never a bound
on how fast (the stations here that never call a bed stale see offline only from a status or a last will)."""


def offline_after(stations, bed_id, timeout_s):
    """Seconds from now until each station shows ``bed_id`` offline."""
    start, delays = time.monotonic(), {}
    while len(delays) < len(stations) and time.monotonic() - start < timeout_s:
        for name, station in stations.items():
            if name not in delays and not bed(station, bed_id)["online"]:
                delays[name] = time.monotonic() - start
        time.sleep(0.02)
    assert len(delays) == len(stations), f"{bed_id} still online after {timeout_s} s: {delays}"
    return delays


@pytest.fixture
def patient_station(broker):
    """A station that never calls a bed stale, so offline comes only from the status and the last will."""
    with subscribed_station(broker.port, client_id="patient-station", stale_after_s=3600) as s:
        yield s


def test_a_bed_gone_silent_shows_offline_by_its_silence_and_by_the_broker_s_last_will(broker, patient_station):
    """A frozen bed keeps its connection open: one station sees it stale (no summary for three intervals), one
    that never calls a bed stale sees the broker's last will once the keep-alive runs out. How soon is printed
    (timings belong to benchmarks; the station's rule itself is tested on its own clock)."""
    keepalive_s = 2
    with WardStation("127.0.0.1", broker.port, client_id="watchful-station", summary_interval_s=0.3) as watchful:
        assert watchful.wait_subscribed(10)
        process = bed_process(broker.port, keepalive_s)
        try:
            assert wait_until(lambda: all((bed(s, "bed9") or {}).get("summary") for s in (watchful, patient_station)),
                              5)
            process.send_signal(signal.SIGSTOP)   # frozen: the connection stays open but nothing more comes
            delays = offline_after({"stale": watchful, "will": patient_station}, "bed9", GENEROUS_S)
        finally:
            end(process)
    print(f"offline after a silent death (keepalive {keepalive_s} s): {delays['stale']:.2f} s by its silence, "
          f"{delays['will']:.2f} s by the broker's last will")
    assert bed(patient_station, "bed9")["status"] == "offline"           # said by the will, not by silence
    # Mosquitto 2.0.11 gives the will later than MQTT's 1.5 keep-alives (measured 2.6 times): hence the silence.


def test_a_killed_bed_process_shows_offline_by_its_last_will(broker, patient_station):
    process = bed_process(broker.port, 30)
    assert wait_until(lambda: (bed(patient_station, "bed9") or {}).get("online"), 5)
    end(process)                               # the kernel closes the socket, with no DISCONNECT
    print(f"offline after a kill: {offline_after({'will': patient_station}, 'bed9', GENEROUS_S)['will']:.2f} s")


def test_a_clean_stop_shows_offline_by_its_own_status(patient_station, beds):
    bed7 = beds("bed7")
    assert wait_until(lambda: (bed(patient_station, "bed7") or {}).get("online"), 5)
    start = time.monotonic()
    bed7.close()
    offline_after({"will": patient_station}, "bed7", GENEROUS_S)
    print(f"offline after a clean stop: {time.monotonic() - start:.2f} s")


def test_a_bed_that_stops_summarising_goes_stale(broker, beds):
    with WardStation("127.0.0.1", broker.port, client_id="hasty-station", stale_after_s=0.5) as station:
        assert station.wait_subscribed(10)
        bed7 = beds("bed7")
        bed7.summarise(summary("bed7"))
        assert wait_until(lambda: (bed(station, "bed7") or {}).get("summary") is not None, 5)
        assert bed(station, "bed7")["status"] == "online"      # connected, but its loop has stopped
        delay = offline_after({"stale": station}, "bed7", GENEROUS_S)["stale"]
        assert bed(station, "bed7")["status"] == "online" and delay > 0.2     # stale by silence, not at once
        bed7.summarise(summary("bed7", time_s=101.0))
        assert wait_until(lambda: bed(station, "bed7")["online"])


# Bad payloads and the ward's order.

def test_garbage_is_counted_never_confirmed_and_the_station_keeps_working(station, publisher, beds, confirmations):
    event = as_sent(alarm(), "bed3", seq=2)
    garbage = [("appliance/bed3/summary", b"\xff\xfe"), ("appliance/bed3/summary", "not json"),
               ("appliance/bed3/summary", [1, 2]), ("appliance/bed3/summary", {**summary("bed3"), "time_s": "soon"}),
               ("appliance/bed3/summary", summary("bed4")),
               ("appliance/bed3/summary", {**summary("bed3"), "alarms": [{"alarm_id": "one"}]}),
               ("appliance/bed3/summary", {**summary("bed3"), "seq": -1}),
               ("appliance/bed3/summary", {**summary("bed3"), "seq": False}),
               ("appliance/bed3/alarm", {"time_s": 1.0, "kind": "raised", "bed_id": "bed3", "seq": 2}),
               ("appliance/bed3/alarm", {**event, "type": "turn"}),
               ("appliance/bed3/alarm", {**event, "priority": "urgent"}),
               ("appliance/bed3/alarm", {**event, "bed_id": "bed4"}),
               ("appliance/bed3/alarm", {k: v for k, v in event.items() if k != "seq"}),
               ("appliance/bed3/alarm", {**event, "seq": 0}), ("appliance/bed3/alarm", {**event, "seq": True}),
               ("appliance/bed3/alarm", {**event, "seq": 2.0}), ("appliance/bed3/alarm", {**event, "seq": "2"}),
               ("appliance/bed3/turn", "null"), ("appliance/bed3/status", "maybe")]
    for topic, payload in garbage:
        publisher.send(topic, payload)
    assert wait_until(lambda: station.bad_payloads == len(garbage), 5)
    assert bed(station, "bed3") is None
    bed3 = beds("bed3")
    bed3.notify(alarm(1))
    bed3.summarise(summary("bed3", time_s=5.0))
    assert wait_until(lambda: (bed(station, "bed3") or {}).get("summary") is not None
                      and bed(station, "bed3")["events"], 5)
    assert wait_until(lambda: confirmations.received, 5)
    assert set(confirmations.seqs("bed3")) == {1}             # a confirmation of garbage would have come first
    assert station.bad_payloads == len(garbage)


def test_high_alarm_beds_come_first_then_medium_low_offline_and_the_rest_by_id(broker, station, publisher):
    ward = {"a-low": [(1, "low")], "b-high": [(1, "medium"), (2, "high")], "c-quiet": [], "e-medium": [(4, "medium")],
            "f-quiet": [], "g-high": [(1, "high")]}
    for bed_id, alarms in ward.items():
        publisher.send(f"appliance/{bed_id}/status", "online", retain=True)
        publisher.send(f"appliance/{bed_id}/summary", summary(bed_id, alarms=alarms), qos=0, retain=True)
    publisher.send("appliance/d-offline/status", "offline", retain=True)
    assert wait_until(lambda: len(station.beds()) == 7 and all(b["summary"] for b in station.beds()
                                                               if b["bed_id"] != "d-offline"), 5)
    assert [b["bed_id"] for b in station.beds()] == ["b-high", "g-high", "e-medium", "a-low", "d-offline",
                                                     "c-quiet", "f-quiet"]
    with WardStation("127.0.0.1", broker.port, client_id="late-station") as late:   # from the retained messages
        assert wait_until(lambda: len(late.beds()) == 7 and all(b["summary"] for b in late.beds()
                                                                if b["bed_id"] != "d-offline"), 5)
        assert [b["bed_id"] for b in late.beds()] == [b["bed_id"] for b in station.beds()]


def test_events_after_the_last_summary_are_applied_over_it_in_seq_order_and_older_ones_not():
    state = BedState("bed7")

    def take(event, seq):
        state.take_event({**as_sent(event, "bed7", seq), "received_at": 0.0})
    take(alarm(1), seq=1)
    assert list(state.open_alarms) == [1]
    state.take_summary(summary("bed7", seq=2, alarms=[(2, "low")]), now=0.0)
    assert list(state.open_alarms) == [2]                                           # alarm 1 ended by seq 2
    take(alarm(3), seq=3)
    take(alarm(2, kind="escalated", priority="medium"), seq=4)
    take(alarm(4), seq=2)                                                           # late, and the summary knew
    assert {i: a["priority"] for i, a in state.open_alarms.items()} == {2: "medium", 3: "high"}
    take(alarm(3, kind="ended"), seq=6)
    take(alarm(3, kind="acknowledged"), seq=5)                                      # after its end: too late
    assert list(state.open_alarms) == [2]
    state.take_summary(summary("bed7", seq=4, alarms=[(2, "medium"), (3, "high")]), now=0.0)
    assert list(state.open_alarms) == [2]                              # seqs 5 and 6 replayed in order: the end last


# The daemon's summaries.

GRID = get_layout("grid-4x4")


def ward_daemon(small_mat_calibration, tmp_path, notifiers):
    model, calibration = small_mat_calibration
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": 600.0, "bed_id": "ward-bed"},
                                  "alerts": {"alarm_dose": 0.05}})
    source = VirtualBedSource(GRID, square_load_scene(100, 100, 30, 70, 40, 6.0), default_protocol(GRID),
                              frame_interval_s=600.0)
    daemon = MonitorDaemon(config, source, model, calibration, Store.open(tmp_path / f"{len(notifiers)}.db"),
                           notifiers=notifiers, say=lambda text: None)
    daemon.start()
    return daemon


def test_the_daemon_publishes_summaries_the_station_sees(small_mat_calibration, tmp_path, station, beds):
    notifier = beds("ward-bed", summary_interval_s=0.05)
    daemon = ward_daemon(small_mat_calibration, tmp_path, [notifier])
    try:
        while not any(a["key"].startswith("pressure:") for a in (bed(station, "ward-bed") or {}).get("alarms", [])):
            daemon.step()
            time.sleep(0.06)
            assert daemon.maps < 100, "no pressure alarm reached the station"
        assert wait_until(lambda: bed(station, "ward-bed")["summary"]["status"]["maps"] == daemon.maps)
        assert wait_until(lambda: notifier.status()["unconfirmed"] == 0, 5)     # every event confirmed to the bed
    finally:
        daemon.close()
    seen = bed(station, "ward-bed")
    body = seen["summary"]
    assert set(body) == {"bed_id", "time_s", "seq", "written_at", "peak_mmhg", "regions", "posture", "patient",
                         "turn", "alarms", "status"}
    assert body["time_s"] == daemon.pipeline.last_time_s and body["peak_mmhg"] > 0
    assert body["regions"] and set(body["regions"][0]) == {"zone", "words", "peak_mmhg", "dose"}
    assert {a["alarm_id"] for a in body["alarms"]} == {a.alarm_id for a in daemon.pipeline.engine.alarms()}
    assert seen["status"] == "offline" and not seen["online"]                     # the daemon closed its notifier


def test_an_unreachable_broker_never_holds_up_the_daemons_frames(small_mat_calibration, tmp_path, monkeypatch):
    """The network is only ever waited on by the link's own thread: the frame loop never connects, sends or
    waits for a socket, so a broker that does not answer cannot slow it (how long a frame takes is in the
    benchmarks, not here)."""
    network_calls, stepping = [], threading.Event()
    for name in ("connect", "connect_ex", "send", "sendall", "recv"):
        original = getattr(socket.socket, name)

        def watched(self, *args, _original=original, _name=name):
            network_calls.append((_name, threading.get_ident(), stepping.is_set()))
            return _original(self, *args)
        monkeypatch.setattr(socket.socket, name, watched)
    unreachable = mqtt_ward_link("10.255.255.1", free_port(), "ward-bed", Outbox(tmp_path / "unreachable-outbox.db"),
                           client_id="unreachable", summary_interval_s=0.001)
    daemon = ward_daemon(small_mat_calibration, tmp_path, [unreachable])
    loop = threading.get_ident()
    try:
        for _ in range(10):
            stepping.set()
            daemon.step()
            stepping.clear()
            time.sleep(0.01)
        assert wait_until(lambda: any(name == "connect" and thread != loop for name, thread, _ in network_calls), 10)
        assert [call for call in network_calls if call[1] == loop and call[2]] == []   # none from a frame
        assert daemon.maps == 10 and any(a.key.startswith("pressure:") for a in daemon.pipeline.engine.alarms())
        assert unreachable.summaries_sent == 0 and unreachable.summaries_skipped > 0
        assert unreachable.status()["unconfirmed"] > 0          # the alarms wait in the outbox for the link
    finally:
        daemon.close()
