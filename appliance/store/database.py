"""The appliance's persistence: one SQLite file holding the event log, alert checkpoints and pressure history.

Durability is chosen per write. The file runs in WAL mode; alarm events,
commands and their outcomes are committed with ``synchronous=FULL`` (the WAL is
fsynced before the commit returns), because an acknowledged alarm that reappears
after a power cut, or an audit entry that vanishes, is a safety defect. The
alert state of a frame without events (doses growing, the turn clock running)
is committed FULL once ``STATE_SYNC_S`` of monitoring time have passed since
the last FULL commit, and with ``synchronous=NORMAL`` in between, as is the
pressure history: a power cut may lose the last seconds of dose and the last few
maps, never an event, and never corrupts the file, and the SD card is spared an
fsync per frame. Because the WAL is written in order, the next FULL commit also
makes every earlier NORMAL commit durable. A killed process loses nothing
committed either way: NORMAL commits are in the operating system's hands.

Times are seconds on whatever clock the caller runs (the alarm engine's); the
store only compares them, so retention ages are measured on that clock too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import sqlite3
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Self

import numpy as np

from appliance.errors import SchemaTooNew, StoreClosed, StoreCorrupt, StoreError

SCHEMA_VERSION = 4
BUSY_TIMEOUT_S = 5.0
STATE_SYNC_S = 15.0
"""Longest stretch of monitoring time whose alert state a power cut may take back: 15 s of a dose that alarms
after hours (Reswick-Rogers allows 32 mmHg for about 8 h), and one fsync per 15 frames at the bed's 1 s."""
DAY_S = 86400.0

EVENT_COLUMNS = ("time_s", "kind", "alarm_id", "key", "category", "priority", "user", "channel", "message")

# MIGRATIONS[v] takes a file from version v - 1 to version v; index 0 is unused.
MIGRATIONS: tuple[tuple[str, ...], ...] = (
    (),
    (
        "CREATE TABLE schema_version (version INTEGER NOT NULL)",
        ("CREATE TABLE events (id INTEGER PRIMARY KEY, time_s REAL NOT NULL, kind TEXT NOT NULL,"
         " alarm_id INTEGER, key TEXT, category TEXT, priority TEXT, user TEXT, channel TEXT, message TEXT,"
         " detail TEXT NOT NULL DEFAULT '{}')"),
        "CREATE INDEX events_time ON events (time_s)",
        "CREATE TABLE state (name TEXT PRIMARY KEY, saved_at_s REAL NOT NULL, value TEXT NOT NULL)",
        ("CREATE TABLE pressure_history (id INTEGER PRIMARY KEY, time_s REAL NOT NULL, rows INTEGER NOT NULL,"
         " cols INTEGER NOT NULL, data BLOB NOT NULL, peak_kpa REAL NOT NULL)"),
        "CREATE INDEX pressure_history_time ON pressure_history (time_s)",
    ),
    (
        ("CREATE TABLE commands (id INTEGER PRIMARY KEY, queued_at REAL NOT NULL, user TEXT NOT NULL,"
         " kind TEXT NOT NULL, args TEXT NOT NULL, state TEXT NOT NULL DEFAULT 'pending', result TEXT,"
         " done_s REAL)"),
        "CREATE INDEX commands_pending ON commands (state)",
    ),
    (
        ("CREATE TABLE region_history (id INTEGER PRIMARY KEY, time_s REAL NOT NULL, region_id INTEGER NOT NULL,"
         " zone TEXT, peak_mmhg REAL NOT NULL, area_cm2 REAL NOT NULL, dose REAL)"),
        "CREATE INDEX region_history_time ON region_history (time_s)",
        "ALTER TABLE commands ADD COLUMN progress REAL",
        "ALTER TABLE commands ADD COLUMN progress_note TEXT",
    ),
    (
        # The ward station's id of a command it sent: unique, so a repeat of one already applied is never kept twice.
        "ALTER TABLE commands ADD COLUMN ward_id TEXT",
        "CREATE UNIQUE INDEX commands_ward_id ON commands (ward_id)",
    ),
)


# Rough bytes per row, page and index overhead included; an underestimate would delete too many rows at once.
_ROW_BYTES = {
    "pressure_history": "length(data) + 64",
    "events": "length(detail) + " + " + ".join(f"ifnull(length({c}), 0)" for c in EVENT_COLUMNS[1:]) + " + 96",
}


