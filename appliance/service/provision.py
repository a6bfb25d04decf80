"""First-boot provisioning: a new bed's appliance set up from a file on the SD card's boot partition.

The image ships with no account, no hostname of its own and no TLS certificate,
so every bed gets its own. The installer writes ``appliance-setup.toml`` on the
FAT boot partition (readable from any laptop) before the first boot::

    hostname = "ward3-bed12"
    bed_id = "ward3-bed12"        # optional, default the hostname
    source = "hardware"           # optional: hardware (default) or virtual (a demonstration unit)

    [admin]                       # the nurse's screen's first administrator
    name = "admin"
    password = "at least ten characters"

    [broker]                      # optional: the ward's MQTT broker
    host = "broker.ward"
    port = 8883
    username = "ward3-bed12"
    password = "the bed's broker password"
    ca_file = "ward-ca.crt"       # beside this file on the boot partition

:func:`provision` then records the hostname, writes the monitor's configuration,
creates the admin account, makes a self-signed certificate for the screen's TLS
proxy, removes the passwords from the boot partition's file (FAT has no
permissions: anyone holding the card could read them) and writes a marker. Each
step is skipped when its result exists, so a first boot cut short by a power cut
simply runs again. The root file system is read-only with a throw-away overlay,
so the hostname is kept in the configuration folder (on the data partition) and
set again at every boot.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import tempfile
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from appliance.accounts.users import AccountError, UserStore
from appliance.core.toml_files import check_keys, read_toml, toml_value
from appliance.errors import ConfigError
from appliance.files import write_atomic
from appliance.service.config import config_from_mapping
from appliance.service.config_sections import mqtt_settings

SETUP_FILE = Path("/boot/firmware/appliance-setup.toml")
CONFIG_DIR = Path("/etc/appliance")
DATA_DIR = Path("/var/lib/appliance")
ACCOUNT = "appliance"               # the service account that runs the monitor and the screen
MARKER = "provisioned"
CERTIFICATE_DAYS = 3650             # a self-signed certificate is trusted by its fingerprint, not its age
_HOSTNAME = re.compile(r"^[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?$")
_PASSWORD_LINE = re.compile(r"^\s*password\s*=")


class ProvisionError(ConfigError):
    """The setup file is missing or wrong, or a step failed; the message names the file and key."""


@dataclass(frozen=True)
class Setup:
    """The setup file's settings, checked. ``admin_password`` is None once it was removed from the file."""

    path: Path
    hostname: str
    bed_id: str
    source: str
    admin_name: str
    admin_password: str | None
    broker: dict | None             # the [broker] table, ``password`` taken out into ``broker_password``
    broker_password: str | None


def read_setup(path: Path) -> Setup:
    """The setup file at ``path``; a missing file or a bad key is a ProvisionError naming both."""
    path = Path(path)
    if not path.is_file():
        raise ProvisionError(f"no setup file {path}: write one on the boot partition before the first boot "
                             f"(image-build/appliance-setup.example.toml shows the keys)")
    data = read_toml(path, "setup file", ProvisionError)
    _only(data, {"hostname", "bed_id", "source", "admin", "broker"}, path, "the top level")
    hostname = _text(data, "hostname", path, "")
    if not _HOSTNAME.match(hostname):
        raise ProvisionError(f"{path}: hostname must be 1-63 lower-case letters, digits and '-', not starting or "
                             f"ending with '-', got {hostname!r}")
    admin = _table(data, "admin", path)
    _only(admin, {"name", "password"}, path, "[admin]")
    broker = _table(data, "broker", path) if "broker" in data else None
    broker_password = None
    if broker is not None:
        _only(broker, {"host", "port", "topic_prefix", "keepalive_s", "username", "password", "ca_file"}, path,
              "[broker]")
        broker_password = broker.pop("password", None)
        checked = {key: str(_beside(path, value)) if key == "ca_file" else value for key, value in broker.items()}
        try:                        # the monitor's own check of a broker table, named as the setup file's
            mqtt_settings(checked, None, where=f"{path}: [broker]")
        except ConfigError as exc:
            raise ProvisionError(str(exc)) from None
        if broker_password is not None and "username" not in broker:
            raise ProvisionError(f"{path}: [broker] password needs a username")
    source = data.get("source", "hardware")
    if source not in ("hardware", "virtual"):
        raise ProvisionError(f"{path}: source must be \"hardware\" or \"virtual\", got {source!r}")
    return Setup(path, hostname, _text(data, "bed_id", path, "", default=hostname), source,
                 _text(admin, "name", path, "[admin] "), admin.get("password"), broker, broker_password)


