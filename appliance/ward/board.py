"""What a ward station knows of its beds, whatever carries their messages: one state per bed, kept from each
bed's status, summary and events, for the station's screen.

A summary carries the bed's whole set of open alarms and the highest ``seq``
the bed had given when it was made; the alarms reflect every event up to it.
Events with a higher ``seq`` are applied on top of it, so a new alarm shows as
soon as its event arrives instead of at the next summary; a lower one is kept
for the event list but not applied over the summary. Order is judged by ``seq``,
never by the bed's ``time_s``, which a clock step can send back: each alarm
remembers the ``seq`` of the last event applied to it, and an older event for it
changes nothing.

A bed is offline when its status says so or when nothing came from it for
``stale_after_s``: a monitor whose loop has hung can still hold its connection.
Payloads that are not what the bed promises are counted and logged, never
raised: one broken bed must not blind the station to the rest of the ward.

On the hospital engine a notification service records what became of each
alarm change it paged (``appliance.hospital.notify``); the board keeps each
alarm's latest record per service, and shows it with the alarm while it is open.
A record may come before its bed is heard from (read back at a station's start)
or twice (read back and heard live): it is kept either way, and shown once.

Each service also says, at its own pace, whether its pages go out; the board
keeps the latest word of each service it heard from or has a record of, and
shows a service that has not said anything for a few of its periods as unknown,
never as delivering: the nurses must not trust pages that may not be sent.
"""

from __future__ import annotations

import copy
import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from appliance.alerts.alarms import AWAITING_ACK, PRIORITIES
from appliance.alerts.events import EVENT_TYPES, Event

log = logging.getLogger(__name__)

STALE_MARGIN_S = 1.0
"""Beyond three missed summaries, the time a late one may still be on its way. With 1 s summaries a hung bed
shows offline 4 s after its last one, so within the least keep-alive a bed may set (5 s) even when it hung
just after a summary and the screen looks a poll later."""

EVENTS_KEPT = 50
"""Latest events kept per bed (for the screen, the latency record, and to replay over a summary)."""

SEEN_KEPT = 1000
"""Event seqs remembered per bed to drop repeats: far more than a retry or a restart can repeat."""

PAGES_KEPT = 100
"""Alarms per bed whose pages are remembered: far more than a bed has open at once."""

PAGE_OUTCOMES = ("paged", "refused")

PAGING_PERIODS_MISSED = 3
"""A notification service not heard for this many of its periods (plus ``STALE_MARGIN_S``) is shown unknown."""

PAGING_FIRST_WORD_S = 20.0
"""How long a service known only from its records may take to be heard before it is shown unknown: a few of its
periods at the services' default pace (``appliance.hospital.notify.STATUS_EVERY_S``), so a station just started
does not flash a warning before the first word comes."""

DELIVERING, NOT_DELIVERING, UNKNOWN = "delivering", "not delivering", "unknown"

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


@dataclass
class PagingState:
    """What the station heard of one notification service: its latest status (None before the first), when it
    was heard (wall clock, for display; monotonic, to judge silence) and when the station learnt of it."""

    known_steady: float
    status: dict | None = None
    heard_at: float | None = None
    heard_steady: float | None = None

    def view(self, name: str, steady_now: float) -> dict:
        status = self.status
        if status is not None and self.heard_steady is not None and \
                steady_now - self.heard_steady <= PAGING_PERIODS_MISSED * status["every_s"] + STALE_MARGIN_S:
            return {"notifier": name, "state": DELIVERING if status["delivering"] else NOT_DELIVERING,
                    "since": status["since"], "reason": status["reason"], "heard_at": self.heard_at}
        if status is None and steady_now - self.known_steady <= PAGING_FIRST_WORD_S:
            return {"notifier": name, "state": None}            # not judged yet: left out
        return {"notifier": name, "state": UNKNOWN, "since": self.heard_at, "reason": "", "heard_at": self.heard_at}


