"""Notifiers: carry alarm and turn events off the bed (webhook) and onto the bed (buzzer, LED).

The ward's MQTT link, with its confirmed delivery, is ``appliance.alerts.wardlink``.

The monitor loop must never wait on a network, so :meth:`Notifier.notify` only
puts the event on a bounded queue; a worker thread per notifier delivers it,
retrying with exponential backoff up to ``max_attempts``. An event that cannot be
delivered (queue full, every attempt failed, notifier closed) is not silently
lost: it is appended to a dead-letter JSONL file with the reason, one record a
line::

    {"dead_lettered_at": <unix time>, "notifier": "webhook", "reason": "...",
     "attempts": 3, "event": {...}}

Delivery is at least once: a retry after a lost acknowledgement can repeat an
event, so receivers de-duplicate on (``alarm_id``, ``kind``, ``time_s``).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
import urllib.error
import urllib.request
from abc import ABC, abstractmethod
from pathlib import Path

from appliance.alerts.alarms import PRIORITIES
from appliance.alerts.events import Event
from appliance.alerts.tones import tone_schedule
from appliance.supervise import Supervised
from appliance.drivers.bus import GPIOLines, LineRequest

log = logging.getLogger(__name__)


class Notifier(ABC):
    """Delivers events in its own thread so that :meth:`notify` never blocks the monitor.

    ``max_attempts`` deliveries are tried per event, waiting ``backoff_s``, then
    twice that, and so on up to ``max_backoff_s`` between them. Counters:
    ``delivered``, ``dropped`` (queue full) and ``dead_lettered`` (all reasons).
    """

    name = "notifier"

    def __init__(self, *, queue_size: int = 256, max_attempts: int = 5, backoff_s: float = 0.5,
                 max_backoff_s: float = 30.0, dead_letter_path: str | Path | None = None):
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be at least 1, got {max_attempts}")
        self.max_attempts = max_attempts
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.dead_letter_path = Path(dead_letter_path) if dead_letter_path is not None else None
        self.delivered = 0
        self.dropped = 0
        self.dead_lettered = 0
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        # Dead letters are written by their own thread: file and log I/O in
        # notify() let other threads take the GIL and cost milliseconds.
        self._dead_letters: queue.SimpleQueue = queue.SimpleQueue()
        self._closed = False
        self._count_lock = threading.Lock()  # notify() and the worker both dead-letter
        self._closing = threading.Event()
        self._abort = threading.Event()
        self._worker = Supervised(f"{self.name}-notifier", self._run)       # restarted if it ever fails
        self._writer = Supervised(f"{self.name}-dead-letters", self._write_dead_letters)
        self._worker.start()
        self._writer.start()

    @property
    def fault(self) -> str | None:
        """What a failing thread of this notifier last raised, while it fails (a technical alarm)."""
        failing = [f"{t.name}: {t.fault}" for t in (self._worker, self._writer) if t.fault is not None]
        return "; ".join(failing) or None

    def notify(self, event: Event) -> bool:
        """Queue ``event`` for delivery and return at once; False if it went to the dead letters instead."""
        if not isinstance(event, Event):
            raise TypeError(f"notifiers send Event records, got {type(event).__name__}")
        if self._closing.is_set():
            self._dead_letter(event, "notifier closed", 0)
            return False
        try:
            self._queue.put_nowait(event)
        except queue.Full:
            self.dropped += 1
            self._dead_letter(event, f"queue full ({self._queue.maxsize} events waiting)", 0)
            return False
        return True

    def close(self, timeout_s: float = 5.0) -> None:
        """Deliver what is queued for up to ``timeout_s``, dead-letter the rest, and release the channel."""
        self._closing.set()
        self._worker.stop()
        self._worker.join(timeout_s)
        if self._worker.is_alive():
            self._abort.set()
            self._worker.join()  # one attempt is bounded by the channel's own timeout
        while True:
            try:
                self._dead_letter(self._queue.get_nowait(), "notifier closed before delivery", 0)
            except queue.Empty:
                break
        self._closed = True  # from now on dead letters are written at once: no writer thread is left
        self._dead_letters.put(None)
        self._writer.stop()
        self._writer.join()
        self._shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abstractmethod
    def _deliver(self, event) -> None:
        """Deliver one event or raise; returning means the receiver has it."""

    def _shutdown(self) -> None:
        """Release the channel once the worker has stopped (override)."""

    def _run(self) -> None:
        while True:
            try:
                event = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self._closing.is_set():
                    return
                continue
            if self._abort.is_set():
                self._dead_letter(event, "notifier closed before delivery", 0)
            else:
                self._send(event)
            self._worker.ok()

    def _send(self, event) -> None:
        for attempt in range(1, self.max_attempts + 1):
            try:
                self._deliver(event)
            except Exception as exc:  # noqa: BLE001  (any failure of the channel is a reason to retry, not to die)
                reason = f"{type(exc).__name__}: {exc}"
                log.warning("%s: delivery failed (attempt %d of %d): %s",
                            self.name, attempt, self.max_attempts, reason)
            else:
                self.delivered += 1
                return
            if attempt < self.max_attempts:
                delay = min(self.backoff_s * 2 ** (attempt - 1), self.max_backoff_s)
                if self._abort.wait(delay):
                    self._dead_letter(event, f"notifier closed during retries; last error: {reason}", attempt)
                    return
        self._dead_letter(event, f"failed {self.max_attempts} attempts; last error: {reason}", self.max_attempts)

    def _dead_letter(self, event, reason: str, attempts: int) -> None:
        with self._count_lock:
            self.dead_lettered += 1
        item = (time.time(), event, reason, attempts)
        if self._closed:
            self._write_dead_letter(*item)
        else:
            self._dead_letters.put(item)

    def _write_dead_letters(self) -> None:
        while (item := self._dead_letters.get()) is not None:
            self._write_dead_letter(*item)

    def _write_dead_letter(self, when: float, event, reason: str, attempts: int) -> None:
        log.error("%s: event dead-lettered: %s: %r", self.name, reason, event)
        if self.dead_letter_path is None:
            return
        record = {"dead_lettered_at": when, "notifier": self.name, "reason": reason, "attempts": attempts,
                  "event": event.to_dict()}
        with self.dead_letter_path.open("a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")
        self._writer.ok()


class WebhookNotifier(Notifier):
    """POSTs each event as JSON to ``url``; any 2xx answer is delivery, anything else is retried."""

    name = "webhook"

    def __init__(self, url: str, *, timeout_s: float = 5.0, **options):
        self.url = url
        self.timeout_s = timeout_s
        super().__init__(**options)

    def _deliver(self, event) -> None:
        request = urllib.request.Request(self.url, data=json.dumps(event.to_dict()).encode(),
                                         headers={"Content-Type": "application/json"}, method="POST")
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                status = response.status
        except urllib.error.HTTPError as exc:
            exc.close()
            raise ConnectionError(f"HTTP {exc.code} from {self.url}") from None
        if not 200 <= status < 300:
            raise ConnectionError(f"HTTP {status} from {self.url}")


# Flash rates of IEC 60601-1-8 visual alarm signals: high 1.4 to 2.8 Hz, medium
# 0.4 to 0.8 Hz, low constant. None: steady on.
BLINK_HZ = {"high": 2.0, "medium": 0.5, "low": None}
SIGNAL_TICK_S = 0.01
"""How often the signal thread sets the lines: fine enough for the tones' 100 ms silences between pulses."""


