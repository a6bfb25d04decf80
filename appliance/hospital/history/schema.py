"""The history's tables, their time partitions, and retention by dropping whole partitions.

``event`` holds every alarm, turn and episode event, partitioned by month on ``stored_at``, the time the ward's
stream stored it (the engine's clock, the same on every redelivery). PostgreSQL lets a unique key of a
partitioned table only include the partition key, which would make a bed's resend stored on another day a
second row; so ``event_key``, unpartitioned and narrow, holds each ``(bed_id, seq)`` once, and an event is
inserted only in the transaction that claims its key. ``pressure_minute`` holds one row per bed and minute,
partitioned by day (a 3,000-bed hospital writes 4.3 million rows a day; a month in one table would make
retention a mass delete). Partitions are made ahead by the writer and for any time it meets; a partition goes
when all of it is older than the retention, so data is kept for the policy's days and at most one partition
more.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import psycopg
from psycopg import sql

UTC = dt.UTC

SCHEMA = (
    """CREATE TABLE IF NOT EXISTS event (
        stored_at timestamptz NOT NULL,
        ward text NOT NULL,
        bed_id text NOT NULL,
        seq bigint NOT NULL,
        type text NOT NULL,
        kind text NOT NULL,
        priority text,
        alarm_id bigint,
        body jsonb NOT NULL
    ) PARTITION BY RANGE (stored_at)""",
    "CREATE INDEX IF NOT EXISTS event_by_time ON event (stored_at DESC)",
    "CREATE INDEX IF NOT EXISTS event_by_ward ON event (ward, stored_at DESC)",
    "CREATE INDEX IF NOT EXISTS event_by_bed ON event (bed_id, stored_at DESC)",
    """CREATE TABLE IF NOT EXISTS event_key (
        bed_id text NOT NULL,
        seq bigint NOT NULL,
        stored_at timestamptz NOT NULL,
        PRIMARY KEY (bed_id, seq)
    )""",
    "CREATE INDEX IF NOT EXISTS event_key_by_time ON event_key (stored_at)",
    """CREATE TABLE IF NOT EXISTS pressure_minute (
        minute timestamptz NOT NULL,
        ward text NOT NULL,
        bed_id text NOT NULL,
        samples smallint NOT NULL,
        maps smallint NOT NULL,
        peak_max_mmhg real,
        peak_last_mmhg real,
        posture text,
        region_max_mmhg jsonb NOT NULL,
        region_dose jsonb NOT NULL,
        last_at timestamptz NOT NULL,
        PRIMARY KEY (bed_id, minute)
    ) PARTITION BY RANGE (minute)""",
    "CREATE INDEX IF NOT EXISTS pressure_by_ward ON pressure_minute (ward, minute)",
    # The larger of two {zone: mmHg} objects, zone by zone: a minute written in two parts (a writer restarted
    # within it) keeps each zone's highest peak.
    """CREATE OR REPLACE FUNCTION zone_max(a jsonb, b jsonb) RETURNS jsonb LANGUAGE sql IMMUTABLE AS $$
        SELECT coalesce(jsonb_object_agg(key, top), '{}'::jsonb)
        FROM (SELECT key, max(value::float8) AS top
              FROM (SELECT * FROM jsonb_each(a) UNION ALL SELECT * FROM jsonb_each(b)) AS both_parts
              GROUP BY key) AS per_zone
    $$""",
)


@dataclass(frozen=True)
class Partitioned:
    """A partitioned table and the width of its partitions."""

    table: str
    monthly: bool

    def start(self, moment: dt.datetime) -> dt.datetime:
        """The start of the partition holding ``moment`` (UTC midnight of its day, or of its month's first)."""
        moment = moment.astimezone(UTC)
        day = moment.replace(hour=0, minute=0, second=0, microsecond=0)
        return day.replace(day=1) if self.monthly else day

    def end(self, start: dt.datetime) -> dt.datetime:
        if not self.monthly:
            return start + dt.timedelta(days=1)
        return (start + dt.timedelta(days=32)).replace(day=1)

    def name(self, start: dt.datetime) -> str:
        return f"{self.table}_{start:%Y%m%d}"


EVENTS = Partitioned("event", monthly=True)
PRESSURE = Partitioned("pressure_minute", monthly=False)
TABLES = (EVENTS, PRESSURE)


def create_schema(db: psycopg.Connection) -> None:
    """Make the tables, indexes and function if they are not there (the writer does this as the database's owner)."""
    with db.transaction():
        for statement in SCHEMA:
            db.execute(statement)


def partitions(db: psycopg.Connection, table: Partitioned) -> list[str]:
    """The names of ``table``'s partitions, oldest first."""
    rows = db.execute("SELECT child.relname FROM pg_inherits JOIN pg_class child ON child.oid = inhrelid "
                      "JOIN pg_class parent ON parent.oid = inhparent WHERE parent.relname = %s "
                      "ORDER BY child.relname", (table.table,)).fetchall()
    return [row[0] for row in rows]


def ensure_partition(db: psycopg.Connection, table: Partitioned, moment: dt.datetime) -> str:
    """The partition of ``table`` that holds ``moment``, made if missing."""
    start = table.start(moment)
    name = table.name(start)
    db.execute(sql.SQL("CREATE TABLE IF NOT EXISTS {} PARTITION OF {} FOR VALUES FROM ({}) TO ({})").format(
        sql.Identifier(name), sql.Identifier(table.table), sql.Literal(start), sql.Literal(table.end(start))))
    return name


def ensure_ahead(db: psycopg.Connection, now: dt.datetime, days: int = 2) -> list[str]:
    """Every partition from ``now`` to ``days`` ahead, so inserts at midnight do not wait for a new table."""
    made = []
    with db.transaction():
        for table in TABLES:
            for ahead in range(days + 1):
                name = ensure_partition(db, table, now + dt.timedelta(days=ahead))
                if name not in made:
                    made.append(name)
    return made


def drop_expired(db: psycopg.Connection, now: dt.datetime, events_days: int, pressure_days: int) -> list[str]:
    """Drop every partition wholly older than its retention, and the event keys as old; the names dropped."""
    dropped = []
    with db.transaction():
        for table, days in ((EVENTS, events_days), (PRESSURE, pressure_days)):
            cutoff = now.astimezone(UTC) - dt.timedelta(days=days)
            for name in partitions(db, table):
                start = dt.datetime.strptime(name.rpartition("_")[2], "%Y%m%d").replace(tzinfo=UTC)
                if table.end(start) <= cutoff:
                    db.execute(sql.SQL("DROP TABLE {}").format(sql.Identifier(name)))
                    dropped.append(name)
            if table is EVENTS:
                # the keys of exactly the events dropped: every partition before the cutoff's month went
                db.execute("DELETE FROM event_key WHERE stored_at < %s", (EVENTS.start(cutoff),))
    return dropped