class WardBoard:
    """Every bed's state as its messages come, from any thread. ``stale_after_s`` defaults to three summary
    intervals plus ``STALE_MARGIN_S``. Counters: ``messages``, ``bad_payloads``; ``version`` grows with every
    message taken, so a screen can tell that something changed without comparing the beds. ``steady_clock``
    (``time.monotonic``) judges silences; a test gives its own."""

    def __init__(self, summary_interval_s: float = 1.0, stale_after_s: float | None = None, *,
                 steady_clock: Callable[[], float] = time.monotonic):
        self.steady_clock = steady_clock
        self.stale_after_s = 3 * summary_interval_s + STALE_MARGIN_S if stale_after_s is None else stale_after_s
        self.messages = self.bad_payloads = self.version = 0
        self._beds: dict[str, BedState] = {}
        self._pages: dict[str, dict[int, dict[str, dict]]] = {}  # bed -> alarm_id -> service -> its latest record
        self._paging: dict[str, PagingState] = {}
        self._lock = threading.Lock()

    def take(self, bed_id: str, kind: str, payload: bytes, now: float | None = None) -> dict | str | None:
        """Take bed ``bed_id``'s message of ``kind`` (``status``, ``summary`` or an event type): the status, the
        checked summary or event, or None when it is bad (counted and logged, never raised)."""
        now = time.time() if now is None else now
        try:
            if kind == "status":
                body: dict | str = payload.decode()
                if body not in ("online", "offline"):
                    raise ValueError(f"status must be 'online' or 'offline', got {body[:40]!r}")
            elif kind == "summary":
                body = _summary(json.loads(payload), bed_id)
            elif kind in EVENT_TYPES:
                body = _event(json.loads(payload), bed_id, kind)
            else:
                raise ValueError(f"no message of kind {kind!r} is expected from a bed")
        except (ValueError, TypeError, UnicodeDecodeError) as exc:  # json's errors are ValueErrors
            self.refused(f"{bed_id}'s {kind}", exc)
            return None
        with self._lock:
            self.messages += 1
            self.version += 1
            bed = self._beds.setdefault(bed_id, BedState(bed_id))
            bed.last_heard_at, bed.last_heard_steady = now, self.steady_clock()
            if isinstance(body, str):
                bed.status = body
            elif kind == "summary":
                bed.take_summary(body, now)
            else:
                bed.take_event({**body, "received_at": now})
        return body

    def restore(self, bed_id: str, event: dict) -> None:
        """Show ``event`` again as the station had it before a restart, the bed not yet heard from."""
        with self._lock:
            self._beds.setdefault(bed_id, BedState(bed_id)).take_event(event)
            self.version += 1

    def refused(self, what: str, problem: Exception) -> None:
        """Count and log a message that is not what a bed promises."""
        with self._lock:
            self.bad_payloads += 1
        log.warning("ward: bad payload (%s) ignored: %s", what, problem)

    def _parsed(self, what: str, parse: Callable[[object, str], dict], payload: bytes, name: str) -> dict | None:
        """``parse`` of the JSON ``payload`` (a record of ``name``), or None, counted and logged, when it is bad."""
        try:
            return parse(json.loads(payload), name)
        except (ValueError, TypeError, UnicodeDecodeError) as exc:     # json's errors are ValueErrors
            self.refused(what, exc)
            return None

    def take_page(self, bed_id: str, payload: bytes) -> dict | None:
        """Take a notification service's record of bed ``bed_id``'s alarm change: the record, or None when it is
        bad (counted and logged, never raised). A record older than the one kept for its alarm and service, or
        of an event of no one alarm, changes nothing; the service becomes known to the board."""
        record = self._parsed(f"a page record of {bed_id}", _page, payload, bed_id)
        if record is None:
            return None
        with self._lock:
            self._paging.setdefault(record["notifier"], PagingState(self.steady_clock()))
            if record["alarm_id"] is None:
                return record
            pages = self._pages.setdefault(bed_id, {})
            kept = pages.setdefault(record["alarm_id"], {})
            if record["seq"] >= kept.get(record["notifier"], {"seq": 0})["seq"]:
                kept[record["notifier"]] = record
                self.version += 1
            if len(pages) > PAGES_KEPT:
                del pages[next(iter(pages))]
        return record

    def take_paging(self, notifier: str, payload: bytes, now: float | None = None) -> dict | None:
        """Take notification service ``notifier``'s word on whether its pages go out: the status, or None when it
        is bad (counted and logged, never raised)."""
        status = self._parsed(f"the paging status of {notifier}", _paging, payload, notifier)
        if status is None:
            return None
        with self._lock:
            state = self._paging.setdefault(notifier, PagingState(self.steady_clock()))
            if state.status is None or any(state.status[k] != status[k] for k in ("delivering", "since", "reason")):
                self.version += 1
            state.status, state.heard_steady = status, self.steady_clock()
            state.heard_at = time.time() if now is None else now
        return status

    def paging(self, steady_now: float | None = None) -> list[dict]:
        """Each notification service known, by name: its ``state`` (delivering, not delivering, or unknown when
        it has not said anything for too long), ``since`` when (for unknown: when last heard, or None), its
        ``reason`` and when it was last heard (``heard_at``, or None). ``steady_now`` is on ``steady_clock``."""
        steady_now = self.steady_clock() if steady_now is None else steady_now
        with self._lock:
            views = [state.view(name, steady_now) for name, state in sorted(self._paging.items())]
        return [view for view in views if view["state"] is not None]

    def changed(self) -> None:
        with self._lock:
            self.version += 1

    def beds(self, *, events: bool = True) -> list[dict]:
        """Every bed as a plain dict: high, then medium, then low alarms first, then the offline beds, then the
        rest, each group by bed id. ``events=False`` leaves out each bed's latest events, the costly part to
        copy, for a screen that polls."""
        with self._lock:
            beds = [self._view(bed, self._pages.get(bed.bed_id, {}), self.steady_clock(), events)
                    for bed in self._beds.values()]
        return sorted(beds, key=lambda b: (_rank(b), b["bed_id"]))

    def online_flags(self) -> tuple[bool, ...]:
        """Each bed's ``online``, in no particular order but stable: cheap enough to poll."""
        with self._lock:
            return tuple(bed.online(self.steady_clock(), self.stale_after_s) for bed in self._beds.values())

    def _view(self, bed: BedState, pages: dict[int, dict[str, dict]], steady_now: float, events: bool) -> dict:
        alarms = sorted(({**alarm, "pages": [{k: page[k] for k in ("notifier", "outcome", "status", "notified_at")}
                                              for _, page in sorted(pages.get(alarm["alarm_id"], {}).items())]}
                         for alarm in bed.open_alarms.values()),
                        key=lambda a: (-PRIORITIES.index(a["priority"]) if a["priority"] in PRIORITIES else 1,
                                       a["alarm_id"]))
        return {"bed_id": bed.bed_id, "online": bed.online(steady_now, self.stale_after_s), "status": bed.status,
                "last_heard_at": bed.last_heard_at, "summary": copy.deepcopy(bed.summary),
                "summary_at": bed.summary_at, "alarms": copy.deepcopy(alarms),
                "highest_priority": bed.highest_priority(),
                "events": copy.deepcopy(list(bed.events)) if events else None,
                "duplicates": bed.duplicates}


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


