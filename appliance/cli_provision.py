"""``appliance provision``: a new bed's first boot, from the setup file on its boot partition.

The image's ``appliance-provision.service`` runs it at every boot before the
monitor and the screen: the first time it provisions the bed
(:mod:`appliance.service.provision`), later it only sets the recorded hostname.
"""

from __future__ import annotations

import sys
from pathlib import Path


def add_parsers(sub) -> None:
    from appliance.service.provision import ACCOUNT, CONFIG_DIR, DATA_DIR, SETUP_FILE

    p = sub.add_parser("provision", help="set up a new bed from its boot partition's setup file (first boot)")
    p.add_argument("--setup", type=Path, default=SETUP_FILE, help=f"the setup file (default {SETUP_FILE})")
    p.add_argument("--config-dir", type=Path, default=CONFIG_DIR,
                   help=f"the monitor's configuration folder, where the marker is kept (default {CONFIG_DIR})")
    p.add_argument("--data-dir", type=Path, default=DATA_DIR,
                   help=f"the monitor's data folder, with the screen's accounts (default {DATA_DIR})")
    p.add_argument("--account", default=ACCOUNT,
                   help=f"the service account given the files the services use (default {ACCOUNT})")
    p.add_argument("--no-hostname", action="store_true",
                   help="record the hostname but leave the running system's alone (image builds, chroots)")
    p.set_defaults(run=_provision)


def _provision(args) -> int:
    import socket

    from appliance.service.provision import provision

    done = provision(args.setup, args.config_dir, args.data_dir, account=args.account,
                     set_hostname=None if args.no_hostname else socket.sethostname)
    for step in done:
        print(f"appliance provision: {step}", file=sys.stderr)
    if not done:
        print("appliance provision: nothing to do", file=sys.stderr)
    return 0
