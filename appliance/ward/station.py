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

A summary carries the bed's whole set of open alarms and the highest ``seq``
the bed had given when it was made; the alarms reflect every event up to it.
Events with a higher ``seq`` are applied on top of it, so a new alarm shows as
soon as its event arrives instead of at the next summary; a lower one is kept
for the event list but not applied over the summary. Order is judged by ``seq``,
never by the bed's ``time_s``, which a clock step can send back: each alarm
remembers the ``seq`` of the last event applied to it, and an older event for it
changes nothing.

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

import copy
import json
import logging
import socket
import sqlite3
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import paho.mqtt.client as mqtt

from appliance.alerts.alarms import AWAITING_ACK, PRIORITIES
from appliance.alerts.events import EVENT_TYPES, Event
from appliance.alerts.ward_commands import RESULT_TOPIC
from appliance.ward.commands import DEFAULT_EXPIRY_S, DEFAULT_RESEND_S, CommandSender
from appliance.ward.config import WardConfig
from appliance.ward.journal import CommandJournal

log = logging.getLogger(__name__)

STALE_MARGIN_S = 1.0
"""Beyond three missed summaries, the time a late one may still be on its way. With 1 s summaries a hung bed
shows offline 4 s after its last one, so within the least keep-alive a bed may set (5 s) even when it hung
just after a summary and the screen looks a poll later."""

EVENTS_KEPT = 50
"""Latest events kept per bed (for the screen, the latency record, and to replay over a summary)."""

SEEN_KEPT = 1000
"""Event seqs remembered per bed to drop repeats: far more than a retry or a restart can repeat."""

ALARM_FIELDS = ("alarm_id", "key", "priority", "state", "message", "acknowledged_by")


@dataclass
class BedState:
    """What the station knows of one bed; times are the station's wall clock (``time.time()``), for display,
    but whether a bed is still heard from is judged on the monotonic clock, which a clock set back cannot
    stop."""

    bed_id: str
    status: str | None = None                 # "online" or "offline", as the bed (or its last will) said
    last_heard_at: float | None = None        # any message at all
    last_heard_steady: float | None = None    # the same moment on time.monotonic()
    summary: dict | None = None
    summary_at: float | None = None
    open_alarms: dict[int, dict] = field(default_factory=dict)
    alarm_seqs: dict[int, int] = field(default_factory=dict)  # alarm_id -> seq of the last event applied to it
    events: deque = field(default_factory=lambda: deque(maxlen=EVENTS_KEPT))  # each with its "received_at"
    seen: dict[int, None] = field(default_factory=dict)                       # an ordered set of event seqs
    duplicates: int = 0

    def online(self, steady_now: float, stale_after_s: float) -> bool:
        """Not offline, and heard from within ``stale_after_s`` (``steady_now`` is ``time.monotonic()``)."""
        return (self.status != "offline" and self.last_heard_steady is not None
                and steady_now - self.last_heard_steady <= stale_after_s)

    def highest_priority(self) -> str | None:
        ranks = [PRIORITIES.index(a["priority"]) for a in self.open_alarms.values() if a["priority"] in PRIORITIES]
        return PRIORITIES[max(ranks)] if ranks else None

    def take_summary(self, summary: dict, now: float) -> None:
        """The summary's alarms become the open set, with the events newer than it applied again on top, in
        ``seq`` order."""
        self.summary, self.summary_at = summary, now
        self.open_alarms = {a["alarm_id"]: {k: a.get(k) for k in ALARM_FIELDS} for a in summary["alarms"]}
        self.alarm_seqs = {}
        for event in sorted((e for e in self.events if e["seq"] > summary["seq"]), key=lambda e: e["seq"]):
            self.apply(event)

    def take_event(self, event: dict) -> bool:
        """Record ``event`` (with its ``received_at``); False for a repeat of its ``seq``, which changes nothing."""
        if event["seq"] in self.seen:
            self.duplicates += 1
            return False
        self.seen[event["seq"]] = None
        if len(self.seen) > SEEN_KEPT:
            del self.seen[next(iter(self.seen))]
        self.events.append(event)
        if self.summary is None or event["seq"] > self.summary["seq"]:
            self.apply(event)
        return True

    def apply(self, event: dict) -> None:
        """Change the open alarms as an alarm event says, unless its alarm already shows a later event; events of
        no one alarm change nothing."""
        if event["type"] != "alarm" or event["alarm_id"] is None:
            return
        if self.alarm_seqs.get(event["alarm_id"], 0) > event["seq"]:
            return
        self.alarm_seqs[event["alarm_id"]] = event["seq"]
        if event["kind"] == "ended":
            self.open_alarms.pop(event["alarm_id"], None)
            return
        alarm = self.open_alarms.setdefault(event["alarm_id"], {"alarm_id": event["alarm_id"], "key": event["key"],
                                                                 "state": "active", "acknowledged_by": None})
        alarm["priority"], alarm["message"] = event["priority"], event["message"]
        if event["kind"] in ("raised", "reactivated"):
            alarm["state"] = "active"
        elif event["kind"] == AWAITING_ACK:
            alarm["state"] = AWAITING_ACK
        elif event["kind"] == "acknowledged":
            alarm["acknowledged_by"] = event["user"]


