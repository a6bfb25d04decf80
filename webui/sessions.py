"""Server-side records of login sessions, so that a session can end before its cookie does.

Flask's session is a signed cookie: clearing it on logout does not stop a copy
of the old cookie from working. So each login is also a row in the accounts
database, found by the hash of a random token the cookie carries, and a request
counts as logged in only while that row exists and the account's generation is
the one the row was opened with. Logging out deletes this session's row alone;
setting a password raises the account's generation (``UserStore.set_password``),
ending every session opened with the old one; removing the account removes its
rows (a foreign key), so an account later made with the same name inherits none.
"""

from __future__ import annotations

import hashlib
import secrets
import sqlite3
import time
from pathlib import Path

from appliance.accounts.users import User

_SCHEMA = ("CREATE TABLE IF NOT EXISTS sessions (token_hash TEXT PRIMARY KEY,"
           " user TEXT NOT NULL REFERENCES users(name) ON DELETE CASCADE,"
           " generation INTEGER NOT NULL, opened_s REAL NOT NULL)")


class SessionStore:
    """Sessions in the accounts database at ``path`` (made by ``UserStore`` first); each lasts ``lifetime_s``."""

    def __init__(self, path: Path, lifetime_s: float):
        self.path, self.lifetime_s = Path(path), lifetime_s
        with self._db() as db:
            db.execute(_SCHEMA)

    def _db(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=5.0)
        db.execute("PRAGMA foreign_keys=ON")
        return db

    def open(self, name: str) -> str:
        """A new session of ``name`` at the account's current generation: the token for the cookie."""
        token = secrets.token_urlsafe(32)
        now = time.time()
        with self._db() as db:
            db.execute("DELETE FROM sessions WHERE opened_s < ?", (now - self.lifetime_s,))
            db.execute("INSERT INTO sessions (token_hash, user, generation, opened_s)"
                       " SELECT ?, name, generation, ? FROM users WHERE name = ?", (_hash(token), now, name))
        return token

    def user(self, token: str) -> User | None:
        """The user of the session ``token`` if it is still open, else None."""
        with self._db() as db:
            row = db.execute("SELECT u.name, u.role FROM sessions s JOIN users u"
                             " ON u.name = s.user AND u.generation = s.generation"
                             " WHERE s.token_hash = ? AND s.opened_s >= ?",
                             (_hash(token), time.time() - self.lifetime_s)).fetchone()
        return User(*row) if row else None

    def close(self, token: str) -> None:
        """End the session ``token`` (and no other)."""
        with self._db() as db:
            db.execute("DELETE FROM sessions WHERE token_hash = ?", (_hash(token),))


def _hash(token: str) -> str:
    """What is stored of a token: a copy of the database gives no usable session."""
    return hashlib.sha256(token.encode()).hexdigest()
