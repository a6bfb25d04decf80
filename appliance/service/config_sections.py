"""The configuration file's sections read and checked: every key's type and range, with the section named.

What needs no front end and no simulator, so the screen reads and checks settings with it alone; the board's
profile and the virtual bed's scenario are checked against the drivers' and the simulator's own data by
:mod:`appliance.service.config`, which the monitor reads its configuration through.
"""

from __future__ import annotations

import contextlib
import ipaddress
import math
import os
import re
import socket
from dataclasses import dataclass, field
from pathlib import Path

from appliance.alerts.dose import BUILT_IN as BUILT_IN_CURVES
from appliance.alerts.dose import RECOVERY_MODES, custom_curve
from appliance.alerts.limits import check_curve, check_safe
from appliance.alerts.nurse_call import MODES as NURSE_CALL_MODES
from appliance.alerts.nurse_call import check as check_nurse_call
from appliance.alerts.pipeline import AlertSettings
from appliance.core.pressure import KPA_PER_MMHG
from appliance.core.toml_files import check_keys, read_toml_as
from appliance.errors import ConfigError, CurveInvalid
from appliance.hospital.tls import client_context
from appliance.time_zones import system_zone, time_zone

SOURCES = ("virtual", "emulated", "hardware")
FRAME_INTERVAL_RANGE_S = (0.05, 3600.0)
"""Seconds between frames, here and for the command line's --interval, which overrides it."""
MQTT_KEYS = ("host", "port", "topic_prefix", "keepalive_s", "username", "password_file", "ca_file")
ENGINE_KEYS = ("servers", "ward", "password_file", "ca_file")
CONFIRMATION_KEYS = ("confirm", "confirm_timeout_s")
"""The ward link's tables: ``[notify.mqtt]`` or ``[notify.engine]``, each with the confirmation's keys."""
HL7_KEYS = ("host", "port", "enabled", "sending_facility", "sending_application", "receiving_application",
            "receiving_facility", "ack_timeout_s", "undelivered_alarm_s", "observation_interval_s")
"""The keys of ``[charting.hl7]``, in the order the screen shows them."""
HOST_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")
SPEED_RANGE = (0.0, 1e6)
"""The virtual bed's scene seconds per wall-clock second, here and for --speed (0: as fast as it goes)."""


@dataclass(frozen=True)
class StoreSettings:
    history_interval_s: float = 60.0
    history_days: float = 30.0
    event_days: float = 365.0
    max_mb: float = 512.0


@dataclass(frozen=True)
class MqttSettings:
    """The ward's broker; ``username`` with the password kept in ``password_file`` (readable by the service
    alone, never in this file), and TLS verified against ``ca_file`` when it is given."""

    host: str
    port: int = 1883
    topic_prefix: str = "appliance"
    keepalive_s: int = 30
    username: str | None = None
    password_file: Path | None = None
    ca_file: Path | None = None

    def password(self) -> str | None:
        """The password file's first line; a missing or unreadable file is a ConfigError naming it."""
        if self.password_file is None:
            return None
        try:
            return self.password_file.read_text(encoding="utf-8").splitlines()[0]
        except (OSError, IndexError, UnicodeDecodeError) as exc:
            raise ConfigError(f"[notify.mqtt] password_file {self.password_file}: cannot read a password "
                              f"({exc or 'the file is empty'})") from None


@dataclass(frozen=True)
class EngineSettings:
    """The hospital engine (``appliance.hospital``): its nodes' client addresses, the bed's ward, and the file
    holding the bed's password (its user name is its ``bed_id``), as ``appliance hospital config`` wrote them; TLS,
    each node's certificate checked against the hospital CA ``ca_file``, when it is given."""

    servers: tuple[str, ...]
    ward: str
    password_file: Path
    ca_file: Path | None = None

    def password(self) -> str:
        """The password file's first line; a missing or unreadable file is a ConfigError naming it."""
        try:
            return self.password_file.read_text(encoding="utf-8").splitlines()[0]
        except (OSError, IndexError, UnicodeDecodeError) as exc:
            raise ConfigError(f"the hospital engine's password_file {self.password_file}: cannot read a password "
                              f"({exc or 'the file is empty'})") from None


