"""The ward station's core: one state per bed, kept from the topics the bedside monitors publish.

Each bed's daemon publishes through its ``WardLink`` (topics and payloads in
``appliance.alerts.wardlink``): a retained ``status``, a retained ``summary``
about once a second, and every ``alarm`` and ``turn`` event. The station
subscribes to them all for every bed under one topic prefix:

- ``status`` and ``summary`` at QoS 0: each replaces the last, and the retained
  copy tells a station that has just started where every bed stands.
- ``alarm`` and ``turn`` (and ``episode``: admissions and discharges) at QoS 1
  on a persistent session (a fixed client id, clean session off), so events
  published while the station was briefly away are held by the broker and
  delivered when it is back.

A broker's PUBACK only says the broker has an event, so a bed keeps each one
until the station confirms it, and resends it until then. Every event carries
its ``bed_id`` and ``seq``: numbered per bed from 1, one more per event, never
reused, the same in a resend. Resends and redeliveries can come in any order
and any number of times, so the station applies each (bed, ``seq``) once, and
for each message of an event it has taken (a repeat too: the bed may have lost
the first confirmation), once the screen's state has it, publishes::

    <prefix>/<bed_id>/confirm   QoS 1, not retained
                                {seq, station: <client id>, confirmed_at: <unix time>}

A payload refused as bad is never confirmed.

What the station makes of the messages (summaries, events, the order by ``seq``,
when a bed is offline) is :class:`~appliance.ward.board.WardBoard`'s.

Nurses at the station can also act on a bed (acknowledge an alarm, record a
turn): with a command journal the station sends them through
:class:`~appliance.ward.commands.CommandSender` on ``<prefix>/<bed_id>/command``
and takes the beds' answers from ``<prefix>/<bed_id>/command-result``
(payloads in ``appliance.alerts.ward_commands``).

A bed is offline when its status says so (a clean stop at once; a dead
connection when the broker gives its last will, 1.5 keep-alives later) or when
nothing came from it for ``stale_after_s``: a monitor whose loop has hung can
still hold its connection. Payloads that are not what the topics promise are
counted and logged, never raised: one broken bed must not blind the station
to the rest of the ward.
"""

from __future__ import annotations

import json
import logging
import socket
import sqlite3
import threading
import time

import paho.mqtt.client as mqtt

from appliance.alerts.events import EVENT_TYPES
from appliance.alerts.ward_commands import COMMAND_TOPIC, RESULT_TOPIC
from appliance.ward.board import WardBoard
from appliance.ward.commands import DEFAULT_EXPIRY_S, DEFAULT_RESEND_S, CommandSender
from appliance.ward.config import WardConfig
from appliance.ward.journal import CommandJournal

log = logging.getLogger(__name__)


