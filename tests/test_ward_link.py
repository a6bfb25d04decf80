"""The bed's ward link and its outbox against a real Mosquitto (tests/mqtt_broker.py): numbered events resent
until confirmed end to end, technical alarms when the ward is not hearing the bed, and an outbox that keeps
its numbers across restarts and disk failures."""

import json
import queue
import socket
import sqlite3
import threading
from collections import Counter
import time

import paho.mqtt.client as mqtt
import pytest
from mqtt_broker import wait_until

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.events import Event, as_event
from appliance.alerts.turns import TurnEvent
from appliance.alerts.ward_mqtt import mqtt_ward_link, release
from appliance.alerts.wardlink import FAILED_FAST_S, FAILED_RETRY_S, MAX_RESEND_S, WardLink, failed_retry_wait
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.errors import StoreCorrupt
from appliance.service.config import config_from_mapping
from appliance.service.daemon import MonitorDaemon
from appliance.service.live import LiveChannel, read_live
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import square_load_scene
from appliance.store import Store
from appliance.store.outbox import SEQ_BLOCK, Outbox

EVENT_FIELDS = {"time_s", "type", "kind", "priority", "category", "key", "site", "posture", "x_mm", "y_mm", "alarm_id",
                "message", "user", "channel", "patient"}


def alarm(alarm_id=1, kind="raised", priority="high", time_s=None):
    return as_event(AlarmEvent(time_s=10.0 * alarm_id if time_s is None else time_s, kind=kind, alarm_id=alarm_id,
                               key="pressure:sacrum", category="clinical", priority=priority,
                               message="Sacrum dose over limit"))