class WardStation:
    """Subscribes to every bed under ``topic_prefix`` on the broker at ``host``:``port`` and keeps their state.

    ``client_id`` names the persistent session, so it must stay the same across
    restarts and differ between stations, and it names the station in its
    confirmations. ``tls`` takes paho's ``tls_set`` arguments (``ca_certs``,
    ``certfile``, ``keyfile``). ``stale_after_s`` defaults to three summary
    intervals plus ``STALE_MARGIN_S``. Counters: ``messages``, ``bad_payloads``,
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
        self.stale_after_s = 3 * summary_interval_s + STALE_MARGIN_S if stale_after_s is None else stale_after_s
        self.subscriptions = [(f"{topic_prefix}/+/status", 0), (f"{topic_prefix}/+/summary", 0),
                              *((f"{topic_prefix}/+/{kind}", 1) for kind in (*EVENT_TYPES, RESULT_TOPIC))]
        self.client_id = client_id or f"ward-station-{socket.gethostname()}"
        self.messages = self.bad_payloads = self.confirmations_sent = self.version = 0
        self._beds: dict[str, BedState] = {}
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id, clean_session=False)
        self.commands = None if journal is None else CommandSender(
            journal, self._publish_command, topic_prefix, self.client_id, expiry_s=command_expiry_s,
            resend_after_s=resend_after_s, on_change=self._changed)
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

    def beds(self, *, events: bool = True) -> list[dict]:
        """Every bed as a plain dict: high, then medium, then low alarms first, then the offline beds, then the
        rest, each group by bed id. ``events=False`` leaves out each bed's latest events, the costly part to
        copy, for a screen that polls."""
        with self._lock:
            beds = [self._view(bed, time.monotonic(), events) for bed in self._beds.values()]
        return sorted(beds, key=lambda b: (_rank(b), b["bed_id"]))

    def online_flags(self) -> tuple[bool, ...]:
        """Each bed's ``online``, in no particular order but stable: cheap enough to poll."""
        with self._lock:
            return tuple(bed.online(time.monotonic(), self.stale_after_s) for bed in self._beds.values())

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

    def _view(self, bed: BedState, steady_now: float, events: bool) -> dict:
        alarms = sorted(bed.open_alarms.values(),
                        key=lambda a: (-PRIORITIES.index(a["priority"]) if a["priority"] in PRIORITIES else 1,
                                       a["alarm_id"]))
        return {"bed_id": bed.bed_id, "online": bed.online(steady_now, self.stale_after_s), "status": bed.status,
                "last_heard_at": bed.last_heard_at, "summary": copy.deepcopy(bed.summary),
                "summary_at": bed.summary_at, "alarms": copy.deepcopy(alarms),
                "highest_priority": bed.highest_priority(),
                "events": copy.deepcopy(list(bed.events)) if events else None,
                "duplicates": bed.duplicates}

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

    def _publish_command(self, topic: str, payload: str) -> bool:
        return self._client.publish(topic, payload, qos=1).rc == mqtt.MQTT_ERR_SUCCESS

    def _changed(self) -> None:
        with self._lock:
            self.version += 1

    def _on_message(self, client, userdata, message) -> None:
        now = time.time()
        try:
            bed_id, kind = self._parse_topic(message.topic)
            if kind == "status":
                status = message.payload.decode()
                if status not in ("online", "offline"):
                    raise ValueError(f"status must be 'online' or 'offline', got {status[:40]!r}")
            elif kind == RESULT_TOPIC:
                if self.commands is None:
                    raise ValueError("an answer to a command, but this station sends none")
                try:
                    self.commands.take_answer(bed_id, message.payload)
                except sqlite3.Error as exc:          # the bed answers the next resend too
                    log.error("ward: %s's answer not journalled: %s", bed_id, exc)
                return
            else:
                body = json.loads(message.payload)
                body = _summary(body, bed_id) if kind == "summary" else _event(body, bed_id, kind)
        except (ValueError, TypeError, UnicodeDecodeError) as exc:  # json's errors are ValueErrors
            with self._lock:
                self.bad_payloads += 1
            log.warning("ward: bad payload on %s ignored: %s", message.topic, exc)
            return
        with self._lock:
            self.messages += 1
            self.version += 1
            bed = self._beds.setdefault(bed_id, BedState(bed_id))
            bed.last_heard_at, bed.last_heard_steady = now, time.monotonic()
            if kind == "status":
                bed.status = status
            elif kind == "summary":
                bed.take_summary(body, now)
            else:
                bed.take_event({**body, "received_at": now})
        if kind in EVENT_TYPES:
            self._confirm(bed_id, body["seq"])
        elif kind == "status" and status == "online" and self.commands is not None:
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