def _event_row(event) -> tuple:
    """An event as a row: the known columns, and every other field in ``detail`` so nothing is dropped."""
    if dataclasses.is_dataclass(event) and not isinstance(event, type):
        fields = {f.name: getattr(event, f.name) for f in dataclasses.fields(event)}
    elif isinstance(event, Mapping):
        fields = dict(event)
    else:
        raise TypeError(f"an event must be a dataclass or a mapping, got {type(event).__name__}")
    if "time_s" not in fields or "kind" not in fields:
        raise ValueError(f"an event needs time_s and kind, got fields {sorted(fields)}")
    time_s = float(fields["time_s"])
    if not math.isfinite(time_s):
        raise ValueError(f"event {fields['kind']!r} has a non-finite time {fields['time_s']!r}")
    detail = {k: v for k, v in fields.items() if k not in EVENT_COLUMNS}
    return (time_s, *(fields.get(c) for c in EVENT_COLUMNS[1:]), json.dumps(detail, allow_nan=False))


class Store:
    """One open store file; build it with ``Store.open``, or ``Store.open_read_only`` to look only. Not
    thread-safe: one owner, the monitor loop or one request of the screen."""

    def __init__(self, db: sqlite3.Connection, path: str, *, history_interval_s: float, history_days: float,
                 event_days: float, max_bytes: int, read_only: bool = False):
        self._db: sqlite3.Connection | None = db
        self.path = path
        self.read_only = read_only
        self.history_interval_s = history_interval_s
        self.history_days = history_days
        self.event_days = event_days
        self.max_bytes = max_bytes
        self._last_map_s = db.execute("SELECT max(time_s) FROM pressure_history").fetchone()[0]
        self._wrote = False
        self._last_full_s: float | None = None        # monitoring time of the last FULL frame commit

    @classmethod
    def open(cls, path, *, history_interval_s: float = 60.0, history_days: float = 30.0, event_days: float = 365.0,
             max_bytes: int = 512 * 1024 * 1024, check: bool = False) -> Store:
        """Open or create the file at ``path`` and bring its schema up to date; ``check`` (the monitor, once at
        start) also reads every page, so a damaged file is refused before the monitor relies on it."""
        if not (history_interval_s >= 0 and history_days > 0 and event_days > 0 and max_bytes > 0):
            raise ValueError(f"store {path}: history interval {history_interval_s!r} s must not be negative; "
                             f"history days {history_days!r}, event days {event_days!r} and max bytes "
                             f"{max_bytes!r} must be positive")
        path = os.fspath(path)
        try:
            db = sqlite3.connect(path, timeout=BUSY_TIMEOUT_S, isolation_level=None)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open store {path}: {exc}") from exc
        try:
            _configure(db, path)
            if check:
                _check_pages(db, path)
            _migrate(db, path)
            return cls(db, path, history_interval_s=history_interval_s, history_days=history_days,
                       event_days=event_days, max_bytes=max_bytes)
        except sqlite3.DatabaseError as exc:
            db.close()
            raise _damage(path, exc) from exc
        except BaseException:
            db.close()
            raise

    @classmethod
    def open_read_only(cls, path) -> Store:
        """Open the file at ``path`` to read alone: no schema change and no write lock (SQLite's ``mode=ro`` and
        ``query_only``), so the screen's page views neither wait for the monitor's writes nor hold them up.

        The file must exist with this software's schema, as the monitor leaves it; a write raises StoreError.
        """
        path = os.fspath(path)
        uri = Path(path).resolve().as_uri() + "?mode=ro"
        try:
            db = sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_S, isolation_level=None)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open store {path} to read: {exc}") from exc
        try:
            db.execute("PRAGMA query_only=ON")
            db.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
            has_table = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_version'"
                                   ).fetchone()
            version = db.execute("SELECT max(version) FROM schema_version").fetchone()[0] if has_table else 0
            if version != SCHEMA_VERSION:
                raise StoreError(f"store {path} has schema version {version}, not {SCHEMA_VERSION}: the monitor "
                                 f"brings it up to date when it starts")
            return cls(db, path, history_interval_s=60.0, history_days=30.0, event_days=365.0,
                       max_bytes=512 * 1024 * 1024, read_only=True)
        except sqlite3.DatabaseError as exc:
            db.close()
            raise _damage(path, exc) from exc
        except BaseException:
            db.close()
            raise

    def close(self) -> None:
        """Checkpoint the WAL into the file if this connection wrote, and close; later calls raise
        ``StoreClosed``. A reader (the screen opens the store per request) leaves the WAL alone, so that
        looking at a page writes nothing to the SD card."""
        if self._db is not None:
            if self._wrote:
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            self._db.close()
            self._db = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            raise StoreClosed(f"store {self.path} is closed")
        return self._db

    @contextlib.contextmanager
    def _transaction(self, synchronous: str):
        """One all-or-nothing write; ``synchronous`` is FULL for what must survive a power cut."""
        db = self._conn()
        if self.read_only:
            raise StoreError(f"store {self.path} is open read-only: it takes no writes")
        db.execute(f"PRAGMA synchronous={synchronous}")
        db.execute("BEGIN IMMEDIATE")
        self._wrote = True
        try:
            yield db
            db.execute("COMMIT")          # may fail too (a full disk): the transaction must not stay open
        except BaseException:
            if db.in_transaction:
                with contextlib.suppress(sqlite3.Error):
                    db.execute("ROLLBACK")
            raise

    # Events and alert state: durable.

    def record_events(self, events: Iterable) -> None:
        """Append events (``AlarmEvent``, ``TurnEvent`` or mappings) to the log in one durable commit."""
        with self._transaction("FULL") as db:
            _insert_events(db, events)

    def save_state(self, name: str, state: dict, now_s: float) -> None:
        """Checkpoint one alert component's state (JSON-serialisable) so a restart resumes it."""
        with self._transaction("FULL") as db:
            _upsert_state(db, name, state, now_s)

    def commit_frame(self, now_s: float, events: Iterable, states: Mapping[str, dict],
                     commands_done: Iterable[tuple[int, bool, str]] = (),
                     ward_commands: Iterable[Mapping] = ()) -> None:
        """A frame's events, the states they led to and the commands it applied (id, applied, result), in one
        transaction: a crash keeps all or none, so a command is applied exactly once. ``ward_commands`` are the
        ward station's commands the frame applied or refused, each a mapping with ``ward_id``, ``kind``,
        ``args``, ``user``, ``queued_at``, ``applied`` and ``result``: kept under their ward id, so a repeat is
        known (:meth:`ward_command`). Durable (FULL) when it carries an event or a command, or ``STATE_SYNC_S``
        after the last durable one (see the module's notes)."""
        events, commands_done, ward_commands = list(events), list(commands_done), list(ward_commands)
        durable = bool(events or commands_done or ward_commands) or self._last_full_s is None \
            or not 0.0 <= now_s - self._last_full_s < STATE_SYNC_S      # a clock step back syncs at once
        with self._transaction("FULL" if durable else "NORMAL") as db:
            for name, state in states.items():
                _upsert_state(db, name, state, now_s)
            _insert_events(db, events)
            for command_id, applied, result in commands_done:
                db.execute("UPDATE commands SET state = ?, result = ?, done_s = ? WHERE id = ?",
                           ("done" if applied else "refused", result, now_s, command_id))
            for c in ward_commands:
                db.execute("INSERT INTO commands (queued_at, user, kind, args, state, result, done_s, ward_id)"
                           " VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (ward_id) DO NOTHING",
                           (c["queued_at"], c["user"], c["kind"], json.dumps(dict(c["args"])),
                            "done" if c["applied"] else "refused", c["result"], now_s, c["ward_id"]))
        if durable:
            self._last_full_s = now_s

    # Commands: what other processes (the web screen) ask the monitor to do.

    def queue_command(self, kind: str, args: Mapping, user: str) -> int:
        """Ask the monitor for ``kind`` (acknowledge, pause-audio) on behalf of ``user``; returns its id."""
        with self._transaction("FULL") as db:
            return db.execute("INSERT INTO commands (queued_at, user, kind, args) VALUES (?, ?, ?, ?)",
                              (time.time(), user, kind, json.dumps(dict(args)))).lastrowid

    def pending_commands(self) -> list[dict]:
        """Commands not yet applied, oldest first."""
        rows = self._conn().execute("SELECT id, user, kind, args FROM commands WHERE state = 'pending' ORDER BY id")
        return [{"id": i, "user": user, "kind": kind, "args": json.loads(args)} for i, user, kind, args in rows]

    def command(self, command_id: int) -> dict | None:
        """One command with its state (pending, done, refused), result and progress (0-1 while a long one runs)."""
        row = self._conn().execute("SELECT id, user, kind, args, state, result, progress, progress_note"
                                   " FROM commands WHERE id = ?", (command_id,)).fetchone()
        if row is None:
            return None
        return dict(zip(("id", "user", "kind", "args", "state", "result", "progress", "progress_note"),
                        row[:3] + (json.loads(row[3]),) + row[4:]))

    def ward_command(self, ward_id: str) -> dict | None:
        """The ward station's command ``ward_id`` as this bed applied or refused it, or None if it never came."""
        row = self._conn().execute("SELECT id FROM commands WHERE ward_id = ?", (ward_id,)).fetchone()
        return None if row is None else self.command(row[0])

    def commands_since(self, queued_after: float, kinds: Iterable[str] | None = None) -> list[dict]:
        """Commands queued after wall time ``queued_after``, newest first (optionally only these kinds)."""
        rows = self._conn().execute("SELECT id FROM commands WHERE queued_at > ? ORDER BY id DESC", (queued_after,))
        wanted = None if kinds is None else set(kinds)
        return [c for (i,) in rows.fetchall() if (c := self.command(i)) and (wanted is None or c["kind"] in wanted)]

    def set_progress(self, command_id: int, share: float, note: str = "") -> None:
        """How far a long command has got (0-1), for screens that show a progress bar; not fsynced."""
        with self._transaction("NORMAL") as db:
            db.execute("UPDATE commands SET progress = ?, progress_note = ? WHERE id = ?",
                       (min(max(float(share), 0.0), 1.0), note, command_id))

    def load_state(self, name: str) -> dict | None:
        """The last checkpoint saved under ``name``, or None if there is none."""
        row = self._conn().execute("SELECT value FROM state WHERE name = ?", (name,)).fetchone()
        if row is None:
            return None
        try:
            return json.loads(row[0])
        except (TypeError, ValueError) as exc:
            raise StoreCorrupt(f"store {self.path}: the saved state {name!r} is not valid JSON ({exc})") from None

    def events_since(self, t: float) -> list[dict]:
        """Events at or after ``t`` in the order logged: the columns, plus the extra fields kept in ``detail``."""
        return self._events("time_s >= ?", (t,))

    def _events(self, where: str, args: tuple) -> list[dict]:
        out = []
        for row in self._conn().execute(
                f"SELECT {', '.join(EVENT_COLUMNS)}, detail FROM events WHERE {where} ORDER BY time_s, id", args):
            event = dict(zip(EVENT_COLUMNS, row[:-1]))
            event.update(json.loads(row[-1]))
            out.append(event)
        return out

    def episodes(self) -> list[dict]:
        """Every admission and discharge in the log, oldest first: ``time_s``, ``kind``, ``patient``, ``user``,
        ``message``."""
        rows = self._conn().execute(
            "SELECT time_s, kind, json_extract(detail, '$.patient'), user, message FROM events"
            " WHERE json_extract(detail, '$.type') = 'episode' ORDER BY time_s, id")
        return [dict(zip(("time_s", "kind", "patient", "user", "message"), row)) for row in rows]

    def patient_events(self, patient: str) -> list[dict]:
        """Every event logged under one patient's identifier, oldest first: their history after discharge."""
        return self._events("json_extract(detail, '$.patient') = ?", (patient,))

    # Pressure history: down-sampled, not fsynced per map.

    @property
    def last_map_s(self) -> float | None:
        """The time of the last map kept in the history (the next is kept ``history_interval_s`` after it)."""
        return self._last_map_s

    def record_map(self, time_s: float, pressure_kpa, regions: Iterable[Mapping] = ()) -> bool:
        """Keep the map, and the loaded regions it shows, if ``history_interval_s`` has passed since the last kept
        one; returns whether it was kept.

        Each region is a mapping with ``id``, ``zone``, ``peak_mmhg``, ``area_cm2``
        and ``dose`` (None before it has any). A map earlier than the last kept one
        is not kept either, so a clock that steps back cannot fill the history.
        """
        self._conn()
        pressure = np.asarray(pressure_kpa, dtype=np.float64)
        if pressure.ndim != 2 or pressure.size == 0:
            raise ValueError(f"a pressure map must be a non-empty 2-D array, got shape {pressure.shape}")
        if not np.all(np.isfinite(pressure)):
            raise ValueError(f"the pressure map at {time_s!r} s has non-finite values")
        if self._last_map_s is not None and time_s - self._last_map_s < self.history_interval_s:
            return False
        data = pressure.astype("<f4").tobytes()
        rows = [(float(time_s), int(r["id"]), r.get("zone"), float(r["peak_mmhg"]), float(r["area_cm2"]),
                 None if r.get("dose") is None else float(r["dose"])) for r in regions]
        with self._transaction("NORMAL") as db:
            db.execute("INSERT INTO pressure_history (time_s, rows, cols, data, peak_kpa) VALUES (?, ?, ?, ?, ?)",
                       (float(time_s), *pressure.shape, data, float(pressure.max())))
            db.executemany("INSERT INTO region_history (time_s, region_id, zone, peak_mmhg, area_cm2, dose)"
                           " VALUES (?, ?, ?, ?, ?, ?)", rows)
        self._last_map_s = float(time_s)
        return True

    def history_between(self, t0: float, t1: float) -> list[tuple[float, np.ndarray]]:
        """Stored maps with ``t0 <= time_s <= t1``, oldest first, as float32 arrays."""
        rows = self._conn().execute("SELECT time_s, rows, cols, data FROM pressure_history"
                                    " WHERE time_s BETWEEN ? AND ? ORDER BY time_s", (t0, t1))
        return [(t, np.frombuffer(data, dtype="<f4").reshape(r, c).astype(np.float32)) for t, r, c, data in rows]

    def regions_between(self, t0: float, t1: float) -> list[dict]:
        """The regions kept with the maps of ``t0 <= time_s <= t1``, oldest first."""
        rows = self._conn().execute("SELECT time_s, region_id, zone, peak_mmhg, area_cm2, dose FROM region_history"
                                    " WHERE time_s BETWEEN ? AND ? ORDER BY time_s, region_id", (t0, t1))
        return [dict(zip(("time_s", "region_id", "zone", "peak_mmhg", "area_cm2", "dose"), row)) for row in rows]

    def last_time(self) -> float | None:
        """The latest time anything was recorded (event, state or map), so a restarted clock can resume past it."""
        return self._conn().execute(
            "SELECT max(t) FROM (SELECT max(time_s) AS t FROM events UNION ALL SELECT max(saved_at_s) FROM state"
            " UNION ALL SELECT max(time_s) FROM pressure_history)").fetchone()[0]

    # Retention.

    def size_bytes(self) -> int:
        """The database's size in pages (what the file shrinks to once the WAL is checkpointed)."""
        db = self._conn()
        return db.execute("PRAGMA page_count").fetchone()[0] * db.execute("PRAGMA page_size").fetchone()[0]

    def prune(self, now_s: float) -> dict[str, int]:
        """Drop what is too old, then the oldest until the file fits ``max_bytes``; returns rows deleted per table.

        History goes first under the size cap: it is a convenience, the event
        log is the audit trail. Events are only cut when no history is left.
        """
        deleted = {"history": 0, "events": 0}
        with self._transaction("FULL") as db:
            deleted["history"] += db.execute("DELETE FROM pressure_history WHERE time_s < ?",
                                             (now_s - self.history_days * DAY_S,)).rowcount
            db.execute("DELETE FROM region_history WHERE time_s < ?", (now_s - self.history_days * DAY_S,))
            deleted["events"] += db.execute("DELETE FROM events WHERE time_s < ?",
                                            (now_s - self.event_days * DAY_S,)).rowcount
        self._vacuum()
        for table, key in (("pressure_history", "history"), ("events", "events")):
            while (over := self.size_bytes() - self.max_bytes) > 0:
                with self._transaction("FULL") as db:
                    row_bytes = db.execute(f"SELECT avg({_ROW_BYTES[table]}) FROM {table}").fetchone()[0]
                    if row_bytes is None:
                        break
                    n = max(1, math.ceil(over / row_bytes))
                    deleted[key] += db.execute(f"DELETE FROM {table} WHERE id IN"
                                               f" (SELECT id FROM {table} ORDER BY time_s, id LIMIT ?)",
                                               (n,)).rowcount
                    if table == "pressure_history":         # the regions kept with the maps just deleted
                        db.execute("DELETE FROM region_history WHERE time_s <"
                                   " ifnull((SELECT min(time_s) FROM pressure_history), 1e308)")
                self._vacuum()
        self._conn().execute("PRAGMA wal_checkpoint(TRUNCATE)")
        return deleted

    def _vacuum(self) -> None:
        """Return free pages to the file system, so deleting rows actually shrinks the file.

        ``executescript`` because ``execute`` steps the pragma once, which frees a single page.
        """
        self._conn().executescript("PRAGMA incremental_vacuum")