class GpioNotifier:
    """Drives the bedside buzzer and LED from the alarm engine's audible priority.

    The buzzer sounds the priority's pulse bursts (:mod:`appliance.alerts.tones`)
    and the LED flashes at its rate, both timed on the notifier's own ``clock``
    from the moment that priority began. Frames come far too seldom for 150 ms
    pulses, so a thread of its own sets the lines every ``tick_s``; with
    ``tick_s=None`` there is none and the caller calls :meth:`drive`.
    """

    def __init__(self, lines: GPIOLines, *, buzzer: str, led: str, clock=time.monotonic,
                 tick_s: float | None = SIGNAL_TICK_S):
        self.lines, self.buzzer, self.led, self.clock = lines, buzzer, led, clock
        self._priority: str | None = None
        self._since = 0.0
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._worker = None if tick_s is None else Supervised("alarm signals", lambda: self._run(tick_s)).start()

    @staticmethod
    def request(buzzer: str, led: str) -> LineRequest:
        """The lines to ask the board for: both outputs, both off until the first alarm."""
        return LineRequest(outputs={buzzer: 0, led: 0}, inputs={})

    def show(self, priority: str | None) -> None:
        """Sound and flash for ``priority`` (``AlarmEngine.audible(now)``) from now on; None is quiet and dark."""
        if priority is not None and priority not in PRIORITIES:
            raise ValueError(f"priority must be one of {PRIORITIES} or None, got {priority!r}")
        with self._lock:
            if priority != self._priority:
                self._priority, self._since = priority, self.clock()
        self.drive()

    def drive(self) -> None:
        """Set both lines as the current priority's tone and flash are at the clock's time now."""
        with self._lock:                    # held while writing, so the last write after close() is the dark one
            if self._priority is None:
                self.lines.set_values({self.buzzer: 0, self.led: 0})
                return
            t = self.clock() - self._since
            hz = BLINK_HZ[self._priority]
            led = 1 if hz is None else int((t * hz) % 1.0 < 0.5)
            self.lines.set_values({self.buzzer: int(tone_schedule(self._priority).sounding(t)), self.led: led})

    def _run(self, tick_s: float) -> None:
        while not self._stopping.wait(tick_s):
            self.drive()
            if self._worker is not None:
                self._worker.ok()

    def close(self) -> None:
        """Stop the signal thread, then silence and darken before the lines are given back."""
        self._stopping.set()
        if self._worker is not None:
            self._worker.stop()
            self._worker.join()
        self.show(None)
