"""Patient and bed settings set on the bedside screen, kept in ``settings.toml`` and applied to the running monitor.

The ward's configuration file says how a bed is monitored by default; what a
nurse sets for the patient in it (threshold, tolerance curve, alarm dose,
recovery, turn and escalation times), what an engineer sets for the bed (its
id and mat layout) and what an admin sets for the site (the time zone clock
times are shown in, the hospital's HL7 interface engine) is kept apart, in the
monitor's data directory, so the configuration file stays the ward's and a
restart keeps the choice made on the screen. The file holds the same tables and
keys as the configuration it overrides::

    [alerts]
    threshold_mmhg = 40
    turn_interval_min = 90

    [monitor]
    bed_id = "ward3-bed12"
    layout = "grid-16x32"
    time_zone = "Europe/London"

    [charting.hl7]
    host = "engine.hospital"
    port = 2575
    sending_facility = "WARD3"
    receiving_application = "EHR"

A ``[charting.hl7]`` table is the whole target and replaces the configuration's.

and is checked by the configuration's own parser, so a value refused in the
configuration file is refused here with the same message. A ``[policy]`` table
(``threshold_mmhg = [28, 40]``), the ward's narrower limits inside each setting's
safe range (:mod:`appliance.alerts.limits`), bounds the patient settings the file
may hold; only an admin changes it on the screen. It is written only
through :func:`write_settings` (a whole new file, fsynced, then renamed over the
old one), so a power cut leaves the old file or the new one, never half of one.

The screen is another process: it writes the file and queues an
``apply-settings`` command (args: the file's tables), which the monitor applies
at its next frame. Patient settings rebuild the alert pipeline from its state,
so doses, the turn clock and open alarms carry over (an open pressure alarm is
held until its site has been relieved for the relief time, whatever the new
threshold or alarm dose says); a new bed id and time zone show at once; a new
charting target takes over the charting queue at once
(:mod:`appliance.service.charting_target`); a new layout needs another
reconstruction model and applies when the monitor restarts.
The monitor keeps the settings it runs with in its store (state
``settings``) for the screen to show.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from appliance.alerts.limits import POLICY, alert_values, check_policy, check_within_policy
from appliance.alerts.pipeline import AlertPipeline
from appliance.core.named_layouts import BUILTIN_NAMES
from appliance.core.toml_files import check_keys, read_toml
from appliance.errors import ConfigError
from appliance.files import write_atomic
from appliance.time_zones import system_zone, time_zone
from appliance.core.toml_files import toml_table
from appliance.service.charting_target import describe_target, hl7_values, retarget
from appliance.service.config_sections import MonitorConfig, read_sections

SETTINGS_FILE = "settings.toml"
COMMAND = "apply-settings"
STATE = "settings"
ALERT_STATE = "alerts"
"""The daemon's saved alert pipeline state in its store."""
RESTART_NOTE = "applies when the monitor restarts"

PATIENT_FIELDS = {"threshold_mmhg": "threshold_kpa", "curve": "curve", "alarm_dose": "alarm_dose",
                  "recovery": "recovery", "relief_min": "relief_s", "turn_interval_min": "turn_interval_s",
                  "turn_grace_min": "turn_grace_s", "reminder_repeat_min": "reminder_repeat_s",
                  "escalate_after_min": "escalate_after_s"}
"""Patient settings (keys of the configuration's ``[alerts]``) and the AlertSettings field each sets."""
BED_KEYS = ("bed_id", "layout")
"""Bed settings (keys of the configuration's ``[monitor]``)."""
CLOCK_KEYS = ("time_zone",)
"""The site's clock (a key of the configuration's ``[monitor]``)."""
CHARTING = "charting"
"""The table of the charting target, ``[charting.hl7]`` as in the configuration."""
SECTIONS = {"alerts": tuple(PATIENT_FIELDS), "monitor": (*BED_KEYS, *CLOCK_KEYS), CHARTING: ("hl7",)}
"""The settings file's tables of settings and the keys each may hold."""
TABLES = (*SECTIONS, POLICY)
"""Every table the settings file may hold: the settings and the ward policy that bounds the patient's."""


