"""The ward's clock: an IANA time zone checked by name, and monitor times read as clock times in it.

Records keep Unix seconds (UTC) throughout; only what a person reads becomes a
local clock time, at the last step, so a daylight-saving change moves no record
and one instant reads the same on every page, in the live view and in the shift
report. A zone is named as the tz database names it (``Europe/London``) and read
by the standard library's :mod:`zoneinfo`, from the system's zone files or, on a
system without them, the ``tzdata`` package. Around the autumn change the same
hour comes twice, so a written time carries its zone's abbreviation (01:30 BST,
then 01:30 GMT an hour later).

>>> clock_text(1792888200.0, time_zone("Europe/London"))
'2026-10-25 01:30:00 BST'
>>> clock_text(1792891800.0, time_zone("Europe/London"))
'2026-10-25 01:30:00 GMT'
>>> time_zone("Mars/Base", "time_zone")
Traceback (most recent call last):
...
appliance.errors.ConfigError: time_zone: unknown time zone 'Mars/Base'; name a tz database zone, such as Europe/London
"""

from __future__ import annotations

import contextlib
import os
from datetime import datetime
from pathlib import Path
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from appliance.errors import ConfigError

WALL_CLOCK_AFTER_S = 1e9
"""Times above this are wall-clock Unix seconds (2001 on); below, a simulated bed's seconds since its start."""
LOCALTIME = Path("/etc/localtime")
TIMEZONE_FILE = Path("/etc/timezone")
FALLBACK_ZONE = "UTC"


def time_zone(name, where: str = "time zone") -> ZoneInfo:
    """The zone the tz database calls ``name``; anything else raises ConfigError naming ``where`` and ``name``."""
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"{where}: a time zone is named as text, such as Europe/London; got {name!r}")
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError, OSError):
        raise ConfigError(f"{where}: unknown time zone {name!r}; name a tz database zone, such as Europe/London") \
            from None


def system_zone() -> str:
    """The system's own zone by its tz database name: ``$TZ``, else what ``/etc/localtime`` links to, else
    ``/etc/timezone`` (Debian's); UTC when none of them names a zone zoneinfo knows."""
    candidates = [os.environ.get("TZ", "").removeprefix(":")]
    if LOCALTIME.is_symlink():
        target = str(LOCALTIME.resolve())
        candidates.append(target.partition("/zoneinfo/")[2])
    with contextlib.suppress(OSError, UnicodeDecodeError):
        candidates.append(TIMEZONE_FILE.read_text(encoding="utf-8").strip())
    for name in candidates:
        try:
            time_zone(name)
        except ConfigError:
            continue
        return name
    return FALLBACK_ZONE


def local_time(time_s: float, zone: ZoneInfo) -> datetime:
    """Unix seconds ``time_s`` as the clock in ``zone`` shows them (an aware datetime)."""
    return datetime.fromtimestamp(time_s, zone)


def clock_text(time_s: float, zone: ZoneInfo, form: str = "%Y-%m-%d %H:%M:%S %Z") -> str:
    """A wall-clock time as a person reads it in ``zone`` (``form`` as for strftime); a simulated bed's seconds
    as h:mm:ss since its start."""
    if time_s > WALL_CLOCK_AFTER_S:
        return local_time(time_s, zone).strftime(form)
    t = round(time_s)
    return f"{t // 3600}:{t % 3600 // 60:02d}:{t % 60:02d}"
