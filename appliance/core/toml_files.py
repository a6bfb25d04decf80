"""Reading a TOML file with an error that names the file, refusing keys a table does not take, and writing the
values of one (layouts, configuration, settings, scenarios, provisioning): the standard library reads TOML but
does not write it, and one reader, key check and writer keep every file alike.

>>> read_toml("no-such-file.toml", "layout file", ValueError)
Traceback (most recent call last):
...
ValueError: layout file no-such-file.toml does not exist
>>> check_keys({"layuot": 1}, {"layout"}, "[monitor]", ValueError)
Traceback (most recent call last):
...
ValueError: [monitor]: unknown key 'layuot'; allowed: layout
>>> print(toml_value(['a "b"', 2, 0.5, True]))
["a \\u0022b\\u0022", 2, 0.5, true]
>>> print(toml_table("charting", {"hl7": {"host": "engine", "port": 2575}}), end="")
[charting.hl7]
host = "engine"
port = 2575
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


def read_toml_as(path, what: str, error: type[Exception], build):
    """``build(data, folder)`` of TOML file ``path`` (paths in it relative to its ``folder``); what is wrong in
    the file is raised as ``error`` naming ``what`` and the path."""
    data = read_toml(path, what, error)
    try:
        return build(data, Path(path).resolve().parent)
    except error as exc:
        raise error(f"{what} {path}: {exc}") from None


def check_keys(table, allowed, where: str, error: type[Exception], *, noun: str = "key") -> None:
    """Refuse a table with a key not in ``allowed``, naming the first (so a typo cannot silently keep a default)."""
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        known = f"; allowed: {', '.join(sorted(allowed))}" if allowed else ""
        raise error(f"{where}: unknown {noun} {unknown[0]!r}{known}")


def toml_value(value) -> str:
    """``value`` (text, a whole number, a float, true or false, or a list of them) as TOML writes it.

    Text is a basic string, its quotes, backslashes and control characters written as ``\\uXXXX`` escapes; a float
    is Python's shortest repr, which TOML reads back to the same number (``inf`` and ``nan`` included). Anything
    else (a table, None) raises TypeError naming it: tables are written whole by :func:`toml_table`.
    """
    if isinstance(value, str):
        escaped = "".join(f"\\u{ord(c):04x}" if c in '"\\' or ord(c) < 0x20 or ord(c) == 0x7f else c for c in value)
        return f'"{escaped}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    raise TypeError(f"TOML values here are text, numbers, true or false and lists of them, got {value!r}")


def toml_table(name: str, table: dict) -> str:
    """Table ``name`` with its values under a ``[name]`` header and each table in it as ``[name.key]`` after them
    (none for an empty one), as TOML writes nested tables."""
    values = {key: value for key, value in table.items() if not isinstance(value, dict)}
    text = f"[{name}]\n" + "".join(f"{key} = {toml_value(value)}\n" for key, value in values.items()) if values else ""
    for key, value in table.items():
        if isinstance(value, dict) and value:
            text += ("\n" if text else "") + toml_table(f"{name}.{key}", value)
    return text