def _page(body, bed_id: str) -> dict:
    """``body`` if it is a notification service's record of one of ``bed_id``'s alarm changes; else ValueError
    saying what is wrong."""
    if not isinstance(body, dict):
        raise TypeError(f"a page record must be a JSON object, got {type(body).__name__}")
    if body.get("bed_id") != bed_id:
        raise ValueError(f"page record of bed {body.get('bed_id')!r} on bed {bed_id!r}'s subject")
    _check_seq(body.get("seq"), 1, "page record")
    alarm_id = body.get("alarm_id")
    if alarm_id is not None and (not isinstance(alarm_id, int) or isinstance(alarm_id, bool)):
        raise ValueError(f"page record alarm_id must be an integer or null, got {alarm_id!r}")
    if not isinstance(body.get("notifier"), str) or body.get("outcome") not in PAGE_OUTCOMES \
            or not _number(body.get("notified_at")) or not isinstance(body.get("status"), int):
        raise ValueError(f"page record needs a notifier, an outcome in {PAGE_OUTCOMES}, a status and notified_at, "
                         f"got {body!r:.200}")
    return body


def _paging(body, notifier: str) -> dict:
    """``body`` if it is notification service ``notifier``'s paging status; else ValueError saying what is wrong."""
    if not isinstance(body, dict):
        raise TypeError(f"a paging status must be a JSON object, got {type(body).__name__}")
    if body.get("notifier") != notifier:
        raise ValueError(f"paging status of {body.get('notifier')!r} on {notifier!r}'s subject")
    if not isinstance(body.get("delivering"), bool) or not _number(body.get("since")) \
            or not isinstance(body.get("reason"), str) or not _number(body.get("every_s")) or body["every_s"] <= 0:
        raise ValueError(f"paging status needs delivering (true or false), since, a reason and every_s over 0, "
                         f"got {body!r:.200}")
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
