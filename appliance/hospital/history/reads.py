"""What the ward and hospital screens ask of the history: recent events, alarm counts per ward, a bed's pressure
and a ward's pressure trends.

Each is one indexed query on the partitioned tables, with the time bound that lets PostgreSQL skip every
partition outside it.
"""

from __future__ import annotations

import datetime as dt

import psycopg
from psycopg.rows import dict_row


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
