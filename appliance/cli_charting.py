"""``appliance fhir-token``: make, list or revoke the bearer tokens of the screen's read-only FHIR API."""

from __future__ import annotations

import sys
import time
from pathlib import Path

TOKENS_FILE = "api-tokens.db"


def add_parsers(sub) -> None:
    p = sub.add_parser("fhir-token", help="make (printed once), list or revoke a token for the FHIR API")
    p.add_argument("--data-dir", type=Path, required=True, help="the monitor's data folder (the screen's)")
    action = p.add_mutually_exclusive_group(required=True)
    action.add_argument("--create", metavar="NAME", help="make a token for the client NAME and print it")
    action.add_argument("--revoke", metavar="NAME", help="revoke NAME's token")
    action.add_argument("--list", action="store_true", help="the names that have a token")
    p.set_defaults(run=_fhir_token)


def _fhir_token(args) -> int:
    from appliance.errors import ConfigError
    from appliance.store.api_tokens import ApiTokens

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
