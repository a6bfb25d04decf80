"""What the ward and hospital screens ask of the history: recent events, alarm counts per ward, a bed's pressure
and a ward's pressure trends; and how a screen connects to it, read-only.

Each is one indexed query on the partitioned tables, with the time bound that lets PostgreSQL skip every
partition outside it.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
from collections.abc import Callable, Iterator

import psycopg
from psycopg.rows import dict_row

CONNECT_TIMEOUT_S = 5
"""A screen gives up on a database that does not answer within this (libpq's ``connect_timeout``, whole seconds):
without it a connection to a host that is down waits for the operating system's TCP timeout, minutes."""


def connector(dsn: str) -> Callable[[], psycopg.Connection]:
    """How a screen reaches the history at ``dsn``: a new connection for each read, given up after
    ``CONNECT_TIMEOUT_S``."""
    return functools.partial(psycopg.connect, dsn, connect_timeout=CONNECT_TIMEOUT_S)


@contextlib.contextmanager
def reading(connect: Callable[[], psycopg.Connection]) -> Iterator[psycopg.Connection]:
    """A connection from ``connect()`` put in read-only mode before any query, closed afterwards: the screens
    read the history and never change it, whatever the role they log in as may do."""
    with connect() as db:
        db.read_only = True
        yield db


def recent_events(db: psycopg.Connection, since: dt.datetime, *, ward: str | None = None,
                  limit: int = 200) -> list[dict]:
    """Events stored since ``since``, newest first: a ward's, or the whole hospital's when ``ward`` is None."""
    if limit < 1:
        raise ValueError(f"limit must be at least 1, got {limit}")
    where = "stored_at >= %(since)s" + ("" if ward is None else " AND ward = %(ward)s")
    with db.cursor(row_factory=dict_row) as cursor:
        return cursor.execute(f"SELECT stored_at, ward, bed_id, seq, type, kind, priority, alarm_id, body FROM event "
                              f"WHERE {where} ORDER BY stored_at DESC, bed_id, seq DESC LIMIT %(limit)s",
                              {"since": since, "ward": ward, "limit": limit}).fetchall()


def alarm_counts(db: psycopg.Connection, since: dt.datetime) -> dict[str, dict[str, int]]:
    """For the hospital overview: per ward, how many alarms were raised since ``since``, by priority."""
    rows = db.execute("SELECT ward, coalesce(priority, 'none'), count(*) FROM event WHERE stored_at >= %s "
                      "AND type = 'alarm' AND kind = 'raised' GROUP BY 1, 2 ORDER BY 1, 2", (since,)).fetchall()
    counts: dict[str, dict[str, int]] = {}
    for ward, priority, count in rows:
        counts.setdefault(ward, {})[priority] = count
    return counts


def pressure_trend(db: psycopg.Connection, bed_id: str, since: dt.datetime,
                   until: dt.datetime | None = None) -> list[dict]:
    """``bed_id``'s minutes from ``since`` (to ``until``), oldest first."""
    with db.cursor(row_factory=dict_row) as cursor:
        return cursor.execute("SELECT minute, samples, maps, peak_max_mmhg, peak_last_mmhg, posture, region_max_mmhg, "
                              "region_dose FROM pressure_minute WHERE bed_id = %s AND minute >= %s "
                              "AND minute < coalesce(%s, 'infinity'::timestamptz) ORDER BY minute",
                              (bed_id, since, until)).fetchall()


def ward_trends(db: psycopg.Connection, ward: str,
                since: dt.datetime) -> dict[str, list[tuple[dt.datetime, float | None]]]:
    """For the ward screen's sparklines: each of ``ward``'s beds' minutes since ``since`` as (minute, highest
    peak in mmHg, None for a minute without a map), oldest first."""
    trends: dict[str, list[tuple[dt.datetime, float | None]]] = {}
    for bed, minute, peak in db.execute("SELECT bed_id, minute, peak_max_mmhg FROM pressure_minute WHERE ward = %s "
                                        "AND minute >= %s ORDER BY bed_id, minute", (ward, since)):
        trends.setdefault(bed, []).append((minute, peak))
    return trends


def open_alarms(db: psycopg.Connection, since: dt.datetime) -> list[dict]:
    """Alarms whose latest event since ``since`` is not their end, across the hospital, highest priority first then
    oldest first: each with its ward, bed, alarm id, priority (as last given), latest kind (raised, escalated,
    acknowledged, ...), when it was raised and its words. An alarm raised before ``since`` and still open is not
    seen: ``since`` is the overview's reach, a day by default, longer than any alarm stays unanswered."""
    with db.cursor(row_factory=dict_row) as cursor:
        rows = cursor.execute(
            "SELECT DISTINCT ON (bed_id, alarm_id) ward, bed_id, alarm_id, kind, stored_at AS changed_at, "
            "first_value(priority) OVER given AS priority, min(stored_at) OVER (PARTITION BY bed_id, alarm_id) "
            "AS raised_at, body->>'message' AS message, body->>'site' AS site "
            "FROM event WHERE type = 'alarm' AND alarm_id IS NOT NULL AND stored_at >= %s "
            "WINDOW given AS (PARTITION BY bed_id, alarm_id ORDER BY priority IS NULL, stored_at DESC, seq DESC) "
            "ORDER BY bed_id, alarm_id, stored_at DESC, seq DESC", (since,)).fetchall()
    rank = {"high": 0, "medium": 1, "low": 2}
    return sorted((row for row in rows if row["kind"] != "ended"),
                  key=lambda alarm: (rank.get(alarm["priority"], 3), alarm["raised_at"]))


def beds_heard(db: psycopg.Connection, since: dt.datetime) -> dict[str, dt.datetime]:
    """Each bed's last summary heard since ``since``: a bed missing here has said nothing in that time."""
    return dict(db.execute("SELECT bed_id, max(last_at) FROM pressure_minute WHERE minute >= %s GROUP BY bed_id",
                           (since,)).fetchall())
