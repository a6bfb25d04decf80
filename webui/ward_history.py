"""The ward screen's look into the hospital history in PostgreSQL: each bed's highest peak pressure per minute, for
its sparkline, and the ward's events, over the station's look-back (a shift), so a nurse sees the last hours even
after the station was restarted or replaced.

It has its own endpoint, ``/api/ward/history``, which the screen polls every ``REFRESH_S``, rather than riding on
``/api/ward``: the live board is pushed on every change, several times a second, while a shift of minutes for
every bed is many times its size and changes once a minute. The answer is read at most once every ``REFRESH_S``
whichever screens ask, with one query for every bed's trend and one for the events, and kept until then; a
database that does not answer is kept as "unavailable" as long, so it costs one connection attempt a period,
and the live board never waits on it. Imported only for a station with ``[history]``: it needs the PostgreSQL
driver of the ``hospital`` extra.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
import time
from collections.abc import Callable

import psycopg
from flask import Blueprint, current_app, jsonify

from appliance.hospital.history.reads import reading, recent_events, ward_trends

log = logging.getLogger(__name__)
bp = Blueprint("ward_history", __name__)
REFRESH_S = 30.0
"""How often the history is read, and the screen asks: the trend gains a row a minute."""
EVENTS_SHOWN = 200
"""The ward's latest events in the look-back: more than a shift brings on a working ward. When the look-back holds
more, the answer says so (``events_cut``) and the screen says that older ones are not listed."""
EVENT_FIELDS = ("bed_id", "seq", "type", "kind", "priority", "alarm_id")


class WardHistory:
    """``ward``'s trends and events of the last ``look_back_h`` hours, through ``connect()`` (a new connection to
    the history), read again once the last answer is ``refresh_s`` old."""

    def __init__(self, connect: Callable[[], psycopg.Connection], ward: str, look_back_h: float, *,
                 refresh_s: float = REFRESH_S, clock: Callable[[], float] = time.time):
        self.connect, self.ward, self.look_back_h = connect, ward, look_back_h
        self.refresh_s, self.clock = refresh_s, clock
        self._lock = threading.Lock()
        self._answer: dict | None = None

    def view(self) -> dict:
        """The latest answer, read now if it is ``refresh_s`` old (one screen reads, the others wait for it)."""
        with self._lock:
            now = self.clock()
            if self._answer is None or now - self._answer["read_at"] >= self.refresh_s:
                self._answer = self._read(now)
            return self._answer

    def _read(self, now: float) -> dict:
        since_s = now - self.look_back_h * 3600.0
        answer = {"read_at": now, "since": since_s, "look_back_h": self.look_back_h}
        since = dt.datetime.fromtimestamp(since_s, dt.UTC)
        try:
            with reading(self.connect) as db:
                trends = ward_trends(db, self.ward, since)
                events = recent_events(db, since, ward=self.ward, limit=EVENTS_SHOWN + 1)     # one more: cut?
        except psycopg.Error as exc:
            log.warning("ward history: the history of %s is not readable, shown as unavailable until the next try "
                        "in %.0f s: %s", self.ward, self.refresh_s, str(exc).strip())
            return {**answer, "available": False, "trends": {}, "events": [], "events_cut": False}
        return {**answer, "available": True, "events_cut": len(events) > EVENTS_SHOWN,
                "trends": {bed: [[minute.timestamp(), None if peak is None else round(peak, 1)]
                                 for minute, peak in minutes] for bed, minutes in trends.items()},
                "events": [{"stored_at": event["stored_at"].timestamp(), **{k: event[k] for k in EVENT_FIELDS},
                            "message": event["body"].get("message")} for event in events[:EVENTS_SHOWN]]}


@bp.route("/api/ward/history")
def current():
    return jsonify(current_app.extensions["ward_history"].view())
