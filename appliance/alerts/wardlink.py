"""The ward link: the bed's alarms and turns to the ward station over MQTT, each confirmed end to end.

IEC 60601-1-8 asks a distributed alarm system that claims confirmed delivery to
raise a technical alarm when the remote end stops confirming. A broker's PUBACK
is not that confirmation (Mosquitto acknowledges from memory), so every event
goes into the durable :class:`~appliance.store.outbox.Outbox` under a per-bed
sequence number and is published again until the ward station answers on the
bed's ``confirm`` topic. The station applies each number once, so a resend is
harmless. The bed keeps sounding its own alarms whatever happens here, and says
how far each alarm got (:meth:`WardLink.delivery`) and when the ward is not
hearing it (:meth:`WardLink.conditions`).

Topics (``<prefix>`` is ``topic_prefix``, "appliance" by default)::

    <prefix>/<bed_id>/alarm    QoS 1: one alarm Event as JSON, with "bed_id" and "seq"
                               {time_s, type: "alarm", kind, priority, category, key,
                                site, posture, x_mm, y_mm, alarm_id, message, user,
                                channel, patient, bed_id, seq}
    <prefix>/<bed_id>/turn     QoS 1: one turn Event (type "turn"), the same fields
    <prefix>/<bed_id>/episode  QoS 1: admitted or discharged, the same fields
    <prefix>/<bed_id>/confirm  QoS 1, from the ward station: {seq, station, confirmed_at}
    <prefix>/<bed_id>/command  QoS 1, from the ward station: acknowledge an alarm, record
                               a turn (``appliance.alerts.ward_commands``)
    <prefix>/<bed_id>/command-result   QoS 1: the bed's answer to each command
    <prefix>/<bed_id>/status   QoS 1, retained: "online" once connected; "offline" on
                               close, and as the last will when the connection dies.
    <prefix>/<bed_id>/summary  QoS 0, retained: the bed at a glance about once a second
                               (``appliance.service.daemon.ward_summary``) with
                               "written_at" (unix time) and "seq", the highest number
                               handed out when it was made: its alarms already hold
                               every event up to that number.

Resends: every unconfirmed event is published on each new connection, and again
after ``resend_after_s``, doubling up to ``MAX_RESEND_S``, so a station away for
an hour finds a handful of copies of each event waiting, not thousands. With
``confirm`` off (a broker with no ward station behind it) the broker's
acknowledgement counts as delivery, and the screen says so.

Commands from the ward station are taken on paho's thread, checked, and held
for the monitor loop (:meth:`WardLink.take_commands`), which applies each once
and hands back its answer (:meth:`WardLink.answer`) for the sender thread to
publish. An answer lost on the way is not kept: the station sends the command
again until it has one, and the bed answers a repeat from its store.
"""

from __future__ import annotations

import json
import logging
import threading
import time

import paho.mqtt.client as mqtt

from appliance.alerts.events import EVENT_TYPES, Event
from appliance.alerts.ward_commands import COMMAND_TOPIC, RESULT_TOPIC, WardCommand, parse_command, result_payload
from appliance.store.outbox import Outbox
from appliance.supervise import Supervised

log = logging.getLogger(__name__)

MAX_RESEND_S = 60.0
MAX_IN_FLIGHT = 100
"""Publications awaiting the broker's PUBACK before the link waits: paho would queue the rest in memory."""

DELIVERY_STEPS = ("bed", "broker", "ward station")
"""How far an alarm's latest change got: kept at the bed, taken by the broker, confirmed by a ward station."""


