"""Notifiers against a real Mosquitto broker (tests/mqtt_broker.py), a local HTTP server and emulated GPIO lines."""

import json
import queue
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import paho.mqtt.client as mqtt
import pytest
from mqtt_broker import wait_until

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.events import Event, as_event
from appliance.alerts.notifiers import (
    GpioNotifier,
    MqttNotifier,
    Notifier,
    WebhookNotifier,
)
from appliance.alerts.turns import TurnEvent
from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, GPIOBank
from appliance.drivers.emulated.clock import SimulatedClock

EVENT_FIELDS = {"time_s", "type", "kind", "priority", "category", "key", "site", "posture", "x_mm", "y_mm", "alarm_id",
                "message", "user", "channel", "patient"}


def alarm(alarm_id=1, kind="raised", priority="high"):
    return as_event(AlarmEvent(time_s=10.0 * alarm_id, kind=kind, alarm_id=alarm_id, key="pressure:sacrum",
                               category="clinical", priority=priority, message="Sacrum dose over limit"))


class Subscriber:
    """A paho client that records (topic, qos, retain, payload) of everything it receives."""

    def __init__(self, port, topic):
        self.messages: queue.Queue = queue.Queue()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-subscriber")
        self.client.on_message = lambda c, u, m: self.messages.put((m.topic, m.qos, m.retain, m.payload.decode()))
        subscribed = threading.Event()
        self.client.on_subscribe = lambda *a: subscribed.set()
        self.client.on_connect = lambda c, *a: c.subscribe(topic, qos=1)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        assert subscribed.wait(5)

    def next(self, topic, timeout_s=10.0, payload=None):
        """The next message on ``topic`` (with ``payload``, if given), skipping others."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = self.messages.get(timeout=max(0.01, deadline - time.monotonic()))
            if got[0] == topic and payload in (None, got[3]):
                return got

    def close(self):
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def subscriber(broker):
    s = Subscriber(broker.port, "appliance/#")
    yield s
    s.close()


def mqtt_notifier(broker, tmp_path, **options):
    options = {"backoff_s": 0.1, "max_backoff_s": 0.5, "dead_letter_path": tmp_path / "dead.jsonl", **options}
    return MqttNotifier("127.0.0.1", broker.port, "bed7", client_id="bed7-notifier", **options)


def dead_letters(path):
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_alarm_arrives_with_qos1_and_documented_payload(broker, subscriber, tmp_path):
    notifier = mqtt_notifier(broker, tmp_path)
    try:
        event = alarm()
        notifier.notify(event)
        _, qos, retain, payload = subscriber.next("appliance/bed7/alarm")
        assert (qos, retain) == (1, False)
        body = json.loads(payload)
        assert set(body) == EVENT_FIELDS
        assert Event(**body) == event and body["site"] == "sacrum"
        notifier.notify(as_event(TurnEvent(time_s=5.0, kind="repositioned", posture="left-30", previous="supine",
                                           how="posture")))
        _, qos, _, payload = subscriber.next("appliance/bed7/turn")
        assert qos == 1 and json.loads(payload)["message"] == "repositioned: on the back to left side, 30 degrees"
        assert wait_until(lambda: notifier.delivered == 2)
    finally:
        notifier.close()
    assert subscriber.next("appliance/bed7/status", payload="offline")


def test_status_is_retained_online_and_last_will_is_offline(broker, subscriber, tmp_path):
    notifier = mqtt_notifier(broker, tmp_path)
    try:
        assert subscriber.next("appliance/bed7/status")[3] == "online"
        late = Subscriber(broker.port, "appliance/bed7/status")  # a retained message reaches late subscribers
        try:
            assert late.next("appliance/bed7/status")[2:] == (True, "online")
        finally:
            late.close()
        # Kill the connection without a DISCONNECT, as a crash or a pulled cable would.
        notifier._client.socket().shutdown(socket.SHUT_RDWR)
        assert subscriber.next("appliance/bed7/status")[3] == "offline"
        assert subscriber.next("appliance/bed7/status")[3] == "online"  # and it reconnects
    finally:
        notifier.close()


def test_events_queued_during_an_outage_are_delivered_after_it(broker, subscriber, tmp_path):
    notifier = mqtt_notifier(broker, tmp_path, max_attempts=30)
    try:
        assert subscriber.next("appliance/bed7/status")[3] == "online"
        subscriber.close()
        broker.stop()
        assert wait_until(lambda: not notifier._client.is_connected())
        for i in range(1, 4):
            notifier.notify(alarm(i))
        time.sleep(1.0)
        assert notifier.delivered == 0
        broker.start()
        again = Subscriber(broker.port, "appliance/bed7/alarm")
        try:
            seen = set()
            while seen != {1, 2, 3}:  # at least once: a repeat is allowed, a loss is not
                seen.add(json.loads(again.next("appliance/bed7/alarm", 15)[3])["alarm_id"])
        finally:
            again.close()
        assert wait_until(lambda: notifier.delivered == 3)
        assert dead_letters(tmp_path / "dead.jsonl") == []
    finally:
        notifier.close()


def test_events_are_dead_lettered_when_the_outage_outlasts_the_attempts(broker, tmp_path):
    notifier = mqtt_notifier(broker, tmp_path, max_attempts=3, backoff_s=0.05)
    try:
        assert wait_until(notifier._client.is_connected)
        broker.stop()
        assert wait_until(lambda: not notifier._client.is_connected())
        notifier.notify(alarm(1))
        notifier.notify(alarm(2))
        assert wait_until(lambda: len(dead_letters(tmp_path / "dead.jsonl")) == 2)
        records = dead_letters(tmp_path / "dead.jsonl")
        assert [r["event"]["alarm_id"] for r in records] == [1, 2]
        assert all(r["attempts"] == 3 and "not connected" in r["reason"] for r in records)
        assert set(records[0]["event"]) == EVENT_FIELDS
    finally:
        notifier.close(timeout_s=0.5)


def test_notify_returns_in_well_under_10_ms_with_the_broker_down(broker, tmp_path):
    broker.stop()
    notifier = mqtt_notifier(broker, tmp_path, max_attempts=1000, queue_size=100)
    try:
        durations = []
        for i in range(200):  # past the queue size, so the dead-letter path is timed too
            start = time.perf_counter()
            notifier.notify(alarm(i))
            durations.append(time.perf_counter() - start)
        assert max(durations) < 0.010
        assert notifier.dropped >= 99
    finally:
        notifier.close(timeout_s=0.2)
    assert notifier.dead_lettered == 200 - notifier.delivered


class Gate(Notifier):
    """A channel that holds every delivery until the test opens it."""

    name = "gate"

    def __init__(self, **options):
        self.open = threading.Event()
        self.received = []
        super().__init__(**options)

    def _deliver(self, event):
        self.open.wait()
        self.received.append(event)


def test_a_full_queue_dead_letters_and_counts_and_close_drains(tmp_path):
    path = tmp_path / "dead.jsonl"
    gate = Gate(queue_size=2, dead_letter_path=path)
    assert gate.notify(alarm(1))
    assert wait_until(lambda: gate._queue.empty())  # the worker holds event 1
    assert gate.notify(alarm(2)) and gate.notify(alarm(3))
    assert not gate.notify(alarm(4))
    assert gate.dropped == 1
    assert wait_until(lambda: dead_letters(path))
    assert [r["event"]["alarm_id"] for r in dead_letters(path)] == [4]
    assert "queue full" in dead_letters(path)[0]["reason"]
    gate.open.set()
    gate.close()
    assert [e.alarm_id for e in gate.received] == [1, 2, 3]
    assert not gate.notify(alarm(5))  # after close: straight to the dead letters, not lost
    assert [r["event"]["alarm_id"] for r in dead_letters(path)] == [4, 5]


class Webhook:
    """A local HTTP server answering with the statuses it is given, then 200; it records the bodies."""

    def __init__(self, statuses=()):
        self.statuses = list(statuses)
        self.bodies = []
        hook = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                hook.bodies.append(json.loads(self.rfile.read(int(self.headers["Content-Length"]))))
                self.send_response(hook.statuses.pop(0) if hook.statuses else 200)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/alarms"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()
        self.thread.join()


@pytest.fixture
def webhook():
    hooks = []

    def make(statuses=()):
        hooks.append(Webhook(statuses))
        return hooks[-1]
    yield make
    for hook in hooks:
        hook.close()


def test_webhook_posts_the_event(webhook, tmp_path):
    hook = webhook()
    notifier = WebhookNotifier(hook.url, timeout_s=2.0, dead_letter_path=tmp_path / "dead.jsonl")
    notifier.notify(alarm())
    notifier.close()
    assert notifier.delivered == 1
    assert len(hook.bodies) == 1 and Event(**hook.bodies[0]) == alarm()


def test_webhook_retries_a_500_then_succeeds(webhook, tmp_path):
    hook = webhook([500, 503])
    notifier = WebhookNotifier(hook.url, timeout_s=2.0, backoff_s=0.05, max_attempts=3,
                               dead_letter_path=tmp_path / "dead.jsonl")
    notifier.notify(alarm())
    notifier.close()
    assert len(hook.bodies) == 3 and notifier.delivered == 1
    assert dead_letters(tmp_path / "dead.jsonl") == []


def test_webhook_dead_letters_after_max_attempts_with_the_reason(webhook, tmp_path):
    hook = webhook([500] * 10)
    path = tmp_path / "dead.jsonl"
    notifier = WebhookNotifier(hook.url, timeout_s=2.0, backoff_s=0.05, max_attempts=3, dead_letter_path=path)
    notifier.notify(alarm(5))
    notifier.close()
    assert len(hook.bodies) == 3 and notifier.delivered == 0
    [record] = dead_letters(path)
    assert record["notifier"] == "webhook" and record["attempts"] == 3
    assert "HTTP 500" in record["reason"] and record["event"]["alarm_id"] == 5


def test_gpio_buzzer_and_led_follow_the_audible_priority():
    bank = GPIOBank(SimulatedClock(), ["GPIO20", "GPIO21"], [])
    lines = EmulatedGPIOLines(bank, GpioNotifier.request("GPIO20", "GPIO21"), "alarm-signal", BusTiming())
    gpio = GpioNotifier(lines, buzzer="GPIO20", led="GPIO21")
    assert lines.get_values() == {"GPIO20": 0, "GPIO21": 0}

    def led_over(priority, times):
        values = []
        for t in times:
            gpio.show(priority, t)
            assert lines.get_values(["GPIO20"]) == {"GPIO20": 1}
            values.append(lines.get_values(["GPIO21"])["GPIO21"])
        return values

    assert led_over("high", [0.0, 0.25, 0.5, 0.75]) == [1, 0, 1, 0]       # 2 Hz
    assert led_over("medium", [0.0, 0.5, 1.0, 1.5, 2.0]) == [1, 1, 0, 0, 1]  # 0.5 Hz
    assert led_over("low", [0.0, 0.3, 1.1]) == [1, 1, 1]                   # steady
    gpio.show(None, 3.0)
    assert lines.get_values() == {"GPIO20": 0, "GPIO21": 0}
    gpio.show("high", 0.0)
    gpio.close()
    assert lines.get_values() == {"GPIO20": 0, "GPIO21": 0}
    with pytest.raises(ValueError):
        gpio.show("urgent", 0.0)
