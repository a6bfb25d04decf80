"""The safe range of each patient setting that could blind the monitor, and the ward's policy inside it.

IEC 60601-1-8 asks that an operator cannot set alarm limits that make the alarm
system useless. A threshold of 200 mmHg, an alarm at five times the tolerance or
a turn every 12 hours would do that quietly, so each such setting has one safe
range, here, applied wherever a value comes in (configuration file, settings
file, Settings page, file upload). Inside it a ward may set a narrower policy
(``[policy]`` in the settings file, set by an admin) that bounds what a nurse may
choose; with no policy the safe range is the policy. The README's settings table
gives each range's source.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from appliance.alerts.pipeline import AlertSettings
from appliance.core.pressure import KPA_PER_MMHG
from appliance.core.toml_files import check_keys
from appliance.errors import ConfigError


@dataclass(frozen=True)
class SafeRange:
    """The lowest and highest value a setting may take, its unit as the settings show it, and why."""

    low: float
    high: float
    unit: str
    why: str

    def text(self) -> str:
        return span_text(self.low, self.high, self.unit)


SAFE_RANGES = {
    "threshold_mmhg": SafeRange(20.0, 60.0, "mmHg",
                                "capillary closing pressure is about 32 mmHg (Landis 1930), quoted 20-30+; above "
                                "60 mmHg the usual peaks on standard foam (sacrum 40, heel 46-59 mmHg, Hermans "
                                "2012) would never count as loaded"),
    "alarm_dose": SafeRange(0.05, 1.0, "",
                            "1.0 is the whole tolerance of the curve; beyond it the alarm comes after the curve's "
                            "own limit of harm; a lower dose only warns earlier"),
    "relief_min": SafeRange(5.0, 30.0, "min",
                            "LS-HAPI counts tissue recovered after 15 min offloaded; under 5 min a brief lift "
                            "would clear a site's dose, over 30 min a real offload would not count"),
    "turn_interval_min": SafeRange(15.0, 240.0, "min",
                                   "EPUAP/NPIAP 2019 individualised repositioning; 4 h is NICE's interval for high "
                                   "risk and the longest of the individualised schedules studied (q1-q4h); a turn "
                                   "counts only after 15 min in the new posture"),
    "turn_grace_min": SafeRange(0.0, 60.0, "min",
                                "the due reminder sounds at the interval whatever the grace; the grace only delays "
                                "the overdue one (HIGH, escalated), by an hour at most"),
    "reminder_repeat_min": SafeRange(5.0, 60.0, "min",
                                     "an overdue reminder repeats at least hourly until a turn; more often than "
                                     "every 5 min is alarm fatigue"),
    "escalate_after_min": SafeRange(1.0, 30.0, "min",
                                    "an unanswered pressure alarm reaches the ward station within half an hour; "
                                    "escalation ladders step every 5 min"),
}
"""Each setting that can blind the monitor (as the settings file names it) and its safe range."""

CURVE_MAX_HOURS_AT = (60.0, 12.0)
"""A ward's own tolerance curve (``curve_points``) may tolerate the top of the threshold's safe range, 60 mmHg,
for at most 12 hours: Reswick & Rogers tolerate it 6.3 h and their data end at about 12 h. A curve's time falls as
pressure rises, so every higher pressure is bounded too; a curve beyond this would alarm long after the harm."""

POLICY = "policy"
"""The settings file's table holding the ward's policy: ``threshold_mmhg = [28, 40]``, one span per setting."""

_DEFAULTS = AlertSettings()


def span_text(low: float, high: float, unit: str = "") -> str:
    """``20-60 mmHg``."""
    return f"{low:g}-{high:g}" + (f" {unit}" if unit else "")


def alert_values(alerts: AlertSettings) -> dict:
    """The patient settings of ``alerts`` in the settings file's keys and units (mmHg, minutes)."""
    return {"threshold_mmhg": round(alerts.threshold_kpa / KPA_PER_MMHG, 6), "curve": alerts.curve,
            "alarm_dose": alerts.alarm_dose, "recovery": alerts.recovery,
            "relief_min": round(alerts.relief_s / 60, 6),
            "turn_interval_min": round(alerts.turn_interval_s / 60, 6),
            "turn_grace_min": round(alerts.turn_grace_s / 60, 6),
            "reminder_repeat_min": round(alerts.reminder_repeat_s / 60, 6),
            "escalate_after_min": round(alerts.escalate_after_s / 60, 6)}


