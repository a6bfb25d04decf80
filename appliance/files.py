"""Writing files: checked before the work that makes them, and written so that a crash or power loss leaves the
old file or the new one, never half of either."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def check_writable(path: Path, what: str, suffixes: tuple[str, ...] = (), kinds: str | None = None) -> Path:
    """``path`` if a file can be written there, else a ConfigError naming ``what`` (an option, or "output"): checked
    before the work that makes the file, so a typo in a folder name does not lose a long computation. ``suffixes``
    are the extensions allowed, described as ``kinds`` (default: the suffixes themselves)."""
    from appliance.errors import ConfigError

    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise ConfigError(f"{what} {path}: the extension must be {kinds or ' or '.join(suffixes)}, got "
                          f"{path.suffix or 'none'!r}")
    if not path.parent.is_dir():
        raise ConfigError(f"{what} {path}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a folder, not a file")
    return path


def write_atomic(path: Path, content) -> None:
    """Write ``content`` to a new file beside ``path``, flush it to the disk, rename it over ``path``, and flush
    the folder so the rename itself survives a power cut. A failed write leaves no temporary file behind.

    ``content`` is text, bytes, or a function writing to the open binary file: a large file (a model's
    matrices) is then streamed rather than held in memory twice."""
    path = Path(path)
    data = content.encode("utf-8") if isinstance(content, str) else content
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as out:
            if callable(data):
                data(out)
            else:
                out.write(data)
            out.flush()
            os.fsync(out.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def read_secret(path: Path, remedy: str) -> str:
    """The first line of secret file ``path`` (a password), or a ConfigError naming it; ``remedy`` says what to
    do when it is empty."""
    from appliance.errors import ConfigError

    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the password ({exc})") from None
    if not lines or not lines[0]:
        raise ConfigError(f"{path}: empty; {remedy}")
    return lines[0]
