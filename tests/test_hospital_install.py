"""Installing a hospital server from its description (appliance.hospital.install and
systemd/install-hospital-server.sh), without systemd: the files written, the units named, the SQL run on a real
PostgreSQL, and the script's steps with the system's tools replaced by recorders."""

import datetime as dt
import os
import re
import stat
import subprocess
import sys
import tomllib
from pathlib import Path

import psycopg
import pytest
from postgres_server import running_postgres

from appliance.cli import main
from appliance.errors import ConfigError
from appliance.hospital.description import HistoryPolicy, hospital_from_mapping, load_hospital
from appliance.hospital.history.reads import recent_events
from appliance.hospital.history.schema import create_schema
from appliance.hospital.history.store import StoredEvent, write_events
from appliance.hospital.install import ACCOUNT, READER, install, setup_sql
from appliance.hospital.nodeconfig import read_password

REPO = Path(__file__).resolve().parents[1]
DESCRIPTION = """
[hospital]
cluster = "st-mary"
store_dir = "/var/lib/appliance-hospital/store"

[[node]]
name = "n1"
host = "10.20.0.11"

[[node]]
name = "n2"
host = "10.20.0.12"

[[node]]
name = "n3"
host = "10.20.0.13"

[[ward]]
name = "ward3"
beds = ["w3-bed01"]
stations = ["ward3-station"]

[history]
database = "st_mary_history"
events_days = 3650
pressure_days = 90
"""


@pytest.fixture
def description(tmp_path):
    path = tmp_path / "hospital.toml"
    path.write_text(DESCRIPTION)
    return path


def test_install_writes_the_nodes_files_the_description_and_the_sql_and_names_the_units(tmp_path, description,
                                                                                        capsys):
    root = tmp_path / "root"
    assert main(["hospital", "install", "--description", str(description), "--root", str(root)]) == 0
    assert capsys.readouterr().out.split() == [*(f"appliance-hospital-node@n{i}.service" for i in (1, 2, 3)),
                                               "appliance-hospital-history.service",
                                               "appliance-hospital-overview.service"]
    folder = root / "etc/appliance/hospital"
    assert sorted(p.name for p in folder.iterdir()) == ["history-setup.sql", "hospital.toml", "n1.conf", "n2.conf",
                                                        "n3.conf", "secrets"]
    assert 'store_dir: "/var/lib/appliance-hospital/store/n2"' in (folder / "n2.conf").read_text()
    assert stat.S_IMODE((folder / "n1.conf").stat().st_mode) == 0o600
    assert load_hospital(folder / "hospital.toml") == load_hospital(description)
    assert read_password(folder / "secrets", "hospital-history")
    assert (folder / "history-setup.sql").read_text() == setup_sql(load_hospital(description).history)

    assert main(["hospital", "install", "--description", str(description), "--root", str(root), "--node", "n2",
                 "--no-history"]) == 0
    assert capsys.readouterr().out.split() == ["appliance-hospital-node@n2.service"]


@pytest.mark.parametrize("change, options, message", [
    (("/var/lib/appliance-hospital/store", "/srv/nats"), {}, "[hospital] store_dir '/srv/nats' must be "
                                                              "/var/lib/appliance-hospital or a folder in it"),
    (("", ""), {"nodes": ["n4"]}, "node 'n4' is not in the hospital description; its nodes: n1, n2, n3"),
    (("[history]", "[unused]"), {}, "unknown key 'unused'"),
])
def test_install_refuses_what_the_units_could_not_run(tmp_path, change, options, message):
    text = DESCRIPTION.replace(*change)
    with pytest.raises(ConfigError) as raised:
        install(hospital_from_mapping(tomllib.loads(text)), tmp_path, **options)
    assert message in str(raised.value)


def test_a_notification_service_installs_only_when_named_and_only_one_the_description_has(tmp_path):
    hospital = hospital_from_mapping(tomllib.loads(DESCRIPTION.replace(
        "[history]", '[[notifier]]\nname = "phones"\nwards = ["ward3"]\nurl = "https://pager.example/"\n\n[history]')))
    assert install(hospital, tmp_path, ["n1"], history=False, notifiers=["phones"]).units == (
        "appliance-hospital-node@n1.service", "appliance-hospital-notify@phones.service")
    assert read_password(tmp_path / "etc/appliance/hospital/secrets", "notify-phones")
    assert install(hospital, tmp_path, ["n1"], history=False).units == ("appliance-hospital-node@n1.service",)
    with pytest.raises(ConfigError, match="no \\[\\[notifier\\]\\] named 'pagers'.*its notifiers: phones"):
        install(hospital, tmp_path, notifiers=["pagers"])


def test_without_a_policy_only_the_nodes_install(tmp_path):
    hospital = hospital_from_mapping(tomllib.loads(DESCRIPTION.split("[history]")[0]))
    with pytest.raises(ConfigError, match="no \\[history\\] table .* or install without the history writer"):
        install(hospital, tmp_path)
    assert install(hospital, tmp_path, history=False).units[-1] == "appliance-hospital-node@n3.service"


