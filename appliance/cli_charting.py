"""``appliance fhir-token``: make, list or revoke the bearer tokens of the screen's read-only FHIR API;
``appliance report``: a bed's shift report as a PDF, or its events as a CSV, from its data folder."""

from __future__ import annotations

import sys
import time
from pathlib import Path


def add_parsers(sub) -> None:
    add_report_parser(sub)
    p = sub.add_parser("fhir-token", help="make (printed once), list or revoke a token for the FHIR API")
    p.add_argument("--data-dir", type=Path, required=True, help="the monitor's data folder (the screen's)")
    action = p.add_mutually_exclusive_group(required=True)
    action.add_argument("--create", metavar="NAME", help="make a token for the client NAME and print it")
    action.add_argument("--revoke", metavar="NAME", help="revoke NAME's token")
    action.add_argument("--list", action="store_true", help="the names that have a token")
    p.set_defaults(run=_fhir_token)


def _fhir_token(args) -> int:
    from appliance.errors import ConfigError
    from appliance.store.api_tokens import TOKENS_FILE, ApiTokens

    if not args.data_dir.is_dir():
        raise ConfigError(f"--data-dir {args.data_dir}: no such folder")
    tokens = ApiTokens(args.data_dir / TOKENS_FILE)
    if args.create is not None:
        print(tokens.create(args.create, time.time()))
        print(f"appliance fhir-token: token for {args.create} made; it is shown only now", file=sys.stderr)
    elif args.revoke is not None:
        if not tokens.revoke(args.revoke):
            raise ConfigError(f"--revoke {args.revoke}: no token has that name")
    else:
        for name in tokens.names():
            print(name)
    return 0


def add_report_parser(sub) -> None:
    from appliance.cli_args import iana_zone, within

    p = sub.add_parser("report", help="write a bed's shift report as a PDF, or the period's events as a CSV")
    p.add_argument("--data-dir", type=Path, required=True, help="the monitor's data folder (its appliance.db)")
    p.add_argument("--hours", type=within(1.0, 168.0, "h"), default=12.0,
                   help="the period: the last HOURS up to the newest record (1 to 168, default 12)")
    p.add_argument("--out", type=Path, required=True, help="the file to write: NAME.pdf or NAME.csv")
    p.add_argument("--time-zone", type=iana_zone, metavar="ZONE",
                   help="the IANA zone of the clock times, such as Europe/London (default: the bed's, as its screen "
                        "shows them)")
    p.set_defaults(run=_report)


def _report(args) -> int:
    from appliance.errors import ConfigError
    from appliance.service.assemble import LIVE_FILE, STORE_FILE
    from appliance.service.live import read_live
    from appliance.service.settings import shown_time_zone
    from appliance.store import Store
    from appliance.time_zones import time_zone
    from webui.history import threshold_mmhg
    from webui.report import report_csv, report_pdf, shift_report

    kind = args.out.suffix.lower()
    if kind not in (".pdf", ".csv"):
        raise ConfigError(f"--out {args.out}: the name must end in .pdf or .csv")
    if not args.out.parent.is_dir():
        raise ConfigError(f"--out {args.out}: no folder {args.out.parent}")
    store_path = args.data_dir / STORE_FILE
    if not store_path.is_file():
        raise ConfigError(f"--data-dir {args.data_dir}: no monitor store ({STORE_FILE}) there")
    try:
        live = read_live(args.data_dir / LIVE_FILE) or {}
    except ValueError as exc:                   # the bed's name and patient's name are missing, nothing else
        print(f"appliance report: the live view is not read ({exc})", file=sys.stderr)
        live = {}
    zone = time_zone(args.time_zone or shown_time_zone(args.data_dir, live))
    with Store.open(store_path) as s:
        made = shift_report(s, args.hours, live, threshold_mmhg(live), zone)
    if made is None:
        raise ConfigError(f"--data-dir {args.data_dir}: the store has recorded nothing yet")
    if kind == ".pdf":
        args.out.write_bytes(report_pdf(made))
    else:
        args.out.write_text(report_csv(made), encoding="utf-8")
    print(f"appliance report: {args.out} ({len(made.events)} events, {made.patient}, times in {zone.key})",
          file=sys.stderr)
    return 0
