"""``appliance hospital``: the hospital engine, a NATS cluster with JetStream for the beds of many wards
(``appliance.hospital``).

``config`` writes each node's nats-server configuration and everyone's passwords from the hospital
description; ``certs`` makes the CA and node certificates its ``[tls]`` folder lacks; ``streams`` creates or
updates every ward's replicated alarm and confirmation streams on a running cluster; ``start-local`` runs a whole
cluster on loopback for trials, until Ctrl-C, and writes its description beside it for the other two;
``history`` runs the history writer into PostgreSQL until stopped; ``notify`` runs one notification service,
paging its wards' alarm changes to its messaging gateway, until stopped; ``overview`` serves the hospital
overview from it; ``install`` writes what a hospital server runs, for
``systemd/install-hospital-server.sh``.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import tempfile
from pathlib import Path

from appliance.cli_args import add_screen_options, whole_within


def add_parsers(sub) -> None:
    p = sub.add_parser("hospital", help="the hospital engine: a replicated NATS cluster for many wards' beds")
    hospital = p.add_subparsers(dest="hospital_command", required=True, metavar="HOSPITAL_COMMAND")

    p = hospital.add_parser("config", help="write each node's nats-server configuration and the users' passwords "
                                           "from the hospital description")
    p.add_argument("--description", type=Path, required=True, help="the hospital description (TOML: [hospital], "
                                                                   "[[node]], [[ward]])")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the folder for <node>.conf and secrets/ (made if missing; earlier passwords are kept)")
    p.set_defaults(run=_config)

    p = hospital.add_parser("certs", help="make the hospital CA and each node's certificate and key that the "
                                          "description's [tls] folder does not hold yet")
    p.add_argument("--description", type=Path, required=True, help="the hospital description, with [tls]")
    p.set_defaults(run=_certs)

    p = hospital.add_parser("streams", help="create or update every ward's alarm and confirmation streams on the "
                                            "running cluster")
    p.add_argument("--description", type=Path, required=True, help="the hospital description")
    p.add_argument("--secrets", type=Path, required=True, metavar="DIR",
                   help="the secrets/ folder `appliance hospital config` wrote (for the administrator's password)")
    p.set_defaults(run=_streams)

    p = hospital.add_parser("start-local", help="run a three-node cluster on loopback, with one trial ward, until "
                                                "Ctrl-C")
    p.add_argument("--dir", type=Path, default=None, help="where the configurations, passwords, stores and logs go "
                                                          "(default: a new temporary folder)")
    p.add_argument("--beds", type=whole_within(1, 1000), default=4, help="beds in the trial ward (default 4)")
    p.set_defaults(run=_start_local)

    p = hospital.add_parser("history", help="write every ward's events and the beds' pressure minutes into "
                                            "PostgreSQL, until stopped")
    p.add_argument("--description", type=Path, required=True, help="the hospital description, with [history]")
    p.add_argument("--secrets", type=Path, required=True, metavar="DIR",
                   help="the secrets/ folder `appliance hospital config` wrote (for hospital-history's password)")
    p.add_argument("--dsn", default=None, help="the PostgreSQL connection string (default: the [history] database "
                                               "on the local Unix socket, as the system user running this)")
    p.set_defaults(run=_history)

    p = hospital.add_parser("notify", help="page a notification service's alarm changes to its messaging gateway, "
                                           "recording each on the engine, until stopped")
    p.add_argument("--description", type=Path, required=True, help="the hospital description, with the [[notifier]]")
    p.add_argument("--secrets", type=Path, required=True, metavar="DIR",
                   help="the secrets/ folder `appliance hospital config` wrote (for notify-NAME's password)")
    p.add_argument("--notifier", required=True, metavar="NAME", help="the [[notifier]] of the description to run")
    p.add_argument("--journal", type=Path, default=None, metavar="FILE",
                   help="the journal of what it has paged (default: the data folder's hospital-notify/NAME.db)")
    p.set_defaults(run=_notify)

    p = hospital.add_parser("overview", help="serve the hospital overview (every ward's beds and open alarms, "
                                             "from the history) until stopped")
    p.add_argument("--description", type=Path, required=True, help="the hospital description, with [history]")
    p.add_argument("--dsn", default=None, help="the PostgreSQL connection string (default: the [history] database "
                                               "on the local Unix socket, as the system user running this)")
    p.add_argument("--data-dir", type=Path, default=None, metavar="DIR",
                   help="the overview's accounts and session key (default: the data folder's hospital-overview/)")
    add_screen_options(p, 8095)
    p.set_defaults(run=_overview)

    p = hospital.add_parser("install", help="write a server's node configurations, description and history SQL "
                                            "under a root folder, and print the units to enable")
    p.add_argument("--description", type=Path, required=True, help="the hospital description")
    p.add_argument("--root", type=Path, required=True, help="/ on the server; another folder to look first")
    p.add_argument("--node", action="append", default=None, metavar="NAME",
                   help="a node this server runs (repeat; default: every node of the description)")
    p.add_argument("--no-history", action="store_true", help="this server does not run the history writer")
    p.add_argument("--notifier", action="append", default=None, metavar="NAME",
                   help="a notification service this server runs (repeat; default: none)")
    p.set_defaults(run=_install)


def _config(args) -> int:
    from appliance.hospital.description import load_hospital
    from appliance.hospital.nodeconfig import write_node_configs

    hospital = load_hospital(args.description)
    written = write_node_configs(hospital, args.out)
    users = sum(len(ward.beds) + len(ward.stations) for ward in hospital.wards)
    print(f"hospital engine {hospital.cluster}: {len(hospital.nodes)} node(s), {len(hospital.wards)} ward(s), "
          f"{users} bed and station user(s)")
    for name, path in written.files.items():
        print(f"  {path}  node {name}: nats-server -c {path}")
    print(f"  {written.secrets_folder}/USER.password  each user's password; added: "
          f"{', '.join(written.added) or 'none'}; removed: {', '.join(written.removed) or 'none'}")
    print("a running node reads its file again, with its users and permissions, on: nats-server --signal reload")
    return 0


def _certs(args) -> int:
    from appliance.hospital.certs import make_certificates
    from appliance.hospital.description import load_hospital

    hospital = load_hospital(args.description)
    made = make_certificates(hospital)
    assert hospital.tls is not None
    print(f"hospital engine {hospital.cluster}: TLS files in {hospital.tls.path}; made: "
          f"{', '.join(path.name for path in made) or 'none, all were there'}")
    if hospital.tls.ca_key in made:
        print(f"  {hospital.tls.ca_file} is the CA that beds, stations and tools trust (their ca_file); keep "
              f"{hospital.tls.ca_key.name} off the nodes")
    return 0


def _streams(args) -> int:
    from appliance.hospital.description import load_hospital

    hospital = load_hospital(args.description)
    names = asyncio.run(_ensure_streams(hospital, [node.client_url for node in hospital.nodes], args.secrets))
    print(f"{len(hospital.wards)} ward(s), their event and confirmation streams with {hospital.replicas} replica(s) "
          f"each: {', '.join(names)}")
    return 0


def _start_local(args) -> int:
    from appliance.files import write_atomic
    from appliance.hospital.cluster import LocalCluster, loopback_hospital, server_version
    from appliance.hospital.description import Ward, description_text
    from appliance.hospital.nodeconfig import ADMIN

    folder = args.dir or Path(tempfile.mkdtemp(prefix="appliance-hospital-"))
    folder.mkdir(parents=True, exist_ok=True)
    ward = Ward("trial", tuple(f"bed{i:02d}" for i in range(1, args.beds + 1)), ("trial-station",))
    hospital = loopback_hospital(folder / "store", [ward])
    description = folder / "hospital.toml"
    write_atomic(description, description_text(hospital))
    signal.signal(signal.SIGTERM, _stop)
    with LocalCluster(hospital, folder / "config") as cluster:
        names = asyncio.run(_ensure_streams(hospital, cluster.urls, cluster.configs.secrets_folder))
        print(f"hospital engine: nats-server {server_version(cluster.binary)}, {len(hospital.nodes)} nodes on "
              f"loopback, stream {names[0]} with {hospital.replicas} replicas")
        for node in hospital.nodes:
            print(f"  {node.name}: {node.client_url}  mqtt://{node.host}:{node.mqtt_port}  "
                  f"http://{node.host}:{node.monitor_port}/jsz  log {folder / 'config' / f'{node.name}.log'}")
        print(f"users {ADMIN}, {', '.join(ward.beds)}, {', '.join(ward.stations)}: passwords in "
              f"{cluster.configs.secrets_folder}; the description in {description}; Ctrl-C stops the cluster",
              flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            signal.pause()
    return 0


def _history(args) -> int:
    import sys

    import psycopg

    from appliance.errors import ConfigError
    from appliance.hospital.description import load_hospital

    hospital = load_hospital(args.description)
    if hospital.history is None:
        raise ConfigError(f"{args.description} has no [history] table: the writer needs the hospital's retention "
                          f"policy (events_days, pressure_days)")
    dsn = args.dsn or f"dbname={hospital.history.database}"
    try:
        db = psycopg.connect(dsn)
    except psycopg.OperationalError as exc:     # not up yet, perhaps: exit 1, which systemd starts again
        print(f"PostgreSQL at {dsn!r} is not reachable: {str(exc).strip()}", file=sys.stderr)
        return 1
    with db:
        asyncio.run(_write_history(hospital, args.secrets, db))
    return 0


async def _write_history(hospital, secrets: Path, db) -> None:
    from appliance.hospital.history.writer import HistoryWriter
    from appliance.hospital.nodeconfig import HISTORY

    policy = hospital.history
    await _serve_on_engine(
        hospital, HISTORY, secrets, lambda connection: HistoryWriter(db, connection, hospital),
        f"history writer: {len(hospital.wards)} ward stream(s) into database {policy.database}; events kept "
        f"{policy.events_days} days, pressure minutes {policy.pressure_days}",
        lambda writer: f"history writer stopped: {writer.stored} event(s) stored, {writer.duplicates} redelivered "
                       f"and dropped, {writer.heard} summaries heard, {writer.rejected} refused")


async def _serve_on_engine(hospital, user: str, secrets: Path, make, started: str, stopped) -> None:
    """Log in to the engine as ``user``, run the service ``make(connection)`` gives until SIGTERM or SIGINT stops
    it, printing ``started`` and then ``stopped(service)``."""
    from appliance.hospital.engine import connect
    from appliance.hospital.nodeconfig import read_password

    connection = await connect([node.client_url for node in hospital.nodes], user, read_password(secrets, user),
                               ca_file=hospital.ca_file)
    try:
        service = make(connection)
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(signum, service.stop)
        print(started, flush=True)
        await service.run()
        print(stopped(service))
    finally:
        await connection.close()


def _notify(args) -> int:
    from appliance.hospital.description import load_hospital
    from appliance.service.config_sections import default_data_dir
    from appliance.ward.applied import AppliedJournal

    hospital = load_hospital(args.description)
    notifier = hospital.notifier(args.notifier)
    path = args.journal or default_data_dir() / "hospital-notify" / f"{notifier.name}.db"
    path.parent.mkdir(parents=True, exist_ok=True)
    journal = AppliedJournal(path)
    try:
        asyncio.run(_run_notifier(hospital, notifier, args.secrets, journal, path))
    finally:
        journal.close()
    return 0


async def _run_notifier(hospital, notifier, secrets: Path, journal, path: Path) -> None:
    from appliance.hospital.nodeconfig import notifier_user
    from appliance.hospital.notify import NotificationService

    await _serve_on_engine(
        hospital, notifier_user(notifier.name), secrets,
        lambda connection: NotificationService(connection, notifier, journal),
        f"notification service {notifier.name}: the {', '.join(notifier.priorities)} alarm changes of "
        f"{', '.join(notifier.wards)} to {notifier.url}; journal {path}",
        lambda service: f"notification service {notifier.name} stopped: {service.paged} paged, {service.refused} "
                        f"refused by the gateway, {service.repeats} given again and not paged twice")


def _overview(args) -> int:
    from appliance.cli_run import listen_address
    from appliance.errors import ConfigError
    from appliance.hospital.description import load_hospital
    from appliance.hospital.history.reads import connector
    from appliance.service.config_sections import default_data_dir
    from webui import create_hospital_app
    from webui.server import serve

    hospital = load_hospital(args.description)
    if args.dsn is None and hospital.history is None:
        raise ConfigError(f"{args.description} has no [history] table and no --dsn was given: the overview reads "
                          f"the history's database")
    dsn = args.dsn or f"dbname={hospital.history.database if hospital.history else ''}"
    host, port = listen_address(args.listen, "--listen")
    data_dir = args.data_dir or default_data_dir() / "hospital-overview"
    app = create_hospital_app(data_dir, hospital, connector(dsn), secure_cookies=not args.plain_http)
    signal.signal(signal.SIGTERM, _stop)
    print(f"hospital overview: {len(hospital.wards)} ward(s) from {dsn!r}; the screen on http://{host}:{port}/ "
          f"(accounts in {data_dir})", flush=True)
    with contextlib.suppress(KeyboardInterrupt):
        serve(app, host, port, threads=4, ident="appliance-hospital", behind_proxy=args.behind_proxy)
    return 0


def _install(args) -> int:
    import sys

    from appliance.hospital.description import load_hospital
    from appliance.hospital.install import install

    installed = install(load_hospital(args.description), args.root, args.node, history=not args.no_history,
                        notifiers=args.notifier)
    print(f"wrote {installed.folder}: node configurations, secrets/, hospital.toml"
          + (f", {installed.sql.name}" if installed.sql else ""), file=sys.stderr)
    print("\n".join(installed.units))
    return 0


async def _ensure_streams(hospital, urls: list[str], secrets: Path) -> list[str]:
    import ssl

    import nats.errors

    from appliance.errors import ConfigError
    from appliance.hospital.engine import connect, ensure_ward_streams
    from appliance.hospital.nodeconfig import ADMIN, read_password

    try:
        connection = await connect(urls, ADMIN, read_password(secrets, ADMIN), ca_file=hospital.ca_file, attempts=3)
    except nats.errors.NoServersError:
        raise ConfigError(f"no node of {', '.join(urls)} let {ADMIN} in: are they running, and is {secrets} the "
                          f"secrets folder of their configuration?") from None
    except ssl.SSLError as exc:
        raise ConfigError(f"a node of {', '.join(urls)} failed the TLS handshake ({exc}): is its certificate the "
                          f"hospital CA's {hospital.ca_file}, naming its host?") from None
    try:
        return await ensure_ward_streams(connection, hospital)
    finally:
        await connection.close()


def _stop(signum, frame):
    """SIGTERM stops the cluster the way Ctrl-C does."""
    raise KeyboardInterrupt
