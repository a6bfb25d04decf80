"""Server-sent event streams that cost the server one encoding per change, however many screens watch.

A stream polls a cheap change key (a file's mtime, the ward station's message
count) and sends the shared event for each new key. A comment line every
``HEARTBEAT_S`` keeps proxies from closing an idle stream, and a stream ends
after ``STREAM_MAX_S`` (the browser reconnects after ``RECONNECT_MS``), so a
client that vanished without closing its connection holds a server thread for
at most that long. Each open stream holds a server thread, so at most
``MAX_STREAMS`` (app config) are open at once; one more is answered 503 with a
Retry-After, and the threads left over still serve page loads, logins and
acknowledgements.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Hashable

from flask import Flask, Response, current_app

HEARTBEAT_S = 15.0
STREAM_MAX_S = 600.0
RECONNECT_MS = 1000
MAX_STREAMS = 40            # the default server's 48 threads less 8 for everything else
RETRY_AFTER_S = 10


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
    # The app itself, not the request-bound proxy that stands for it (werkzeug's documented way).
    app = current_app._get_current_object()     # type: ignore[attr-defined]
    slots = _slots(app)
    if not slots.acquire(blocking=False):
        return Response(f"all {app.config.get('MAX_STREAMS', MAX_STREAMS)} live streams are open: "
                        f"try again shortly\n", status=503, mimetype="text/plain",
                        headers={"Retry-After": str(RETRY_AFTER_S), "Cache-Control": "no-store"})
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

    response = Response(events(), mimetype="text/event-stream", headers={"Cache-Control": "no-store"})
    response.call_on_close(slots.release)          # the server closes every response, streamed to its end or not
    return response


def _slots(app: Flask) -> threading.BoundedSemaphore:
    """The app's semaphore of open streams (made at the first stream, from ``MAX_STREAMS``)."""
    with _SLOTS_LOCK:
        return app.extensions.setdefault(
            "stream_slots", threading.BoundedSemaphore(app.config.get("MAX_STREAMS", MAX_STREAMS)))


_SLOTS_LOCK = threading.Lock()
