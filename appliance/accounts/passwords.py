"""The password policy for the screen's accounts, applied wherever a password is set.

It follows NIST SP 800-63B section 5.1.1.2 and OWASP ASVS 4.0 V2.1: length
rather than composition rules (at least 10 characters here, above the guideline's 8,
because one account can acknowledge a patient's alarms), and a check against
passwords attackers try first: well-known common passwords (``common_passwords.txt``,
also with digits or punctuation appended), passwords of digits only or of one
repeated character, and passwords containing the user's own name. Every refusal
names what is wrong, as the guideline asks.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

MIN_LENGTH = 10
MAX_LENGTH = 128            # Argon2 takes any length; this only bounds the work per login
NAME_PART_MIN = 4           # parts of a user name ('nurse', 'jones' of 'nurse.jones') checked on their own
_TRAILING = re.compile(r"[\W\d_]+$")


class WeakPassword(ValueError):
    """A password the policy refuses; the message says why."""


@functools.cache
def common_passwords() -> frozenset[str]:
    """The shipped list of common passwords, lower case."""
    text = Path(__file__).with_name("common_passwords.txt").read_text(encoding="utf-8")
    return frozenset(line.strip().lower() for line in text.splitlines() if line.strip() and not line.startswith("#"))


def check(name: str, password: str) -> None:
    """Raise :class:`WeakPassword` naming the first rule ``password`` breaks for user ``name``."""
    password = password or ""
    if len(password) < MIN_LENGTH:
        raise WeakPassword(f"a password needs at least {MIN_LENGTH} characters")
    if len(password) > MAX_LENGTH:
        raise WeakPassword(f"a password has at most {MAX_LENGTH} characters")
    if password.isdigit():
        raise WeakPassword("a password of digits only is too easy to guess: use words or mix in letters")
    if len(set(password)) == 1:
        raise WeakPassword("a password of one repeated character is too easy to guess")
    lowered = password.lower()
    if lowered in common_passwords() or _TRAILING.sub("", lowered) in common_passwords():
        raise WeakPassword("this password is one of the most common ones and would be guessed first")
    name = (name or "").lower()
    parts = [name] + [part for part in re.split(r"[._-]", name) if len(part) >= NAME_PART_MIN]
    if any(part and part in lowered for part in parts):
        raise WeakPassword("the password must not contain the user name")
