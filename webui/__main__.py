"""``python -m webui``: serve the nurse's screen for the monitor's data directory.

Served by waitress, a production WSGI server in pure Python (no compiler on the
appliance, the same on arm64 and x86). Each open live view holds one of its
threads for its event stream, so ``--threads`` bounds how many screens can watch
at once, less a few kept for page loads (``webui.server.stream_limit``); streams end
after ``webui.streams.STREAM_MAX_S`` and browsers reconnect at once, so a vanished
client frees its thread. The appliance's image puts the server behind TLS. Session
cookies are Secure, so browsers keep them only over HTTPS or on localhost;
``--plain-http`` drops that for a trusted test network.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from appliance.service.config_sections import default_data_dir
from webui import create_app
from webui.server import serve

DEFAULT_THREADS = 48        # 40 live views and requests beside them


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m webui", description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="the monitor's data directory (default as `appliance run`)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    parser.add_argument("--threads", type=int, default=DEFAULT_THREADS,
                        help=f"worker threads, one per open live view (default {DEFAULT_THREADS})")
    parser.add_argument("--plain-http", action="store_true", help="session cookies without the Secure flag")
    parser.add_argument("--behind-proxy", action="store_true",
                        help="trust X-Forwarded-For/-Proto from the TLS proxy on 127.0.0.1 (as on the appliance)")
    args = parser.parse_args(argv)
    if not 1 <= args.threads <= 1000:
        parser.error(f"--threads must be 1-1000, got {args.threads}")
    app = create_app(args.data_dir or default_data_dir(), secure_cookies=not args.plain_http)
    print(f"serving the screen for {app.config['LIVE_PATH'].parent} on http://{args.host}:{args.port}/", flush=True)
    serve(app, args.host, args.port, threads=args.threads, ident="appliance", behind_proxy=args.behind_proxy)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