def provision(setup_path: Path = SETUP_FILE, config_dir: Path = CONFIG_DIR, data_dir: Path = DATA_DIR, *,
              set_hostname: Callable[[str], None] | None = socket.sethostname,
              account: str | None = ACCOUNT) -> list[str]:
    """Provision once (see the module's description), then set the recorded hostname; returns what was done.

    ``set_hostname`` None leaves the running system's hostname alone (an image build, a test in a chroot);
    ``account`` (a user with a group of the same name) gets the files the services write or read; None leaves
    them to the caller.
    """
    config_dir, data_dir = Path(config_dir), Path(data_dir)
    done = []
    if not (config_dir / MARKER).exists():
        done = _first_boot(read_setup(setup_path), config_dir, data_dir, account)
        _write_readable(config_dir / MARKER, f"provisioned on {time.strftime('%Y-%m-%d %H:%M:%S %z')}\n")
    hostname_file = config_dir / "hostname"
    try:
        hostname = hostname_file.read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        raise ProvisionError(f"{hostname_file} is missing although {config_dir / MARKER} says the appliance was "
                             f"provisioned: remove the marker to provision again") from None
    if set_hostname is not None:
        set_hostname(hostname)
        done.append(f"hostname set to {hostname}")
    return done


def _first_boot(setup: Setup, config_dir: Path, data_dir: Path, account: str | None) -> list[str]:
    done = []
    config_dir.mkdir(parents=True, exist_ok=True)
    _write_readable(config_dir / "hostname", setup.hostname + "\n")
    if not (config_dir / "monitor.toml").exists():
        _write_monitor_config(setup, config_dir, account)
        done.append(f"wrote {config_dir / 'monitor.toml'}")
    if _create_admin(setup, data_dir, account):
        done.append(f"created the screen's admin account {setup.admin_name!r}")
    if make_certificate(config_dir / "tls", setup.hostname):
        done.append(f"made a TLS certificate for {setup.hostname} in {config_dir / 'tls'}")
    if scrub_passwords(setup.path):
        done.append(f"removed the passwords from {setup.path}")
    return done


def _write_monitor_config(setup: Setup, config_dir: Path, account: str | None) -> None:
    """``monitor.toml`` for this bed, checked as the monitor will read it before it is written."""
    mapping: dict[str, dict] = {"monitor": {"bed_id": setup.bed_id, "source": setup.source}}
    if setup.broker is not None:
        mqtt = dict(setup.broker)
        if "ca_file" in mqtt:
            shutil.copyfile(_beside(setup.path, mqtt["ca_file"]), config_dir / "ward-ca.crt")
            mqtt["ca_file"] = "ward-ca.crt"
        if setup.broker_password is not None:
            secret = config_dir / "mqtt-password"
            write_atomic(secret, setup.broker_password + "\n")
            secret.chmod(0o640)                     # root writes, the monitor's group reads
            if account is not None:
                shutil.chown(secret, group=account)
            mqtt["password_file"] = "mqtt-password"
        mapping["notify"] = {"mqtt": mqtt}
    try:
        config_from_mapping(mapping, base=config_dir)
    except ConfigError as exc:
        raise ProvisionError(f"{setup.path}: the monitor's configuration made from it is refused: {exc}") from None
    lines = ["# Written by `appliance provision` from the boot partition's setup file; edit freely.",
             "# The monitor's keys are described in appliance/service/config.py."]
    for table, values in (("monitor", mapping["monitor"]), ("notify.mqtt", mapping.get("notify", {}).get("mqtt"))):
        if values:
            lines += ["", f"[{table}]"] + [f"{key} = {toml_value(value)}" for key, value in values.items()]
    _write_readable(config_dir / "monitor.toml", "\n".join(lines) + "\n")


