"""The ward station's commands to beds: journalled, sent, and sent again until the bed answers or time is up.

A nurse's acknowledgement must reach the bed even when the network, the broker
or the bed is briefly away, and must never be applied twice. So a command is
journalled first (:class:`~appliance.ward.journal.CommandJournal`, the audit),
then published (at QoS 1 on the ward's broker, a plain message on the hospital
engine), and published again, under the same id, on every new
connection of the station, as soon as its bed says it is back online, and
every ``resend_after_s`` (doubling up to ``MAX_RESEND_S``) in between, until
the bed's answer comes or ``expires_at`` passes. The bed applies each id once
(``appliance.alerts.ward_commands``), so the copies cost nothing but traffic.

Expiry is the station's answer to a bed away too long: after ``expiry_s``
(default ``DEFAULT_EXPIRY_S``) the station stops sending and shows the command
expired, and a bed that takes a copy later refuses it, since an alarm
acknowledged or a turn recorded minutes ago no longer says what the nurse saw.
Both sides judge expiry on their wall clocks, which the ward keeps in step
(NTP); if they disagree, the bed's answer is what the journal keeps.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from appliance.alerts.ward_commands import WardCommand, new_command, parse_result
from appliance.supervise import Supervised
from appliance.ward.journal import CommandJournal

log = logging.getLogger(__name__)

DEFAULT_EXPIRY_S = 120.0
"""How long a nurse's command from the ward may wait for its bed: long enough for a bed's restart or a
broker's, short enough that what it acknowledges is still what the nurse saw."""
DEFAULT_RESEND_S = 2.0
MAX_RESEND_S = 30.0
TICK_S = 0.2


class CommandSender:
    """Sends commands from ``station`` (the station's client id) to beds.

    ``publish(bed_id, payload)`` sends the command to that bed by the
    station's own transport (the ward broker, the hospital engine) and says
    whether the connection took it; ``on_change()`` is called when a
    command's state changes (an answer, an expiry), so a screen can redraw.
    """

    def __init__(self, journal: CommandJournal, publish: Callable[[str, str], bool], station: str, *,
                 expiry_s: float = DEFAULT_EXPIRY_S, resend_after_s: float = DEFAULT_RESEND_S,
                 on_change: Callable[[], None] = lambda: None):
        if not expiry_s > 0 or not resend_after_s > 0:
            raise ValueError(f"expiry_s ({expiry_s}) and resend_after_s ({resend_after_s}) must be more than 0")
        self.journal, self._publish, self.station = journal, publish, station
        self.expiry_s, self.resend_after_s, self.on_change = expiry_s, resend_after_s, on_change
        self.sends = self.answers = self.bad_answers = 0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._connected = False
        self._due: dict[str, tuple[float, float]] = {}     # command id -> (next send, wait after it), monotonic
        self._worker = Supervised("ward-station-commands", self._run)
        self._worker.start()

    @property
    def fault(self) -> str | None:
        """Why the resending thread is failing (restarting), or None."""
        return self._worker.fault

    def send(self, bed_id: str, kind: str, args: dict, user: str) -> dict:
        """Journal and send a command from ``user`` (the station's account); the journal's entry for it."""
        command = new_command(bed_id, kind, args, user, self.station, time.time(), self.expiry_s)
        self.journal.add(command)
        self._send(command)
        self.on_change()
        return self.journal.get(command.id) or {}

    def connected(self, up: bool) -> None:
        """The station's connection came (everything pending is sent again at once) or went."""
        with self._lock:
            self._connected = up
            if up:
                self._due.clear()
        self._wake.set()

    def bed_online(self, bed_id: str) -> None:
        """``bed_id`` is back: what waits for it goes now rather than at its next resend."""
        pending = {c.id for c in self.journal.pending(bed_id)}
        with self._lock:
            for command_id in pending:
                self._due.pop(command_id, None)
        if pending:
            self._wake.set()

    def take_answer(self, bed_id: str, payload: bytes) -> None:
        """A bed's answer; ValueError if it is not one."""
        answer = parse_result(payload)
        if self.journal.answer(answer["id"], bed_id, answer["state"], answer["result"], answer["answered_at"]):
            with self._lock:
                self.answers += 1
                self._due.pop(answer["id"], None)
            self.on_change()

    def close(self) -> None:
        self._stopping.set()
        self._wake.set()
        self._worker.stop()
        self._worker.join()

    def _send(self, command: WardCommand) -> None:
        with self._lock:
            if not self._connected:
                return                            # sent when the connection comes
            _, wait = self._due.get(command.id, (0.0, self.resend_after_s / 2))
            wait = min(2 * wait, MAX_RESEND_S)
            self._due[command.id] = (time.monotonic() + wait, wait)
        if self._publish(command.bed_id, command.to_payload()):
            self.journal.sent(command.id)
            with self._lock:
                self.sends += 1

    def _run(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(TICK_S)
            self._wake.clear()
            if self.journal.expire(time.time()):
                self.on_change()
            steady = time.monotonic()
            for command in self.journal.pending():
                with self._lock:
                    due = self._due.get(command.id, (steady, 0.0))[0]
                if due <= steady:
                    self._send(command)
            self._worker.ok()
