"""The monitor's one configuration file, read and checked before anything starts.

Every key has a default, so an empty file (or none) runs the virtual bed; a
ward's file names only what differs. A wrong key, type or range is refused
with the section and key named, so ward IT fixes a typo before the monitor
runs, not after it silently ignored it::

    [monitor]
    layout = "grid-16x32"         # a built-in layout name or a layout .toml file
    source = "virtual"            # virtual | emulated | hardware
    frame_interval_s = 1.0
    bed_id = "ward3-bed12"        # MQTT topics and the live view name the bed by this
    time_zone = "Europe/London"   # IANA zone for the clock times shown and reported (default: the system's)
    data_dir = "/var/lib/appliance"
    # calibration = "pressure.json"   (default: the virtual mat's own, made once)

    [virtual]                     # source = "virtual": the simulated patient
    scenario = "turn-schedule"
    speed = 1.0                   # scene seconds per wall second; 0 = as fast as it goes
    seed = 0

    [board]                       # source = "emulated" or "hardware": as in drivers/profile.py

    [alerts]                      # defaults: appliance.alerts.pipeline.AlertSettings; safe ranges:
                                  # appliance.alerts.limits.SAFE_RANGES; sources in the README
    threshold_mmhg = 32
    curve = "reswick-rogers"      # or linder-ganz, or curve_points = [[minutes, mmHg], ...]
    alarm_dose = 1.0
    recovery = "reset"            # or "decay"
    relief_min = 15               # below the threshold this long relieves a site
    turn_interval_min = 120
    turn_grace_min = 30           # a due turn is overdue (high priority, escalated) this much later
    reminder_repeat_min = 30      # and repeated this often until a turn
    escalate_after_min = 15
    escalation_channel = "ward-station"

    [store]
    history_interval_s = 60
    history_days = 30
    event_days = 365
    max_mb = 512

    [notify.mqtt]
    host = "broker.ward"
    port = 8883
    topic_prefix = "appliance"
    username = "ward3-bed12"              # with password_file: the broker's account for this bed
    password_file = "/etc/appliance/mqtt-password"
    ca_file = "/etc/appliance/ward-ca.crt"  # TLS, the broker's certificate checked against this CA
    confirm = true                # each alarm change resent until a ward station confirms it end to end
    confirm_timeout_s = 10        # unconfirmed (or the link down) this long: a technical alarm at the bed

    [notify.engine]               # instead of [notify.mqtt]: the hospital engine (appliance.hospital)
    servers = ["nats://10.20.0.11:4222", "nats://10.20.0.12:4222", "nats://10.20.0.13:4222"]
    ward = "ward3"                # the bed's ward in the hospital description; the bed logs in as its bed_id
    password_file = "/etc/appliance/engine-password"   # secrets/<bed_id>.password of appliance hospital config
    ca_file = "/etc/appliance/hospital-ca.crt"   # with the description's [tls]: TLS to every node, checked by this CA
    confirm = true                # and confirm_timeout_s: as for [notify.mqtt]

    [notify.webhook]
    url = "https://station.ward/alarms"

    [notify.gpio]                 # the board's buzzer and LED (roles in [board]'s gpio table)
    buzzer = "buzzer"
    led = "status_led"

    [notify.nurse_call]           # dry-contact relays to the nurse-call system; off without this section
    high = "nurse_call_high"      # per priority, a role in [board]'s gpio table; a priority left out: no relay
    medium = "nurse_call_medium"
    low = "nurse_call_low"
    mode = "latched"              # closed until acknowledged; "follow": only while the condition holds too
    active_low = false            # true: a low line closes the relay

    [charting.hl7]                # HL7 v2 ORU^R01 over MLLP to the hospital's interface engine
    host = "engine.hospital"      # a host name or an IP address
    port = 2575
    enabled = true                # false: nothing is sent; what is queued waits
    sending_facility = "WARD3"
    receiving_application = "EHR"
    receiving_facility = "HOSPITAL"
    sending_application = "APPLIANCE"
    ack_timeout_s = 10
    undelivered_alarm_s = 300     # a message unacknowledged this long: a technical alarm at the bed
    observation_interval_s = 600  # peak pressure per site and posture charted this often
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from appliance.drivers.profile import board_profile
from appliance.errors import ConfigError
from appliance.service.config_sections import MonitorConfig, read_config, read_sections
from appliance.sim.scenes import builtin_scenes


def load_config(path) -> MonitorConfig:
    """The configuration in TOML file ``path``, checked whole; paths in it are taken relative to the file's folder."""
    config = read_config(path)
    try:
        return _checked(config, Path(path).resolve().parent)
    except ConfigError as exc:
        raise ConfigError(f"configuration file {path}: {exc}") from None


def config_from_mapping(data: dict, base: Path | None = None) -> MonitorConfig:
    """Build and check the configuration from parsed TOML; every bad section, key and value is named."""
    return _checked(read_sections(data, base), base)


def _checked(config: MonitorConfig, base: Path | None) -> MonitorConfig:
    """``config`` with its [board] table held against the board profiles and its scenario made a built-in's name
    or a file's absolute path."""
    try:
        board_profile(config.board)
    except ConfigError as exc:
        raise ConfigError(f"[board]: {exc}") from None
    return dataclasses.replace(config, scenario=_scenario(config.scenario, base))


def _scenario(name: str, base: Path | None) -> str:
    """A built-in scenario's name, or a scenario file's path made absolute against the config's folder."""
    if name in builtin_scenes():
        return name
    path = Path(name) if base is None or Path(name).is_absolute() else base / name
    if not path.is_file():
        raise ConfigError(f"[virtual] scenario {name!r} is neither a built-in scenario ({', '.join(builtin_scenes())}) "
                          f"nor a file")
    return str(path)
