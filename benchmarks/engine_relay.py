"""Relays to a server (each node of a hospital engine, or a ward's broker) that a test or the soak can cut: the
bed's side of a pulled cable, seen at once by the client, with new connections refused until it is mended."""

from __future__ import annotations

import contextlib
import socket
import threading

from appliance.hospital.cluster import LOOPBACK, LocalCluster, free_ports


class CuttableLink:
    """TCP relays on free loopback ports, one to each of ``targets`` (host, port): a client given :attr:`ports`
    (:attr:`urls` for engine nodes) reaches them only through the relays, so :meth:`cut` drops its connections at
    once (a pulled cable that the client sees) and refuses new ones until :meth:`mend`."""

    def __init__(self, targets: list[tuple[str, int]]):
        self.targets = list(targets)
        self.ports = free_ports(len(self.targets))
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []
        self._cut = threading.Event()
        self._acceptors: list[threading.Thread] = []
        self.mend()

    @classmethod
    def to_cluster(cls, cluster: LocalCluster) -> CuttableLink:
        """Relays to every node's client port of ``cluster``."""
        return cls([(node.host, node.client_port) for node in cluster.hospital.nodes])

    @property
    def urls(self) -> list[str]:
        return [f"nats://{LOOPBACK}:{port}" for port in self.ports]

    def mend(self) -> None:
        self._cut.clear()
        self._acceptors = [threading.Thread(target=self._accept, args=(socket.create_server((LOOPBACK, port)),
                                                                       target), daemon=True)
                           for port, target in zip(self.ports, self.targets)]
        for thread in self._acceptors:
            thread.start()

    def cut(self) -> None:
        self._cut.set()
        for thread in self._acceptors:             # each closes its listening socket: new connections are refused
            thread.join()
        with self._lock:
            doomed, self._sockets = self._sockets, []
        for s in doomed:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    close = cut

    def _accept(self, listener: socket.socket, target) -> None:
        listener.settimeout(0.05)
        with listener:
            while not self._cut.is_set():
                try:
                    client, _ = listener.accept()
                except TimeoutError:
                    continue
                client.settimeout(None)
                try:
                    server = socket.create_connection(target, timeout=2)
                except OSError:
                    client.close()
                    continue
                server.settimeout(None)
                with self._lock:
                    self._sockets += [client, server]
                for a, b in ((client, server), (server, client)):
                    threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                sink.sendall(data)
        except OSError:
            pass
        for s in (source, sink):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