class Peer:
    """A paho client that records what it receives on ``topic`` and can confirm a bed's events as a ward
    station does (``confirming``)."""

    def __init__(self, port, topic, client_id="test-peer", confirming=False):
        self.messages: queue.Queue = queue.Queue()
        self.confirming = confirming
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self.client.on_message = self._on_message
        subscribed = threading.Event()
        self.client.on_subscribe = lambda *a: subscribed.set()
        self.client.on_connect = lambda c, *a: c.subscribe(topic, qos=1)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        assert subscribed.wait(5)

    def _on_message(self, client, userdata, message):
        self.messages.put((message.topic, message.qos, message.retain, message.payload.decode()))
        bed_topic, _, kind = message.topic.rpartition("/")
        if self.confirming and kind in ("alarm", "turn", "episode"):
            seq = json.loads(message.payload)["seq"]
            client.publish(f"{bed_topic}/confirm", json.dumps({"seq": seq, "station": "test-station",
                                                               "confirmed_at": time.time()}), qos=1)

    def next(self, topic, timeout_s=10.0, payload=None):
        """The next message on ``topic`` (with ``payload``, if given), skipping others."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = self.messages.get(timeout=max(0.01, deadline - time.monotonic()))
            if got[0] == topic and payload in (None, got[3]):
                return got

    def close(self):
        release(self.client)


@pytest.fixture
def peer(broker):
    made = []

    def make(topic="appliance/#", **options):
        made.append(Peer(broker.port, topic, **options))
        return made[-1]
    yield make
    for p in made:
        p.close()


def link(broker, tmp_path, **options):
    options = {"resend_after_s": 0.2, "summary_interval_s": 0.1, **options}
    return mqtt_ward_link("127.0.0.1", broker.port, "bed7", Outbox(tmp_path / "outbox.db"), client_id="bed7-link",
                    **options)


# The outbox on its own.

def test_numbers_grow_by_one_survive_a_restart_and_an_event_handed_in_again_keeps_its_number(tmp_path):
    outbox = Outbox(tmp_path / "outbox.db")
    first = [outbox.add(alarm(i).to_dict(), 100.0) for i in (1, 2, 3)]
    assert first[1:] == [first[0] + 1, first[0] + 2]
    assert outbox.add(alarm(2).to_dict(), 101.0) == first[1]          # the daemon's re-notify after a crash
    assert outbox.confirm(first[0], "station-a", 102.0) and not outbox.confirm(first[0], "station-a", 103.0)
    outbox.close()
    again = Outbox(tmp_path / "outbox.db")
    assert [e.seq for e in again.pending()] == first[1:]              # confirmed is done, the rest still waits
    assert again.add(alarm(3).to_dict(), 104.0) == first[2]
    assert again.add(alarm(4).to_dict(), 104.0) > first[2]            # never a number given before
    assert again.alarm_entry(1).confirmed_by == "station-a"
    again.close()


def test_a_crash_during_a_disk_failure_never_reuses_a_number(tmp_path):
    """Numbers handed out from memory while the disk refused them are past the reserved block's start, and a
    restart continues after the whole block, so the station never takes a new event for an old one."""
    outbox = Outbox(tmp_path / "outbox.db")
    kept = outbox.add(alarm(1).to_dict(), 1.0)
    real = outbox._db
    outbox._db = FailingWrites(real)
    unwritten = [outbox.add(alarm(i).to_dict(), 2.0) for i in (2, 3, 4)]
    assert outbox.unwritten == 3 and "disk is full" in outbox.write_failure
    assert [e.seq for e in outbox.pending()] == [kept, *unwritten]   # sent from memory meanwhile
    real.close()                                                       # the crash: memory is gone
    after = Outbox(tmp_path / "outbox.db")
    assert after.add(alarm(5).to_dict(), 3.0) > max(unwritten)
    assert after.add(alarm(5).to_dict(), 3.0) >= kept + SEQ_BLOCK
    after.close()


def test_writes_refused_by_the_disk_are_written_when_it_takes_them_again(tmp_path):
    outbox = Outbox(tmp_path / "outbox.db")
    real = outbox._db
    outbox._db = FailingWrites(real)
    seq = outbox.add(alarm(1).to_dict(), 1.0)
    assert outbox.unwritten == 1
    outbox._db = real
    outbox.retry_writes()
    assert outbox.unwritten == 0 and outbox.write_failure is None
    outbox.close()
    assert [e.seq for e in Outbox(tmp_path / "outbox.db").pending()] == [seq]


def test_a_damaged_outbox_is_refused_with_its_name(tmp_path):
    (tmp_path / "outbox.db").write_bytes(b"this is not a database, just bytes that look like one" * 100)
    with pytest.raises(StoreCorrupt, match="outbox.db is damaged"):
        Outbox(tmp_path / "outbox.db")


class FailingWrites:
    """A connection whose writes fail as a full disk's do; reads go through."""

    def __init__(self, db):
        self.db = db
        self.in_transaction = False

    def execute(self, sql, *args):
        if sql.split()[0].upper() in ("INSERT", "UPDATE", "DELETE", "BEGIN"):
            raise sqlite3.OperationalError("database or disk is full")
        return self.db.execute(sql, *args)


# The link with a broker.

def test_events_carry_bed_and_number_and_are_resent_until_confirmed(broker, peer, tmp_path):
    watcher = peer("appliance/bed7/alarm")
    with link(broker, tmp_path) as bed:
        bed.notify(alarm(1))
        bodies = [json.loads(watcher.next("appliance/bed7/alarm")[3]) for _ in range(2)]   # sent, and again
        assert bodies[0] == bodies[1] and set(bodies[0]) == EVENT_FIELDS | {"bed_id", "seq"}
        assert bodies[0]["bed_id"] == "bed7" and Event(**{k: bodies[0][k] for k in EVENT_FIELDS}) == alarm(1)
        assert bed.delivery(1) == "broker"                     # taken by the broker, not yet confirmed
        peer(client_id="station", confirming=True)              # a station comes and confirms the next resend
        assert wait_until(lambda: bed.delivery(1) == "ward station")
        assert bed.outbox.pending() == [] and bed.confirmed == 1
        published = bed.published
        bed.notify(as_event(TurnEvent(time_s=5.0, kind="repositioned", posture="left-30", previous="supine",
                                      how="posture")))
        assert wait_until(lambda: bed.confirmed == 2)
        assert bed.published == published + 1                  # confirmed at the first try: nothing more sent


