"""The charting link: the bed's events and periodic pressures to the hospital's interface engine as HL7 over MLLP.

Each alarm change, turn and admission or discharge, and every
``observation_interval_s`` of monitoring the peak pressure at each loaded site
with the posture, becomes a record in the durable
:class:`~appliance.charting.chartqueue.ChartQueue` and then an ORU^R01
(:mod:`appliance.charting.hl7`). One sender thread sends the records in order,
one at a time, each waiting for the engine's ACK: AA is delivered, AE or AR is
refused (kept in the queue with the engine's words, logged, counted, not sent
again), no answer within ``ack_timeout_s`` is a failure and the same message
goes again after a back-off that doubles up to ``max_backoff_s``. Delivery is
at least once: an ACK lost on the way back means a resend under the same
control id (MSH-10), which the engine can drop.

The monitor loop only writes to the queue; when the oldest message has waited
for its ACK longer than ``undelivered_alarm_s`` the bed raises
``technical:charting`` (see :meth:`ChartingLink.conditions`), as the ward link
raises ``technical:ward-link``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable

from appliance.alerts.events import EVENT_TYPES, Event
from appliance.charting.chartqueue import ChartQueue, Queued
from appliance.charting.hl7 import Parties, acknowledgement, oru_r01
from appliance.charting.mllp import MllpConnection
from appliance.supervise import Supervised

log = logging.getLogger(__name__)

DELIVERED = ("AA", "CA")
REFUSED = ("AE", "AR", "CE", "CR")
"""MSA-1 codes, original and enhanced acknowledgement modes (HL7 table 0008)."""


class ChartingLink:
    """Sends ``queue``'s records (it closes the queue) to the engine at ``host``:``port``.

    Counters: ``sent`` (attempts, resends included), ``delivered``, ``refusals``.
    ``patient`` may be set to a callable giving the admitted episode (with
    ``patient_id`` and ``name``), read on the monitor loop's thread, so an
    admission's message names the patient.
    """

    name = "charting"

    def __init__(self, host: str, port: int, parties: Parties, queue: ChartQueue, *, ack_timeout_s: float = 10.0,
                 undelivered_alarm_s: float = 300.0, observation_interval_s: float = 600.0, backoff_s: float = 1.0,
                 max_backoff_s: float = 60.0):
        if min(ack_timeout_s, undelivered_alarm_s, observation_interval_s, backoff_s, max_backoff_s) <= 0:
            raise ValueError("the charting link's timeouts, intervals and back-offs must be more than 0")
        self.host, self.port, self.parties, self.queue = host, port, parties, queue
        self.ack_timeout_s, self.undelivered_alarm_s = ack_timeout_s, undelivered_alarm_s
        self.observation_interval_s = observation_interval_s
        self.backoff_s, self.max_backoff_s = backoff_s, max_backoff_s
        self.sent = self.delivered = self.refusals = 0
        self.last_error: str | None = None
        self.patient: Callable[[], object | None] | None = None
        self._names: dict[str, str | None] = {}
        self._next_observation_s: float | None = None
        self._lock = threading.Lock()
        self._head: tuple[int, float] | None = None          # the oldest pending record, since when (monotonic)
        self._connection: MllpConnection | None = None
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._worker = Supervised(f"{self.name}-sender", self._run)
        self._worker.start()

    # The monitor loop's side.

    def notify(self, event: Event) -> bool:
        """Queue ``event``'s record (a durable write) and wake the sender."""
        if not isinstance(event, Event):
            raise TypeError(f"the charting link sends Event records, got {type(event).__name__}")
        if event.type not in EVENT_TYPES:
            return False
        self._learn_patient()
        self.queue.add({"event": event.to_dict(), "name": self._names.get(event.patient or "")}, time.time())
        self._wake.set()
        return True

    def summarise(self, summary: dict) -> None:
        """Queue the peak pressure per site and the posture when an observation is due (monitoring time)."""
        now = summary["time_s"]
        patient = summary.get("patient")
        if patient:
            self._names[patient["patient_id"]] = patient.get("name")
        if self._next_observation_s is not None and now < self._next_observation_s:
            return
        peaks: dict[str, float] = {}
        for region in summary.get("regions", []):
            if region.get("zone") and region.get("peak_mmhg") is not None:
                peaks[region["zone"]] = max(peaks.get(region["zone"], 0.0), float(region["peak_mmhg"]))
        if not peaks:
            return                                      # an empty bed or a gap: the next map is charted
        self._next_observation_s = now + self.observation_interval_s
        patient_id = patient["patient_id"] if patient else None
        self.queue.add({"observation": {"time_s": now, "posture": summary.get("posture"), "patient": patient_id,
                                        "peaks": peaks}, "name": self._names.get(patient_id or "")}, time.time())
        self._wake.set()

    @property
    def fault(self) -> str | None:
        """The sender thread's failure, if it is failing (the daemon shows it as a technical alarm)."""
        return self._worker.fault

    def status(self) -> dict:
        with self._lock:
            waiting = None if self._head is None else time.monotonic() - self._head[1]
        return {"target": f"{self.host}:{self.port}", "connected": self._connection is not None,
                "waiting": self.queue.waiting(), "oldest_undelivered_s": waiting,
                "delivered": self.delivered, "refused": self.refusals, "unwritten": self.queue.unwritten,
                "last_error": self.last_error}

    def conditions(self) -> dict[str, str]:
        """``technical:charting`` while the oldest message has waited longer than ``undelivered_alarm_s``;
        ``technical:charting-queue`` while the queue's disk refuses records."""
        found = {}
        with self._lock:
            waiting = None if self._head is None else time.monotonic() - self._head[1]
        if waiting is not None and waiting > self.undelivered_alarm_s:
            found["technical:charting"] = f"the hospital's interface engine has not acknowledged charting for " \
                                          f"{waiting:.0f} s ({self.last_error or 'no answer'}): it is kept and resent"
        if self.queue.write_failure is not None:
            found["technical:charting-queue"] = f"the charting queue cannot be written ({self.queue.write_failure}):" \
                                                f" {self.queue.unwritten} record(s) kept in memory"
        return found

    def close(self, timeout_s: float = 5.0) -> None:
        """Give the sender up to ``timeout_s`` to empty the queue, then stop; what is left is sent at the next
        start."""
        deadline = time.monotonic() + timeout_s
        while self._connection is not None and self.queue.pending(1) and time.monotonic() < deadline:
            self._wake.set()
            time.sleep(0.05)
        self._stopping.set()
        self._wake.set()
        connection = self._connection
        if connection is not None:
            with contextlib.suppress(OSError):
                connection.sock.shutdown(2)             # ends a wait for an ACK at once
        self._worker.stop()
        self._worker.join()
        self._disconnect()
        self.queue.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _learn_patient(self) -> None:
        episode = self.patient() if self.patient is not None else None
        if episode is not None:
            self._names[episode.patient_id] = episode.name   # type: ignore[attr-defined]

    # The sender thread.

    def _run(self) -> None:
        delay = self.backoff_s
        while not self._stopping.is_set():
            self.queue.retry_writes()
            batch = self.queue.pending()
            if not batch:
                with self._lock:
                    self._head = None
                self._worker.ok()
                self._wake.wait(0.5)
                self._wake.clear()
                continue
            for item in batch:
                with self._lock:
                    if self._head is None or self._head[0] != item.seq:
                        self._head = (item.seq, time.monotonic())
                if not self._send(item):
                    self._stopping.wait(delay)
                    delay = min(2 * delay, self.max_backoff_s)
                    break
                delay = self.backoff_s
                if self._stopping.is_set():
                    break
            self._worker.ok()

    def _send(self, item: Queued) -> bool:
        """Send one record and take the answer; False if it must be sent again."""
        control_id = f"{self.parties.bed_id}-{item.seq}"
        message = oru_r01(item.record, self.parties, control_id, item.queued_at)
        try:
            if self._connection is None:
                self._connection = MllpConnection(self.host, self.port, self.ack_timeout_s)
            self.sent += 1
            code, answered, detail = acknowledgement(self._connection.exchange(message))
        except (OSError, ValueError) as exc:
            self._failed(f"{type(exc).__name__}: {exc}")
            return False
        if answered != control_id:
            self._failed(f"the ACK answers {answered!r}, not {control_id!r}")
            return False
        if code in DELIVERED:
            self.queue.answered(item.seq, True, code, time.time())
            self.delivered += 1
        elif code in REFUSED:
            self.queue.answered(item.seq, False, f"{code} {detail}".strip(), time.time())
            self.refusals += 1
            log.error("charting: the interface engine refused message %s: %s %s", control_id, code, detail)
        else:
            self._failed(f"an ACK with the unknown code {code!r}")
            return False
        self.last_error = None
        return True

    def _failed(self, why: str) -> None:
        if why != self.last_error:
            log.warning("charting: %s; the message is kept and sent again", why)
        self.last_error = why
        self._disconnect()

    def _disconnect(self) -> None:
        connection, self._connection = self._connection, None
        if connection is not None:
            connection.close()
