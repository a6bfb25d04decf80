"""The engineering commands' names and arguments, and the folder their files live in.

Checked here, once, for both sides: the screen refuses bad input before queueing (:func:`checked_args`), and the
daemon (:mod:`appliance.service.engineering`, which runs the commands on the front end) refuses it again, since the
store accepts whatever any process queues. Apart from the commands themselves so that the screen imports no
front end or simulator.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

ENGINEERING_DIR = "engineering"
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


@dataclass(frozen=True)
class Whole:
    """An integer from ``low`` to ``high``; ``default`` when it may be left out."""

    low: int
    high: int
    default: int | None = None

    @property
    def allowed(self) -> str:
        return f"an integer from {self.low} to {self.high}"

    def check(self, value) -> int:
        if isinstance(value, str) and re.fullmatch(r"\s*[+-]?\d+\s*", value):
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int) or not self.low <= value <= self.high:
            raise ValueError(self.allowed)
        return value


@dataclass(frozen=True)
class Number:
    """A number from ``low`` to ``high``."""

    low: float
    high: float
    default: float | None = None

    @property
    def allowed(self) -> str:
        return f"a number from {self.low:g} to {self.high:g}"

    def check(self, value) -> float:
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                raise ValueError(self.allowed) from None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or not self.low <= value <= self.high:
            raise ValueError(self.allowed)
        return float(value)


@dataclass(frozen=True)
class OneOf:
    """One of ``choices``."""

    choices: tuple[str, ...]
    default: str | None = None

    @property
    def allowed(self) -> str:
        return "one of " + ", ".join(self.choices)

    def check(self, value) -> str:
        if value not in self.choices:
            raise ValueError(self.allowed)
        return value


@dataclass(frozen=True)
class FileName:
    """A plain file name in the engineering folder."""

    default: None = None

    @property
    def allowed(self) -> str:
        return (f"a plain file name in {ENGINEERING_DIR}/ (letters, digits, '.', '_' and '-', at most 128 characters, "
                "no folder and no '..')")

    def check(self, value) -> str:
        if not isinstance(value, str) or not NAME_PATTERN.fullmatch(value) or ".." in value:
            raise ValueError(self.allowed)
        return value


TASKS: dict[str, dict] = {
    "acquire": {"averages": Whole(1, 100)},
    "series": {"count": Whole(2, 600), "interval_s": Number(0.0, 60.0)},
    "contact-check": {},
    "self-test": {},
    "capture-reference": {},
    "calibrate": {"kind": OneOf(("pressure",)), "positions": Whole(1, 3, default=2)},
    "rebuild-model": {},
    "save": {"what": OneOf(("image",))},
    "load": {"what": OneOf(("calibration",)), "file": FileName()},
}
"""Each engineering command's arguments and what they may be."""


def checked_args(task: str, args: Mapping) -> dict:
    """``args`` for ``task`` checked and brought to their types (defaults filled in); ValueError names the
    first argument that is wrong and what it may be."""
    if task not in TASKS:
        raise ValueError(f"unknown engineering task {task!r}: one of {', '.join(TASKS)}")
    rules = TASKS[task]
    unknown = sorted(set(args) - set(rules))
    if unknown:
        raise ValueError(f"{task} takes {', '.join(rules) or 'no arguments'}, not {', '.join(unknown)}")
    checked = {}
    for field, rule in rules.items():
        value = args.get(field)
        if value is None or value == "":
            if rule.default is None:
                raise ValueError(f"{task}: {field} is missing; it must be {rule.allowed}")
            checked[field] = rule.default
            continue
        try:
            checked[field] = rule.check(value)
        except ValueError as exc:
            raise ValueError(f"{task}: {field} must be {exc}, got {value!r}") from None
    return checked


def engineering_file(data_dir: Path, name: str) -> Path:
    """The file ``name`` in ``data_dir``'s engineering folder; ValueError for anything but a plain name."""
    try:
        return Path(data_dir) / ENGINEERING_DIR / FileName().check(name)
    except ValueError as exc:
        raise ValueError(f"file must be {exc}, got {name!r}") from None