def test_a_confirmation_for_another_number_or_a_garbled_one_changes_nothing(broker, peer, tmp_path):
    with link(broker, tmp_path, resend_after_s=30.0) as bed:
        sender = peer("appliance/bed7/alarm")
        bed.notify(alarm(1))
        seq = bed.outbox.last_seq
        sender.next("appliance/bed7/alarm")
        for body in (b"not json", json.dumps({"seq": seq + 100, "station": "x"}).encode(),
                     json.dumps({"seq": True, "station": "x"}).encode(), json.dumps({"seq": seq}).encode()):
            sender.client.publish("appliance/bed7/confirm", body, qos=1).wait_for_publish(5)
        sender.client.publish("appliance/bed7/confirm", json.dumps({"seq": seq, "station": "ward-a"}),
                              qos=1).wait_for_publish(5)               # the positive control, sent last
        assert wait_until(lambda: bed.confirmed == 1)
        assert bed.outbox.entry(seq).confirmed_by == "ward-a"


def test_status_is_retained_online_and_last_will_is_offline(broker, peer, tmp_path):
    watcher = peer()
    bed = link(broker, tmp_path)
    try:
        assert watcher.next("appliance/bed7/status")[3] == "online"
        late = peer("appliance/bed7/status", client_id="late")    # a retained message reaches late subscribers
        assert late.next("appliance/bed7/status")[2:] == (True, "online")
        bed.transport.client.socket().shutdown(socket.SHUT_RDWR)          # a crash or a pulled cable: no DISCONNECT
        assert watcher.next("appliance/bed7/status")[3] == "offline"
        assert watcher.next("appliance/bed7/status")[3] == "online"  # and it reconnects
    finally:
        bed.close()
    assert watcher.next("appliance/bed7/status", payload="offline")


def test_summaries_carry_the_highest_number_handed_out(broker, peer, tmp_path):
    watcher = peer("appliance/bed7/summary")
    with link(broker, tmp_path) as bed:
        bed.notify(alarm(1))
        bed.notify(alarm(2))
        bed.summarise({"bed_id": "bed7", "time_s": 1.0, "alarms": []})
        body = json.loads(watcher.next("appliance/bed7/summary")[3])
        assert body["seq"] == bed.outbox.last_seq == bed.outbox.pending()[-1].seq


def test_a_broker_restart_that_loses_what_it_acknowledged_loses_no_alarm(broker, peer, tmp_path):
    """Mosquitto acknowledges from memory: events it took while the station was away die with it. The bed
    resends what no station confirmed, so the station, back after the broker, still gets every one."""
    with link(broker, tmp_path, resend_after_s=0.5) as bed:
        for i in (1, 2, 3):
            bed.notify(alarm(i))
        assert wait_until(lambda: all(bed.delivery(i) == "broker" for i in (1, 2, 3)))
        broker.stop()
        assert wait_until(lambda: not bed.status()["connected"])
        bed.notify(alarm(4))                                     # raised during the outage
        broker.start()
        station = peer("appliance/+/alarm", client_id="station", confirming=True)
        seen = set()
        while seen != {1, 2, 3, 4}:
            seen.add(json.loads(station.next("appliance/bed7/alarm", 20)[3])["alarm_id"])
        assert wait_until(lambda: bed.outbox.pending() == [], 20)
        assert [bed.delivery(i) for i in (1, 2, 3, 4)] == ["ward station"] * 4


def test_the_link_down_and_unconfirmed_changes_are_technical_alarms_that_clear(broker, peer, tmp_path):
    with link(broker, tmp_path, confirm_timeout_s=0.5) as bed:
        assert bed.conditions() == {}
        bed.notify(alarm(1))
        assert wait_until(lambda: "technical:ward-confirm" in bed.conditions())
        assert "1 alarm change(s) not confirmed by the ward station" in bed.conditions()["technical:ward-confirm"]
        broker.stop()
        assert wait_until(lambda: "technical:ward-link" in bed.conditions())
        assert "technical:ward-confirm" not in bed.conditions()          # the cause is named, not both
        assert bed.status()["connected"] is False and bed.status()["unconfirmed"] == 1
        broker.start()
        peer("appliance/+/alarm", client_id="station", confirming=True)
        assert wait_until(lambda: bed.conditions() == {}, 20)


