"""The hospital description: its engine's nodes and its wards, beds and stations, in one TOML file, checked.

::

    [hospital]
    cluster = "st-mary"            # the NATS cluster's name
    store_dir = "/var/lib/appliance-hospital"   # each node keeps its JetStream files in <store_dir>/<node>
    replicas = 3                   # copies of every ward's alarm stream (1 or 3; 3 survives a node's loss)

    [[node]]                       # three nodes: a stream of 3 replicas needs 2 of them up to take a write
    name = "n1"
    host = "10.20.0.11"            # the address the node listens on and the others reach it at
    client_port = 4222             # beds, stations and tools (default 4222)
    cluster_port = 6222            # the other nodes (default 6222)
    monitor_port = 8222            # /healthz and /jsz over HTTP (default 8222)
    mqtt_port = 1883               # omit for no MQTT listener

    [[ward]]
    name = "ward3"
    beds = ["w3-bed01", "w3-bed02"]
    stations = ["ward3-station"]

    [[notifier]]                   # optional, any number: a notification service (appliance.hospital.notify)
    name = "phones"                # its engine user is notify-phones
    wards = ["ward3"]              # whose alarm changes it pages
    url = "https://pager.example/pages"        # the messaging gateway it POSTs each page to
    probe_url = "https://pager.example/health" # optional: answers 2xx while the gateway can page (default: any
                                               # answer below 500 to a HEAD of url shows the gateway is there)
    priorities = ["high", "medium"]            # the alarms it pages (default high and medium)

    [tls]                          # optional: TLS on every node's client and MQTT listeners and between nodes
    dir = "tls"                    # ca.crt, and <node>.crt and <node>.key for each node (appliance hospital certs)

    [history]                      # optional: the history store in PostgreSQL (appliance.hospital.history)
    database = "appliance_history" # the database's name (default appliance_history)
    events_days = 3650             # alarm, turn and episode events are kept this many days, then dropped
    pressure_days = 90             # the per-minute pressure trend likewise

A relative ``dir`` of ``[tls]`` is relative to the description's folder, as ``store_dir`` is. The retention
periods are the hospital's policy, so there is no default: without both the history writer does
not start. Names become tokens of NATS subjects and user names, so they may not hold '.', '*', '>', spaces or control
characters; a bed id or station is unique in the hospital, not only in its ward.
"""

from __future__ import annotations

import unicodedata
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

from appliance.alerts.alarms import PRIORITIES
from appliance.core.toml_files import check_keys, read_toml_as, toml_value
from appliance.errors import ConfigError
from appliance.hospital.tls import TlsFolder

MAX_NAME = 64
NAME_FORBIDDEN = ".*>/\\\"'#+:$"
"""Subject tokens may not hold '.', '*' or '>'; the rest would need quoting in the server's configuration, in a
stream's name or in an MQTT topic."""
MAX_RETENTION_DAYS = 36525
"""A hundred years: a larger figure is a typing error, not a policy."""
REPLICAS = (1, 3)
"""1 for a trial on one node; 3 for a stream that keeps taking writes, and loses none it acknowledged, when one
node dies (a quorum of 2). 2 would stop at the loss of either node and is refused."""
PAGED_PRIORITIES = ("high", "medium")
"""What a notification service pages unless its description says otherwise: low alarms wait for the screen."""


@dataclass(frozen=True)
class Node:
    name: str
    host: str
    client_port: int = 4222
    cluster_port: int = 6222
    monitor_port: int = 8222
    mqtt_port: int | None = None

    @property
    def client_url(self) -> str:
        return f"nats://{self.host}:{self.client_port}"


@dataclass(frozen=True)
class Ward:
    name: str
    beds: tuple[str, ...]
    stations: tuple[str, ...]


@dataclass(frozen=True)
class HistoryPolicy:
    """Where the history goes and how long each kind is kept, in days."""

    events_days: int
    pressure_days: int
    database: str = "appliance_history"


@dataclass(frozen=True)
class Notifier:
    """A service paging its wards' alarm changes of ``priorities`` to the messaging gateway at ``url``; the gateway's
    health address ``probe_url`` (None: the service asks ``url`` itself) tells while no page is due whether it is
    there."""

    name: str
    wards: tuple[str, ...]
    url: str
    priorities: tuple[str, ...] = PAGED_PRIORITIES
    probe_url: str | None = None


@dataclass(frozen=True)
class Hospital:
    cluster: str
    store_dir: Path
    nodes: tuple[Node, ...]
    wards: tuple[Ward, ...]
    replicas: int = 3
    history: HistoryPolicy | None = None
    notifiers: tuple[Notifier, ...] = ()
    tls: TlsFolder | None = None

    @property
    def ca_file(self) -> Path | None:
        """The hospital CA its clients trust, or None when the engine does not speak TLS."""
        return None if self.tls is None else self.tls.ca_file

    def notifier(self, name: str) -> Notifier:
        """The notification service ``name``, or a ConfigError naming the ones there are."""
        for service in self.notifiers:
            if service.name == name:
                return service
        raise ConfigError(f"no [[notifier]] named {name!r} in the hospital description; its notifiers: "
                          f"{', '.join(s.name for s in self.notifiers) or 'none'}")


