"""Serving a screen with waitress, alone or behind the TLS proxy on the same machine.

Behind the proxy every request comes from 127.0.0.1, so the login limiter's
per-address count would lock every user out after one person's five wrong
passwords. ``behind_proxy`` trusts the proxy's ``X-Forwarded-For`` and
``X-Forwarded-Proto`` from 127.0.0.1 alone, so the limiter and the audit log see
the browser's address; from anywhere else those headers are dropped.
"""

from __future__ import annotations

import waitress

PROXY = "127.0.0.1"


def serve(app, host: str, port: int, *, threads: int, ident: str, behind_proxy: bool = False) -> None:
    waitress.serve(app, **server_options(host, port, threads=threads, ident=ident, behind_proxy=behind_proxy))


def server_options(host: str, port: int, *, threads: int, ident: str, behind_proxy: bool) -> dict:
    options = {"host": host, "port": port, "threads": threads, "ident": ident, "clear_untrusted_proxy_headers": True}
    if behind_proxy:
        options.update(trusted_proxy=PROXY, trusted_proxy_count=1,
                       trusted_proxy_headers={"x-forwarded-for", "x-forwarded-proto"})
    return options
