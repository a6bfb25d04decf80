"""Notifiers against a local HTTP server and emulated GPIO lines (the ward link: tests/test_ward_link.py)."""

import json
import time
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from mqtt_broker import wait_until

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.events import Event, as_event
from appliance.alerts.notifiers import GpioNotifier, Notifier, WebhookNotifier
from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, GPIOBank
from appliance.drivers.emulated.clock import SimulatedClock

EVENT_FIELDS = {"time_s", "type", "kind", "priority", "category", "key", "site", "posture", "x_mm", "y_mm", "alarm_id",
                "message", "user", "channel", "patient"}


def alarm(alarm_id=1, kind="raised", priority="high"):
    return as_event(AlarmEvent(time_s=10.0 * alarm_id, kind=kind, alarm_id=alarm_id, key="pressure:sacrum",
                               category="clinical", priority=priority, message="Sacrum dose over limit"))


def dead_letters(path):
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


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


def gpio_signals(**options):
    bank = GPIOBank(SimulatedClock(), ["GPIO20", "GPIO21"], [])
    lines = EmulatedGPIOLines(bank, GpioNotifier.request("GPIO20", "GPIO21"), "alarm-signal", BusTiming())
    return lines, GpioNotifier(lines, buzzer="GPIO20", led="GPIO21", **options)


def test_gpio_buzzer_sounds_the_tone_schedule_and_the_led_flashes_at_the_priority_rate():
    now = [100.0]
    lines, gpio = gpio_signals(clock=lambda: now[0], tick_s=None)
    assert lines.get_values() == {"GPIO20": 0, "GPIO21": 0}

    def over(priority, times):
        """(buzzer, LED) at each time after ``priority`` began."""
        now[0] = 100.0
        gpio.show(None)
        gpio.show(priority)
        values = []
        for t in times:
            now[0] = 100.0 + t
            gpio.drive()
            got = lines.get_values()
            values.append((got["GPIO20"], got["GPIO21"]))
        return values

    # high: pulses at 0, 0.25, 0.5 s (150 ms each), the 4th after an extra 350 ms; LED at 2 Hz
    assert over("high", [0.0, 0.2, 0.25, 0.6, 0.8, 1.15, 4.0, 8.85]) == [
        (1, 1), (0, 1), (1, 0), (1, 1), (0, 0), (1, 1), (0, 1), (1, 0)]
    # medium: 3 pulses of 200 ms every 400 ms, then quiet until the burst repeats at 11 s; LED at 0.5 Hz
    assert over("medium", [0.1, 0.3, 0.9, 1.1, 11.1]) == [(1, 1), (0, 1), (1, 1), (0, 0), (1, 0)]
    assert over("low", [0.1, 0.5, 1.0, 20.7]) == [(1, 1), (1, 1), (0, 1), (1, 1)]          # 2 pulses, LED steady
    gpio.show("high")
    gpio.close()
    assert lines.get_values() == {"GPIO20": 0, "GPIO21": 0}
    with pytest.raises(ValueError):
        gpio.show("urgent")


def test_gpio_signal_thread_sounds_the_buzzer_between_frames_and_is_quiet_once_closed():
    """The monitor calls show() once a frame; the notifier's own thread plays the pulses in between."""
    lines, gpio = gpio_signals(tick_s=0.005)
    gpio.show("high")
    seen = set()
    deadline = time.monotonic() + 5.0
    while len(seen) < 2 and time.monotonic() < deadline:        # on in a pulse, off between two
        seen.add(lines.get_values(["GPIO20"])["GPIO20"])
        time.sleep(0.01)
    gpio.close()
    assert seen == {0, 1}
    assert lines.get_values() == {"GPIO20": 0, "GPIO21": 0}
