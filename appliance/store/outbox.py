"""The ward link's durable outbox: every event the bed sends, numbered, kept until the ward station confirms it.

A broker's acknowledgement is not delivery: Mosquitto acknowledges from memory,
so an alarm it took and then lost on a restart would be gone for the ward. Each
event is written here (``synchronous=FULL``) before it is sent, under a per-bed
sequence number, and resent until a ward station confirms that sequence number
end to end. The number is not a time (a clock step would break it): it grows by
one per event and is never reused, even across a crash, because numbers are
reserved on disk a block at a time and a restart continues past the reserved
block. An event handed in twice (the daemon notifies the last frame again after
a restart) keeps its first number, so the station never shows it twice.

A full or failing disk must not cut the ward off: an event that cannot be
written is numbered from the reserved block, kept in memory and sent as usual,
and written when the disk takes it again (``unwritten`` counts them).

It lives in its own SQLite file, not the monitor's store: the link's threads
write confirmations while the monitor loop owns the store.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import threading
from dataclasses import dataclass

from appliance.errors import StoreCorrupt, StoreError

SEQ_BLOCK = 1000
"""Sequence numbers reserved on disk at a time: a restart continues after the block, so an event numbered in
memory during a disk failure is never renumbered into a clash."""

KEEP_CONFIRMED = 1000
"""Confirmed entries kept (for the screen's "how far did it get" and to recognise an event handed in again)."""

SCHEMA = (
    ("CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY, identity TEXT NOT NULL UNIQUE,"
     " event TEXT NOT NULL, queued_at REAL NOT NULL, confirmed_at REAL, confirmed_by TEXT)"),
    "CREATE TABLE IF NOT EXISTS reserved (id INTEGER PRIMARY KEY CHECK (id = 1), up_to INTEGER NOT NULL)",
)


@dataclass
class Entry:
    """One numbered event; ``queued_at`` and ``confirmed_at`` are wall times (``time.time()``), for display."""

    seq: int
    event: dict
    queued_at: float
    confirmed_at: float | None = None
    confirmed_by: str | None = None


def identity(event: dict) -> str:
    """What makes an event the same event when handed in again: its whole record."""
    return hashlib.sha256(json.dumps(event, sort_keys=True, allow_nan=False).encode()).hexdigest()


def write_held(db: sqlite3.Connection, held: list, write) -> str | None:
    """Write the records held in memory while the disk refused them, all or none, in one synced transaction
    (``write(db, record)`` each); what failed, in words, or None once they are on disk."""
    try:
        db.execute("PRAGMA synchronous=FULL")
        db.execute("BEGIN IMMEDIATE")
        try:
            for record in held:
                write(db, record)
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise
    except sqlite3.Error as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def open_durable(path: str, what: str, lost: str, prepare) -> sqlite3.Connection:
    """SQLite file ``path`` in WAL mode with every commit synced, for records that must outlive a crash;
    ``prepare(db)`` makes its schema and reads it. A damaged file is refused naming ``what`` and what moving it
    aside would ``lose``."""
    try:
        db = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=5.0)
    except sqlite3.Error as exc:
        raise StoreError(f"cannot open {what} {path}: {exc}") from exc
    try:
        if db.execute("PRAGMA journal_mode=WAL").fetchone()[0] != "wal":
            raise StoreError(f"{what} {path}: cannot switch to WAL journal mode")
        db.execute("PRAGMA synchronous=FULL")
        prepare(db)
    except sqlite3.DatabaseError as exc:
        db.close()
        if getattr(exc, "sqlite_errorcode", None) in (sqlite3.SQLITE_NOTADB, sqlite3.SQLITE_CORRUPT):
            raise StoreCorrupt(f"{what} {path} is damaged ({exc}); move it aside to start an empty one ({lost})") \
                from exc
        raise StoreError(f"cannot read {what} {path}: {exc}") from exc
    except StoreError:
        db.close()
        raise
    return db