def _insert_events(db: sqlite3.Connection, events: Iterable) -> None:
    for event in events:
        db.execute(f"INSERT INTO events ({', '.join(EVENT_COLUMNS)}, detail) VALUES ({', '.join('?' * 10)})",
                   _event_row(event))


def _upsert_state(db: sqlite3.Connection, name: str, state: dict, now_s: float) -> None:
    if not isinstance(name, str) or not name:
        raise ValueError(f"a state name must be a non-empty string, got {name!r}")
    if not isinstance(state, dict):
        raise TypeError(f"state {name!r} must be a dict, got {type(state).__name__}")
    db.execute("INSERT INTO state (name, saved_at_s, value) VALUES (?, ?, ?)"
               " ON CONFLICT (name) DO UPDATE SET saved_at_s = excluded.saved_at_s, value = excluded.value",
               (name, float(now_s), json.dumps(state, allow_nan=False)))


RECOVERY = ("left as found, since it may hold records: move it aside (with any -wal and -shm files beside it) to "
            "start with an empty store, and keep it to recover what it holds")


def _damage(path: str, exc: sqlite3.DatabaseError) -> StoreError:
    """The error for a database error while opening: StoreCorrupt, saying how to recover, if the file is
    damaged; StoreError for anything else (locked, unreadable)."""
    if getattr(exc, "sqlite_errorcode", None) in (sqlite3.SQLITE_NOTADB, sqlite3.SQLITE_CORRUPT):
        return StoreCorrupt(f"store {path} is damaged ({exc}); {RECOVERY}")
    return StoreError(f"cannot read store {path}: {exc}")


