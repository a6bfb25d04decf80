"""``appliance ward``: the ward station, every bed of a ward on one screen, for a server at the nurses' station.

It subscribes to the ward's MQTT broker (``appliance.ward.station``) with the
broker settings of its configuration file (``appliance.ward.config``) and serves
the ward's screen (``webui.create_ward_app``) with waitress until SIGTERM. The
screen's accounts are its own, kept in the data directory; the first visit sets
up the admin. Put it behind a TLS proxy as a bed's screen is.
"""

from __future__ import annotations

import signal
from pathlib import Path

DEFAULT_THREADS = 16        # a few station screens and their event streams


def add_parsers(sub) -> None:
    p = sub.add_parser("ward", help="run the ward station: every bed's state and alarms from the MQTT broker")
    p.add_argument("--config", type=Path, required=True, help="the station's TOML configuration ([broker], "
                                                             "[station])")
    p.add_argument("--check-config", action="store_true", help="check the configuration, print it and exit")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where the screen's accounts and audit log are kept (default $APPLIANCE_DATA_DIR/ward "
                        "or ~/.local/share/appliance/ward)")
    p.add_argument("--listen", metavar="[HOST:]PORT", default="8090", help="the screen's address (default "
                                                                           "127.0.0.1:8090)")
    p.add_argument("--threads", type=int, default=DEFAULT_THREADS,
                   help=f"server threads, one per open ward screen (default {DEFAULT_THREADS})")
    p.add_argument("--plain-http", action="store_true", help="session cookies without the Secure flag")
    p.add_argument("--behind-proxy", action="store_true",
                   help="trust X-Forwarded-For/-Proto from the TLS proxy on 127.0.0.1")
    p.set_defaults(run=_ward)


def _ward(args) -> int:
    from appliance.cli_run import listen_address
    from appliance.errors import ConfigError
    from appliance.service.virtual_bed import default_data_dir
    from appliance.ward.config import load_ward_config
    from appliance.ward.station import WardStation
    from webui import create_ward_app
    from webui.server import serve

    config = load_ward_config(args.config)
    host, port = listen_address(args.listen, "--listen")
    if not 1 <= args.threads <= 1000:
        raise ConfigError(f"--threads must be 1-1000, got {args.threads}")
    if args.data_dir is not None and args.data_dir.exists() and not args.data_dir.is_dir():
        raise ConfigError(f"--data-dir {args.data_dir} is a file, not a folder")
    if args.check_config:
        print(config)
        return 0
    data_dir = args.data_dir or default_data_dir() / "ward"
    signal.signal(signal.SIGTERM, _stop)
    with WardStation.from_config(config) as station:
        app = create_ward_app(data_dir, station, config, secure_cookies=not args.plain_http)
        b = config.broker
        print(f"ward station: beds under {b.topic_prefix}/ on {b.host}:{b.port}{' (TLS)' if b.ca_file else ''}; "
              f"the screen on http://{host}:{port}/ (accounts in {data_dir})", flush=True)
        try:
            serve(app, host, port, threads=args.threads, ident="appliance-ward", behind_proxy=args.behind_proxy)
        except KeyboardInterrupt:
            pass
    return 0


def _stop(signum, frame):
    """SIGTERM (systemd's stop) ends the server the way Ctrl-C does, so the station disconnects cleanly."""
    raise KeyboardInterrupt