@dataclass(frozen=True)
class ConfirmSettings:
    """End-to-end confirmation of the ward link: ``confirm`` off counts the broker's acknowledgement as delivery
    (a broker with no ward station behind it); either way a technical alarm comes after ``timeout_s``."""

    confirm: bool = True
    timeout_s: float = 10.0


@dataclass(frozen=True)
class WebhookSettings:
    url: str
    timeout_s: float = 5.0


@dataclass(frozen=True)
class Hl7Settings:
    """The hospital's interface engine for charting (``appliance.charting.link``)."""

    host: str
    port: int
    sending_facility: str
    receiving_application: str
    receiving_facility: str = ""
    sending_application: str = "APPLIANCE"
    ack_timeout_s: float = 10.0
    undelivered_alarm_s: float = 300.0
    observation_interval_s: float = 600.0
    enabled: bool = True
    """False keeps the target but sends nothing (what is queued waits for it to be switched on)."""


@dataclass(frozen=True)
class GpioSettings:
    """Roles in the board profile's ``[gpio]`` table (not pins), so a board that moved a pin needs no change here."""

    buzzer: str = "buzzer"
    led: str = "status_led"


@dataclass(frozen=True)
class NurseCallSettings:
    """The nurse-call relays (:mod:`appliance.alerts.nurse_call`): a role in the board profile's ``[gpio]`` table
    per priority that has a relay, how they follow the alarms, and whether a low line closes them."""

    relays: dict[str, str]
    mode: str = "latched"
    active_low: bool = False


@dataclass(frozen=True)
class MonitorConfig:
    """Everything the daemon is told: built by :func:`read_sections`, checked whole by
    :mod:`appliance.service.config`."""

    layout: str = "grid-16x32"
    source: str = "virtual"
    frame_interval_s: float = 1.0
    bed_id: str = field(default_factory=socket.gethostname)
    time_zone: str = field(default_factory=system_zone)
    """The IANA zone the screen and the shift report show clock times in."""
    data_dir: Path | None = None
    calibration: Path | None = None
    cache_dir: Path | None = None
    scenario: str = "turn-schedule"
    speed: float = 1.0
    seed: int = 0
    board: dict = field(default_factory=dict)
    alerts: AlertSettings = AlertSettings()
    store: StoreSettings = StoreSettings()
    mqtt: MqttSettings | None = None
    engine: EngineSettings | None = None
    confirmation: ConfirmSettings = ConfirmSettings()
    webhook: WebhookSettings | None = None
    gpio: GpioSettings | None = None
    nurse_call: NurseCallSettings | None = None
    hl7: Hl7Settings | None = None


def default_data_dir() -> Path:
    """``$APPLIANCE_DATA_DIR``, else ``$XDG_DATA_HOME/appliance``, else ``~/.local/share/appliance``."""
    if os.environ.get("APPLIANCE_DATA_DIR"):
        return Path(os.environ["APPLIANCE_DATA_DIR"])
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "appliance"


def read_config(path) -> MonitorConfig:
    """The configuration in TOML file ``path``, its sections checked as :func:`read_sections` does; paths in it
    are taken relative to the file's folder."""
    return read_toml_as(path, "configuration file", ConfigError, read_sections)