def settings_path(data_dir) -> Path:
    """The settings file in the monitor's data directory ``data_dir``."""
    return Path(data_dir) / SETTINGS_FILE


def check_settings(settings: dict) -> MonitorConfig:
    """``settings`` (tables ``alerts`` and ``monitor`` as in the file) checked by the configuration's rules: the
    configuration they describe on their own; a wrong table, key or value raises ConfigError naming it."""
    unknown = sorted(set(settings) - set(TABLES))
    if unknown:
        raise ConfigError(f"unknown table [{unknown[0]}]; settings have {', '.join(f'[{s}]' for s in TABLES)}")
    policy = check_policy(settings.get(POLICY, {}))
    for section, keys in SECTIONS.items():
        table = settings.get(section, {})
        if not isinstance(table, dict):
            raise ConfigError(f"[{section}] must be a table, got {table!r}")
        check_keys(table, keys, f"[{section}]", ConfigError)
    checked = read_sections({section: dict(settings[section]) for section in SECTIONS if section in settings})
    if "layout" in settings.get("monitor", {}) and checked.layout not in BUILTIN_NAMES:
        raise ConfigError(f"[monitor]: layout must be one of {', '.join(BUILTIN_NAMES)}, got {checked.layout!r}")
    check_within_policy(settings.get("alerts", {}), policy)
    return checked


def policy_of(settings: dict) -> dict[str, tuple[float, float]]:
    """The ward policy a settings file holds (each setting's safe range where it sets none)."""
    return check_policy(settings.get(POLICY, {}))


def overlay(config: MonitorConfig, settings: dict) -> MonitorConfig:
    """``config`` with the keys ``settings`` holds replaced by their values (checked as in :func:`check_settings`)."""
    checked = check_settings(settings)
    patient = settings.get("alerts", {})
    alerts = {PATIENT_FIELDS[key]: getattr(checked.alerts, PATIENT_FIELDS[key]) for key in patient}
    if "curve" in patient:
        alerts["curve_points"] = None                  # a built-in curve replaces the ward's own points
    bed = {key: getattr(checked, key) for key in settings.get("monitor", {})}
    if CHARTING in settings:
        bed["hl7"] = checked.hl7
    return dataclasses.replace(config, alerts=dataclasses.replace(config.alerts, **alerts), **bed)


def settings_values(config: MonitorConfig) -> dict:
    """The patient, bed and clock settings of ``config`` in the file's tables and units (mmHg, minutes)."""
    return {"alerts": alert_values(config.alerts),
            "monitor": {"bed_id": config.bed_id, "layout": config.layout, "time_zone": config.time_zone}}


def same(a, b) -> bool:
    """Whether two setting values are equal (numbers to within rounding)."""
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (a, b))
    return abs(a - b) <= 1e-9 * max(1.0, abs(a), abs(b)) if numbers else a == b      # inf is never "the same"


def changes(old: dict, new: dict) -> list[tuple[str, object, object]]:
    """(key, old value, new value) of each setting ``new`` (tables as in the file) holds with another value."""
    return [(key, old.get(section, {}).get(key), value) for section, table in new.items()
            for key, value in table.items() if not same(old.get(section, {}).get(key), value)]


def describe(changed: list[tuple[str, object, object]]) -> str:
    """``threshold_mmhg 32 -> 40, layout grid-8x16 -> grid-4x4``."""
    return ", ".join(f"{key} {shown(old)} -> {shown(new)}" for key, old, new in changed)


def read_settings(path) -> dict:
    """The settings in file ``path``: {} when there is none; a file that is not valid TOML or holds a wrong
    table, key or value raises ConfigError naming the file."""
    path = Path(path)
    if not path.exists():
        return {}
    settings = read_toml(path, "settings file", ConfigError)
    try:
        check_settings(settings)
    except ConfigError as exc:
        raise ConfigError(f"settings file {path}: {exc}") from None
    return settings


def write_settings(path, settings: dict) -> None:
    """Replace file ``path`` with ``settings`` (checked first): written whole, fsynced, then renamed over."""
    write_atomic(Path(path), settings_text(settings))


