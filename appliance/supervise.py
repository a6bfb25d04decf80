"""Background threads that outlive their own failures.

A helper thread that dies on an exception (a write error, a full disk) stops
its work silently while the monitor looks healthy. A supervised thread logs
the exception, keeps it as ``fault`` for the monitor to show as a technical
alarm, and runs its work again after a back-off that doubles up to a ceiling.
The work reports each success with :meth:`Supervised.ok`, which ends the fault
and resets the back-off.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


class Supervised:
    """``work()`` on a daemon thread named ``name``, restarted after any exception until it returns.

    ``fault`` is the last failure (``"OSError: ..."``) until the work reports an
    ``ok()``; ``failures`` counts them all. ``stop()`` cuts a back-off short, so
    the work gets one more run to finish (a writer draining what it holds).
    """

    def __init__(self, name: str, work: Callable[[], None], *, backoff_s: float = 0.5, max_backoff_s: float = 30.0):
        self.name, self.work = name, work
        self.backoff_s, self.max_backoff_s = backoff_s, max_backoff_s
        self.fault: str | None = None
        self.failures = 0
        self._delay = backoff_s
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)

    def start(self) -> Supervised:
        self._thread.start()
        return self

    def ok(self) -> None:
        """The work did a unit of its job: the fault is over."""
        if self.fault is not None:
            log.warning("%s: working again after %s", self.name, self.fault)
        self.fault, self._delay = None, self.backoff_s

    def stop(self) -> None:
        """No more restarts after the next failure, and no waiting out a back-off."""
        self._stopping.set()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def _loop(self) -> None:
        while True:
            try:
                self.work()
                return
            except Exception as exc:        # whatever kills the work is reported, never fatal
                self.failures += 1
                self.fault = f"{type(exc).__name__}: {exc}"
                if self._stopping.is_set():
                    log.error("%s failed while stopping: %s", self.name, self.fault)
                    return
                log.exception("%s failed (%d so far); restarting in %.1f s", self.name, self.failures, self._delay)
            self._stopping.wait(self._delay)
            self._delay = min(2 * self._delay, self.max_backoff_s)