def read_sections(data: dict, base: Path | None = None) -> MonitorConfig:
    """Build the configuration from parsed TOML, every bad section, key and value named; the [board] table and
    the [virtual] scenario are kept as written, for :func:`appliance.service.config.config_from_mapping` to check
    against the board profiles and the scenarios."""
    _only(data, {"monitor", "virtual", "board", "alerts", "store", "notify", "charting"}, "the configuration")
    monitor = _section(data, "monitor")
    _only(monitor, {"layout", "source", "frame_interval_s", "bed_id", "time_zone", "data_dir", "calibration",
                    "cache_dir"}, "[monitor]")
    virtual = _section(data, "virtual")
    _only(virtual, {"scenario", "speed", "seed"}, "[virtual]")
    source = _choice(monitor, "source", SOURCES, "virtual", "[monitor]")
    if virtual and source != "virtual":
        raise ConfigError(f"[virtual] is only for source = \"virtual\", but [monitor] source = {source!r}")
    notify = _section(data, "notify")
    _only(notify, {"mqtt", "engine", "webhook", "gpio", "nurse_call"}, "[notify]")
    gpio = _gpio(_section(notify, "gpio", "notify.gpio")) if "gpio" in notify else None
    if gpio is not None and source == "virtual":
        raise ConfigError("[notify.gpio] needs a board: the virtual bed has no buzzer or LED lines")
    nurse_call = _nurse_call(_section(notify, "nurse_call", "notify.nurse_call")) if "nurse_call" in notify else None
    if nurse_call is not None and source == "virtual":
        raise ConfigError("[notify.nurse_call] needs a board: the virtual bed has no relay lines")
    mqtt = dict(_section(notify, "mqtt", "notify.mqtt"))
    engine = dict(_section(notify, "engine", "notify.engine"))
    if mqtt and engine:
        raise ConfigError("[notify.mqtt] and [notify.engine] are both given: a bed reaches its ward through one")
    link, where, needed = (engine, "[notify.engine]", "servers") if engine else (mqtt, "[notify.mqtt]", "host")
    confirming = {key: link.pop(key) for key in CONFIRMATION_KEYS if key in link}
    if confirming and not link:
        raise ConfigError(f"{where} is missing {needed!r}")
    confirmation = _confirmation(confirming, where)
    board = _section(data, "board")
    return MonitorConfig(
        layout=_text(monitor, "layout", "grid-16x32", "[monitor]"),
        source=source,
        frame_interval_s=_number(monitor, "frame_interval_s", 1.0, "[monitor]", *FRAME_INTERVAL_RANGE_S),
        bed_id=_bed_id(monitor),
        time_zone=_time_zone(monitor),
        data_dir=_path(monitor, "data_dir", base),
        calibration=_path(monitor, "calibration", base),
        cache_dir=_path(monitor, "cache_dir", base),
        scenario=_text(virtual, "scenario", "turn-schedule", "[virtual]"),
        speed=_number(virtual, "speed", 1.0, "[virtual]", *SPEED_RANGE),
        seed=int(_number(virtual, "seed", 0, "[virtual]", low=0, high=2**32 - 1, integer=True)),
        board=board,
        alerts=_alerts(_section(data, "alerts")),
        store=_store(_section(data, "store")),
        mqtt=mqtt_settings(mqtt, base),
        engine=engine_settings(engine, base),
        confirmation=confirmation,
        webhook=_webhook(_section(notify, "webhook", "notify.webhook")),
        gpio=gpio,
        nurse_call=nurse_call,
        hl7=_hl7(_section(data, "charting")),
    )


