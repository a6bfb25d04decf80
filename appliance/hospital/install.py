"""What a hospital server needs from the description, written under a root folder: the configuration of each node
it runs and the passwords, the description itself for the history writer, and the SQL that makes the history's
role and database; and the systemd units to enable there. With ``[tls]``, the hospital CA's certificate and the
certificate and key of each node it runs are copied into ``/etc/appliance/hospital/tls`` (the key 0600, no other
node's key), and the description written there names that folder.

``systemd/install-hospital-server.sh`` runs it on Debian as root (``appliance hospital install --root /``), then
runs the SQL as PostgreSQL's superuser and enables the units it printed. The units are templates from
``systemd/``: ``appliance-hospital-node@<node>.service`` reads ``/etc/appliance/hospital/<node>.conf``,
``appliance-hospital-history.service`` runs the writer, and ``appliance-hospital-notify@<name>.service`` a
notification service. All run as the account ``appliance-hospital``, whose
state folder holds the nodes' stores, and the writer reaches PostgreSQL on its Unix socket as the role of the
same name (Debian's peer authentication: no password to keep).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from appliance.errors import ConfigError
from appliance.files import write_atomic
from appliance.hospital.description import Hospital, HistoryPolicy, description_text
from appliance.hospital.nodeconfig import write_node_configs
from appliance.hospital.tls import TlsFolder

CONFIG_DIR = PurePosixPath("/etc/appliance/hospital")
STATE_DIR = PurePosixPath("/var/lib/appliance-hospital")
ACCOUNT = "appliance-hospital"
"""The system account of the units (systemd/appliance-hospital.sysusers) and the writer's PostgreSQL role."""
HISTORY_UNIT = "appliance-hospital-history.service"
OVERVIEW_UNIT = "appliance-hospital-overview.service"
READER = "appliance-history-reader"
"""The PostgreSQL group role that may read the history, nothing else: ward IT makes each ward station's login role
a member of it (the stations' ``[history]``)."""
SETUP_SQL = "history-setup.sql"
TLS_DIR = "tls"


@dataclass(frozen=True)
class Installed:
    """The folder written (under the root), the SQL file in it, and the units to enable, in start order."""

    folder: Path
    sql: Path | None
    units: tuple[str, ...]


def node_unit(name: str) -> str:
    return f"appliance-hospital-node@{name}.service"


def notify_unit(name: str) -> str:
    return f"appliance-hospital-notify@{name}.service"


def setup_sql(policy: HistoryPolicy) -> str:
    """psql input, safe to run again, that makes the writer's role and the history's database it owns, and the
    readers' group role, which may connect and read every table the writer makes; nobody else may connect."""
    return "\n".join([
        "-- The history's roles and database, for appliance-hospital-history.service: run as PostgreSQL's superuser",
        "-- (runuser -u postgres -- psql -v ON_ERROR_STOP=1 -f - < this-file). It can be run again.",
        f"SELECT format('CREATE ROLE %I LOGIN', '{ACCOUNT}') WHERE NOT EXISTS "
        f"(SELECT FROM pg_roles WHERE rolname = '{ACCOUNT}') \\gexec",
        f"SELECT format('CREATE ROLE %I NOLOGIN', '{READER}') WHERE NOT EXISTS "
        f"(SELECT FROM pg_roles WHERE rolname = '{READER}') \\gexec",
        f"SELECT format('CREATE DATABASE %I OWNER %I', '{policy.database}', '{ACCOUNT}') WHERE NOT EXISTS "
        f"(SELECT FROM pg_database WHERE datname = '{policy.database}') \\gexec",
        f'REVOKE ALL ON DATABASE "{policy.database}" FROM PUBLIC;',
        f'GRANT ALL ON DATABASE "{policy.database}" TO "{ACCOUNT}";',
        f'GRANT CONNECT ON DATABASE "{policy.database}" TO "{READER}";',
        "-- A ward station reads as a member of the readers' role, e.g.",
        f'-- CREATE ROLE "ward3-station" LOGIN PASSWORD \'...\' IN ROLE "{READER}";  (and a pg_hba.conf line)',
        f'\\connect "{policy.database}"',
        f'GRANT USAGE ON SCHEMA public TO "{READER}";',
        f'GRANT SELECT ON ALL TABLES IN SCHEMA public TO "{READER}";',
        f'ALTER DEFAULT PRIVILEGES FOR ROLE "{ACCOUNT}" IN SCHEMA public GRANT SELECT ON TABLES TO "{READER}";',
        ""])


def install(hospital: Hospital, root: Path, nodes: list[str] | None = None, history: bool = True,
            notifiers: list[str] | None = None) -> Installed:
    """Write what the server runs into ``root`` (``/`` on the server itself): ``nodes`` (all by default) are the
    ones this server runs; ``history`` whether it runs the history writer too; ``notifiers`` the notification
    services it runs (none by default)."""
    names = [node.name for node in hospital.nodes]
    chosen = names if nodes is None else nodes
    for name in chosen:
        if name not in names:
            raise ConfigError(f"node {name!r} is not in the hospital description; its nodes: {', '.join(names)}")
    for name in notifiers or []:
        hospital.notifier(name)                     # a ConfigError naming the ones there are
    store = PurePosixPath(hospital.store_dir)
    if chosen and store != STATE_DIR and STATE_DIR not in store.parents:
        raise ConfigError(f"[hospital] store_dir {str(store)!r} must be {STATE_DIR} or a folder in it: the node's "
                          f"unit may write nowhere else")
    if history and hospital.history is None:
        raise ConfigError("the hospital description has no [history] table (events_days, pressure_days): add the "
                          "hospital's retention policy, or install without the history writer")
    folder = Path(root) / CONFIG_DIR.relative_to("/")
    folder.parent.mkdir(parents=True, exist_ok=True)
    if hospital.tls is not None:
        hospital = dataclasses.replace(hospital, tls=_copy_tls(hospital.tls, folder / TLS_DIR, chosen))
    write_node_configs(hospital, folder, chosen)
    write_atomic(folder / "hospital.toml", description_text(hospital))
    sql = None
    if history:
        assert hospital.history is not None
        sql = folder / SETUP_SQL
        write_atomic(sql, setup_sql(hospital.history))
    units = tuple(node_unit(name) for name in chosen) + ((HISTORY_UNIT, OVERVIEW_UNIT) if history else ()) \
        + tuple(notify_unit(name) for name in notifiers or [])
    return Installed(folder, sql, units)


def _copy_tls(source: TlsFolder, folder: Path, nodes: list[str]) -> TlsFolder:
    """The CA's certificate and ``nodes``' certificates and keys copied from ``source`` into ``folder``."""
    if not source.ca_file.is_file():
        raise ConfigError(f"[tls] {source.ca_file} does not exist: the hospital CA's certificate, which every client "
                          f"trusts (`appliance hospital certs` makes it)")
    installed = TlsFolder(folder)
    copies = [(source.ca_file, installed.ca_file, 0o644)]
    for name in nodes:
        _, cert, key = source.node_files(name)          # a ConfigError naming a missing file
        copies += [(cert, installed.cert_file(name), 0o644), (key, installed.key_file(name), 0o600)]
    folder.mkdir(mode=0o755, parents=True, exist_ok=True)
    for origin, target, mode in copies:
        if origin.resolve() != target.resolve():
            write_atomic(target, origin.read_bytes())   # made 0600, so a key is never readable by others
        target.chmod(mode)
    return installed
