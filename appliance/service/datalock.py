"""One data folder per monitor: an exclusive lock on a file in it, held while the monitor runs.

Two monitors on one folder would write one store and one live view with two
beds' frames. ``flock`` is released by the kernel when the holder dies, even by
SIGKILL, so a restart after a crash never finds a stale lock; the lock file is
never deleted, since unlinking it would let a second monitor lock a new file
while the first still holds the old one.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from appliance.errors import DataDirInUse

LOCK_FILE = "monitor.lock"


class DataDirLock:
    """The held lock on ``folder``; ``release`` (or the process's end) gives it up."""

    def __init__(self, folder: Path, fd: int):
        self.folder = folder
        self._fd: int | None = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)                  # closing the only descriptor drops the flock
            self._fd = None


def lock_data_dir(folder) -> DataDirLock:
    """Take the folder's lock and write this process's id in the lock file; DataDirInUse naming the folder
    and the holder's pid if another monitor has it."""
    folder = Path(folder)
    fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        raise DataDirInUse(f"data folder {folder} is in use by another monitor (pid {holder}): "
                           f"each monitor needs a folder of its own") from None
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
    return DataDirLock(folder, fd)