def _alerts(table: dict) -> AlertSettings:
    where = "[alerts]"
    _only(table, {"threshold_mmhg", "curve", "curve_points", "alarm_dose", "recovery", "relief_min",
                  "turn_interval_min", "turn_grace_min", "reminder_repeat_min", "escalate_after_min",
                  "escalation_channel"}, where)
    if "curve" in table and "curve_points" in table:
        raise ConfigError(f"{where}: give curve or curve_points, not both")
    points = None
    if "curve_points" in table:
        try:
            curve = custom_curve(table["curve_points"])
        except (CurveInvalid, TypeError) as exc:
            raise ConfigError(f"{where} curve_points: {exc}") from None
        check_curve(curve, f"{where} curve_points")
        points = tuple((float(m), float(p)) for m, p in table["curve_points"])
        name = curve.name
    else:
        name = _choice(table, "curve", tuple(BUILT_IN_CURVES), "reswick-rogers", where)
    d = AlertSettings()                                  # the one definition of each clinical default

    def safe(key: str, default: float) -> float:
        """``key`` (its default when absent) inside its safe range (alerts/limits.py)."""
        return check_safe(key, table.get(key, default), where)

    return AlertSettings(
        threshold_kpa=safe("threshold_mmhg", d.threshold_kpa / KPA_PER_MMHG) * KPA_PER_MMHG,
        curve=name, curve_points=points,
        alarm_dose=safe("alarm_dose", d.alarm_dose),
        recovery=_choice(table, "recovery", RECOVERY_MODES, d.recovery, where),
        relief_s=60.0 * safe("relief_min", d.relief_s / 60.0),
        turn_interval_s=60.0 * safe("turn_interval_min", d.turn_interval_s / 60.0),
        turn_grace_s=60.0 * safe("turn_grace_min", d.turn_grace_s / 60.0),
        reminder_repeat_s=60.0 * safe("reminder_repeat_min", d.reminder_repeat_s / 60.0),
        escalate_after_s=60.0 * safe("escalate_after_min", d.escalate_after_s / 60.0),
        escalation_channel=_text(table, "escalation_channel", d.escalation_channel, where))


def _store(table: dict) -> StoreSettings:
    where = "[store]"
    _only(table, {"history_interval_s", "history_days", "event_days", "max_mb"}, where)
    return StoreSettings(_number(table, "history_interval_s", 60.0, where, low=0.0, high=86400.0),
                         _number(table, "history_days", 30.0, where, low=0.01, high=3650.0),
                         _number(table, "event_days", 365.0, where, low=1.0, high=36500.0),
                         _number(table, "max_mb", 512.0, where, low=1.0, high=1e6))


def mqtt_settings(table: dict, base: Path | None, where: str = "[notify.mqtt]") -> MqttSettings | None:
    """The broker table ``where`` (a bed's ``[notify.mqtt]``, the ward station's ``[broker]``); None if empty."""
    if not table:
        return None
    _only(table, set(MQTT_KEYS), where)
    if "host" not in table:
        raise ConfigError(f"{where} is missing 'host'")
    prefix = _text(table, "topic_prefix", "appliance", where)
    if any(c in prefix for c in "#+") or prefix.startswith("/") or prefix.endswith("/"):
        raise ConfigError(f"{where}: topic_prefix must not hold wildcards or start or end with '/', got {prefix!r}")
    if "password_file" in table and "username" not in table:
        raise ConfigError(f"{where}: password_file needs a username")
    password_file = _path(table, "password_file", base, where)
    if password_file is not None and not password_file.is_file():
        raise ConfigError(f"{where} password_file: no file {password_file}")
    files = {"password_file": password_file, "ca_file": _ca_file(table, base, where)}
    return MqttSettings(_text(table, "host", None, where),
                        int(_number(table, "port", 1883, where, low=1, high=65535, integer=True)), prefix,
                        int(_number(table, "keepalive_s", 30, where, low=5, high=3600, integer=True)),
                        _text(table, "username", None, where) if "username" in table else None, **files)


