"""Serving a screen with waitress, alone or behind the TLS proxy on the same machine.

Behind the proxy every request comes from 127.0.0.1, so the login limiter's
per-address count would lock every user out after one person's failed logins.
``behind_proxy`` trusts the proxy's ``X-Forwarded-For`` and
``X-Forwarded-Proto`` from 127.0.0.1 alone, so the limiter and the audit log see
the browser's address; from anywhere else those headers are dropped.

Why waitress stays: it reads requests and writes answers in one asynchronous
loop, and a worker thread is taken only while a request is being answered. Idle
keep-alive connections and slow senders therefore cost a socket, not a thread;
``CONNECTION_LIMIT`` bounds those sockets (well above a ward's browsers, well
below the process's file limit) and ``CHANNEL_TIMEOUT_S`` closes idle ones. The
threads are taken by live streams, which hold one each for their whole life:
``stream_limit`` leaves some for everything else (:mod:`webui.streams` refuses
the rest with 503). That holds the load of one bed or one ward; a screen for far
more watchers would want an asynchronous server that holds streams without a
thread each (an ASGI server such as uvicorn or hypercorn), not more threads.
"""

from __future__ import annotations

import waitress

PROXY = "127.0.0.1"
CONNECTION_LIMIT = 500      # open sockets; each idle one costs a little memory and a file descriptor
CHANNEL_TIMEOUT_S = 30      # an idle connection is closed after this long (a stream is never idle)
CLEANUP_INTERVAL_S = 10     # how often idle connections are looked for
RESERVED_THREADS = 8        # threads no live stream may take: page loads, logins, acknowledgements


def serve(app, host: str, port: int, *, threads: int, ident: str, behind_proxy: bool = False) -> None:
    app.config.setdefault("MAX_STREAMS", stream_limit(threads))
    waitress.serve(app, **server_options(host, port, threads=threads, ident=ident, behind_proxy=behind_proxy))


def stream_limit(threads: int) -> int:
    """Live streams ``threads`` worker threads may hold: all but ``RESERVED_THREADS`` (or half of a few).

    >>> stream_limit(48), stream_limit(4), stream_limit(1)
    (40, 2, 1)
    """
    return max(1, threads - min(RESERVED_THREADS, threads // 2))


def server_options(host: str, port: int, *, threads: int, ident: str, behind_proxy: bool) -> dict:
    options = {"host": host, "port": port, "threads": threads, "ident": ident, "clear_untrusted_proxy_headers": True,
               "connection_limit": CONNECTION_LIMIT, "channel_timeout": CHANNEL_TIMEOUT_S,
               "cleanup_interval": CLEANUP_INTERVAL_S, "asyncore_use_poll": True}
    if behind_proxy:
        options.update(trusted_proxy=PROXY, trusted_proxy_count=1,
                       trusted_proxy_headers={"x-forwarded-for", "x-forwarded-proto"})
    return options