def load_hospital(path) -> Hospital:
    """The hospital described in TOML file ``path``; a relative ``store_dir`` is relative to the file's folder."""
    return read_toml_as(path, "hospital description", ConfigError, hospital_from_mapping)


def hospital_from_mapping(data: dict, base: Path | None = None) -> Hospital:
    check_keys(data, {"hospital", "node", "ward", "history", "notifier", "tls"}, "the hospital description",
               ConfigError)
    top = _table(data.get("hospital"), "[hospital]")
    check_keys(top, {"cluster", "store_dir", "replicas"}, "[hospital]", ConfigError)
    cluster = check_name(_string(top, "cluster", "[hospital]"), "[hospital] cluster")
    store_dir = _folder(top, "store_dir", "[hospital]", base)
    replicas = top.get("replicas", 3)
    if replicas not in REPLICAS or isinstance(replicas, bool):
        raise ConfigError(f"[hospital] replicas must be 1 or 3, got {replicas!r}")
    nodes = tuple(_node(table, number) for number, table in enumerate(_array(data, "node"), start=1))
    if len(nodes) < replicas:
        raise ConfigError(f"[hospital] replicas = {replicas} needs at least {replicas} [[node]] tables, "
                          f"got {len(nodes)}")
    _unique([node.name for node in nodes], "node name")
    _unique([(node.host, port) for node in nodes for port in _ports(node)], "host and port")
    wards = tuple(_ward(table, number) for number, table in enumerate(_array(data, "ward"), start=1))
    _unique([ward.name for ward in wards], "ward name")
    _unique([name for ward in wards for name in (*ward.beds, *ward.stations)], "bed id or station")
    history = None if "history" not in data else history_policy(data["history"])
    notifiers = data.get("notifier", [])
    if not isinstance(notifiers, list):
        raise ConfigError("notifier must be [[notifier]] tables, one per notification service")
    services = tuple(_notifier(table, number, wards) for number, table in enumerate(notifiers, start=1))
    _unique([service.name for service in services], "notifier name")
    tls = None
    if "tls" in data:
        table = _table(data["tls"], "[tls]")
        check_keys(table, {"dir"}, "[tls]", ConfigError)
        tls = TlsFolder(_folder(table, "dir", "[tls]", base))
    return Hospital(cluster, store_dir, nodes, wards, replicas, history, services, tls)


def history_policy(table) -> HistoryPolicy:
    """The ``[history]`` table checked: each retention a whole number of days, the database a plain name."""
    table = _table(table, "[history]")
    check_keys(table, {"database", "events_days", "pressure_days"}, "[history]", ConfigError)
    days = {}
    for key in ("events_days", "pressure_days"):
        value = table.get(key)
        if value is None:
            raise ConfigError(f"[history] {key} is missing: how many days the hospital keeps them is its policy, "
                              f"so there is no default")
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_RETENTION_DAYS:
            raise ConfigError(f"[history] {key} must be a whole number of days from 1 to {MAX_RETENTION_DAYS}, "
                              f"got {value!r}")
        days[key] = value
    database = table.get("database", "appliance_history")
    if not isinstance(database, str) or not (database.isascii() and database.isidentifier()) \
            or database != database.lower() or len(database) > 63:
        raise ConfigError(f"[history] database {database!r}: must be 1-63 lower-case letters, digits and '_', "
                          f"not starting with a digit")
    return HistoryPolicy(days["events_days"], days["pressure_days"], database)


def description_text(hospital: Hospital) -> str:
    """``hospital`` as a description file that :func:`load_hospital` reads back to the same hospital."""
    lines = ["[hospital]", f"cluster = {toml_value(hospital.cluster)}",
             f"store_dir = {toml_value(str(hospital.store_dir))}", f"replicas = {hospital.replicas}"]
    for node in hospital.nodes:
        lines += ["", "[[node]]", f"name = {toml_value(node.name)}", f"host = {toml_value(node.host)}",
                  f"client_port = {node.client_port}", f"cluster_port = {node.cluster_port}",
                  f"monitor_port = {node.monitor_port}"]
        if node.mqtt_port is not None:
            lines.append(f"mqtt_port = {node.mqtt_port}")
    for ward in hospital.wards:
        lines += ["", "[[ward]]", f"name = {toml_value(ward.name)}", f"beds = {toml_value(ward.beds)}",
                  f"stations = {toml_value(ward.stations)}"]
    for service in hospital.notifiers:
        lines += ["", "[[notifier]]", f"name = {toml_value(service.name)}", f"wards = {toml_value(service.wards)}",
                  f"url = {toml_value(service.url)}", f"priorities = {toml_value(service.priorities)}"]
        if service.probe_url is not None:
            lines.append(f"probe_url = {toml_value(service.probe_url)}")
    if hospital.tls is not None:
        lines += ["", "[tls]", f"dir = {toml_value(str(hospital.tls.path))}"]
    if hospital.history is not None:
        lines += ["", "[history]", f"database = {toml_value(hospital.history.database)}",
                  f"events_days = {hospital.history.events_days}", f"pressure_days = {hospital.history.pressure_days}"]
    return "\n".join(lines) + "\n"