def engine_settings(table: dict, base: Path | None, where: str = "[notify.engine]") -> EngineSettings | None:
    """The engine table ``where`` (a bed's ``[notify.engine]``, the ward station's ``[engine]``); None if empty."""
    if not table:
        return None
    _only(table, set(ENGINE_KEYS), where)
    servers = table.get("servers")
    if not isinstance(servers, list) or not servers or not all(isinstance(s, str) and s.strip() for s in servers):
        raise ConfigError(f"{where}: servers must be a non-empty list of the nodes' addresses, got {servers!r}")
    ca_file = _ca_file(table, base, where)
    for server in servers:
        scheme, _, address = server.partition("://")
        if scheme not in ("nats", "tls") or not address or any(c.isspace() or c in "@/" for c in address):
            raise ConfigError(f"{where}: server {server!r} must be nats://HOST:PORT or tls://HOST:PORT, without a "
                              f"login")
        if scheme == "tls" and ca_file is None:
            raise ConfigError(f"{where}: server {server!r} is tls://, but no ca_file names the hospital CA that its "
                              f"certificate is checked against")
    ward = _text(table, "ward", None, where)
    if any(c in ward for c in ".*> ") or len(ward) > 64:
        raise ConfigError(f"{where}: ward must be the ward's name in the hospital description, without '.', '*', "
                          f"'>' or spaces, got {ward!r}")
    password_file = _path(table, "password_file", base, where)
    if password_file is None:
        raise ConfigError(f"{where} is missing 'password_file' (from appliance hospital config)")
    if not password_file.is_file():
        raise ConfigError(f"{where} password_file: no file {password_file}")
    return EngineSettings(tuple(servers), ward, password_file, ca_file)


def _confirmation(table: dict, where: str) -> ConfirmSettings:
    confirm = table.get("confirm", True)
    if not isinstance(confirm, bool):
        raise ConfigError(f"{where}: confirm must be true or false, got {confirm!r}")
    return ConfirmSettings(confirm, _number(table, "confirm_timeout_s", 10.0, where, low=1.0, high=600.0))


def _webhook(table: dict) -> WebhookSettings | None:
    if not table:
        return None
    where = "[notify.webhook]"
    _only(table, {"url", "timeout_s"}, where)
    url = _text(table, "url", None, where)
    if not url.startswith(("http://", "https://")):
        raise ConfigError(f"{where}: url must start with http:// or https://, got {url!r}")
    return WebhookSettings(url, _number(table, "timeout_s", 5.0, where, low=0.1, high=60.0))


def _hl7(charting: dict) -> Hl7Settings | None:
    _only(charting, {"hl7"}, "[charting]")
    table = _section(charting, "hl7", "charting.hl7")
    if not table:
        return None
    where = "[charting.hl7]"
    _only(table, set(HL7_KEYS), where)
    if "port" not in table:
        raise ConfigError(f"{where} is missing 'port'")
    enabled = table.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"{where}: enabled must be true or false, got {enabled!r}")
    names = {key: _text(table, key, default, where) for key, default in (
        ("sending_facility", None), ("receiving_application", None), ("sending_application", "APPLIANCE"))}
    names["receiving_facility"] = table.get("receiving_facility", "")     # MSH-6 may be empty: written as it is
    if not isinstance(names["receiving_facility"], str):
        raise ConfigError(f"{where}: receiving_facility must be text, got {names['receiving_facility']!r}")
    bad = [key for key, value in names.items() if any(c in value for c in "|^~\\&\r\n")]
    if bad:
        raise ConfigError(f"{where}: {bad[0]} must not hold HL7's delimiters | ^ ~ \\ & or line breaks")
    return Hl7Settings(host_name(table, "host", where),
                       int(_number(table, "port", 2575, where, low=1, high=65535, integer=True)), **names,
                       ack_timeout_s=_number(table, "ack_timeout_s", 10.0, where, low=0.5, high=300.0),
                       undelivered_alarm_s=_number(table, "undelivered_alarm_s", 300.0, where, low=10.0, high=86400.0),
                       observation_interval_s=_number(table, "observation_interval_s", 600.0, where, low=10.0,
                                                      high=86400.0), enabled=enabled)


def host_name(table: dict, key: str, where: str) -> str:
    """``table[key]`` as a host: a DNS name (letters, digits and '-' in dot-separated labels of 1-63, 253 in all)
    or an IPv4 or IPv6 address; anything else (a URL, a port, a space) is refused naming it."""
    host = _text(table, key, None, where)
    with contextlib.suppress(ValueError):
        ipaddress.ip_address(host)
        return host
    if len(host) > 253 or not all(HOST_LABEL.fullmatch(label) for label in host.removesuffix(".").split(".")):
        raise ConfigError(f"{where}: {key} must be a host name (such as engine.hospital) or an IP address, "
                          f"got {host!r}")
    return host


