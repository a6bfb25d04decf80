"""The web screen's accounts and audit log: one SQLite file beside the monitor's store.

Passwords are hashed with Argon2id (argon2-cffi, the OWASP-recommended memory-hard
hash); nothing else about a password is kept. Roles are ordered: a nurse sees and
acknowledges, an engineer also calibrates and diagnoses, an admin also manages
accounts. Every acknowledgement and settings change is appended to the audit log
with who did it and when; its entries are bounded in size, so a request cannot
fill the disk through it. Each account has a generation, raised whenever its
password is set, that ends every session opened before (:mod:`webui.sessions`).
The file is readable by its owner alone (:mod:`appliance.accounts.private`).
"""

from __future__ import annotations

import re
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

from appliance.accounts import passwords
from appliance.accounts.private import narrow, private_file

ROLES = ("nurse", "engineer", "admin")
MIN_PASSWORD_LENGTH = passwords.MIN_LENGTH
MAX_AUDIT_USER, MAX_AUDIT_DETAIL = 64, 512
"""Longest user name and detail kept in an audit entry; longer ones are cut and marked."""
_NAME = re.compile(r"^[a-z0-9][a-z0-9._-]{1,31}$")
_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS users (name TEXT PRIMARY KEY, role TEXT NOT NULL, hash TEXT NOT NULL,"
    " created_s REAL NOT NULL, generation INTEGER NOT NULL DEFAULT 0)",
    "CREATE TABLE IF NOT EXISTS audit (id INTEGER PRIMARY KEY, time_s REAL NOT NULL, user TEXT NOT NULL,"
    " action TEXT NOT NULL, detail TEXT NOT NULL)",
)


class AccountError(ValueError):
    """A user name, password or role that cannot be accepted; the message says why."""


@dataclass(frozen=True)
class User:
    name: str
    role: str

    def can(self, role: str) -> bool:
        """Whether this user has ``role``'s rights (roles are ordered nurse < engineer < admin)."""
        return ROLES.index(self.role) >= ROLES.index(role)


