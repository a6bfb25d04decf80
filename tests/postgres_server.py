"""A throw-away PostgreSQL server for the history tests: initdb and pg_ctl in a new folder, on a Unix socket in
that folder and a free port, stopped and deleted afterwards.

PostgreSQL refuses to run as root, so under root the server runs as the ``postgres`` account Debian's package
makes (``runuser -u postgres``). The tests skip, saying why, only when the server's programs are absent; the
README's test command installs them (apt-get install postgresql).
"""

import contextlib
import glob
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from mqtt_broker import free_port

SUPERUSER = "postgres"


def binaries() -> Path | None:
    """The newest installed PostgreSQL's bin folder (Debian: /usr/lib/postgresql/<major>/bin), or None."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb else None


class PostgresServer:
    """One server in its own folder; ``dsn(database, user)`` to reach it, ``psql(sql)`` to run SQL as the
    superuser the way an install script does. ``fsync`` off (the tests) trades durability for speed; a benchmark
    that times writes keeps it on."""

    def __init__(self, bin_dir: Path, fsync: bool = False):
        self.bin, self.fsync = bin_dir, fsync
        self.folder = Path(tempfile.mkdtemp(prefix="appliance-pg-"))
        self.data = self.folder / "data"
        self.port = free_port()
        self.as_user = ["runuser", "-u", SUPERUSER, "--"] if os.geteuid() == 0 else []
        if self.as_user:
            shutil.chown(self.folder, SUPERUSER, SUPERUSER)

    def start(self) -> None:
        self._run(str(self.bin / "initdb"), "-D", str(self.data), "-U", SUPERUSER, "--auth=trust", "-E", "UTF8",
                  "--locale=C.UTF-8")
        fsync = "on" if self.fsync else "off"
        options = f"-c listen_addresses='' -c unix_socket_directories='{self.folder}' -p {self.port} -c fsync={fsync}"
        self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-l", str(self.folder / "server.log"), "-w",
                  "-o", options, "start")

    def stop(self) -> None:
        if (self.data / "postmaster.pid").exists():
            self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(self.folder, ignore_errors=True)

    def dsn(self, database: str = "postgres", user: str = SUPERUSER) -> str:
        return f"host={self.folder} port={self.port} dbname={database} user={user}"

    def psql(self, script: str, database: str = "postgres") -> str:
        """Run ``script`` (SQL and psql's backslash commands) as the superuser with psql, stopping at the first
        error, as an install script does; what it printed."""
        return self._run(str(self.bin / "psql"), "-X", "-q", "-v", "ON_ERROR_STOP=1", "-h", str(self.folder),
                         "-p", str(self.port), "-U", SUPERUSER, "-d", database, "-f", "-", stdin=script).stdout

    def _run(self, *command: str, stdin: str | None = None) -> subprocess.CompletedProcess:
        result = subprocess.run([*self.as_user, *command], capture_output=True, text=True, check=False,
                                cwd=self.folder, input=stdin)
        if result.returncode:
            log = self.folder / "server.log"
            raise RuntimeError(f"{' '.join(command)}: {result.stderr.strip()}"
                               + (f"\n{log.read_text()[-2000:]}" if log.exists() else ""))
        return result


@contextlib.contextmanager
def running_postgres(fsync: bool = False):
    bin_dir = binaries()
    if bin_dir is None:
        import pytest
        pytest.skip("PostgreSQL is not installed (apt-get install postgresql): the history tests need its server")
    server = PostgresServer(bin_dir, fsync)
    try:
        server.start()
        yield server
    finally:
        server.stop()