def check_name(name: str, what: str) -> str:
    """``name`` if it can be a subject token, a user name and part of a stream's name, else a ConfigError naming
    ``what`` it is."""
    if not isinstance(name, str) or not 1 <= len(name) <= MAX_NAME or any(
            c in NAME_FORBIDDEN or c.isspace() or unicodedata.category(c) == "Cc" for c in name):
        raise ConfigError(f"{what} {name!r}: must be 1-{MAX_NAME} characters without spaces, control characters "
                          f"or any of {NAME_FORBIDDEN}")
    return name


def _node(table, number: int) -> Node:
    where = f"[[node]] number {number}"
    table = _table(table, where)
    check_keys(table, {"name", "host", "client_port", "cluster_port", "monitor_port", "mqtt_port"}, where,
               ConfigError)
    name = check_name(_string(table, "name", where), f"{where} name")
    host = _string(table, "host", where)
    if any(c.isspace() or c in "/@" for c in host):
        raise ConfigError(f"{where} host {host!r}: an address or host name, without spaces, '/' or '@'")
    mqtt_port = table.get("mqtt_port")
    return Node(name, host, _port(table, "client_port", 4222, where), _port(table, "cluster_port", 6222, where),
                _port(table, "monitor_port", 8222, where),
                None if mqtt_port is None else _port(table, "mqtt_port", 0, where))


def _ward(table, number: int) -> Ward:
    where = f"[[ward]] number {number}"
    table = _table(table, where)
    check_keys(table, {"name", "beds", "stations"}, where, ConfigError)
    name = check_name(_string(table, "name", where), f"{where} name")
    beds = tuple(check_name(bed, f"[[ward]] {name} bed id") for bed in _strings(table, "beds", f"[[ward]] {name}"))
    stations = tuple(check_name(station, f"[[ward]] {name} station")
                     for station in _strings(table, "stations", f"[[ward]] {name}"))
    return Ward(name, beds, stations)


def _notifier(table, number: int, wards: tuple[Ward, ...]) -> Notifier:
    where = f"[[notifier]] number {number}"
    table = _table(table, where)
    check_keys(table, {"name", "wards", "url", "priorities", "probe_url"}, where, ConfigError)
    name = check_name(_string(table, "name", where), f"{where} name")
    where = f"[[notifier]] {name}"
    known = [ward.name for ward in wards]
    served = _strings(table, "wards", where)
    for ward in served:
        if ward not in known:
            raise ConfigError(f"{where} wards: {ward!r} is not a [[ward]] of the hospital; its wards: "
                              f"{', '.join(known)}")
    _unique(served, f"{where} ward")
    url = _web_address(_string(table, "url", where), f"{where} url")
    probe_url = None if "probe_url" not in table else _web_address(_string(table, "probe_url", where),
                                                                    f"{where} probe_url")
    priorities = table.get("priorities", list(PAGED_PRIORITIES))
    if not isinstance(priorities, list) or not priorities or any(p not in PRIORITIES for p in priorities):
        raise ConfigError(f"{where} priorities must be a non-empty list of {', '.join(PRIORITIES)}, got "
                          f"{priorities!r}")
    _unique(priorities, f"{where} priority")
    return Notifier(name, tuple(served), url, tuple(priorities), probe_url)


def _web_address(url: str, where: str) -> str:
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname or any(c.isspace() for c in url):
        raise ConfigError(f"{where} {url!r}: must be an http:// or https:// address with a host")
    return url


def _ports(node: Node) -> list[int]:
    return [port for port in (node.client_port, node.cluster_port, node.monitor_port, node.mqtt_port)
            if port is not None]


def _port(table: dict, key: str, default: int, where: str) -> int:
    port = table.get(key, default)
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ConfigError(f"{where} {key} must be a port from 1 to 65535, got {port!r}")
    return port


def _folder(table: dict, key: str, where: str, base: Path | None) -> Path:
    """The folder ``key`` names, a relative one taken from ``base`` (the description's folder)."""
    folder = Path(_string(table, key, where))
    return folder if folder.is_absolute() else (base or Path.cwd()) / folder


def _table(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{where} is missing or not a table")
    return value


def _array(data: dict, key: str) -> list:
    value = data.get(key)
    if not isinstance(value, list) or not value:
        raise ConfigError(f"no [[{key}]] tables: the hospital needs at least one")
    return value


def _string(table: dict, key: str, where: str) -> str:
    value = table.get(key)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: '{key}' must be a non-empty string, got {value!r}")
    return value


def _strings(table: dict, key: str, where: str) -> list[str]:
    value = table.get(key)
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{where}: '{key}' must be a non-empty list of names, got {value!r}")
    return value


def _unique(values: list, what: str) -> None:
    seen = set()
    for value in values:
        if value in seen:
            raise ConfigError(f"{what} {value!r} is given twice in the hospital description")
        seen.add(value)