class UserStore:
    """Accounts and the audit log in ``path``; one connection per call, so any thread may use it."""

    def __init__(self, path: Path):
        self.path = private_file(Path(path))
        self.hasher = PasswordHasher()
        with self._db() as db:
            for statement in _SCHEMA:
                db.execute(statement)
            columns = [row[1] for row in db.execute("PRAGMA table_info(users)")]
            if "generation" not in columns:            # a store made before sessions could be ended
                db.execute("ALTER TABLE users ADD COLUMN generation INTEGER NOT NULL DEFAULT 0")
        for suffix in ("-wal", "-shm"):                # SQLite gives these the main file's mode once it is narrow
            narrow(self.path.with_name(self.path.name + suffix))

    def _db(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=5.0)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA foreign_keys=ON")           # removing an account removes its sessions
        return db

    def count(self) -> int:
        with self._db() as db:
            return db.execute("SELECT count(*) FROM users").fetchone()[0]

    def create(self, name: str, password: str, role: str, *, by: str) -> User:
        """A new account; a bad name, a weak password or an unknown role is refused with the reason."""
        if not _NAME.match(name or ""):
            raise AccountError("a user name is 2-32 lower-case letters, digits, '.', '_' or '-', starting with a "
                               "letter or digit")
        _check_role(role)
        _check_password(name, password)
        try:
            with self._db() as db:
                db.execute("INSERT INTO users (name, role, hash, created_s) VALUES (?, ?, ?, ?)",
                           (name, role, self.hasher.hash(password), time.time()))
        except sqlite3.IntegrityError:
            raise AccountError(f"user {name!r} already exists") from None
        self.audit(by, "account created", f"{name} ({role})")
        return User(name, role)

    def verify(self, name: str, password: str) -> User | None:
        """The user if ``password`` is theirs, else None (an unknown name costs the same hashing time)."""
        with self._db() as db:
            row = db.execute("SELECT role, hash FROM users WHERE name = ?", (name,)).fetchone()
        stored = row[1] if row else _DUMMY_HASH
        try:
            self.hasher.verify(stored, password or "")
        except (VerificationError, InvalidHashError):
            return None
        return User(name, row[0]) if row else None

    def users(self) -> list[User]:
        with self._db() as db:
            return [User(*row) for row in db.execute("SELECT name, role FROM users ORDER BY name")]

    def set_password(self, name: str, password: str, *, by: str) -> None:
        """A new password for ``name`` (by an admin, or the user after giving the old one); every session of
        ``name`` ends, since whoever knew the old password may hold one."""
        self._existing(name)
        _check_password(name, password)
        with self._db() as db:
            db.execute("UPDATE users SET hash = ?, generation = generation + 1 WHERE name = ?",
                       (self.hasher.hash(password), name))
        self.audit(by, "password changed", name)

    def set_role(self, name: str, role: str, *, by: str) -> None:
        """``name``'s role; the last admin cannot be demoted, so the accounts can always be managed."""
        old = self._existing(name).role
        _check_role(role)
        if old == "admin" and role != "admin" and self._admins() == 1:
            raise AccountError(f"{name} is the last admin: make another admin first")
        with self._db() as db:
            db.execute("UPDATE users SET role = ? WHERE name = ?", (role, name))
        self.audit(by, "role changed", f"{name}: {old} -> {role}")

    def remove(self, name: str, *, by: str) -> None:
        """Delete ``name``'s account (its audit entries stay); not one's own, nor the last admin."""
        user = self._existing(name)
        if name == by:
            raise AccountError("you cannot remove your own account")
        if user.role == "admin" and self._admins() == 1:
            raise AccountError(f"{name} is the last admin: make another admin first")
        with self._db() as db:
            db.execute("DELETE FROM users WHERE name = ?", (name,))
        self.audit(by, "account removed", f"{name} ({user.role})")

    def _existing(self, name: str) -> User:
        user = self.get(name)
        if user is None:
            raise AccountError(f"there is no user {name!r}")
        return user

    def _admins(self) -> int:
        with self._db() as db:
            return db.execute("SELECT count(*) FROM users WHERE role = 'admin'").fetchone()[0]

    def get(self, name: str) -> User | None:
        with self._db() as db:
            row = db.execute("SELECT role FROM users WHERE name = ?", (name,)).fetchone()
        return User(name, row[0]) if row else None

    def audit(self, user: str, action: str, detail: str = "") -> None:
        """Append an entry; a user name or detail too long to keep is cut (see :func:`bounded`)."""
        with self._db() as db:
            db.execute("INSERT INTO audit (time_s, user, action, detail) VALUES (?, ?, ?, ?)",
                       (time.time(), bounded(user, MAX_AUDIT_USER), action, bounded(detail, MAX_AUDIT_DETAIL)))

    def audit_log(self, limit: int = 200) -> list[dict]:
        with self._db() as db:
            rows = db.execute("SELECT time_s, user, action, detail FROM audit ORDER BY id DESC LIMIT ?", (limit,))
            return [dict(zip(("time_s", "user", "action", "detail"), row)) for row in rows]


def _check_role(role: str) -> None:
    if role not in ROLES:
        raise AccountError(f"role must be one of {', '.join(ROLES)}")


def _check_password(name: str, password: str) -> None:
    try:
        passwords.check(name, password)
    except passwords.WeakPassword as exc:
        raise AccountError(str(exc)) from None


def bounded(text: str, limit: int) -> str:
    """``text``, or its first ``limit`` characters and how many more there were.

    >>> bounded("abcdef", 4)
    'abcd...(+2 chars)'
    """
    return text if len(text) <= limit else f"{text[:limit]}...(+{len(text) - limit} chars)"


_DUMMY_HASH = PasswordHasher().hash("no such user: equal time for unknown names")
