"""Rows into the history: events once per ``(bed_id, seq)``, minutes merged into any earlier part of the same.

Each call is one transaction; the caller acknowledges the engine's messages only after it returned, so a
crash before the commit leaves nothing and the redelivery writes it, and a crash after the commit leaves the
rows and the redelivery finds their keys taken.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass

import psycopg
from psycopg.types.json import Jsonb

from appliance.hospital.history.schema import EVENTS, PRESSURE, ensure_partition
from appliance.hospital.history.trend import Minute


@dataclass(frozen=True)
class StoredEvent:
    """One event as the writer read it from a ward's stream."""

    stored_at: dt.datetime
    ward: str
    bed_id: str
    seq: int
    type: str
    body: dict


CLAIM_AND_INSERT = """
WITH claimed AS (
    INSERT INTO event_key (bed_id, seq, stored_at) VALUES (%(bed_id)s, %(seq)s, %(stored_at)s)
    ON CONFLICT DO NOTHING RETURNING bed_id)
INSERT INTO event (stored_at, ward, bed_id, seq, type, kind, priority, alarm_id, body)
SELECT %(stored_at)s, %(ward)s, %(bed_id)s, %(seq)s, %(type)s, %(kind)s, %(priority)s, %(alarm_id)s, %(body)s
FROM claimed"""

MERGE_MINUTE = """
INSERT INTO pressure_minute AS old (minute, ward, bed_id, samples, maps, peak_max_mmhg, peak_last_mmhg, posture,
                                    region_max_mmhg, region_dose, last_at)
VALUES (%(minute)s, %(ward)s, %(bed_id)s, %(samples)s, %(maps)s, %(peak_max_mmhg)s, %(peak_last_mmhg)s,
        %(posture)s, %(region_max_mmhg)s, %(region_dose)s, %(last_at)s)
ON CONFLICT (bed_id, minute) DO UPDATE SET
    samples = old.samples + excluded.samples,
    maps = old.maps + excluded.maps,
    peak_max_mmhg = greatest(old.peak_max_mmhg, excluded.peak_max_mmhg),
    region_max_mmhg = zone_max(old.region_max_mmhg, excluded.region_max_mmhg),
    peak_last_mmhg = CASE WHEN excluded.last_at > old.last_at THEN excluded.peak_last_mmhg ELSE old.peak_last_mmhg END,
    posture = CASE WHEN excluded.last_at > old.last_at THEN excluded.posture ELSE old.posture END,
    region_dose = CASE WHEN excluded.last_at > old.last_at THEN old.region_dose || excluded.region_dose
                       ELSE excluded.region_dose || old.region_dose END,
    last_at = greatest(old.last_at, excluded.last_at)"""


def write_events(db: psycopg.Connection, events: Sequence[StoredEvent]) -> int:
    """Store each event whose ``(bed_id, seq)`` is new, in one transaction; how many were new."""
    fresh = 0
    with db.transaction():
        for partition in {EVENTS.start(event.stored_at) for event in events}:
            ensure_partition(db, EVENTS, partition)
        for event in events:
            alarm_id = event.body.get("alarm_id")
            cursor = db.execute(CLAIM_AND_INSERT, {
                "stored_at": event.stored_at, "ward": event.ward, "bed_id": event.bed_id, "seq": event.seq,
                "type": event.type, "kind": str(event.body.get("kind", "")), "priority": event.body.get("priority"),
                "alarm_id": alarm_id if isinstance(alarm_id, int) and not isinstance(alarm_id, bool) else None,
                "body": Jsonb(event.body)})
            fresh += cursor.rowcount
    return fresh


def write_minutes(db: psycopg.Connection, minutes: Sequence[Minute]) -> None:
    """Store the minutes in one transaction, each merged with a row already there for its bed and minute."""
    with db.transaction():
        for partition in {PRESSURE.start(minute.minute) for minute in minutes}:
            ensure_partition(db, PRESSURE, partition)
        for minute in minutes:
            db.execute(MERGE_MINUTE, {
                "minute": minute.minute, "ward": minute.ward, "bed_id": minute.bed_id, "samples": minute.samples,
                "maps": minute.maps, "peak_max_mmhg": minute.peak_max_mmhg, "peak_last_mmhg": minute.peak_last_mmhg,
                "posture": minute.posture, "region_max_mmhg": Jsonb(minute.region_max_mmhg),
                "region_dose": Jsonb(minute.region_dose), "last_at": minute.last_at})