DEFAULTS = alert_values(_DEFAULTS)
"""The patient settings' defaults (``AlertSettings``) in the settings file's keys and units."""


def check_safe(key: str, value, where: str = "[alerts]") -> float:
    """``value`` of setting ``key`` as a float; ConfigError naming the setting, its value and its safe range
    when it is no number or outside that range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {key} must be a number, got {value!r}")
    safe = SAFE_RANGES[key]
    if not safe.low <= value <= safe.high:
        raise ConfigError(f"{where}: {key} must be from {safe.low:g} to {safe.high:g}"
                          f"{' ' + safe.unit if safe.unit else ''} (its safe range), got {value:g}")
    return float(value)


def check_curve(curve, where: str = "[alerts] curve_points") -> None:
    """A ward's own tolerance curve (a ``ToleranceCurve``) refused, naming what it tolerates, when it
    tolerates ``CURVE_MAX_HOURS_AT`` longer than allowed."""
    mmhg, hours = CURVE_MAX_HOURS_AT
    tolerated = float(dataclasses.replace(curve, floor_kpa=0.0).tolerable_s(mmhg * KPA_PER_MMHG)) / 3600.0
    if not tolerated <= hours:
        raise ConfigError(f"{where}: the curve tolerates {mmhg:g} mmHg for {tolerated:.3g} h; a ward's curve may "
                          f"tolerate it for at most {hours:g} h (Reswick & Rogers: 6.3 h)")


def default_policy() -> dict[str, tuple[float, float]]:
    """The policy where a ward has set none: each setting's safe range."""
    return {key: (safe.low, safe.high) for key, safe in SAFE_RANGES.items()}


def check_policy(table) -> dict[str, tuple[float, float]]:
    """A ``[policy]`` table checked: each key a setting with a safe range, each value a ``[low, high]`` pair
    inside it. Returns the whole policy (settings it leaves out keep their safe range)."""
    if not isinstance(table, dict):
        raise ConfigError(f"[{POLICY}] must be a table, got {table!r}")
    policy = default_policy()
    check_keys(table, SAFE_RANGES, f"[{POLICY}]", ConfigError)
    for key, span in table.items():
        if not isinstance(span, (list, tuple)) or len(span) != 2 or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in span):
            raise ConfigError(f"[{POLICY}]: {key} must be a pair of numbers [low, high], got {span!r}")
        low, high = float(span[0]), float(span[1])
        safe = SAFE_RANGES[key]
        if low > high:
            raise ConfigError(f"[{POLICY}]: {key} {span_text(low, high, safe.unit)}: low is above high")
        if low < safe.low or high > safe.high:
            raise ConfigError(f"[{POLICY}]: {key} {span_text(low, high, safe.unit)} is outside its safe range "
                              f"{safe.text()}")
        policy[key] = (low, high)
    return policy


def check_within_policy(values: dict, policy: dict[str, tuple[float, float]]) -> None:
    """Each setting of ``values`` (file keys) inside ``policy``; ConfigError naming the setting, its value and
    the policy's span otherwise."""
    for key, value in values.items():
        if key in policy and isinstance(value, (int, float)):
            low, high = policy[key]
            if not low <= value <= high:
                raise ConfigError(f"[alerts]: {key} {value:g} is outside the ward policy "
                                  f"{span_text(low, high, SAFE_RANGES[key].unit)} (an admin sets the policy)")


def not_default(alerts: AlertSettings) -> list[dict]:
    """The patient settings of ``alerts`` that differ from the defaults, each with its value, default, unit and
    a line to show (``threshold 40 mmHg (default 32)``)."""
    out = []
    for key, value in alert_values(alerts).items():
        default = DEFAULTS[key]
        same = value == default if isinstance(value, str) else math.isclose(value, default, abs_tol=1e-9)
        if same and not (key == "curve" and alerts.curve_points):
            continue
        unit = SAFE_RANGES[key].unit if key in SAFE_RANGES else ""
        words = key.removesuffix("_mmhg").removesuffix("_min").replace("_", " ")
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        default_shown = f"{default:g}" if isinstance(default, float) else str(default)
        out.append({"key": key, "value": value, "default": default, "unit": unit,
                    "text": f"{words} {shown}{' ' + unit if unit else ''} (default {default_shown})"})
    return out