class WardStation:
    """Subscribes to every bed under ``topic_prefix`` on the broker at ``host``:``port`` and keeps their state.

    ``client_id`` names the persistent session, so it must stay the same across
    restarts and differ between stations, and it names the station in its
    confirmations. ``tls`` takes paho's ``tls_set`` arguments (``ca_certs``,
    ``certfile``, ``keyfile``). ``stale_after_s`` defaults to three summary
    intervals plus ``appliance.ward.board.STALE_MARGIN_S``. Counters: ``messages``, ``bad_payloads``,
    ``confirmations_sent``; ``version`` grows with every message taken, so a
    screen can tell that something changed without comparing the beds.
    ``journal`` lets the station's nurses send commands to beds (``commands``,
    a :class:`CommandSender`, is None without one); ``command_expiry_s`` and
    ``resend_after_s`` are its timings.
    """

    def __init__(self, host: str, port: int, *, topic_prefix: str = "appliance", keepalive_s: int = 30,
                 client_id: str | None = None, username: str | None = None, password: str | None = None,
                 tls: dict | None = None, summary_interval_s: float = 1.0, stale_after_s: float | None = None,
                 journal: CommandJournal | None = None, command_expiry_s: float = DEFAULT_EXPIRY_S,
                 resend_after_s: float = DEFAULT_RESEND_S):
        if any(c in topic_prefix for c in "+#") or not topic_prefix:
            raise ValueError(f"topic_prefix must be a topic without wildcards, got {topic_prefix!r}")
        self.topic_prefix = topic_prefix
        self.board = WardBoard(summary_interval_s, stale_after_s)
        self.stale_after_s = self.board.stale_after_s
        self.subscriptions = [(f"{topic_prefix}/+/status", 0), (f"{topic_prefix}/+/summary", 0),
                              *((f"{topic_prefix}/+/{kind}", 1) for kind in (*EVENT_TYPES, RESULT_TOPIC))]
        self.client_id = client_id or f"ward-station-{socket.gethostname()}"
        self.confirmations_sent = 0
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id, clean_session=False)
        self.commands = None if journal is None else CommandSender(
            journal, self._publish_command, self.client_id, expiry_s=command_expiry_s,
            resend_after_s=resend_after_s, on_change=self.board.changed)
        if username is not None:
            self._client.username_pw_set(username, password)
        if tls is not None:
            self._client.tls_set(**tls)
        self._client.reconnect_delay_set(min_delay=1, max_delay=10)
        self._client.on_connect = self._on_connect
        self._client.on_subscribe = self._on_subscribe
        self._client.on_disconnect = self._on_disconnect
        self._client.on_message = self._on_message
        self._client.connect_async(host, port, keepalive=keepalive_s)
        self._client.loop_start()

    @classmethod
    def from_config(cls, config: WardConfig, journal: CommandJournal | None = None) -> WardStation:
        broker = config.broker
        if broker is None:
            raise ValueError("the configuration names the hospital engine, not a broker: use EngineStation")
        return cls(broker.host, broker.port, topic_prefix=broker.topic_prefix, keepalive_s=broker.keepalive_s,
                   client_id=config.client_id, username=broker.username, password=broker.password(),
                   tls=None if broker.ca_file is None else {"ca_certs": str(broker.ca_file)},
                   summary_interval_s=config.summary_interval_s, journal=journal,
                   command_expiry_s=config.command_expiry_s)

    @property
    def connected(self) -> bool:
        """Connected to the broker and subscribed: the beds' states are current."""
        return self._subscribed.is_set()

    def wait_subscribed(self, timeout_s: float = 10.0) -> bool:
        """True once the station is connected and subscribed, False if that took more than ``timeout_s``."""
        return self._subscribed.wait(timeout_s)

    @property
    def messages(self) -> int:
        return self.board.messages

    @property
    def bad_payloads(self) -> int:
        return self.board.bad_payloads

    @property
    def version(self) -> int:
        return self.board.version

    def beds(self, *, events: bool = True) -> list[dict]:
        """Every bed, alarming ones first (:meth:`WardBoard.beds`)."""
        return self.board.beds(events=events)

    def online_flags(self) -> tuple[bool, ...]:
        return self.board.online_flags()

    def paging(self) -> list[dict]:
        """No notification service pages a ward broker's alarms: none to show (:meth:`WardBoard.paging`)."""
        return self.board.paging()

    def close(self) -> None:
        """Disconnect; the broker keeps the session, and the events for it, until the station is back. Commands
        not yet answered stay in the journal, sent again at the next start."""
        if self.commands is not None:
            self.commands.close()
        self._client.disconnect()
        self._client.loop_stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # paho's network thread.

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            log.warning("ward: broker refused the connection: %s", reason_code)
            return
        client.subscribe(self.subscriptions)

    def _on_subscribe(self, client, userdata, mid, reason_codes, properties) -> None:
        refused = [code for code in reason_codes if code.is_failure]
        if refused:
            log.error("ward: broker refused subscriptions: %s", refused)
            return
        self._subscribed.set()
        if self.commands is not None:
            self.commands.connected(True)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        self._subscribed.clear()
        if self.commands is not None:
            self.commands.connected(False)

    def _publish_command(self, bed_id: str, payload: str) -> bool:
        return self._client.publish(f"{self.topic_prefix}/{bed_id}/{COMMAND_TOPIC}", payload,
                                    qos=1).rc == mqtt.MQTT_ERR_SUCCESS

    def _on_message(self, client, userdata, message) -> None:
        try:
            bed_id, kind = self._parse_topic(message.topic)
            if kind == RESULT_TOPIC:
                if self.commands is None:
                    raise ValueError("an answer to a command, but this station sends none")
                try:
                    self.commands.take_answer(bed_id, message.payload)
                except sqlite3.Error as exc:          # the bed answers the next resend too
                    log.error("ward: %s's answer not journalled: %s", bed_id, exc)
                return
        except (ValueError, TypeError, UnicodeDecodeError) as exc:  # json's errors are ValueErrors
            self.board.refused(message.topic, exc)
            return
        body = self.board.take(bed_id, kind, message.payload)
        if body is None:
            return
        if kind in EVENT_TYPES:
            assert isinstance(body, dict)
            self._confirm(bed_id, body["seq"])
        elif kind == "status" and body == "online" and self.commands is not None:
            self.commands.bed_online(bed_id)

    def _confirm(self, bed_id: str, seq: int) -> None:
        """Tell the bed its event ``seq`` is on the screen; if this is lost the bed resends and is told again."""
        payload = json.dumps({"seq": seq, "station": self.client_id, "confirmed_at": time.time()})
        info = self._client.publish(f"{self.topic_prefix}/{bed_id}/confirm", payload, qos=1)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            log.warning("ward: confirmation of %s seq %d not sent: %s", bed_id, seq, mqtt.error_string(info.rc))
            return
        with self._lock:
            self.confirmations_sent += 1

    def _parse_topic(self, topic: str) -> tuple[str, str]:
        parts = topic.removeprefix(self.topic_prefix + "/").split("/")
        if len(parts) != 2 or not parts[0]:
            raise ValueError(f"topic {topic!r} is not {self.topic_prefix}/<bed_id>/<kind>")
        return parts[0], parts[1]
