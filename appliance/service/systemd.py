"""systemd's notify protocol: readiness, status, stopping and watchdog pings.

With ``Type=notify`` systemd waits for ``READY=1`` before it counts the monitor
as started, and with ``WatchdogSec`` it restarts a monitor whose loop stops
sending ``WATCHDOG=1``. The protocol is one datagram to the socket named in
``$NOTIFY_SOCKET`` (a path, or an abstract name written with a leading ``@``),
so it needs no library. Outside systemd the variable is unset and every call
does nothing.
"""

from __future__ import annotations

import os
import socket
import time


class SystemdNotifier:
    """Sends notify messages, and watchdog pings at half the interval systemd asked for."""

    def __init__(self, environ=os.environ):
        address = environ.get("NOTIFY_SOCKET", "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        usec = environ.get("WATCHDOG_USEC", "")
        pid = environ.get("WATCHDOG_PID", "")
        wanted = usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid()))
        self.watchdog_s = int(usec) / 1e6 if wanted else None
        self._last_ping = float("-inf")

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def send(self, *fields: str) -> bool:
        """Send ``KEY=value`` lines as one message; False when there is no systemd to hear it."""
        if not self.address:
            return False
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            try:
                sock.sendto("\n".join(fields).encode(), self.address)
            except OSError:
                return False
        return True

    def ready(self, status: str) -> None:
        self.send("READY=1", f"STATUS={status}")

    def status(self, status: str) -> None:
        self.send(f"STATUS={status}")

    def stopping(self) -> None:
        self.send("STOPPING=1")

    def ping(self, now: float | None = None) -> bool:
        """``WATCHDOG=1`` if half the watchdog interval has passed since the last one; whether it was sent."""
        if self.watchdog_s is None:
            return False
        now = time.monotonic() if now is None else now
        if now - self._last_ping < self.watchdog_s / 2:
            return False
        self._last_ping = now
        return self.send("WATCHDOG=1")