class Outbox:
    """The outbox in SQLite file ``path``; safe to use from several threads (one lock)."""

    def __init__(self, path):
        self.path = os.fspath(path)
        self._lock = threading.Lock()
        self._db = open_durable(self.path, "the ward outbox", "unconfirmed events in it would not be resent",
                                self._open)

    def _open(self, db: sqlite3.Connection) -> None:
        self._db = db
        problems = [row[0] for row in db.execute("PRAGMA quick_check(1)")]
        if problems != ["ok"]:
            raise sqlite3.DatabaseError(f"quick_check: {problems[0]}")
        for statement in SCHEMA:
            db.execute(statement)
        reserved = db.execute("SELECT up_to FROM reserved").fetchone()
        top = db.execute("SELECT max(seq) FROM outbox").fetchone()[0] or 0
        self._next = max(top, reserved[0] if reserved else 0) + 1
        self._reserved = self._next - 1
        self._pending: dict[int, Entry] = {}
        self._identities: dict[str, int] = {}
        self._alarm_seq: dict[int, int] = {}
        self._confirmed: dict[int, Entry] = {}
        for seq, ident, text, queued_at, confirmed_at, by in db.execute(
                "SELECT seq, identity, event, queued_at, confirmed_at, confirmed_by FROM outbox ORDER BY seq"):
            entry = Entry(seq, json.loads(text), queued_at, confirmed_at, by)
            self._index(entry, ident)
        self._unwritten: list[tuple[Entry, str]] = []
        self.write_failure: str | None = None
        self._reserve()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # The link's questions.

    @property
    def last_seq(self) -> int:
        """The highest number handed out (0 before the first event)."""
        return self._next - 1

    @property
    def unwritten(self) -> int:
        """Events numbered and sent from memory because the disk refused them."""
        return len(self._unwritten)

    def pending(self) -> list[Entry]:
        """The unconfirmed entries, oldest first."""
        with self._lock:
            return sorted(self._pending.values(), key=lambda e: e.seq)

    def entry(self, seq: int) -> Entry | None:
        with self._lock:
            return self._pending.get(seq) or self._confirmed.get(seq)

    def alarm_entry(self, alarm_id: int) -> Entry | None:
        """The newest entry about alarm ``alarm_id`` (its latest change), if it is still kept."""
        with self._lock:
            seq = self._alarm_seq.get(alarm_id)
            return None if seq is None else self._pending.get(seq) or self._confirmed.get(seq)

    # Changes.

    def add(self, event: dict, now: float) -> int:
        """Number ``event`` and keep it until it is confirmed; an event already here keeps its number."""
        ident = identity(event)
        with self._lock:
            if ident in self._identities:
                return self._identities[ident]
            if self._next > self._reserved:
                self._reserve()
            entry = Entry(self._next, event, now)
            self._next += 1
            self._index(entry, ident)
            self._unwritten.append((entry, ident))
            self._write_unwritten()
            return entry.seq

    def confirm(self, seq: int, by: str, now: float) -> bool:
        """Record that ``by`` confirmed ``seq``; False if it was not waiting (already confirmed, or unknown)."""
        with self._lock:
            entry = self._pending.pop(seq, None)
            if entry is None:
                return False
            entry.confirmed_at, entry.confirmed_by = now, by
            self._confirmed[seq] = entry
            try:
                self._db.execute("UPDATE outbox SET confirmed_at = ?, confirmed_by = ? WHERE seq = ?",
                                 (now, by, seq))                      # losing this only means one more resend
                if len(self._confirmed) > KEEP_CONFIRMED:
                    self._forget_oldest_confirmed()
            except sqlite3.Error:
                pass
            return True

    def retry_writes(self) -> None:
        """Write what the disk refused before, if it takes it now."""
        with self._lock:
            if self._unwritten:
                self._write_unwritten()

    # Inside the lock.

    def _index(self, entry: Entry, ident: str) -> None:
        self._identities[ident] = entry.seq
        (self._pending if entry.confirmed_at is None else self._confirmed)[entry.seq] = entry
        if entry.event.get("type") == "alarm" and entry.event.get("alarm_id") is not None:
            self._alarm_seq[entry.event["alarm_id"]] = entry.seq

    def _reserve(self) -> None:
        """Reserve the next block of numbers on disk; if the disk refuses, numbers still come from memory and the
        block is reserved once it takes writes again."""
        up_to = self._next + SEQ_BLOCK - 1
        try:
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("INSERT INTO reserved (id, up_to) VALUES (1, ?) ON CONFLICT (id) DO UPDATE SET "
                             "up_to = excluded.up_to", (up_to,))
        except sqlite3.Error as exc:
            self.write_failure = f"{type(exc).__name__}: {exc}"
        self._reserved = up_to

    def _write_unwritten(self) -> None:
        def insert(db: sqlite3.Connection, held: tuple[Entry, str]) -> None:
            entry, ident = held
            db.execute("INSERT OR IGNORE INTO outbox (seq, identity, event, queued_at, confirmed_at, confirmed_by) "
                       "VALUES (?, ?, ?, ?, ?, ?)", (entry.seq, ident, json.dumps(entry.event, allow_nan=False),
                                                     entry.queued_at, entry.confirmed_at, entry.confirmed_by))

        self.write_failure = write_held(self._db, self._unwritten, insert)
        if self.write_failure is None:
            self._unwritten.clear()

    def _forget_oldest_confirmed(self) -> None:
        cut = sorted(self._confirmed)[:len(self._confirmed) - KEEP_CONFIRMED]
        self._db.execute(f"DELETE FROM outbox WHERE seq IN ({','.join('?' * len(cut))})", cut)
        for seq in cut:
            entry = self._confirmed.pop(seq)
            self._identities.pop(identity(entry.event), None)
            alarm_id = entry.event.get("alarm_id")
            if alarm_id is not None and self._alarm_seq.get(alarm_id) == seq:
                del self._alarm_seq[alarm_id]
