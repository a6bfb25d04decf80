"""Web load benchmark: does the nurse's live page still load while many screens watch and idle connections sit?

    python benchmarks/web_load.py        # writes benchmarks/web_load.md (about 2 min after the first map)

The monitor runs a few frames on the default virtual bed so the screen serves a real live snapshot. The screen
is then served by waitress as the appliance serves it (``python -m webui``'s default 48 threads, the same server
options), a nurse logs in, and the live page (its HTML, script and style files and ``/api/live``) is loaded
``LOADS`` times over fresh connections: first with nothing else going on, then with ``STREAMS`` live streams
held open and ``IDLE`` idle connections on top. The target: the page loads within 2 s while loaded. Timings
are wall-clock on a shared machine, so the two cases are measured in the same run and compared as a ratio;
medians are reported.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import http.client
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from report import machine  # noqa: E402

HERE = Path(__file__).parent
THREADS = 48
STREAMS, IDLE, LOADS = 100, 200, 20
TARGET_S = 2.0
NURSE, PASSWORD = "nurse.benchmark", "a long bedside passphrase 7"
PAGE = ("/", "/static/style.css", "/static/clock.js", "/static/live.js", "/api/live")


def live_snapshot(data_dir: Path) -> None:
    """A few frames of the monitor on the default bed, so ``live.json`` holds a whole map."""
    subprocess.run([sys.executable, "-m", "appliance", "run", "--frames", "3", "--speed", "0",
                    "--data-dir", str(data_dir)], check=True, stdout=subprocess.DEVNULL)


def serve(data_dir: Path):
    """The screen on waitress with the appliance's options, on a free port: (server, port)."""
    from waitress import create_server

    from webui import create_app
    from webui.server import server_options

    app = create_app(data_dir, secure_cookies=False)
    app.extensions["users"].create(NURSE, PASSWORD, "nurse", by="benchmark")
    server = create_server(app, **server_options("127.0.0.1", 0, threads=THREADS, ident="benchmark",
                                                 behind_proxy=False))
    threading.Thread(target=server.run, daemon=True).start()
    return server, server.effective_port


def request(port: int, path: str, cookie: str = "", *, method: str = "GET", body: bytes | None = None,
            headers: dict | None = None):
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    connection.request(method, path, body=body, headers={"Cookie": cookie, **(headers or {})})
    return connection, connection.getresponse()


def log_in(port: int) -> str:
    """The nurse's session cookie."""
    connection, answer = request(port, "/login")
    page, cookie = answer.read().decode(), _cookie(answer)
    connection.close()
    csrf = re.search(r'name="csrf_token" value="([^"]+)"', page).group(1)
    form = urllib.parse.urlencode({"name": NURSE, "password": PASSWORD, "csrf_token": csrf}).encode()
    connection, answer = request(port, "/login", cookie, method="POST", body=form,
                                 headers={"Content-Type": "application/x-www-form-urlencoded"})
    answer.read()
    connection.close()
    return _cookie(answer) or cookie


def _cookie(answer) -> str:
    return "; ".join(h.split(";", 1)[0] for k, h in answer.getheaders() if k.lower() == "set-cookie")


def load_page(port: int, cookie: str) -> float:
    """Seconds to fetch the live page and everything it loads, each over a new connection."""
    start = time.perf_counter()
    for path in PAGE:
        connection, answer = request(port, path, cookie)
        if answer.status != 200:
            raise RuntimeError(f"{path} answered {answer.status}")
        answer.read()
        connection.close()
    return time.perf_counter() - start


def open_streams(port: int, cookie: str, n: int) -> tuple[list, dict]:
    """``n`` live streams opened and held: the connections and a count of the answers' statuses."""
    held, statuses = [], {}
    for _ in range(n):
        connection, answer = request(port, "/api/live/stream", cookie)
        statuses[answer.status] = statuses.get(answer.status, 0) + 1
        if answer.status == 200:
            answer.read(5)                                  # the stream has begun
            held.append(connection)
        else:
            answer.read()
            connection.close()
    return held, statuses


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(tmp)
        live_snapshot(data_dir)
        server, port = serve(data_dir)
        try:
            cookie = log_in(port)
            quiet = [load_page(port, cookie) for _ in range(LOADS)]
            streams, statuses = open_streams(port, cookie, STREAMS)
            idle = [socket.create_connection(("127.0.0.1", port), timeout=60) for _ in range(IDLE)]
            loaded = [load_page(port, cookie) for _ in range(LOADS)]
            for s in idle + [c.sock for c in streams if c.sock]:
                s.close()
        finally:
            server.close()
    q, w = statistics.median(quiet), statistics.median(loaded)
    rows = [["nothing else", f"{1e3 * q:.0f}", f"{1e3 * max(quiet):.0f}", "1.0"],
            [f"{STREAMS} streams asked, {IDLE} idle connections", f"{1e3 * w:.0f}", f"{1e3 * max(loaded):.0f}",
             f"{w / q:.1f}"]]
    verdict = "holds" if max(loaded) <= TARGET_S else "does NOT hold"
    report = f"""# The live page under load

Made by `python benchmarks/web_load.py` on {machine()}.
The screen on waitress with {THREADS} threads (the appliance's default) and its stream limit; the live page
(HTML, `style.css`, `clock.js`, `live.js`, `/api/live` with a map of the default bed) loaded {LOADS} times, each file
over a new connection.

| while | median load (ms) | slowest (ms) | median / quiet |
|---|---|---|---|
""" + "\n".join("| " + " | ".join(r) + " |" for r in rows) + f"""

Of the {STREAMS} live streams asked for: {", ".join(f"{n} answered {s}" for s, n in sorted(statuses.items()))}
(a refused stream is told to retry after 10 s; the browser's page does so). The target, the live page within
{TARGET_S:g} s while loaded, {verdict}: the slowest loaded page took {max(loaded):.2f} s.
"""
    (HERE / "web_load.md").write_text(report, encoding="utf-8")
    print(report)


if __name__ == "__main__":
    main()
