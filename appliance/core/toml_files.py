"""Reading a TOML file with an error that names the file (layouts, configuration).

>>> read_toml("no-such-file.toml", "layout file", ValueError)
Traceback (most recent call last):
...
ValueError: layout file no-such-file.toml does not exist
"""

from __future__ import annotations

import tomllib
from pathlib import Path


def read_toml(path, what: str, error: type[Exception]) -> dict:
    """The parsed file; a missing or malformed file raises ``error`` naming ``what`` and the path."""
    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise error(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise error(f"{what} {path} is a folder, not a file") from None
    except OSError as exc:
        raise error(f"{what} {path} cannot be read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{what} {path} is not valid TOML: {exc}") from None
