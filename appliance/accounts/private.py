"""Files only the screen's own user may read: the session key and the accounts database.

The key signs every session cookie and the database holds password hashes and
the audit log, so neither may be readable by other users of the machine. New
files are made owner-only; files an older version left readable are narrowed
when they are opened.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

OWNER_ONLY = 0o600


def private_file(path: Path) -> Path:
    """``path`` made (empty) if missing, and readable and writable by its owner alone."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, OWNER_ONLY)
    os.close(fd)
    narrow(path)
    return path


def narrow(path: Path) -> None:
    """Take group and other rights off ``path`` if it exists and has any."""
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        return
    if mode & 0o077:
        os.chmod(path, mode & 0o700)
