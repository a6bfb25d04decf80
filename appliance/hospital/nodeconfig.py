"""Each engine node's configuration, written from the hospital description, and everyone's passwords.

``write_node_configs`` writes into one folder:

- ``<node>.conf`` for every ``[[node]]``: the ``nats-server`` configuration of that node. JetStream writes to
  disk with ``sync_interval: always``, an fsync before every acknowledgement (the default, every 2 minutes, let
  Jepsen lose 14 % of acknowledged writes in a power cut of all nodes); routes to the other nodes, which log in
  with the cluster's own password, and tell no client of the other nodes' addresses (a bed or station reaches
  the nodes its own configuration names, through whatever firewall ward IT set for them); an MQTT 3.1.1 listener
  where the node has an ``mqtt_port``; and one account,
  HOSPITAL, holding every user with their permissions (file 0600: it holds the passwords). With the description's
  ``[tls]``, the client and MQTT listeners take TLS alone, with the node's certificate, and the routes are TLS
  both ways, each node showing its certificate and checking the other's against the hospital CA
  (``appliance.hospital.tls``); the monitoring port stays plain HTTP on the node's host.
- ``secrets/<user>.password``: each user's password on its first line, for the bed, the station or the tools
  (folder 0700, files 0600), and ``secrets/routes.password`` for the routes between nodes.

Users and what they may do (``appliance.hospital.subjects`` names the subjects):

- a bed (its id is its user name) publishes only ``hospital.<ward>.<bed>.{alarm,turn,episode,status,summary}``
  and its answers on ``hospital.<ward>.<bed>.command-result``, reads only its own ``confirm``, its own
  ``command`` and its own inbox, and may look up its own confirmations in the ward's confirmation stream;
- a station reads every subject of its ward (its beds' answers among them), writes its beds' ``confirm`` and
  ``command`` and the ward's confirmation stream, and may only read its ward's event stream through a consumer
  (create, fetch, acknowledge), never change or delete it; it reads the notification services' records back from
  the ward's confirmation stream through consumers it makes filtered on them, nothing else of that stream;
- ``hospital-admin`` may do everything: it creates the streams (``appliance hospital streams``);
- ``hospital-history``, the history writer, reads every ward's stream through its own consumers and hears every
  bed's summary (``appliance.hospital.history``);
- ``notify-<name>``, each ``[[notifier]]``, reads the streams of the wards it serves through its own consumers,
  records its own ``notified`` records in their confirmation streams and says its own paging status to them,
  nothing else (``appliance.hospital.notify``).

Running it again keeps every existing password and adds or drops users. A running node reads its file again
on ``nats-server --signal reload`` (SIGHUP), so a bed is added without a restart.
"""

from __future__ import annotations

import json
import secrets
from dataclasses import dataclass
from pathlib import Path

from appliance.errors import ConfigError
from appliance.files import read_secret, write_atomic
from appliance.hospital.description import Hospital, Node, Notifier, Ward
from appliance.hospital.subjects import (BED_KINDS, CONFIRM, CONFIRMED, ROOT, SUMMARY, answer_subject, bed_subject,
                                         command_subject, confirms_stream_name, inbox_prefix, notified_subject,
                                         paging_status_subject, stream_name)
from appliance.hospital.tls import HANDSHAKE_TIMEOUT_S

ADMIN = "hospital-admin"
HISTORY = "hospital-history"
"""The history writer's user: it reads every ward's stream and the beds' summaries, and publishes nothing else."""
NOTIFIER_PREFIX = "notify-"
"""A notification service's user is its name after this: the name of its durable consumers too."""
ROUTE_USER = "route"
ACCOUNT = "HOSPITAL"
PASSWORD_BYTES = 24
DUPLICATE_WINDOW_S = 900.0
"""How long each ward's stream remembers a message id: a bed's resends within it are stored once."""


def notifier_user(name: str) -> str:
    """The engine user (and consumer) of notification service ``name``."""
    return f"{NOTIFIER_PREFIX}{name}"


@dataclass(frozen=True)
class NodeConfigs:
    """What one run wrote: each node's configuration file, the secrets folder, and the users added and dropped."""

    files: dict[str, Path]
    secrets_folder: Path
    added: tuple[str, ...]
    removed: tuple[str, ...]


