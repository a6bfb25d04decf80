"""The ward link: the bed's alarms and turns to the ward, each confirmed end to end, over any transport.

IEC 60601-1-8 asks a distributed alarm system that claims confirmed delivery to
raise a technical alarm when the remote end stops confirming. A broker's
acknowledgement is not that confirmation (Mosquitto acknowledges from memory), so
every event goes into the durable :class:`~appliance.store.outbox.Outbox` under a
per-bed sequence number and is handed to the transport again until a ward station
confirms that number. The station applies each number once, so a resend is
harmless. The bed keeps sounding its own alarms whatever happens here, and says
how far each alarm got (:meth:`WardLink.delivery`) and when the ward is not
hearing it (:meth:`WardLink.conditions`).

What travels how is the transport's business (:class:`Transport`): the ward's MQTT
broker (``appliance.alerts.ward_mqtt``) or the hospital engine
(``appliance.hospital.bedlink``). Everything that decides what is sent when, and
what the bed is told, is here, the same for both.

Resends: every unconfirmed event is sent on each new connection, and again after
``resend_after_s``, doubling up to ``MAX_RESEND_S``, so a station away for an hour
finds a handful of copies of each event waiting, not thousands. A send the transport
reports as come to nothing (``transport_failed``) is tried again every ``FAILED_RETRY_S``
while it has been failing for less than ``FAILED_FAST_S``, then twice as long after each
further failure (:func:`failed_retry_wait`): no copy of it is waiting anywhere, and a
leader's election (seconds) should not hold an alarm back longer than itself, while an
engine without a quorum for an hour is not asked every second for every event. Once
held, its wait starts again from ``resend_after_s``. With ``confirm`` off (a broker
with no ward station behind it) the transport's acknowledgement counts as delivery,
and the screen says so.

Commands from the ward station are taken on the transport's thread, checked, and
held for the monitor loop (:meth:`WardLink.take_commands`), which applies each
once and hands back its answer (:meth:`WardLink.answer`) for the sender thread to
send. An answer lost on the way is not kept: the station sends the command again
until it has one, and the bed answers a repeat from its store.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Protocol

from appliance.alerts.events import Event
from appliance.alerts.ward_commands import WardCommand, parse_command, result_payload
from appliance.store.outbox import Outbox
from appliance.supervise import Supervised

log = logging.getLogger(__name__)

MAX_RESEND_S = 60.0
FAILED_RETRY_S = 1.0
"""How soon an event the transport could not hand over (the engine did not acknowledge it: a leader being
elected) is sent again: nothing holds a copy yet, so it is not left to wait out the resend wait of one the
broker or engine holds."""
FAILED_FAST_S = 60.0
"""How long failed sends are tried again every ``FAILED_RETRY_S``: longer than an election (the engine elects a
new leader within seconds; its nodes paused for 45 s in the hospital soak) and short of an outage, after which
the wait doubles with each failure up to ``MAX_RESEND_S``."""
IDLE_WAKE_S = 1.0
"""The longest the sender sleeps with nothing due: it is woken by new events, answers, connections and the
transport's word, and otherwise sleeps until the next resend falls due (a bed's link is idle most of the time)."""
UNWRITTEN_RETRY_S = 0.2
"""How often events the disk refused are offered to it again."""
IN_FLIGHT_WAKE_S = 0.2
MAX_IN_FLIGHT = 100
"""Events handed to the transport and not yet acknowledged by it before the link waits: a transport would
queue the rest in memory."""

DELIVERY_STEPS = ("bed", "broker", "ward station")
"""How far an alarm's latest change got: kept at the bed, held by the broker or engine, confirmed by a ward
station."""


class Transport(Protocol):
    """How a :class:`WardLink` reaches the ward. It reports back through the link's ``transport_*`` methods,
    from any thread: ``transport_ready`` once connected and listening for confirmations, ``transport_down`` when
    the connection goes, ``transport_held(seq)`` when the far end holds an event (a broker's PUBACK, the engine's
    acknowledgement from a quorum), ``transport_failed(seq)`` when a send came to nothing,
    ``transport_confirmed(seq, station)`` for a ward station's confirmation and ``transport_command(payload)``
    for a ward station's command."""

    peer: str
    """Who the bed cannot reach when the link is down, for the technical alarm: "the ward broker"."""

    def start(self, link: WardLink) -> None:
        """Begin connecting (and reconnecting for ever), reporting to ``link``."""

    def send_event(self, seq: int, event: dict) -> bool:
        """Hand event ``seq`` over without waiting; False when the connection has just gone."""

    def send_summary(self, payload: str) -> bool:
        """Send the bed's summary (each replaces the last; none is kept if it cannot be sent)."""

    def send_answer(self, payload: str) -> bool:
        """Send an answer to a ward station's command."""

    def connected(self) -> bool:
        """Whether a summary could go now."""

    def close(self, timeout_s: float) -> None:
        """Say the bed is going offline and disconnect, within ``timeout_s``."""