def _rank(bed: dict) -> int:
    """Sort rank: high 0, medium 1, low 2, offline 3, the rest 4."""
    if bed["highest_priority"] is not None:
        return len(PRIORITIES) - 1 - PRIORITIES.index(bed["highest_priority"])
    return len(PRIORITIES) if not bed["online"] else len(PRIORITIES) + 1


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_seq(seq, least: int, what: str) -> None:
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < least:
        raise ValueError(f"{what} seq must be an integer of {least} or more, got {seq!r}")


def _summary(body, bed_id: str) -> dict:
    """``body`` if it is a summary of ``bed_id`` as the notifier writes it; else ValueError saying what is wrong."""
    if not isinstance(body, dict):
        raise TypeError(f"a summary must be a JSON object, got {type(body).__name__}")
    if body.get("bed_id") != bed_id:
        raise ValueError(f"summary of bed {body.get('bed_id')!r} on bed {bed_id!r}'s topic")
    _check_seq(body.get("seq"), 0, "summary")
    if not _number(body.get("time_s")):
        raise ValueError(f"summary time_s must be a number, got {body.get('time_s')!r}")
    if body.get("peak_mmhg") is not None and not _number(body["peak_mmhg"]):
        raise ValueError(f"summary peak_mmhg must be a number or null, got {body['peak_mmhg']!r}")
    if not isinstance(body.get("regions"), list) or not all(isinstance(r, dict) for r in body["regions"]):
        raise ValueError("summary regions must be a list of objects")
    if not isinstance(body.get("alarms"), list):
        raise TypeError("summary alarms must be a list")
    for alarm in body["alarms"]:
        if not isinstance(alarm, dict) or not isinstance(alarm.get("alarm_id"), int) \
                or alarm.get("priority") not in PRIORITIES:
            raise ValueError(f"summary alarm {alarm!r} needs an integer alarm_id and a priority in {PRIORITIES}")
    return body


def _event(body, bed_id: str, kind: str) -> dict:
    """``body`` if it is an Event of type ``kind`` of ``bed_id`` as the notifier writes it, with its ``bed_id`` and
    ``seq``; else ValueError saying what is wrong."""
    if not isinstance(body, dict):
        raise TypeError(f"an event must be a JSON object, got {type(body).__name__}")
    if body.get("bed_id") != bed_id:
        raise ValueError(f"event of bed {body.get('bed_id')!r} on bed {bed_id!r}'s topic")
    _check_seq(body.get("seq"), 1, "event")
    Event(**{k: v for k, v in body.items() if k not in ("bed_id", "seq")})  # TypeError on missing or unknown fields
    if body["type"] != kind:
        raise ValueError(f"{body['type']!r} event on the {kind} topic")
    if not _number(body["time_s"]) or not isinstance(body["kind"], str):
        raise ValueError(f"event time_s must be a number and kind a string, got {body['time_s']!r}, "
                         f"{body['kind']!r}")
    if body["alarm_id"] is not None and (not isinstance(body["alarm_id"], int) or isinstance(body["alarm_id"], bool)):
        raise ValueError(f"event alarm_id must be an integer or null, got {body['alarm_id']!r}")
    if kind == "alarm" and body["alarm_id"] is not None and body["priority"] not in PRIORITIES:
        raise ValueError(f"alarm event priority must be one of {PRIORITIES}, got {body['priority']!r}")
    return body
