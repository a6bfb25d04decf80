"""The ward station's journal of the events it has applied: each bed's numbers, kept on disk before the station
confirms anything, so a station restarted (or killed) applies no event twice and can show what it had.

The engine gives a message again when the station died before acknowledging it, and a bed resends what it has no
confirmation for: both come back here as numbers already taken. Each event is written (``synchronous=FULL``)
before its confirmation leaves the station, so a confirmation never names an event the station could forget.

A notification service (``appliance.hospital.notify``) keeps one too, of the alarm changes it has paged: there each
event is written with what the gateway answered, after the gateway answered and before the service records it on
the engine, so a service restarted pages nothing again that the gateway had taken.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time

from appliance.hospital.engine import Delivery
from appliance.store.outbox import open_durable

SCHEMA = ("CREATE TABLE IF NOT EXISTS applied (bed_id TEXT NOT NULL, seq INTEGER NOT NULL, kind TEXT NOT NULL,"
          " event TEXT NOT NULL, applied_at REAL NOT NULL, PRIMARY KEY (bed_id, seq))",)


class AppliedJournal:
    """The journal in SQLite file ``path`` (made if missing); one connection, safe from several threads."""

    def __init__(self, path):
        self._lock = threading.Lock()
        self._db = open_durable(str(path), "the ward station's applied events",
                                "events given again would be shown again", self._prepare)

    @staticmethod
    def _prepare(db: sqlite3.Connection) -> None:
        for statement in SCHEMA:
            db.execute(statement)

    def take(self, delivery: Delivery) -> bool:
        """Journal ``delivery``; False, writing nothing, when its bed's number was taken before."""
        with self._lock:
            return self._db.execute(
                "INSERT OR IGNORE INTO applied (bed_id, seq, kind, event, applied_at) VALUES (?, ?, ?, ?, ?)",
                (delivery.bed, delivery.seq, delivery.kind, json.dumps(delivery.event, allow_nan=False),
                 time.time())).rowcount == 1

    def event(self, bed_id: str, seq: int) -> dict | None:
        """What was journalled as bed ``bed_id``'s event ``seq``, or None when that number was never taken."""
        with self._lock:
            row = self._db.execute("SELECT event FROM applied WHERE bed_id = ? AND seq = ?", (bed_id, seq)).fetchone()
        return None if row is None else json.loads(row[0])

    def seqs(self, bed_id: str) -> list[int]:
        """Bed ``bed_id``'s numbers in the order applied."""
        with self._lock:
            return [seq for (seq,) in self._db.execute("SELECT seq FROM applied WHERE bed_id = ? ORDER BY rowid",
                                                       (bed_id,))]

    def latest(self, per_bed: int) -> list[Delivery]:
        """Each bed's last ``per_bed`` events, oldest first per bed: what a restarted station shows again."""
        with self._lock:
            rows = self._db.execute(
                "SELECT bed_id, seq, kind, event, applied_at FROM (SELECT *, row_number() OVER (PARTITION BY bed_id"
                " ORDER BY seq DESC) AS n FROM applied) WHERE n <= ? ORDER BY bed_id, seq", (per_bed,)).fetchall()
        return [Delivery(bed, seq, kind, {**json.loads(event), "received_at": at})
                for bed, seq, kind, event, at in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()