def test_without_confirmation_the_brokers_acknowledgement_is_delivery(broker, tmp_path):
    with link(broker, tmp_path, confirm=False) as bed:
        bed.notify(alarm(1))
        assert wait_until(lambda: bed.outbox.pending() == [])
        assert bed.delivery(1) == "broker" and bed.outbox.alarm_entry(1).confirmed_by == "broker"


def test_close_does_not_wait_for_confirmations_and_the_next_start_resends(broker, peer, tmp_path):
    bed = link(broker, tmp_path)
    assert wait_until(lambda: bed.status()["connected"])
    bed.notify(alarm(1))
    assert wait_until(lambda: bed.delivery(1) == "broker")
    bed.close(timeout_s=30.0)                                   # nothing unsent: it returns at once
    station = peer("appliance/+/alarm", client_id="station", confirming=True)
    with link(broker, tmp_path) as again:
        assert json.loads(station.next("appliance/bed7/alarm")[3])["alarm_id"] == 1
        assert wait_until(lambda: again.outbox.pending() == [])


# The link in the monitor.

def test_the_monitor_raises_a_technical_alarm_while_the_ward_is_not_hearing_it_and_shows_each_alarms_delivery(
        small_mat_calibration, broker, peer, tmp_path):
    model, calibration = small_mat_calibration
    grid = get_layout("grid-4x4")
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": 600.0, "bed_id": "bed7"},
                                  "alerts": {"alarm_dose": 0.05}})
    source = VirtualBedSource(grid, square_load_scene(100, 100, 30, 70, 40, 6.0), default_protocol(grid),
                              frame_interval_s=600.0)
    live = LiveChannel(tmp_path / "live.json")
    daemon = MonitorDaemon(config, source, model, calibration, Store.open(tmp_path / "store.db"),
                           notifiers=[link(broker, tmp_path, confirm_timeout_s=0.5)], live=live,
                           say=lambda text: None)
    daemon.start()

    def alarms_now():
        before = (read_live(tmp_path / "live.json") or {}).get("sequence")
        daemon.step()
        assert wait_until(lambda: (read_live(tmp_path / "live.json") or {}).get("sequence") != before)
        return {a["key"]: a for a in read_live(tmp_path / "live.json")["alarms"]}
    try:
        broker.stop()
        alarms = alarms_now()
        while not any(key.startswith("pressure:") for key in alarms) or "technical:ward-link" not in alarms:
            assert daemon.maps < 100, "no pressure alarm, or no technical alarm for the lost link"
            time.sleep(0.1)
            alarms = alarms_now()
        assert alarms["technical:ward-link"]["message"].endswith("alarms are shown only at this bed")
        assert {a["delivery"] for a in alarms.values()} == {"bed"}
        assert read_live(tmp_path / "live.json")["ward_link"]["connected"] is False
        broker.start()
        peer("appliance/+/+", client_id="station", confirming=True)
        alarms = alarms_now()
        while "technical:ward-link" in alarms or {a["delivery"] for a in alarms.values()} != {"ward station"}:
            assert daemon.maps < 300, f"the link did not recover: {alarms}"
            time.sleep(0.1)
            alarms = alarms_now()
    finally:
        daemon.close()
    ended = [e for e in Store.open(tmp_path / "store.db").events_since(0.0) if e["key"] == "technical:ward-link"]
    assert ended[0]["kind"] == "raised" and ended[-1]["kind"] == "ended"


class RefusingTransport:
    """A transport whose far end refuses the first ``refusals`` sends of each event (a leader being elected), then
    holds each event and has a station confirm it."""

    peer = "the hospital engine"

    def __init__(self, refusals):
        self.refusals, self.sends = refusals, Counter()
        self.sent_at: list[float] = []                  # monotonic
        self.link = None

    def start(self, link):
        self.link = link
        link.transport_ready()

    def send_event(self, seq, event):
        self.sends[seq] += 1
        self.sent_at.append(time.monotonic())
        refused = self.sends[seq] <= self.refusals
        threading.Timer(0.01, self._answer, (seq, refused)).start()
        return True

    def _answer(self, seq, refused):
        if refused:
            self.link.transport_failed(seq)
        else:
            self.link.transport_held(seq)
            self.link.transport_confirmed(seq, "station1")

    send_summary = send_answer = lambda self, payload: True

    def connected(self):
        return True

    def close(self, timeout_s):
        pass


