"""``python -m webui``: serve the nurse's screen for the monitor's data directory.

Runs Flask's threaded server, enough for a bedside screen and a few station
browsers; the appliance's image puts it behind TLS. Session cookies are Secure,
so browsers keep them only over HTTPS or on localhost; ``--plain-http`` drops that
for a trusted test network.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from appliance.service.virtual_bed import default_data_dir
from webui import create_app


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m webui", description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="the monitor's data directory (default as `appliance run`)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    parser.add_argument("--plain-http", action="store_true", help="session cookies without the Secure flag")
    args = parser.parse_args(argv)
    app = create_app(args.data_dir or default_data_dir(), secure_cookies=not args.plain_http)
    app.run(host=args.host, port=args.port, threaded=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