def failed_retry_wait(failing_for_s: float, last_wait_s: float) -> float:
    """The wait before sending again an event whose sends have come to nothing for ``failing_for_s``, the last
    wait having been ``last_wait_s``."""
    if failing_for_s < FAILED_FAST_S:
        return FAILED_RETRY_S
    return min(max(2 * last_wait_s, FAILED_RETRY_S), MAX_RESEND_S)


class WardLink:
    """Sends ``bed_id``'s events from ``outbox`` (which it closes) through ``transport`` until confirmed.

    :meth:`notify` and :meth:`summarise` never wait on the network: one worker
    thread sends, the transport's own thread reports back. Counters: ``published``
    (events handed over, resends included), ``confirmed``, ``summaries_sent``,
    ``summaries_skipped``, ``commands_received``, ``bad_commands``;
    ``confirm_latencies_s`` holds the latest few queue-to-confirmation times.
    """

    name = "ward-link"

    def __init__(self, transport: Transport, bed_id: str, outbox: Outbox, *, summary_interval_s: float = 1.0,
                 confirm: bool = True, confirm_timeout_s: float = 10.0, resend_after_s: float = 5.0):
        if summary_interval_s <= 0 or confirm_timeout_s <= 0 or resend_after_s <= 0:
            raise ValueError(f"summary_interval_s ({summary_interval_s}), confirm_timeout_s ({confirm_timeout_s}) "
                             f"and resend_after_s ({resend_after_s}) must be more than 0")
        self.transport, self.bed_id, self.outbox, self.confirm = transport, bed_id, outbox, confirm
        self.summary_interval_s, self.confirm_timeout_s, self.resend_after_s = \
            summary_interval_s, confirm_timeout_s, resend_after_s
        self.published = self.confirmed = self.summaries_sent = self.summaries_skipped = 0
        self.commands_received = self.bad_commands = 0
        self._commands: list[WardCommand] = []                  # taken from the station, for the monitor loop
        self._answers: list[str] = []                           # answers for the sender to send
        self.confirm_latencies_s: list[float] = []
        self._summary_due = float("-inf")
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._ready = False                      # connected and listening for the confirmations
        self._connection = 0                     # grows with each connection: everything is resent on a new one
        self._down_since: float | None = time.monotonic()  # not yet connected counts as down from the start
        self._sends: dict[int, tuple[int, float, float]] = {}   # seq -> (connection, last sent, wait before next)
        self._queued_steady: dict[int, float] = {}               # seq -> when it was queued, monotonic
        self._in_flight: set[int] = set()                        # handed over, awaiting the transport's word
        self._held: set[int] = set()                             # held by the broker or engine
        self._failed: dict[int, tuple[float, float]] = {}       # seq -> (first send that came to nothing, wait)
        now = time.monotonic()
        for entry in outbox.pending():
            self._queued_steady[entry.seq] = now  # from an earlier run: the deadline starts again now
        transport.start(self)
        self._worker = Supervised(f"{self.name}-sender", self._run)
        self._worker.start()

    # The monitor loop's side.

    def notify(self, event: Event) -> bool:
        """Number ``event`` in the outbox (a durable write) and wake the sender; True once it is kept."""
        if not isinstance(event, Event):
            raise TypeError(f"the ward link sends Event records, got {type(event).__name__}")
        seq = self.outbox.add(event.to_dict(), time.time())
        with self._lock:
            self._queued_steady.setdefault(seq, time.monotonic())
        self._wake.set()
        return True

    def summarise(self, summary: dict) -> None:
        """Send ``summary`` if one is due and the link is up; else skip it (each replaces the last)."""
        now = time.monotonic()
        if now < self._summary_due:
            return
        self._summary_due = max(self._summary_due + self.summary_interval_s, now + self.summary_interval_s / 2)
        if not self.transport.connected():
            self.summaries_skipped += 1
            return
        payload = json.dumps({**summary, "written_at": time.time(), "seq": self.outbox.last_seq})
        if self.transport.send_summary(payload):
            self.summaries_sent += 1
        else:
            self.summaries_skipped += 1

    def take_commands(self) -> list[WardCommand]:
        """The ward station's commands received since the last call, oldest first (repeats included: the loop
        knows which it has applied)."""
        with self._lock:
            commands, self._commands = self._commands, []
        return commands

    def answer(self, command_id: str, applied: bool, result: str) -> None:
        """Tell the ward station command ``command_id`` was applied (or refused, with ``result`` saying why);
        sent by the sender thread, never waited for."""
        payload = result_payload(command_id, "done" if applied else "refused", result, time.time())
        with self._lock:
            self._answers.append(payload)
        self._wake.set()

    def delivery(self, alarm_id: int) -> str | None:
        """How far alarm ``alarm_id``'s latest change got: one of ``DELIVERY_STEPS``."""
        entry = self.outbox.alarm_entry(alarm_id)
        if entry is None:
            return "bed"                                # raised this frame: the outbox gets it next
        if entry.confirmed_at is not None:
            return "broker" if entry.confirmed_by == "broker" else "ward station"
        with self._lock:
            return "broker" if entry.seq in self._held else "bed"

    def status(self) -> dict:
        """The link for the screen: connected, unconfirmed events, and the oldest one's wait in seconds."""
        with self._lock:
            waits = [time.monotonic() - t for t in self._queued_steady.values()]
            return {"connected": self._ready, "confirming": self.confirm, "unconfirmed": len(waits),
                    "oldest_unconfirmed_s": max(waits, default=None), "unwritten": self.outbox.unwritten}

    def conditions(self) -> dict[str, str]:
        """The technical alarms the link earns now: down, or the ward station not confirming, for longer than
        ``confirm_timeout_s``; the outbox's disk refusing writes; the sender thread failing."""
        found = {}
        steady = time.monotonic()
        with self._lock:
            down_s = None if self._down_since is None else steady - self._down_since
            overdue = [steady - t for t in self._queued_steady.values() if steady - t > self.confirm_timeout_s]
        if down_s is not None and down_s > self.confirm_timeout_s:
            found["technical:ward-link"] = f"no connection to {self.transport.peer} for {down_s:.0f} s: alarms " \
                                           f"are shown only at this bed"
        elif overdue:
            who = "the ward station" if self.confirm else self.transport.peer
            found["technical:ward-confirm"] = f"{len(overdue)} alarm change(s) not confirmed by {who} for " \
                                              f"{max(overdue):.0f} s: alarms are shown only at this bed"
        if self.outbox.write_failure is not None:
            found["technical:ward-outbox"] = f"the ward outbox cannot be written ({self.outbox.write_failure}): " \
                                             f"{self.outbox.unwritten} event(s) kept in memory"
        if self._worker.fault is not None:
            found["technical:ward-link-sender"] = f"the ward link's sender is failing (restarting): " \
                                                  f"{self._worker.fault}"
        return found

    def close(self, timeout_s: float = 5.0) -> None:
        """Give the sender up to ``timeout_s`` to hand what is waiting over, say "offline", disconnect.
        Confirmations are not waited for: what is unconfirmed stays in the outbox and is resent at the next start."""
        deadline = time.monotonic() + timeout_s
        while self._ready and self._unsent() and time.monotonic() < deadline:
            self._wake.set()
            time.sleep(0.05)
        self._stopping.set()
        self._wake.set()
        self._worker.stop()
        self._worker.join()
        self.transport.close(max(0.1, deadline - time.monotonic()))
        self.outbox.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _unsent(self) -> bool:
        """Whether an unconfirmed event is not held by the broker or engine yet."""
        pending = [entry.seq for entry in self.outbox.pending()]
        with self._lock:
            return any(seq not in self._held for seq in pending)

    # The transport's reports.

    def transport_ready(self) -> None:
        with self._lock:
            self._ready, self._down_since = True, None
            self._connection += 1
            self._in_flight.clear()
        self._wake.set()

    def transport_down(self) -> None:
        with self._lock:
            if self._ready or self._down_since is None:
                self._down_since = time.monotonic()
            self._ready = False
            self._in_flight.clear()

    def transport_held(self, seq: int) -> None:
        with self._lock:
            self._in_flight.discard(seq)
            if seq not in self._queued_steady:
                return                                  # confirmed meanwhile
            self._held.add(seq)
            self._failed.pop(seq, None)
        if not self.confirm:
            self._confirmed(seq, "broker")
        self._wake.set()

    def transport_failed(self, seq: int) -> None:
        with self._lock:
            self._in_flight.discard(seq)
            sent = self._sends.get(seq)
            if sent is not None and seq in self._queued_steady:
                now = time.monotonic()
                first, wait = self._failed.get(seq, (now, 0.0))
                retry = failed_retry_wait(now - first, wait)
                self._failed[seq] = (first, retry)
                self._sends[seq] = (sent[0], now, retry)
        self._wake.set()

    def transport_confirmed(self, seq, station) -> None:
        """A ward station's confirmation of ``seq``; a malformed one is logged and ignored."""
        if not isinstance(seq, int) or isinstance(seq, bool) or not isinstance(station, str) or not station:
            log.warning("ward link: bad confirmation ignored: seq must be an integer and station a name, got %r "
                        "and %r", seq, station)
            return
        self._confirmed(seq, station)

    def transport_command(self, payload: bytes) -> None:
        try:
            command = parse_command(payload, self.bed_id)
        except (ValueError, TypeError, UnicodeDecodeError) as exc:      # json's errors are ValueErrors
            with self._lock:
                self.bad_commands += 1
            log.warning("ward link: bad command from the ward station ignored: %s", exc)
            return
        with self._lock:
            self.commands_received += 1
            self._commands.append(command)

    def _confirmed(self, seq: int, by: str) -> None:
        if not self.outbox.confirm(seq, by, time.time()):
            return                                      # a repeat, or a number this bed never gave
        with self._lock:
            queued = self._queued_steady.pop(seq, None)
            self._sends.pop(seq, None)
            self._held.discard(seq)
            self._failed.pop(seq, None)
            self.confirmed += 1
            if queued is not None:
                self.confirm_latencies_s = [*self.confirm_latencies_s[-999:], time.monotonic() - queued]

    # The sender thread.

    def _run(self) -> None:
        next_send = float("inf")
        while not self._stopping.is_set():
            cap = UNWRITTEN_RETRY_S if self.outbox.unwritten else IDLE_WAKE_S
            self._wake.wait(min(cap, max(0.0, next_send - time.monotonic())))
            self._wake.clear()
            self.outbox.retry_writes()
            next_send = float("inf")
            if self._ready:
                self._send_answers()
                next_send = self._send_due()
            self._worker.ok()

    def _send_answers(self) -> None:
        with self._lock:
            answers, self._answers = self._answers, []
        for payload in answers:
            if not self.transport.send_answer(payload):   # the station asks again, and is answered from the store
                log.warning("ward link: an answer to the ward station was not sent")

    def _send_due(self) -> float:
        """Send every unconfirmed event whose wait is over; when the next one falls due (monotonic)."""
        steady = time.monotonic()
        next_send = float("inf")
        for entry in self.outbox.pending():
            with self._lock:
                if len(self._in_flight) >= MAX_IN_FLIGHT and entry.seq not in self._in_flight:
                    return steady + IN_FLIGHT_WAKE_S              # or sooner, woken by the transport's word
                # One still awaiting the transport's word is sent again after its wait like any other: the word
                # can be missed (a PUBACK that beats the transport's note of its message id).
                connection, sent, wait = self._sends.get(entry.seq, (-1, 0.0, self.resend_after_s))
                if connection == self._connection and steady - sent < wait:
                    next_send = min(next_send, sent + wait)
                    continue
                again = connection == self._connection and entry.seq not in self._failed
                wait = min(2 * wait, MAX_RESEND_S) if again else self.resend_after_s
                self._sends[entry.seq] = (self._connection, steady, wait)
                next_send = min(next_send, steady + wait)
                self._in_flight.add(entry.seq)
            if not self.transport.send_event(entry.seq, entry.event):
                with self._lock:
                    self._in_flight.discard(entry.seq)
                return float("inf")                     # the connection went: all is resent on the next one
            self.published += 1
        return next_send
