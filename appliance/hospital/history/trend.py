"""The beds' summaries down-sampled to one row per bed and minute: how long the history keeps pressure.

A bed sends a summary about once a second (``appliance.service.daemon.ward_summary``): its peak pressure, each
region's peak and dose, its posture. Keeping every one would be 259 million rows a day for 3,000 beds; maps
are not sent at all. A minute keeps what a nurse reviewing a night asks of it: the highest peak and each
region's highest (a short high load is not averaged away), the last peak, posture and doses, how many
summaries it was made from and how many of them had a map (a minute of faults shows as such, not as calm).

>>> trend = MinuteTrend()
>>> for second, peak in enumerate([40.0, 55.5, None]):
...     trend.add("ward3", "bed1", 1_800_000_000.0 + second, {"peak_mmhg": peak, "posture": "supine",
...               "regions": [] if peak is None else [{"zone": "sacrum", "peak_mmhg": peak, "dose": 0.1 * second}]})
>>> [(m.bed_id, m.samples, m.maps, m.peak_max_mmhg, m.peak_last_mmhg, m.region_max_mmhg) for m in trend.take()]
[('bed1', 3, 2, 55.5, None, {'sacrum': 55.5})]
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field

from appliance.alerts.anatomy import UNIDENTIFIED_SITE

MINUTE_S = 60


@dataclass
class Minute:
    """One bed's minute so far; ``minute`` is its start, ``last_at`` the newest summary's arrival."""

    ward: str
    bed_id: str
    minute: dt.datetime
    samples: int = 0
    maps: int = 0
    peak_max_mmhg: float | None = None
    peak_last_mmhg: float | None = None
    posture: str | None = None
    region_max_mmhg: dict[str, float] = field(default_factory=dict)
    region_dose: dict[str, float] = field(default_factory=dict)
    last_at: dt.datetime | None = None


class MinuteTrend:
    """Summaries gathered into minutes until :meth:`take` hands over the finished ones."""

    def __init__(self) -> None:
        self._open: dict[tuple[str, int], Minute] = {}

    def __len__(self) -> int:
        return len(self._open)

    def add(self, ward: str, bed: str, at_s: float, summary: dict) -> None:
        """Count ``summary`` of ``bed``, heard at unix time ``at_s``; a ValueError naming what is wrong."""
        peak = _mmhg(summary.get("peak_mmhg"), "peak_mmhg")
        regions = summary.get("regions")
        if not isinstance(regions, list):
            raise ValueError(f"summary of {bed}: 'regions' must be a list, got {regions!r}")
        start = int(at_s // MINUTE_S) * MINUTE_S
        minute = self._open.get((bed, start))
        if minute is None:
            minute = self._open[(bed, start)] = Minute(ward, bed, dt.datetime.fromtimestamp(start, dt.UTC))
        minute.samples += 1
        minute.last_at = dt.datetime.fromtimestamp(at_s, dt.UTC)
        minute.peak_last_mmhg = peak
        posture = summary.get("posture")
        minute.posture = posture if isinstance(posture, str) else None
        if peak is not None:
            minute.maps += 1
            minute.peak_max_mmhg = peak if minute.peak_max_mmhg is None else max(minute.peak_max_mmhg, peak)
        for region in regions:
            if not isinstance(region, dict):
                raise ValueError(f"summary of {bed}: a region must be an object, got {region!r}")
            zone = region.get("zone") or UNIDENTIFIED_SITE
            value = _mmhg(region.get("peak_mmhg"), f"region {zone} peak_mmhg")
            if value is not None:
                minute.region_max_mmhg[zone] = max(value, minute.region_max_mmhg.get(zone, value))
            dose = region.get("dose")
            if isinstance(dose, int | float) and not isinstance(dose, bool) and math.isfinite(dose):
                minute.region_dose[zone] = float(dose)

    def take(self, before_s: float | None = None) -> list[Minute]:
        """The minutes that ended by unix time ``before_s`` (all of them when None), no longer held here."""
        done = [key for key in self._open if before_s is None or key[1] + MINUTE_S <= before_s]
        return [self._open.pop(key) for key in sorted(done, key=lambda key: (key[1], key[0]))]


def _mmhg(value, what: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise ValueError(f"summary {what} must be a pressure in mmHg or null, got {value!r}")
    return float(value)
