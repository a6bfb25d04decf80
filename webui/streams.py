"""Server-sent event streams that cost the server one encoding per change, however many screens watch.

A stream polls a cheap change key (a file's mtime, the ward station's message
count) and sends the shared event for each new key. A comment line every
``HEARTBEAT_S`` keeps proxies from closing an idle stream, and a stream ends
after ``STREAM_MAX_S`` (the browser reconnects after ``RECONNECT_MS``), so a
client that vanished without closing its connection holds a server thread for
at most that long.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Hashable

from flask import Response, current_app

HEARTBEAT_S = 15.0
STREAM_MAX_S = 600.0
RECONNECT_MS = 1000


class SharedEvents:
    """The ``data:`` event of ``make()``, made once per change key for every open stream."""

    def __init__(self, make: Callable[[], dict]):
        self._make = make
        self._lock = threading.Lock()
        self._key: Hashable = None
        self._event = ""

    def event(self, key: Hashable) -> str:
        with self._lock:
            if key != self._key:
                self._key = key
                self._event = f"data: {json.dumps(self._make(), separators=(',', ':'))}\n\n"
            return self._event


def event_stream(name: str, make: Callable[[], dict], key_of: Callable[[], Hashable], poll_s: float) -> Response:
    """A stream of ``make()`` for every new ``key_of()`` (None: nothing to send yet), checked every ``poll_s``.

    ``name`` keys the app's one SharedEvents for this stream; ``make`` and
    ``key_of`` run in the app's context.
    """
    app = current_app._get_current_object()
    shared = app.extensions.setdefault(name, SharedEvents(make))
    max_s = app.config.get("STREAM_MAX_S", STREAM_MAX_S)

    def events():
        started = last_beat = time.monotonic()
        last_key = None
        yield f"retry: {RECONNECT_MS}\n\n"
        while time.monotonic() - started < max_s:
            with app.app_context():
                key = key_of()
                if key is not None and key != last_key:
                    last_key = key
                    yield shared.event(key)
                    last_beat = time.monotonic()
                elif time.monotonic() - last_beat > HEARTBEAT_S:
                    yield ": keep-alive\n\n"
                    last_beat = time.monotonic()
            time.sleep(poll_s)

    return Response(events(), mimetype="text/event-stream", headers={"Cache-Control": "no-store"})