def _check_pages(db: sqlite3.Connection, path: str) -> None:
    """``PRAGMA quick_check``: every page read and its structure checked (not the indexes' contents)."""
    problems = [" ".join(str(row[0]).split()) for row in db.execute("PRAGMA quick_check(3)")]   # one line
    if problems != ["ok"]:
        raise StoreCorrupt(f"store {path} is damaged ({'; '.join(problems)}); {RECOVERY}")


def _configure(db: sqlite3.Connection, path: str) -> None:
    """Check the file really is a database before anything writes to it, then set the connection's pragmas."""
    try:
        fresh = db.execute("SELECT count(*) FROM sqlite_master").fetchone()[0] == 0
    except sqlite3.DatabaseError as exc:
        raise _damage(path, exc) from exc
    if fresh:
        # Must precede the first table: SQLite cannot switch an existing file to incremental vacuum cheaply.
        db.execute("PRAGMA auto_vacuum=INCREMENTAL")
    if db.execute("PRAGMA journal_mode=WAL").fetchone()[0] != "wal":
        raise StoreError(f"store {path}: cannot switch to WAL journal mode (is it on a network file system?)")
    db.execute("PRAGMA foreign_keys=ON")
    db.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
    db.execute("PRAGMA synchronous=FULL")


def _migrate(db: sqlite3.Connection, path: str) -> None:
    """Apply the missing migrations, all in one transaction so a crash never leaves a half-migrated file."""
    db.execute("BEGIN IMMEDIATE")
    try:
        has_table = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_version'"
                               ).fetchone()
        version = db.execute("SELECT max(version) FROM schema_version").fetchone()[0] if has_table else 0
        if version > SCHEMA_VERSION:
            raise SchemaTooNew(f"store {path} has schema version {version}, newer than {SCHEMA_VERSION} which "
                               f"this software knows; update the software rather than downgrade the file")
        for target in range(version + 1, SCHEMA_VERSION + 1):
            for statement in MIGRATIONS[target]:
                db.execute(statement)
            db.execute("DELETE FROM schema_version")
            db.execute("INSERT INTO schema_version (version) VALUES (?)", (target,))
    except BaseException:
        db.execute("ROLLBACK")
        raise
    db.execute("COMMIT")