class WardLink:
    """Publishes ``bed_id``'s events from ``outbox`` (which it closes) to the broker at ``host``:``port`` until
    confirmed.

    :meth:`notify` and :meth:`summarise` never wait on the network: one worker
    thread publishes, paho's thread receives the confirmations. Counters:
    ``published`` (publications, resends included), ``confirmed``,
    ``summaries_sent``, ``summaries_skipped``, ``commands_received``,
    ``bad_commands``; ``confirm_latencies_s`` holds the latest few
    queue-to-confirmation times.
    """

    name = "ward-link"

    def __init__(self, host: str, port: int, bed_id: str, outbox: Outbox, *, client_id: str,
                 topic_prefix: str = "appliance", keepalive_s: int = 30, username: str | None = None,
                 password: str | None = None, ca_file=None, summary_interval_s: float = 1.0, confirm: bool = True,
                 confirm_timeout_s: float = 10.0, resend_after_s: float = 5.0):
        if summary_interval_s <= 0 or confirm_timeout_s <= 0 or resend_after_s <= 0:
            raise ValueError(f"summary_interval_s ({summary_interval_s}), confirm_timeout_s ({confirm_timeout_s}) "
                             f"and resend_after_s ({resend_after_s}) must be more than 0")
        self.bed_id, self.outbox, self.confirm = bed_id, outbox, confirm
        base = f"{topic_prefix}/{bed_id}"
        self.topics = {kind: f"{base}/{kind}" for kind in EVENT_TYPES}
        self.status_topic, self.summary_topic, self.confirm_topic = f"{base}/status", f"{base}/summary", \
            f"{base}/confirm"
        self.command_topic, self.result_topic = f"{base}/{COMMAND_TOPIC}", f"{base}/{RESULT_TOPIC}"
        self.summary_interval_s, self.confirm_timeout_s, self.resend_after_s = \
            summary_interval_s, confirm_timeout_s, resend_after_s
        self.published = self.confirmed = self.summaries_sent = self.summaries_skipped = 0
        self.commands_received = self.bad_commands = 0
        self._commands: list[WardCommand] = []                  # taken from the station, for the monitor loop
        self._command_subscription: int | None = None           # the mid of its subscription
        self._answers: list[str] = []                           # answers for the sender to publish
        self.confirm_latencies_s: list[float] = []
        self._summary_due = float("-inf")
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._ready = False                      # connected and subscribed to the confirmations
        self._connection = 0                     # grows with each connection: everything is resent on a new one
        self._down_since: float | None = time.monotonic()  # not yet connected counts as down from the start
        self._sends: dict[int, tuple[int, float, float]] = {}   # seq -> (connection, last sent, wait before next)
        self._queued_steady: dict[int, float] = {}               # seq -> when it was queued, monotonic
        self._in_flight: dict[int, int] = {}                     # mid -> seq, awaiting PUBACK
        self._at_broker: set[int] = set()
        now = time.monotonic()
        for entry in outbox.pending():
            self._queued_steady[entry.seq] = now  # from an earlier run: the deadline starts again now
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self._client.will_set(self.status_topic, "offline", qos=1, retain=True)
        if username is not None:
            self._client.username_pw_set(username, password)
        if ca_file is not None:
            self._client.tls_set(ca_certs=str(ca_file))          # the broker's name is checked against its cert
        self._client.reconnect_delay_set(min_delay=1, max_delay=10)
        self._client.on_connect = self._on_connect
        self._client.on_subscribe = self._on_subscribe
        self._client.on_disconnect = self._on_disconnect
        self._client.on_publish = self._on_publish
        self._client.on_message = self._on_message
        self._client.message_callback_add(self.confirm_topic, self._on_confirm)
        self._client.message_callback_add(self.command_topic, self._on_command)
        self._client.connect_async(host, port, keepalive=keepalive_s)
        self._client.loop_start()
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
        """Publish ``summary`` if one is due and the broker is there; else skip it (each replaces the last)."""
        now = time.monotonic()
        if now < self._summary_due:
            return
        self._summary_due = max(self._summary_due + self.summary_interval_s, now + self.summary_interval_s / 2)
        if not self._client.is_connected():
            self.summaries_skipped += 1
            return
        payload = json.dumps({**summary, "written_at": time.time(), "seq": self.outbox.last_seq})
        if self._client.publish(self.summary_topic, payload, qos=0, retain=True).rc == mqtt.MQTT_ERR_SUCCESS:
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
        published by the sender thread, never waited for."""
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
            return "broker" if entry.seq in self._at_broker else "bed"

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
            found["technical:ward-link"] = f"no connection to the ward broker for {down_s:.0f} s: alarms are " \
                                           f"shown only at this bed"
        elif overdue:
            who = "the ward station" if self.confirm else "the ward broker"
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
        """Give the sender up to ``timeout_s`` to hand what is waiting to the broker, say "offline", disconnect.
        Confirmations are not waited for: what is unconfirmed stays in the outbox and is resent at the next start."""
        deadline = time.monotonic() + timeout_s
        while self._ready and self._unsent() and time.monotonic() < deadline:
            self._wake.set()
            time.sleep(0.05)
        self._stopping.set()
        self._wake.set()
        self._worker.stop()
        self._worker.join()
        if self._client.is_connected():
            info = self._client.publish(self.status_topic, "offline", qos=1, retain=True)
            try:
                info.wait_for_publish(max(0.1, deadline - time.monotonic()))
            except (RuntimeError, ValueError) as exc:
                log.warning("ward link: could not publish the offline status: %s", exc)
        release(self._client)
        self.outbox.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _unsent(self) -> bool:
        """Whether an unconfirmed event has not reached the broker yet."""
        pending = [entry.seq for entry in self.outbox.pending()]
        with self._lock:
            return any(seq not in self._at_broker for seq in pending)

    # The sender thread.

    def _run(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(0.2)
            self._wake.clear()
            self.outbox.retry_writes()
            if self._ready:
                self._send_answers()
                self._send_due()
            self._worker.ok()

    def _send_answers(self) -> None:
        with self._lock:
            answers, self._answers = self._answers, []
        for payload in answers:
            info = self._client.publish(self.result_topic, payload, qos=1)
            if info.rc != mqtt.MQTT_ERR_SUCCESS:          # the station asks again, and is answered from the store
                log.warning("ward link: an answer to the ward station was not sent: %s", mqtt.error_string(info.rc))

    def _send_due(self) -> None:
        steady = time.monotonic()
        for entry in self.outbox.pending():
            with self._lock:
                if len(self._in_flight) >= MAX_IN_FLIGHT:
                    return
                connection, sent, wait = self._sends.get(entry.seq, (-1, 0.0, self.resend_after_s))
                if connection == self._connection and steady - sent < wait:
                    continue
                fresh = connection != self._connection
                self._sends[entry.seq] = (self._connection, steady,
                                          self.resend_after_s if fresh else min(2 * wait, MAX_RESEND_S))
            payload = json.dumps({**entry.event, "bed_id": self.bed_id, "seq": entry.seq})
            info = self._client.publish(self.topics[entry.event["type"]], payload, qos=1)
            if info.rc != mqtt.MQTT_ERR_SUCCESS:
                return                                  # the connection went: all is resent on the next one
            with self._lock:
                self._in_flight[info.mid] = entry.seq
            self.published += 1

    # paho's network thread.

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            log.warning("ward link: the broker refused the connection: %s", reason_code)
            return
        client.publish(self.status_topic, "online", qos=1, retain=True)
        client.subscribe(self.confirm_topic, qos=1)
        # Apart: a broker whose ACL predates the ward's commands refuses this one, and must still get the alarms.
        self._command_subscription = client.subscribe(self.command_topic, qos=1)[1]

    def _on_subscribe(self, client, userdata, mid, reason_codes, properties) -> None:
        if mid == self._command_subscription:
            if any(code.is_failure for code in reason_codes):
                log.error("ward link: the broker refused %s (%s): the ward station's commands cannot reach this "
                          "bed; write its ACL again with appliance ward-broker", self.command_topic, reason_codes)
            return
        if any(code.is_failure for code in reason_codes):
            log.error("ward link: the broker refused the confirmations' topic %s: %s", self.confirm_topic,
                      reason_codes)
            return
        with self._lock:
            self._ready, self._down_since = True, None
            self._connection += 1
            self._in_flight.clear()
        self._wake.set()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        with self._lock:
            if self._ready or self._down_since is None:
                self._down_since = time.monotonic()
            self._ready = False
            self._in_flight.clear()

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        with self._lock:
            seq = self._in_flight.pop(mid, None)
            if seq is None:
                return
            self._at_broker.add(seq)
        if not self.confirm:
            self._confirmed(seq, "broker")

    def _on_message(self, client, userdata, message) -> None:
        log.warning("ward link: unexpected message on %s ignored", message.topic)

    def _on_confirm(self, client, userdata, message) -> None:
        try:
            body = json.loads(message.payload)
            seq, station = body["seq"], body["station"]
            if not isinstance(seq, int) or isinstance(seq, bool) or not isinstance(station, str) or not station:
                raise ValueError(f"seq must be an integer and station a name, got {seq!r} and {station!r}")
        except (ValueError, TypeError, KeyError) as exc:
            log.warning("ward link: bad confirmation ignored: %s", exc)
            return
        self._confirmed(seq, station)

    def _on_command(self, client, userdata, message) -> None:
        try:
            command = parse_command(message.payload, self.bed_id)
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
            self._at_broker.discard(seq)
            self.confirmed += 1
            if queued is not None:
                self.confirm_latencies_s = [*self.confirm_latencies_s[-999:], time.monotonic() - queued]


def release(client: mqtt.Client) -> None:
    """Disconnect ``client``, stop its network thread and close its wake-up socket pair, which paho would close
    only when the client is collected: in a reference cycle that can come after the sockets' own finalisers,
    which then warn of unclosed sockets."""
    client.disconnect()
    client.loop_stop()
    client._reset_sockets(sockpair_only=True)     # private: paho has no public call for it