def _create_admin(setup: Setup, data_dir: Path, account: str | None) -> bool:
    """The screen's first admin, unless that account exists; the screen's store is given to ``account``."""
    data_dir.mkdir(parents=True, exist_ok=True)
    path = data_dir / "webui.db"
    store = UserStore(path)
    if any(user.name == setup.admin_name for user in store.users()):
        return False
    if setup.admin_password is None:
        raise ProvisionError(f"{setup.path}: [admin] password is missing (the account {setup.admin_name!r} "
                             f"does not exist yet)")
    try:
        store.create(setup.admin_name, setup.admin_password, "admin", by="provisioning")
    except AccountError as exc:
        raise ProvisionError(f"{setup.path}: [admin]: {exc}") from None
    if account is not None:
        for name in ("webui.db", "webui.db-wal", "webui.db-shm"):
            if (data_dir / name).exists():
                shutil.chown(data_dir / name, user=account, group=account)
    return True


def make_certificate(folder: Path, hostname: str) -> bool:
    """A self-signed certificate and key (P-256) for ``hostname`` in ``folder``, unless both exist; the key is
    readable by root alone (nginx reads it before it drops its privileges)."""
    certificate, key = folder / "screen.crt", folder / "screen.key"
    if certificate.exists() and key.exists():
        return False
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as temporary:
        new_key, new_certificate = Path(temporary, "screen.key"), Path(temporary, "screen.crt")
        command = ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                   "-keyout", str(new_key), "-out", str(new_certificate), "-days", str(CERTIFICATE_DAYS),
                   "-subj", f"/CN={hostname}", "-addext", f"subjectAltName=DNS:{hostname},DNS:{hostname}.local"]
        try:
            result = subprocess.run(command, capture_output=True, text=True, check=False)
        except FileNotFoundError:
            raise ProvisionError("openssl is needed to make the screen's TLS certificate") from None
        if result.returncode != 0:
            raise ProvisionError(f"openssl could not make the screen's TLS certificate: {result.stderr.strip()}")
        new_key.chmod(0o600)
        os.replace(new_key, key)
        os.replace(new_certificate, certificate)
    return True


def scrub_passwords(path: Path) -> bool:
    """Replace every ``password = ...`` line of the setup file by a comment; True if there was one.

    A password the lines cannot remove (a multi-line string) is refused rather than left on the card."""
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    kept = [f"# password removed by appliance provision on {time.strftime('%Y-%m-%d')}\n"
            if _PASSWORD_LINE.match(line) else line for line in lines]
    if kept == lines:
        return False
    text = "".join(kept)
    try:
        left = tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        left = None
    if left is None or any(isinstance(table, dict) and "password" in table for table in left.values()):
        raise ProvisionError(f"{path}: a password could not be removed: write each as password = \"...\" on one "
                             f"line")
    write_atomic(path, text)
    return True


def _write_readable(path: Path, text: str) -> None:
    """``text`` in ``path``, readable by all: the services read it as their own account, and a new file made
    atomically is the owner's alone."""
    write_atomic(path, text)
    path.chmod(0o644)


def _beside(setup_path: Path, name: str) -> Path:
    return Path(name) if Path(name).is_absolute() else setup_path.parent / name


def _only(table: dict, allowed: set, path: Path, where: str) -> None:
    check_keys(table, allowed, f"{path}, {where}", ProvisionError)


def _table(data: dict, key: str, path: Path) -> dict:
    if not isinstance(data.get(key), dict):
        raise ProvisionError(f"{path}: [{key}] is missing or not a table")
    return dict(data[key])


def _text(table: dict, key: str, path: Path, where: str, default: str | None = None) -> str:
    value = table.get(key, default)
    if value is None:
        raise ProvisionError(f"{path}: {where}{key} is missing")
    if not isinstance(value, str) or not value.strip():
        raise ProvisionError(f"{path}: {where}{key} must be non-empty text, got {value!r}")
    return value
