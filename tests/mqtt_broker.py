"""A real Mosquitto broker for the MQTT tests (notifiers, ward station), and the small helpers they share.

No skip when Mosquitto is missing: CI installs it (.ci/run), and a test of the
alarm path that silently does not run would hide a broken alarm path.
"""

import contextlib
import getpass
import socket
import subprocess
import time
from pathlib import Path

from report import free_port as free_port  # the tests take it from here, with the broker
from report import mosquitto_binary


def wait_until(condition, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return False


def accepting(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
        return True
    except OSError:
        return False


class Broker:
    """A Mosquitto process on a fixed port that a test can stop and start again; ``settings`` (mosquitto.conf
    lines, written to ``folder``) for a listener with TLS and passwords."""

    def __init__(self, settings: str = "", folder: Path | None = None):
        self.binary = mosquitto_binary()
        self.port = free_port()
        self.process = None
        self.command = [self.binary, "-p", str(self.port)]
        if settings:
            conf = folder / "mosquitto.conf"
            # as root, mosquitto would drop to its own user, who cannot read the test's files
            conf.write_text(f"user {getpass.getuser()}\nlistener {self.port} 127.0.0.1\n{settings}")
            self.command = [self.binary, "-c", str(conf)]

    def start(self, *more_ports: int):
        """Start it and return once it accepts on its own port and on ``more_ports`` (listeners its settings
        add, which Mosquitto may open after the first)."""
        self.process = subprocess.Popen(self.command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for port in (self.port, *more_ports):
            assert wait_until(lambda port=port: accepting(port)), f"mosquitto did not listen on port {port}"

    def stop(self):
        self.process.terminate()
        self.process.wait(5)
        self.process = None


@contextlib.contextmanager
def subscribed_station(port: int, **options):
    """A ward station on the broker at ``port``, subscribed before it is handed over, closed after."""
    from appliance.ward.station import WardStation

    with WardStation("127.0.0.1", port, **options) as station:
        assert station.wait_subscribed(10), "the ward station did not subscribe within 10 s"
        yield station