def write_node_configs(hospital: Hospital, folder: Path, nodes: list[str] | None = None) -> NodeConfigs:
    """Write the configuration of each of ``nodes`` (every node by default) and the users' passwords into
    ``folder`` (made if missing)."""
    users = [ADMIN, HISTORY, *(name for ward in hospital.wards for name in (*ward.beds, *ward.stations)),
             *(notifier_user(service.name) for service in hospital.notifiers)]
    if users.count(ADMIN) > 1:
        raise ConfigError(f"{ADMIN!r} is the engine's administrator: no bed or station may take that name")
    if users.count(HISTORY) > 1:
        raise ConfigError(f"{HISTORY!r} is the history writer: no bed or station may take that name")
    for service in hospital.notifiers:
        if users.count(notifier_user(service.name)) > 1:
            raise ConfigError(f"{notifier_user(service.name)!r} is notification service {service.name}'s user: no "
                              f"bed or station may take that name")
    folder = Path(folder).absolute()
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"configuration folder {folder} is a file, not a folder")
    if not folder.parent.is_dir():
        raise ConfigError(f"configuration folder {folder}: the folder {folder.parent} does not exist")
    folder.mkdir(mode=0o755, exist_ok=True)
    secrets_folder = folder / "secrets"
    secrets_folder.mkdir(mode=0o700, exist_ok=True)
    secrets_folder.chmod(0o700)
    existing = {path.name.removesuffix(".password") for path in secrets_folder.glob("*.password")}
    passwords = {user: _password(secrets_folder / f"{user}.password") for user in [*users, "routes"]}
    removed = sorted(existing - set(passwords))
    for user in removed:
        (secrets_folder / f"{user}.password").unlink()
    files = {}
    for node in hospital.nodes:
        if nodes is not None and node.name not in nodes:
            continue
        path = folder / f"{node.name}.conf"
        write_atomic(path, node_config_text(hospital, node, passwords))
        path.chmod(0o600)
        files[node.name] = path
    return NodeConfigs(files, secrets_folder, tuple(sorted(set(users) - existing)), tuple(removed))


def node_config_text(hospital: Hospital, node: Node, passwords: dict[str, str]) -> str:
    """``node``'s nats-server configuration; ``passwords`` holds every user's and the routes' ("routes")."""
    route_password = passwords["routes"]
    routes = [f"nats-route://{ROUTE_USER}:{route_password}@{other.host}:{other.cluster_port}"
              for other in hospital.nodes if other is not node]
    lines = [f"# Node {node.name} of the hospital engine {hospital.cluster}, written by `appliance hospital config`",
             "# from the hospital description: edit that and run it again, then `nats-server --signal reload`.",
             f"server_name: {_q(node.name)}",
             f"listen: {_q(f'{node.host}:{node.client_port}')}",
             f"http: {_q(f'{node.host}:{node.monitor_port}')}",
             "jetstream {",
             f"  store_dir: {_q(str(hospital.store_dir / node.name))}",
             "  # fsync before every acknowledgement: an acknowledged alarm is on the disks of a quorum",
             "  sync_interval: always",
             "}",
             "cluster {",
             f"  name: {_q(hospital.cluster)}",
             f"  listen: {_q(f'{node.host}:{node.cluster_port}')}",
             f"  authorization {{ user: {_q(ROUTE_USER)}, password: {_q(route_password)} }}",
             f"  routes: [{', '.join(_q(route) for route in routes)}]",
             "  # clients use the addresses they are configured with, never others a node tells them of",
             "  no_advertise: true",
             *tls_block(hospital, node, "  ", routes=True),
             "}",
             *tls_block(hospital, node, "")]
    if node.mqtt_port is not None:
        lines += ["mqtt {",
                  f"  listen: {_q(f'{node.host}:{node.mqtt_port}')}",
                  f"  stream_replicas: {hospital.replicas}",
                  *tls_block(hospital, node, "  "),
                  "}"]
    lines += ["accounts {", f"  {ACCOUNT}: {{", "    jetstream: enabled", "    users: [",
              f"      {{user: {_q(ADMIN)}, password: {_q(passwords[ADMIN])}}}",
              f"      {_user(HISTORY, passwords[HISTORY], history_permissions(hospital))}"]
    for ward in hospital.wards:
        lines += [f"      {_user(bed, passwords[bed], bed_permissions(ward, bed))}" for bed in ward.beds]
        lines += [f"      {_user(station, passwords[station], station_permissions(ward, station))}"
                  for station in ward.stations]
    for service in hospital.notifiers:
        user = notifier_user(service.name)
        lines.append(f"      {_user(user, passwords[user], notifier_permissions(service))}")
    lines += ["    ]", "  }", "}"]
    return "\n".join(lines) + "\n"


def tls_block(hospital: Hospital, node: Node, indent: str, routes: bool = False) -> list[str]:
    """The ``tls`` block of a listener of ``node``: none without ``[tls]``; on the routes, the other node's
    certificate is asked for and checked against the hospital CA too (clients log in with passwords instead)."""
    if hospital.tls is None:
        return []
    ca_file, cert_file, key_file = hospital.tls.node_files(node.name)
    lines = ["tls {", f"  cert_file: {_q(str(cert_file))}", f"  key_file: {_q(str(key_file))}",
             f"  timeout: {HANDSHAKE_TIMEOUT_S}"]
    if routes:
        lines += [f"  ca_file: {_q(str(ca_file))}", "  verify: true"]
    return [indent + line for line in [*lines, "}"]]