def test_a_send_that_came_to_nothing_is_tried_again_soon_not_after_the_doubled_resend_wait(tmp_path):
    """Nothing holds a refused event, so it does not wait out resend_after_s (here a minute), let alone twice that:
    after three refusals (tried again after 1, 2 and 4 s) it is confirmed within the time the test waits, far less
    than a minute."""
    transport = RefusingTransport(refusals=3)
    with WardLink(transport, "bed7", Outbox(tmp_path / "outbox.db"), resend_after_s=60.0) as bed:
        bed.notify(alarm(1))
        assert wait_until(lambda: bed.confirmed == 1, 40)
        assert transport.sends[1] == 4 and bed.published == 4


def test_failed_sends_are_retried_every_second_through_an_election_then_less_and_less_often():
    """A leader's election takes seconds: retried every second for the first minute; an engine without a quorum
    for longer is asked half as often after each failure, up to the resend ceiling."""
    assert [failed_retry_wait(t, 1.0) for t in (0.0, 10.0, FAILED_FAST_S - 0.1)] == [FAILED_RETRY_S] * 3
    waits, wait = [], FAILED_RETRY_S
    for failing_for in range(int(FAILED_FAST_S), int(FAILED_FAST_S) + 600, 30):
        wait = failed_retry_wait(failing_for, wait)
        waits.append(wait)
    assert waits[:6] == [2.0, 4.0, 8.0, 16.0, 32.0, MAX_RESEND_S] and set(waits[6:]) == {MAX_RESEND_S}


def test_the_link_tries_a_failing_send_again_at_the_policys_waits(tmp_path, monkeypatch):
    """Refused for ever, with the fast phase cut to 2.5 s: three tries a second apart, then gaps of at least 2 and
    4 s (lower bounds, which a busy machine only lengthens)."""
    monkeypatch.setattr("appliance.alerts.wardlink.FAILED_FAST_S", 2.5)
    transport = RefusingTransport(refusals=10 ** 6)
    with WardLink(transport, "bed7", Outbox(tmp_path / "outbox.db"), resend_after_s=60.0) as bed:
        bed.notify(alarm(1))
        assert wait_until(lambda: transport.sends[1] == 6, 40)
    gaps = [later - earlier for earlier, later in zip(transport.sent_at, transport.sent_at[1:], strict=False)]
    assert min(gaps[:2]) >= 1.0 and gaps[3] >= 2.0 and gaps[4] >= 4.0


def test_an_idle_link_sleeps_until_its_next_resend_instead_of_polling_its_outbox(tmp_path):
    """A bed's link is idle nearly all the time, and a hospital has thousands: with one event held and its resend a
    minute away the sender looks at its outbox about once a second (a busy machine only makes it fewer), not five
    times a second; a new event still goes at once."""
    transport = RefusingTransport(refusals=0)
    transport._answer = lambda seq, refused: transport.link.transport_held(seq)    # held, never confirmed
    outbox = Outbox(tmp_path / "outbox.db")
    looks = Counter()
    pending = outbox.pending
    outbox.pending = lambda: (looks.update(["pending"]), pending())[1]
    with WardLink(transport, "bed7", outbox, resend_after_s=60.0) as bed:
        bed.notify(alarm(1))
        assert wait_until(lambda: transport.sends[1] == 1 and bed.delivery(1) == "broker", 10)
        before = looks["pending"]
        time.sleep(4.0)
        assert looks["pending"] - before <= 5
        bed.notify(alarm(2))
        assert wait_until(lambda: transport.sends[2] == 1, 0.9)
        assert transport.sends[1] == 1                  # its minute is not up
