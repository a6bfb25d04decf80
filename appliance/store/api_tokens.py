"""Bearer tokens for the read-only FHIR API: made by an admin, kept only as hashes, revoked by name.

A token is 32 random bytes (256 bits), shown once when it is made. Only its
SHA-256 is kept: unlike a password it cannot be guessed, so a fast hash is
enough and a request is not slowed by a memory-hard one (Argon2 is for the
screen's passwords). The tokens live in ``api-tokens.db`` in the data folder.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import sqlite3
from pathlib import Path

from appliance.errors import ConfigError

TOKENS_FILE = "api-tokens.db"
"""The tokens' file in the monitor's data folder, beside the screen's accounts."""
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
SCHEMA = "CREATE TABLE IF NOT EXISTS tokens (name TEXT PRIMARY KEY, hash TEXT NOT NULL UNIQUE, made_at REAL NOT NULL)"


def digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class ApiTokens:
    """The tokens in SQLite file ``path``; one connection per call, so the screen's threads can share it."""

    def __init__(self, path):
        self.path = Path(path)
        with self._db() as db:
            db.execute(SCHEMA)

    def _db(self) -> sqlite3.Connection:
        return sqlite3.connect(self.path, timeout=5.0)

    def create(self, name: str, now: float) -> str:
        """A new token for client ``name`` (letters, digits, ``_.-``; 1-64), returned once."""
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise ConfigError(f"a token's name is 1-64 letters, digits, '_', '.' or '-', starting with a letter or "
                              f"digit; got {name!r}")
        token = secrets.token_urlsafe(32)
        try:
            with self._db() as db:
                db.execute("INSERT INTO tokens (name, hash, made_at) VALUES (?, ?, ?)", (name, digest(token), now))
        except sqlite3.IntegrityError:
            raise ConfigError(f"a token named {name!r} exists: revoke it first") from None
        return token

    def revoke(self, name: str) -> bool:
        with self._db() as db:
            return db.execute("DELETE FROM tokens WHERE name = ?", (name,)).rowcount > 0

    def names(self) -> list[str]:
        with self._db() as db:
            return [row[0] for row in db.execute("SELECT name FROM tokens ORDER BY name")]

    def made(self) -> list[tuple[str, float]]:
        """Each token's name and when it was made (Unix seconds), by name."""
        with self._db() as db:
            return [(name, made_at) for name, made_at in db.execute("SELECT name, made_at FROM tokens ORDER BY name")]

    def client(self, token: str) -> str | None:
        """The name the token was made for, or None if it is not a current token."""
        with self._db() as db:
            row = db.execute("SELECT name FROM tokens WHERE hash = ?", (digest(token),)).fetchone()
        return None if row is None else row[0]
