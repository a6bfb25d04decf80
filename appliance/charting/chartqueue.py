"""The charting queue: every HL7 message the bed owes the hospital, on disk before it is sent, until it is ACKed.

Records (not message text) are kept, numbered in the order they came; the
message is built from the record and its number when sent, so a resend is the
same message with the same control id and the engine can drop a repeat. A
record handed in twice (the daemon notifies the last frame again after a
restart) keeps its first number. Writes are ``synchronous=FULL``: a record
the queue took survives a power cut. A record the disk refuses is kept in
memory and written (then sent) when the disk takes it again, so the order
holds; ``write_failure`` says why meanwhile.

States: ``pending`` until the engine answers; ``delivered`` (AA), kept a while
to recognise a repeat; ``refused`` (AE, AR), kept with the engine's answer for
someone to read: a refusal is not resent, since the same message would be
refused again. It is its own SQLite file beside the store: the sender thread
writes here while the monitor loop owns the store.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
from dataclasses import dataclass

from appliance.store.outbox import identity, open_durable, write_held

KEEP_DELIVERED = 1000
"""Delivered records kept (to recognise a record handed in again); older ones are deleted."""

SCHEMA = ("CREATE TABLE IF NOT EXISTS messages (seq INTEGER PRIMARY KEY AUTOINCREMENT, identity TEXT NOT NULL UNIQUE,"
          " record TEXT NOT NULL, queued_at REAL NOT NULL, state TEXT NOT NULL DEFAULT 'pending',"
          " answered_at REAL, answer TEXT)")


@dataclass(frozen=True)
class Queued:
    """One record; ``queued_at`` is wall time (``time.time()``), the message's MSH-7."""

    seq: int
    record: dict
    queued_at: float
    state: str = "pending"
    answer: str | None = None


class ChartQueue:
    """The queue in SQLite file ``path``; safe to use from several threads (one lock)."""

    def __init__(self, path):
        self.path = os.fspath(path)
        self._lock = threading.Lock()
        self._unwritten: list[tuple[dict, float]] = []
        self.write_failure: str | None = None
        self._db = open_durable(self.path, "the charting queue", "messages in it would not be sent",
                                lambda db: db.execute(SCHEMA))

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @property
    def unwritten(self) -> int:
        """Records held in memory because the disk refused them."""
        return len(self._unwritten)

    def add(self, record: dict, now: float) -> None:
        """Keep ``record`` on disk (or in memory while the disk refuses) until it is delivered or refused."""
        with self._lock:
            self._unwritten.append((record, now))
            self._write_unwritten()

    def retry_writes(self) -> None:
        with self._lock:
            if self._unwritten:
                self._write_unwritten()

    def pending(self, limit: int = 100) -> list[Queued]:
        """The oldest ``limit`` records waiting for an answer, in order."""
        with self._lock:
            rows = self._db.execute("SELECT seq, record, queued_at FROM messages WHERE state = 'pending'"
                                    " ORDER BY seq LIMIT ?", (limit,)).fetchall()
        return [Queued(seq, json.loads(text), queued_at) for seq, text, queued_at in rows]

    def waiting(self) -> int:
        """How many records wait for the engine's answer (those held in memory not counted: see ``unwritten``)."""
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM messages WHERE state = 'pending'").fetchone()[0]

    def refused(self) -> list[Queued]:
        """Records the engine refused, oldest first, with its answer."""
        with self._lock:
            rows = self._db.execute("SELECT seq, record, queued_at, answer FROM messages WHERE state = 'refused'"
                                    " ORDER BY seq").fetchall()
        return [Queued(seq, json.loads(text), queued_at, "refused", answer) for seq, text, queued_at, answer in rows]

    def answered(self, seq: int, delivered: bool, answer: str, now: float) -> None:
        """Record the engine's answer to ``seq``: delivered (AA), or refused with ``answer``."""
        with self._lock:
            self._db.execute("UPDATE messages SET state = ?, answered_at = ?, answer = ? WHERE seq = ?",
                             ("delivered" if delivered else "refused", now, answer, seq))
            if delivered:
                self._db.execute("DELETE FROM messages WHERE state = 'delivered' AND seq <= (SELECT seq FROM messages"
                                 " WHERE state = 'delivered' ORDER BY seq DESC LIMIT 1 OFFSET ?)", (KEEP_DELIVERED,))

    def _write_unwritten(self) -> None:
        def insert(db: sqlite3.Connection, held: tuple[dict, float]) -> None:
            record, now = held
            key = identity(record)
            if db.execute("SELECT 1 FROM messages WHERE identity = ?", (key,)).fetchone() is None:
                db.execute("INSERT INTO messages (identity, record, queued_at) VALUES (?, ?, ?)",
                           (key, json.dumps(record, allow_nan=False), now))

        self.write_failure = write_held(self._db, self._unwritten, insert)
        if self.write_failure is None:
            self._unwritten.clear()