def _time_zone(monitor: dict) -> str:
    if "time_zone" not in monitor:
        return system_zone()
    name = monitor["time_zone"]
    time_zone(name, "[monitor] time_zone")
    return name


def _gpio(table: dict) -> GpioSettings:
    where = "[notify.gpio]"
    _only(table, {"buzzer", "led"}, where)
    return GpioSettings(_text(table, "buzzer", "buzzer", where), _text(table, "led", "status_led", where))


def _nurse_call(table: dict) -> NurseCallSettings:
    where = "[notify.nurse_call]"
    _only(table, {"high", "medium", "low", "mode", "active_low"}, where)
    relays = {priority: _text(table, priority, None, where) for priority in ("high", "medium", "low")
              if priority in table}
    mode = _choice(table, "mode", NURSE_CALL_MODES, "latched", where)
    active_low = table.get("active_low", False)
    if not isinstance(active_low, bool):
        raise ConfigError(f"{where}: active_low must be true or false, got {active_low!r}")
    try:
        check_nurse_call(relays, mode)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc} (give high, medium and/or low: roles in [board.gpio])") from None
    return NurseCallSettings(relays, mode, active_low)


def _bed_id(monitor: dict) -> str:
    bed = _text(monitor, "bed_id", socket.gethostname(), "[monitor]")
    if not bed or any(c in bed for c in "#+/ ") or len(bed) > 64:
        raise ConfigError(f"[monitor] bed_id must be 1-64 characters without spaces, '/', '#' or '+', got {bed!r}")
    return bed


def _section(data: dict, name: str, label: str | None = None) -> dict:
    table = data.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"[{label or name}] must be a table, got {table!r}")
    return dict(table)


def _only(table: dict, allowed: set, where: str) -> None:
    check_keys(table, allowed, where, ConfigError)


def _text(table: dict, key: str, default: str | None, where: str) -> str:
    if key not in table:
        if default is None:
            raise ConfigError(f"{where} is missing {key!r}")
        return default
    value = table[key]
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: {key} must be non-empty text, got {value!r}")
    return value


def _choice(table: dict, key: str, allowed: tuple, default: str, where: str) -> str:
    value = table.get(key, default)
    if value not in allowed:
        raise ConfigError(f"{where}: {key} must be one of {', '.join(allowed)}, got {value!r}")
    return value


def _number(table: dict, key: str, default: float, where: str, low: float, high: float, *,
            integer: bool = False) -> float:
    value = table.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {key} must be a number, got {value!r}")
    if integer and value != int(value):
        raise ConfigError(f"{where}: {key} must be a whole number, got {value!r}")
    if not low <= value <= high:
        raise ConfigError(f"{where}: {key} must be from {low:g} to {high:g}, got {value:g}")
    return float(value)


def _ca_file(table: dict, base: Path | None, where: str) -> Path | None:
    """The table's ``ca_file``, checked now to be a CA certificate TLS can load: found wrong only when a link first
    connects, a typo would leave a bed or a station retrying in the background instead of refusing to start."""
    path = _path(table, "ca_file", base, where)
    if path is None:
        return None
    if not path.is_file():
        raise ConfigError(f"{where} ca_file: no file {path}")
    try:
        client_context(path)
    except ConfigError:
        raise ConfigError(f"{where} ca_file: {path} holds no certificate TLS can load (a PEM CA certificate is "
                          f"needed)") from None
    return path


def _path(table: dict, key: str, base: Path | None, where: str = "[monitor]") -> Path | None:
    if key not in table:
        return None
    path = Path(_text(table, key, None, where))
    return path if base is None or path.is_absolute() else base / path
