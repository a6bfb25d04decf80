"""Argument types and input checks the ``appliance`` subcommands share.

Apart from :mod:`appliance.cli`, which builds the parser from every subcommand's module, so that those modules
import these from below instead of from the module that imports them.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from appliance.errors import ConfigError, ModelInputInvalid


def _number(kind, test, wanted: str):
    """An argparse ``type=`` for numbers that pass ``test``: NaN, infinity or a value out of range is refused where
    it enters, naming the option, instead of reaching a model or a loop that cannot use it."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"takes {wanted}, got {text!r}") from None
        if not math.isfinite(value) or not test(value):
            raise argparse.ArgumentTypeError(f"takes {wanted}, got {text!r}")
        return value

    parse.__name__ = wanted        # argparse names the type in its message when a conversion fails
    return parse


def within(low: float, high: float, unit: str = "", *, above: bool = False):
    """A ``type=`` for a number from ``low`` (or, ``above``, over it) to ``high`` in ``unit``: a value outside is
    refused with the range, so a unit slip or a stray exponent never reaches a model or a loop."""
    start = f"above {low:g} and at most" if above else f"from {low:g} to"
    return _number(float, lambda v: (v > low if above else v >= low) and v <= high,
                   f"a number {start} {high:g}{' ' + unit if unit else ''}")


def whole_within(low: int, high: int):
    """A ``type=`` for a whole number from ``low`` to ``high``."""
    return _number(int, lambda v: low <= v <= high, f"a whole number from {low} to {high}")


def numbers(item, count: int | None = None):
    """A ``type=`` for numbers separated by commas (``count`` of them, or any number), each parsed by ``item``."""
    wanted = f"{count or 'one or more'} numbers separated by commas, each {item.__name__}"

    def parse(text: str) -> list:
        try:
            values = [item(v) for v in text.split(",")]
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"takes {wanted}, got {text!r}") from None
        if count is not None and len(values) != count:
            raise argparse.ArgumentTypeError(f"takes {wanted}, got {text!r}")
        return values

    parse.__name__ = wanted
    return parse


seed = whole_within(0, 2**32 - 1)           # numpy's seeds, as the configuration's [virtual] seed
MAX_DENSITY = 8.0
"""The finest mesh density: each doubling has four times the elements, so beyond this a mesh only exhausts memory."""
density = within(0.0, MAX_DENSITY, above=True)
LONGEST_RUN_H = 24 * 365
"""A year: longer than any scenario or stay on one mat, so a longer run is a slip (seconds given for hours)."""
MAT_MM = 10_000.0
"""Positions and sizes on a mat: ten metres is far beyond any (a bed's is 1.9 m), so more is a unit slip."""
CONTRAST_RANGE = (1e-6, 1e6)
"""Conductivity ratios, insulator to metal in saline, that the forward solve stays accurate for (core/linsolve.py)."""


def check_input(path: Path, option: str) -> Path:
    """``path`` if it is a file, else a ConfigError naming ``option``, before anything slow is built."""
    if not path.exists():
        raise ConfigError(f"{option} {path} does not exist")
    if not path.is_file():
        raise ConfigError(f"{option} {path} is not a file")
    return path


MAX_PIXELS = 256
"""The finest pixel grid on a side: the KTC2023 label image's; finer grids only cost memory and time."""


def parse_pixels(text: str | None) -> tuple[int, int] | None:
    """``ROWSxCOLS`` as two whole numbers of 1 to MAX_PIXELS (None without ``text``); a ConfigError naming
    --pixels otherwise."""
    if not text:
        return None
    rows, _, cols = text.lower().partition("x")
    if not (rows.strip().isdigit() and cols.strip().isdigit()
            and 1 <= int(rows) <= MAX_PIXELS and 1 <= int(cols) <= MAX_PIXELS):
        raise ConfigError(f"--pixels takes ROWSxCOLS, whole numbers from 1 to {MAX_PIXELS}, got {text!r}")
    return int(rows), int(cols)


def parse_inclusion(text: str):
    from appliance.core.phantoms import Inclusion   # the model's stack only for the commands that use it

    shape, _, listed = text.partition(":")
    try:
        values = [float(v) for v in listed.split(",")]
    except ValueError:
        raise ModelInputInvalid(f"inclusion {text!r}: values must be numbers") from None
    try:
        if shape == "rect" and len(values) == 5:
            return physical(Inclusion("rect", *values))
        if shape == "disc" and len(values) == 4:
            x, y, d, contrast = values
            return physical(Inclusion("disc", x, y, d, d, contrast))
    except ModelInputInvalid as exc:
        raise ModelInputInvalid(f"inclusion {text!r}: {exc}") from None
    raise ModelInputInvalid(f"inclusion {text!r}: use rect:X,Y,W,H,CONTRAST or disc:X,Y,D,CONTRAST")


def physical(inclusion):
    """``inclusion`` if it could lie on a mat and its contrast is one the model solves; a ModelInputInvalid naming
    which is not."""
    low, high = CONTRAST_RANGE
    if max(abs(inclusion.x_mm), abs(inclusion.y_mm), inclusion.width_mm, inclusion.height_mm) > MAT_MM:
        raise ModelInputInvalid(f"positions must be from -{MAT_MM:g} to {MAT_MM:g} mm and sizes at most "
                                f"{MAT_MM:g} mm")
    if not low <= inclusion.contrast <= high:
        raise ModelInputInvalid(f"contrast must be from {low:g} to {high:g} (a conductivity ratio), got "
                                f"{inclusion.contrast:g}")
    return inclusion


def iana_zone(text: str) -> str:
    """A ``type=`` for a time zone the tz database names (``Europe/London``)."""
    from appliance.time_zones import time_zone

    try:
        time_zone(text, "time zone")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("time zone: ")) from None
    return text


def add_screen_options(parser, default_port: int) -> None:
    """``--listen``, ``--plain-http`` and ``--behind-proxy``: how a screen the command serves (the ward station's,
    the hospital overview) is reached."""
    parser.add_argument("--listen", metavar="[HOST:]PORT", default=str(default_port),
                        help=f"the screen's address (default 127.0.0.1:{default_port})")
    parser.add_argument("--plain-http", action="store_true", help="session cookies without the Secure flag")
    parser.add_argument("--behind-proxy", action="store_true",
                        help="trust X-Forwarded-For/-Proto from the TLS proxy on 127.0.0.1")