def bed_permissions(ward: Ward, bed: str) -> dict:
    """Publish its own subjects and answers; read its own confirmations (sent, or kept in the engine), its own
    commands and the replies to its publishes."""
    return {"publish": {"allow": [*(bed_subject(ward.name, bed, kind) for kind in BED_KINDS),
                                  answer_subject(ward.name, bed),
                                  f"$JS.API.DIRECT.GET.{confirms_stream_name(ward.name)}."
                                  f"{bed_subject(ward.name, bed, CONFIRMED)}.*"]},
            "subscribe": {"allow": [bed_subject(ward.name, bed, CONFIRM), command_subject(ward.name, bed),
                                    f"{inbox_prefix(bed)}.>"]}}


def station_permissions(ward: Ward, station: str) -> dict:
    """Read the ward (the beds' answers too), confirm to and command its beds, consume (never change) the ward's
    stream, and read the ward's page records back (:func:`page_replay_permissions`)."""
    return {"publish": {"allow": [bed_subject(ward.name, "*", CONFIRM), command_subject(ward.name, "*"),
                                  f"{bed_subject(ward.name, '*', CONFIRMED)}.*",
                                  *consumer_permissions(stream_name(ward.name)), *page_replay_permissions(ward.name)]},
            "subscribe": {"allow": [f"{ROOT}.{ward.name}.>", f"{inbox_prefix(station)}.>"]}}


def history_permissions(hospital: Hospital) -> dict:
    """Consume (never change) every ward's stream through its own durable consumers, and hear every summary."""
    allow = [call for ward in hospital.wards for call in consumer_permissions(stream_name(ward.name))]
    return {"publish": {"allow": allow},
            "subscribe": {"allow": [bed_subject("*", "*", SUMMARY), f"{inbox_prefix(HISTORY)}.>"]}}


def notifier_permissions(service: Notifier) -> dict:
    """Consume (never change) the streams of the wards it serves, and record only its own notifications in their
    confirmation streams: it cannot publish a bed's event or a station's confirmation."""
    allow = [call for ward in service.wards for call in consumer_permissions(stream_name(ward))]
    allow += [subject for ward in service.wards for subject in (notified_subject(ward, "*", "*", service.name),
                                                                paging_status_subject(ward, service.name))]
    return {"publish": {"allow": allow},
            "subscribe": {"allow": [f"{inbox_prefix(notifier_user(service.name))}.>"]}}


def page_replay_permissions(ward: str) -> list[str]:
    """The API calls that read ``ward``'s page records back: make a consumer of the confirmation stream whose
    filter is those records (the filter is part of the call's subject, which the server checks against the
    consumer's), and fetch from it; no look-up, acknowledgement or change of the stream. Only records the station
    cannot write: the server does not hold a consumer's delivery subject to its maker's permissions, so a station
    must not be able to send what it wrote itself (its confirmations) anywhere through one."""
    confirms = confirms_stream_name(ward)
    return [f"$JS.API.CONSUMER.CREATE.{confirms}.*.{notified_subject(ward, '*', '*', '*')}",
            f"$JS.API.CONSUMER.MSG.NEXT.{confirms}.*"]


def consumer_permissions(stream: str) -> list[str]:
    """The API calls that read ``stream`` through a durable consumer: look the stream up, make, look up and fetch
    from a consumer, acknowledge; none that changes or deletes a stream."""
    return [f"$JS.API.STREAM.INFO.{stream}", f"$JS.API.CONSUMER.CREATE.{stream}.>",
            f"$JS.API.CONSUMER.DURABLE.CREATE.{stream}.>", f"$JS.API.CONSUMER.INFO.{stream}.>",
            f"$JS.API.CONSUMER.MSG.NEXT.{stream}.>", f"$JS.ACK.{stream}.>"]


def read_password(secrets_folder: Path, user: str) -> str:
    """``user``'s password from the secrets folder an earlier run wrote."""
    path = Path(secrets_folder) / f"{user}.password"
    if not path.exists():
        raise ConfigError(f"{path} does not exist: is {user!r} in the hospital description, and was "
                          f"`appliance hospital config` run?")
    return read_secret(path, "delete it and run `appliance hospital config` for a new password")


def _password(path: Path) -> str:
    if path.exists():
        return read_password(path.parent, path.name.removesuffix(".password"))
    password = secrets.token_urlsafe(PASSWORD_BYTES)
    write_atomic(path, password + "\n")
    path.chmod(0o600)
    return password


def _user(name: str, password: str, permissions: dict) -> str:
    return f"{{user: {_q(name)}, password: {_q(password)}, permissions: {json.dumps(permissions)}}}"


def _q(text: str) -> str:
    """A quoted string of the configuration format, which reads JSON's strings."""
    return json.dumps(text)
