"""``appliance ward``: the ward station, every bed of a ward on one screen, for a server at the nurses' station;
``appliance ward-broker``: the ward broker's logins and ACL (``appliance.ward.broker``).

It subscribes to the ward's MQTT broker (``appliance.ward.station``) with the
broker settings of its configuration file (``appliance.ward.config``), or reads
its ward from the hospital engine (``appliance.ward.engine_station``), and serves
the ward's screen (``webui.create_ward_app``) with waitress until SIGTERM. The
screen's accounts are its own, kept in the data directory with the journal of
the commands its nurses send to beds; the first visit sets up the admin. Put it behind a TLS proxy as a bed's screen is.
"""

from __future__ import annotations

import contextlib
import signal
from pathlib import Path

DEFAULT_THREADS = 16        # a few station screens and their event streams
MAX_THREADS = 1000          # far more screens than a ward has
DEFAULT_STATION = "ward-station"
JOURNAL = "ward-commands.db"
APPLIED = "ward-applied.db"


def add_parsers(sub) -> None:
    from appliance.cli_args import add_screen_options, whole_within

    p = sub.add_parser("ward", help="run the ward station: every bed's state and alarms from the MQTT broker")
    p.add_argument("--config", type=Path, required=True, help="the station's TOML configuration ([broker] or "
                                                             "[engine], [station], [history])")
    p.add_argument("--check-config", action="store_true", help="check the configuration, print it and exit")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where the screen's accounts, audit log and command journal are kept (default "
                        "$APPLIANCE_DATA_DIR/ward or ~/.local/share/appliance/ward)")
    add_screen_options(p, 8090)
    p.add_argument("--threads", type=whole_within(1, MAX_THREADS), default=DEFAULT_THREADS,
                   help=f"server threads, one per open ward screen (default {DEFAULT_THREADS})")
    p.set_defaults(run=_ward)

    p = sub.add_parser("ward-broker", help="write the ward broker's password file, ACL and Mosquitto settings: each "
                                           "bed may publish only as itself")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the folder for the files (made if missing; an earlier run's passwords in it are kept)")
    p.add_argument("--bed", action="append", default=[], metavar="ID", help="a bed's id, its user name; repeatable")
    p.add_argument("--beds-file", type=Path, metavar="FILE", help="more bed ids, one a line ('#' starts a comment)")
    p.add_argument("--station", action="append", default=[], metavar="USER",
                   help=f"a ward station's user name; repeatable (default {DEFAULT_STATION})")
    p.add_argument("--topic-prefix", default="appliance", help="the beds' topic_prefix (default appliance)")
    p.add_argument("--listener", type=whole_within(1, 65535), metavar="PORT",
                   help="also open this port (default: the broker's own listeners)")
    p.add_argument("--certfile", type=Path, help="--listener with TLS: the broker's certificate")
    p.add_argument("--keyfile", type=Path, help="--listener with TLS: the certificate's key")
    p.add_argument("--persistence-location", type=Path, metavar="DIR",
                   help="where Mosquitto keeps its sessions (default: as the broker's own configuration says; "
                        "Debian's does)")
    p.add_argument("--broker-user", metavar="USER", help="give the password file and ACL to Mosquitto's user "
                                                         "(mosquitto on Debian), who reads them; needs root")
    p.set_defaults(run=_ward_broker)


def _ward(args) -> int:
    from appliance.cli_run import listen_address
    from appliance.errors import ConfigError
    from appliance.service.config_sections import default_data_dir
    from appliance.ward.config import load_ward_config
    from webui import create_ward_app
    from webui.server import serve

    config = load_ward_config(args.config)
    host, port = listen_address(args.listen, "--listen")
    if args.data_dir is not None and args.data_dir.exists() and not args.data_dir.is_dir():
        raise ConfigError(f"--data-dir {args.data_dir} is a file, not a folder")
    if args.check_config:
        print(config)
        return 0
    data_dir = args.data_dir or default_data_dir() / "ward"
    signal.signal(signal.SIGTERM, _stop)
    data_dir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        station, source = open_station(config, data_dir, stack)
        app = create_ward_app(data_dir, station, config, secure_cookies=not args.plain_http)
        history = "" if config.history is None else \
            f"; the history of {config.history.ward}, the last {config.history.look_back_h:g} h"
        print(f"ward station: beds {source}; the screen on http://{host}:{port}/ (accounts in {data_dir}){history}",
              flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            serve(app, host, port, threads=args.threads, ident="appliance-ward", behind_proxy=args.behind_proxy)
    return 0


def open_station(config, data_dir: Path, stack: contextlib.ExitStack):
    """The station the configuration names, closed with ``stack``, and where it reads its beds, in words; on
    the engine as on a broker it sends its nurses' commands through the journal in ``data_dir``."""
    from appliance.ward.applied import AppliedJournal
    from appliance.ward.engine_station import EngineStation
    from appliance.ward.journal import CommandJournal
    from appliance.ward.station import WardStation

    if config.engine is not None:
        journal = AppliedJournal(data_dir / APPLIED)
        stack.callback(journal.close)
        e = config.engine
        return (stack.enter_context(EngineStation.from_config(config, journal, CommandJournal(data_dir / JOURNAL))),
                f"of {e.ward} on the hospital engine ({', '.join(e.servers)}) as {config.client_id}")
    b = config.broker
    assert b is not None
    return (stack.enter_context(WardStation.from_config(config, CommandJournal(data_dir / JOURNAL))),
            f"under {b.topic_prefix}/ on {b.host}:{b.port}{' (TLS)' if b.ca_file else ''}")


def _ward_broker(args) -> int:
    from appliance.errors import ConfigError
    from appliance.ward.broker import Listener, beds_from_file, write_ward_broker

    beds = [*args.bed, *(beds_from_file(args.beds_file) if args.beds_file else [])]
    stations = args.station or [DEFAULT_STATION]
    listener = None if args.listener is None else Listener(args.listener, args.certfile, args.keyfile)
    if listener is None and (args.certfile or args.keyfile):
        raise ConfigError("--certfile and --keyfile are for --listener PORT: the port that takes TLS")
    files = write_ward_broker(args.out, beds, stations, topic_prefix=args.topic_prefix, listener=listener,
                              persistence_location=args.persistence_location, broker_user=args.broker_user)
    print(f"ward broker for {len(beds)} bed(s) and {len(stations)} station(s) under {args.topic_prefix}/:")
    print(f"  {files.password_file}  logins; added: {', '.join(files.added) or 'none'}; kept: "
          f"{', '.join(files.kept) or 'none'}; removed: {', '.join(files.removed) or 'none'}")
    print(f"  {files.acl_file}  each bed writes only its own topics; stations read every bed and write confirm")
    print(f"  {files.config_file}  for /etc/mosquitto/conf.d (link it there once, then restart mosquitto)")
    print(f"  {files.secrets_folder}/USER.password  each bed's [notify.mqtt] password_file, the station's "
          f"[broker] password_file")
    print("reload (SIGHUP: reads the logins and ACL again, no restart): systemctl reload mosquitto")
    return 0


def _stop(signum, frame):
    """SIGTERM (systemd's stop) ends the server the way Ctrl-C does, so the station disconnects cleanly."""
    raise KeyboardInterrupt