def test_the_setup_sql_makes_a_database_only_its_roles_reach_that_the_writer_builds_in_and_readers_read(
        tmp_path, description):
    sql = setup_sql(load_hospital(description).history)
    with running_postgres() as postgres:
        postgres.psql(sql)
        postgres.psql(sql)                                      # run again: nothing new, no error
        assert postgres.psql("SELECT datname, pg_get_userbyid(datdba) FROM pg_database WHERE datname LIKE 'st%'") \
            .split("\n")[2].split("|") == [" st_mary_history ", f" {ACCOUNT}"]
        with psycopg.connect(postgres.dsn("st_mary_history", ACCOUNT)) as db:
            create_schema(db)
            now = dt.datetime.now(dt.UTC)
            assert write_events(db, [StoredEvent(now, "ward3", "w3-bed01", 1, "alarm", {"kind": "raised"})]) == 1
            assert [e["seq"] for e in recent_events(db, now - dt.timedelta(minutes=1))] == [1]
        postgres.psql("CREATE ROLE someone LOGIN")
        with pytest.raises(psycopg.OperationalError, match="permission denied for database"):
            psycopg.connect(postgres.dsn("st_mary_history", "someone"))
        postgres.psql(f'CREATE ROLE "ward3-station" LOGIN IN ROLE "{READER}"')    # as the SQL's comment says
        with psycopg.connect(postgres.dsn("st_mary_history", "ward3-station")) as station:
            assert [e["seq"] for e in recent_events(station, now - dt.timedelta(minutes=1), ward="ward3")] == [1]
            with pytest.raises(psycopg.errors.InsufficientPrivilege, match="permission denied for table event"):
                station.execute("DELETE FROM event")


RECORDER = """#!/bin/sh
echo "$(basename "$0") $*" >> "$RECORD"
"""


def test_the_install_script_runs_each_step_on_the_description(tmp_path, description):
    """apt-get, pip, systemd-sysusers, chown, runuser and systemctl replaced by recorders; the appliance command
    is this environment's, so the files it writes are real."""
    tools, root, prefix = tmp_path / "tools", tmp_path / "root", tmp_path / "prefix"
    for folder in (tools, prefix / "bin"):
        folder.mkdir(parents=True)
    for name in ("apt-get", "systemd-sysusers", "chown", "runuser", "systemctl"):
        (tools / name).write_text(RECORDER)
        (tools / name).chmod(0o755)
    (prefix / "bin/pip").write_text(RECORDER)
    (prefix / "bin/appliance").write_text(f'#!/bin/sh\nexec {sys.executable} -m appliance "$@"\n')
    for tool in ("pip", "appliance"):
        (prefix / "bin" / tool).chmod(0o755)
    record = tmp_path / "record"
    environment = {**os.environ, "PATH": f"{tools}:{os.environ['PATH']}", "RECORD": str(record),
                   "PYTHONPATH": str(REPO)}
    result = subprocess.run(["bash", str(REPO / "systemd/install-hospital-server.sh"), "--description",
                             str(description), "--node", "n1", "--prefix", str(prefix), "--root", str(root)],
                            capture_output=True, text=True, check=False, env=environment)
    assert result.returncode == 0, result.stderr
    steps = record.read_text().splitlines()
    assert steps == [
        "apt-get install -y -qq python3-venv postgresql",
        f"pip install -q {REPO}[hospital]",
        f"systemd-sysusers --root={root} {root}/usr/lib/sysusers.d/appliance-hospital.conf",
        f"chown -R appliance-hospital:appliance-hospital {root}/etc/appliance/hospital",
        "runuser -u postgres -- psql -X -q -v ON_ERROR_STOP=1 -f -",
        "systemctl daemon-reload",
        "systemctl enable --now appliance-hospital-node@n1.service appliance-hospital-history.service "
        "appliance-hospital-overview.service"]
    for unit in ("appliance-hospital-node@.service", "appliance-hospital-history.service",
                 "appliance-hospital-overview.service", "appliance-hospital-notify@.service"):
        assert (root / "usr/lib/systemd/system" / unit).read_text() == (REPO / "systemd" / unit).read_text()
    assert (root / "etc/appliance/hospital/n1.conf").exists()
    assert "installed and started: appliance-hospital-node@n1.service appliance-hospital-history.service " \
        "appliance-hospital-overview.service" in result.stdout

    bad = subprocess.run(["bash", str(REPO / "systemd/install-hospital-server.sh"), "--node"], capture_output=True,
                         text=True, check=False, env=environment)
    assert bad.returncode != 0 and "--node needs a name" in bad.stderr


def test_the_documented_history_table_is_a_policy_the_description_accepts():
    text = (REPO / "docs/hospital-history.md").read_text()
    [example] = re.findall(r"```toml\n(.*?)```", text, re.S)
    hospital = hospital_from_mapping(tomllib.loads(DESCRIPTION.split("[history]")[0] + example))
    assert hospital.history == HistoryPolicy(3650, 90, "appliance_history")
    policy = text.split("## The policy")[1].split("\n## ")[0]
    documented = set(re.findall(r"^\| `([a-z_]+)` \|", policy, re.M))
    assert documented == {"database", "events_days", "pressure_days"}
