"""The ward station's journal of the commands its nurses sent to beds: the audit, and what is still unanswered.

Every command is written here (``synchronous=FULL``) before it is published,
with who sent it, when, to which bed and what it asked, and then its fate:
``pending`` until the bed answers ``done`` or ``refused`` (with the bed's reason),
or ``expired`` when no answer came by its ``expires_at``. The bed's answer is
the last word: one that arrives after the station gave up replaces ``expired``,
since it says what the bed did. What is pending survives a restart of the
station, which sends it again; the bed applies each id once.

A file of its own beside the screen's accounts, with one connection per call,
so paho's thread and the screen's requests may all use it.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
from collections.abc import Iterator
from pathlib import Path

from appliance.alerts.ward_commands import WardCommand
from appliance.errors import StoreError

STATES = ("pending", "done", "refused", "expired")
SCHEMA = (
    ("CREATE TABLE IF NOT EXISTS commands (id TEXT PRIMARY KEY, bed_id TEXT NOT NULL, kind TEXT NOT NULL,"
     " args TEXT NOT NULL, user TEXT NOT NULL, station TEXT NOT NULL, issued_at REAL NOT NULL,"
     " expires_at REAL NOT NULL, state TEXT NOT NULL DEFAULT 'pending', result TEXT, answered_at REAL,"
     " sends INTEGER NOT NULL DEFAULT 0)"),
    "CREATE INDEX IF NOT EXISTS commands_state ON commands (state)",
    "CREATE INDEX IF NOT EXISTS commands_bed ON commands (bed_id, issued_at)",
)
COLUMNS = ("id", "bed_id", "kind", "args", "user", "station", "issued_at", "expires_at", "state", "result",
           "answered_at", "sends")


class CommandJournal:
    """The journal in SQLite file ``path`` (made if missing)."""

    def __init__(self, path):
        self.path = Path(path)
        try:
            with self._db() as db:
                for statement in SCHEMA:
                    db.execute(statement)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"the ward's command journal {self.path} cannot be used: {exc}") from exc

    @contextlib.contextmanager
    def _db(self) -> Iterator[sqlite3.Connection]:
        db = sqlite3.connect(self.path, timeout=5.0)
        try:
            db.execute("PRAGMA synchronous=FULL")
            with db:                                # one transaction, committed or rolled back
                yield db
        finally:
            db.close()

    def add(self, command: WardCommand) -> None:
        """Journal a command about to be sent: the audit entry is written before anything leaves the station."""
        with self._db() as db:
            db.execute(f"INSERT INTO commands ({', '.join(COLUMNS[:8])}) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       (command.id, command.bed_id, command.kind, json.dumps(command.args), command.user,
                        command.station, command.issued_at, command.expires_at))

    def sent(self, command_id: str) -> None:
        """Count one more publication of ``command_id`` (the first, or a resend)."""
        with self._db() as db:
            db.execute("UPDATE commands SET sends = sends + 1 WHERE id = ?", (command_id,))

    def answer(self, command_id: str, bed_id: str, state: str, result: str, answered_at: float) -> bool:
        """Record the bed's answer; False when it changes nothing (a repeat, or an id this station never sent
        to that bed)."""
        with self._db() as db:
            return db.execute("UPDATE commands SET state = ?, result = ?, answered_at = ? WHERE id = ? AND"
                              " bed_id = ? AND state IN ('pending', 'expired')",
                              (state, result, answered_at, command_id, bed_id)).rowcount > 0

    def expire(self, now: float) -> list[str]:
        """Mark every pending command whose time is up as expired; their ids."""
        with self._db() as db:
            ids = [i for (i,) in db.execute("SELECT id FROM commands WHERE state = 'pending' AND expires_at < ?",
                                            (now,))]
            db.executemany("UPDATE commands SET state = 'expired', result = 'no answer from the bed in time: it "
                           "was away or unreachable; the bed refuses it if it comes later', answered_at = ? "
                           "WHERE id = ?", [(now, i) for i in ids])
        return ids

    def pending(self, bed_id: str | None = None) -> list[WardCommand]:
        """Commands still awaiting their bed's answer, oldest first (only ``bed_id``'s, if given)."""
        where, args = ("state = 'pending'", ()) if bed_id is None else ("state = 'pending' AND bed_id = ?",
                                                                        (bed_id,))
        return [WardCommand(**{k: c[k] for k in COLUMNS[:8]}) for c in self._select(where, args)]

    def get(self, command_id: str) -> dict | None:
        found = self._select("id = ?", (command_id,))
        return found[0] if found else None

    def recent(self, since: float) -> list[dict]:
        """Commands issued at or after ``since``, newest first: the station's audit of who asked what."""
        return list(reversed(self._select("issued_at >= ?", (since,))))

    def _select(self, where: str, args: tuple) -> list[dict]:
        with self._db() as db:
            rows = db.execute(f"SELECT {', '.join(COLUMNS)} FROM commands WHERE {where} ORDER BY issued_at, rowid",
                              args).fetchall()
        return [{**dict(zip(COLUMNS, row)), "args": json.loads(row[3])} for row in rows]