def settings_text(settings: dict) -> str:
    """``settings`` (checked first) as a settings file's TOML."""
    check_settings(settings)
    lines = ["# Settings made on the bedside screen; they override the configuration file.\n"]
    lines += [f"\n{toml_table(section, settings[section])}" for section in TABLES if settings.get(section)]
    return "".join(lines)


def shown_time_zone(data_dir, live: dict | None) -> str:
    """The zone clock times are shown in for the monitor of ``data_dir``: the settings file's, else the one the
    monitor runs with (its live view ``live``), else the system's. A settings file that cannot be read is passed
    over here, since the clock must still be shown; the settings page says what is wrong with it."""
    try:
        saved = read_settings(settings_path(data_dir))
    except ConfigError:
        saved = {}
    for name in (saved.get("monitor", {}).get("time_zone"), (live or {}).get("time_zone")):
        try:
            return time_zone(name).key
        except ConfigError:
            continue
    return system_zone()


def load_overlaid(config: MonitorConfig, data_dir) -> MonitorConfig:
    """``config`` with the settings file in ``data_dir`` laid over it (as it is, when there is no file)."""
    return overlay(config, read_settings(settings_path(data_dir)))


def attach(daemon) -> None:
    """Before ``daemon.start()``: let it take ``apply-settings`` commands, and record the settings it runs with
    for the screen."""
    daemon.add_commands({COMMAND: lambda now, args, user, command_id: apply_settings(daemon, now, args)})
    publish(daemon, daemon.source.now())


def published(config: MonitorConfig) -> dict:
    """What the monitor running with ``config`` tells the screen: its settings, and its charting target."""
    return {**settings_values(config), CHARTING: {"hl7": hl7_values(config.hl7)}}


def publish(daemon, now: float) -> None:
    """Save what ``daemon`` runs with (:func:`published`) in its store (state ``settings``), where the screen
    reads it."""
    daemon.writes.save_state(STATE, published(daemon.config), now)


def apply_settings(daemon, now: float, args: dict) -> tuple[list, str]:
    """The ``apply-settings`` command: lay ``args`` (tables as in the settings file) over the running
    configuration; patient settings take effect now, the pipeline rebuilt from its state so doses, turn
    clock and open alarms carry over, and a new charting target takes over the charting queue. A wrong value,
    or a patient setting outside the ward policy in the settings file, raises ConfigError, which refuses the
    command (the store takes whatever any process queues)."""
    wanted = overlay(daemon.config, args)
    if daemon.config.data_dir is not None:
        check_within_policy(args.get("alerts", {}), policy_of(read_settings(settings_path(daemon.config.data_dir))))
    changed = changes(settings_values(daemon.config), settings_values(wanted))
    target = wanted.hl7 != daemon.config.hl7
    if not changed and not target:
        return [], "nothing changed"
    old_target = daemon.config.hl7
    if target:
        retarget(daemon, wanted)                   # first: a queue that cannot be opened refuses the whole command
    if wanted.alerts != daemon.config.alerts:
        daemon.pipeline = AlertPipeline.from_state(daemon.grid, daemon.pipeline.state(), wanted.alerts)
    daemon.config = dataclasses.replace(wanted, layout=daemon.config.layout)   # the running model's mat
    publish(daemon, now)
    applied = [c for c in changed if c[0] != "layout"]
    later = [c for c in changed if c[0] == "layout"]
    parts = [f"applied {describe(applied)}"] if applied else []
    if target:
        parts.append(f"charting target {describe_target(old_target)} -> {describe_target(wanted.hl7)}")
    if later:
        parts.append(f"{describe(later)} {RESTART_NOTE}")
    if daemon.config.mqtt is not None and any(c[0] == "bed_id" for c in changed):
        parts.append("MQTT topics take the new bed id when the monitor restarts")
    return [], "; ".join(parts)


def shown(value) -> str:
    """A setting's value as a person reads it (32, not 32.0)."""
    return f"{value:g}" if isinstance(value, float) else str(value)
