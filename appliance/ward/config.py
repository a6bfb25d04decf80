"""The ward station's configuration file, checked like the monitor's: every bad key and value is named.

::

    [broker]                      # the same keys as a bed's [notify.mqtt]
    host = "broker.ward"
    port = 8883
    topic_prefix = "appliance"
    keepalive_s = 30
    username = "ward-station"
    password_file = "/etc/appliance/ward-password"
    ca_file = "/etc/appliance/ward-ca.crt"

    [engine]                      # instead of [broker]: the hospital engine (appliance.hospital)
    servers = ["nats://10.20.0.11:4222", "nats://10.20.0.12:4222", "nats://10.20.0.13:4222"]
    ward = "ward3"                # the ward in the hospital description
    password_file = "/etc/appliance/engine-password"   # secrets/<client_id>.password of appliance hospital config
    ca_file = "/etc/appliance/hospital-ca.crt"   # with the description's [tls]: TLS to every node, checked by this CA

    [station]
    client_id = "ward3-station"   # names the broker session that holds alarms while the station is away; on
                                  # the engine, the station's name in the hospital description and its consumer
    summary_interval_s = 1.0      # the beds' summary interval: a bed silent for 3 of them (+2 s) is offline
    screen_url = "https://{bed_id}.ward3.example/"   # each bed's own screen; omit for no link
    command_expiry_s = 120.0      # a nurse's command a bed has not answered by then is given up, and refused

    [history]                     # optional: the hospital history in PostgreSQL (appliance hospital history)
    dsn = "host=history.hospital dbname=appliance_history user=ward3-station"   # libpq's; no password in it
    ward = "ward3"                # the ward's name in the history (default: the [engine] ward)
    look_back_h = 12              # how far back the sparklines and the ward's history list reach: a shift
"""

from __future__ import annotations

import socket
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from appliance.core.toml_files import read_toml_as
from appliance.errors import ConfigError
from appliance.hospital.description import check_name
from appliance.service.config_sections import (EngineSettings, MqttSettings, _number, _only, _section, _text,
                                               engine_settings, mqtt_settings)
from appliance.ward.commands import DEFAULT_EXPIRY_S


LOOK_BACK_H = 12.0                  # a shift
MAX_LOOK_BACK_H = 24.0              # two shifts: at a row a minute, what a screen still draws at once


@dataclass(frozen=True)
class HistorySource:
    """Where the ward screen reads the hospital history: PostgreSQL at ``dsn``, as ward ``ward``, the last
    ``look_back_h`` hours."""

    dsn: str
    ward: str
    look_back_h: float = LOOK_BACK_H


@dataclass(frozen=True)
class WardConfig:
    broker: MqttSettings | None
    client_id: str = field(default_factory=lambda: f"ward-station-{socket.gethostname()}")
    summary_interval_s: float = 1.0
    screen_url: str | None = None
    command_expiry_s: float = DEFAULT_EXPIRY_S
    engine: EngineSettings | None = None
    history: HistorySource | None = None

    def screen_of(self, bed_id: str) -> str | None:
        """The bed's own screen, from the ``screen_url`` pattern (None without one)."""
        return None if self.screen_url is None else self.screen_url.format(bed_id=quote(bed_id, safe=""))


def load_ward_config(path) -> WardConfig:
    """The station's configuration in TOML file ``path``; paths in it are relative to the file's folder."""
    return read_toml_as(path, "ward station configuration", ConfigError, ward_config_from_mapping)


def ward_config_from_mapping(data: dict, base: Path | None = None) -> WardConfig:
    _only(data, {"broker", "engine", "station", "history"}, "the ward station configuration")
    broker = mqtt_settings(_section(data, "broker"), base, "[broker]")
    engine = engine_settings(_section(data, "engine"), base, "[engine]")
    if broker is None and engine is None:
        raise ConfigError("[broker] is missing: the station needs the ward's broker 'host' (or [engine], the "
                          "hospital engine)")
    if broker is not None and engine is not None:
        raise ConfigError("[broker] and [engine] are both given: a station reads its ward from one")
    station = _section(data, "station")
    where = "[station]"
    _only(station, {"client_id", "summary_interval_s", "screen_url", "command_expiry_s"}, where)
    client_id = _text(station, "client_id", f"ward-station-{socket.gethostname()}", where)
    if len(client_id) > 64 or any(c in client_id for c in "/#+ "):
        raise ConfigError(f"{where}: client_id must be 1-64 characters without spaces, '/', '#' or '+', "
                          f"got {client_id!r}")
    screen_url = _text(station, "screen_url", None, where) if "screen_url" in station else None
    if screen_url is not None:
        _check_screen_url(screen_url, where)
    history = history_source(_section(data, "history"), engine) if "history" in data else None
    return WardConfig(broker, client_id, _number(station, "summary_interval_s", 1.0, where, low=0.1, high=60.0),
                      screen_url, _number(station, "command_expiry_s", DEFAULT_EXPIRY_S, where, low=5.0,
                                          high=3600.0), engine, history)


def history_source(table: dict, engine: EngineSettings | None) -> HistorySource:
    """The ``[history]`` table: the ward is the engine's unless named, which a station on a ward broker must."""
    where = "[history]"
    _only(table, {"dsn", "ward", "look_back_h"}, where)
    dsn = _text(table, "dsn", None, where)
    _check_dsn(dsn, where)
    if "ward" in table:
        ward = check_name(table["ward"], f"{where} ward")
    elif engine is not None:
        ward = engine.ward
    else:
        raise ConfigError(f"{where} is missing 'ward': the ward's name in the hospital history (a station on the "
                          f"engine takes its [engine] ward)")
    return HistorySource(dsn, ward, _number(table, "look_back_h", LOOK_BACK_H, where, low=1.0, high=MAX_LOOK_BACK_H))


def _check_dsn(dsn: str, where: str) -> None:
    """A libpq connection string without a password: this file is no place for one (libpq's passfile is)."""
    try:
        from psycopg import ProgrammingError
        from psycopg.conninfo import conninfo_to_dict
    except ImportError:
        raise ConfigError(f"{where} needs the PostgreSQL driver: install the appliance with its hospital extra "
                          f"(pip install 'appliance[hospital]')") from None
    try:
        keys = conninfo_to_dict(dsn)
    except ProgrammingError as exc:
        raise ConfigError(f"{where}: dsn is not a PostgreSQL connection string ({str(exc).strip()})") from None
    if "password" in keys:
        raise ConfigError(f"{where}: dsn must not hold the password: put it in a passfile and name that in the dsn "
                          f"(passfile=...)")


def _check_screen_url(pattern: str, where: str) -> None:
    if not pattern.startswith(("http://", "https://")):
        raise ConfigError(f"{where}: screen_url must start with http:// or https://, got {pattern!r}")
    try:
        pattern.format(bed_id="bed")
    except (KeyError, IndexError, ValueError) as exc:
        raise ConfigError(f"{where}: screen_url may hold only {{bed_id}}, got {pattern!r} ({exc!r})") from None
