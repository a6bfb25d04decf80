"""First-boot provisioning (``appliance provision``) against temporary folders in place of the image's.

The hostname step is a recorded callable here, so the tests never rename this machine.
"""

import os
import pwd
import shutil
import stat
import subprocess
from types import SimpleNamespace

import pytest

from appliance.accounts.users import UserStore
from appliance.cli import main
from appliance.service.config import load_config
from appliance.service.provision import ProvisionError, provision, read_setup

SETUP = """\
hostname = "ward3-bed12"
source = "virtual"

[admin]
name = "sister"
password = "correct horse battery"
"""
BROKER = """
[broker]
host = "broker.ward"
port = 8883
username = "ward3-bed12"
password = "broker secret"
ca_file = "ward-ca.crt"
"""
ME = pwd.getpwuid(os.getuid()).pw_name          # a real account to give files to, with a same-named group


@pytest.fixture
def card(tmp_path, ca_certificate):
    """The setup file on a "boot partition", the configuration and data folders, and the hostnames set."""
    boot = tmp_path / "boot"
    boot.mkdir()
    shutil.copy(ca_certificate, boot / "ward-ca.crt")
    return SimpleNamespace(setup=boot / "appliance-setup.toml", config_dir=tmp_path / "etc",
                           data_dir=tmp_path / "data", hostnames=[])


def run(card):
    return provision(card.setup, card.config_dir, card.data_dir, set_hostname=card.hostnames.append, account=ME)


def test_a_first_boot_provisions_everything_and_removes_the_passwords(card):
    card.setup.write_text(SETUP + BROKER)
    done = run(card)
    assert len(done) == 5 and card.hostnames == ["ward3-bed12"]
    assert UserStore(card.data_dir / "webui.db").verify("sister", "correct horse battery").role == "admin"
    config = load_config(card.config_dir / "monitor.toml")
    assert (config.bed_id, config.source, config.mqtt.host, config.mqtt.port) == ("ward3-bed12", "virtual",
                                                                                 "broker.ward", 8883)
    assert config.mqtt.password() == "broker secret" and config.mqtt.ca_file == card.config_dir / "ward-ca.crt"
    assert stat.S_IMODE((card.config_dir / "mqtt-password").stat().st_mode) == 0o640
    for name in ("monitor.toml", "hostname", "provisioned"):                  # the service account reads them
        assert stat.S_IMODE((card.config_dir / name).stat().st_mode) == 0o644, name
    assert stat.S_IMODE((card.config_dir / "tls/screen.key").stat().st_mode) == 0o600
    subject = subprocess.run(["openssl", "x509", "-noout", "-subject", "-ext", "subjectAltName", "-in",
                              str(card.config_dir / "tls/screen.crt")], capture_output=True, text=True,
                             check=True).stdout
    assert "CN = ward3-bed12" in subject and "DNS:ward3-bed12.local" in subject
    text = card.setup.read_text()
    assert "secret" not in text and "horse" not in text and "password removed" in text
    assert read_setup(card.setup).admin_password is None and (card.config_dir / "provisioned").exists()


def test_later_boots_only_set_the_recorded_hostname(card):
    card.setup.write_text(SETUP)
    run(card)
    key = (card.config_dir / "tls/screen.key").read_bytes()
    card.setup.unlink()                                   # the boot file is no longer needed
    assert run(card) == ["hostname set to ward3-bed12"] and card.hostnames == ["ward3-bed12"] * 2
    assert (card.config_dir / "tls/screen.key").read_bytes() == key


def test_a_first_boot_cut_short_runs_again_without_repeating_its_steps(card):
    card.setup.write_text(SETUP)
    run(card)
    (card.config_dir / "provisioned").unlink()            # as if the power went before the marker was written
    assert run(card) == ["hostname set to ward3-bed12"]
    assert [user.name for user in UserStore(card.data_dir / "webui.db").users()] == ["sister"]


def test_the_hostname_can_be_left_alone_for_a_chroot(card):
    card.setup.write_text(SETUP)
    provision(card.setup, card.config_dir, card.data_dir, set_hostname=None, account=None)
    assert card.hostnames == [] and (card.config_dir / "hostname").read_text() == "ward3-bed12\n"


@pytest.mark.parametrize("text, complaint", [
    (SETUP.replace("ward3-bed12", "Ward 3"), "hostname must be"),
    (SETUP.replace('source = "virtual"', 'sorce = "virtual"'), "the top level: unknown key 'sorce'"),
    (SETUP.replace('name = "sister"\n', ""), "[admin] name is missing"),
    (SETUP.replace('password = "correct horse battery"', 'password = "short"'), "[admin]: a password needs at least"),
    (SETUP + BROKER.replace("port = 8883", "port = 0"), "[broker]: port must be from 1 to 65535"),
    (SETUP + BROKER.replace("ward-ca.crt", "missing.crt"), "[broker] ca_file: no file"),
    (SETUP + BROKER.replace("password =", "pasword ="), "[broker]: unknown key 'pasword'"),
    (SETUP.replace('"virtual"', '"emulated"'), 'source must be "hardware" or "virtual"'),
    (SETUP.replace('hostname = "ward3-bed12"', 'hostname = "ward3-bed12"\nbed_id = "bed/12"'), "bed_id"),
    ("hostname = ", "is not valid TOML"),
])
def test_a_bad_setup_file_is_refused_naming_the_file_and_key(card, text, complaint):
    card.setup.write_text(text)
    with pytest.raises(ProvisionError) as error:
        run(card)
    assert complaint in str(error.value) and str(card.setup) in str(error.value)
    assert not (card.config_dir / "provisioned").exists() and card.hostnames == []


def test_a_password_that_cannot_be_removed_is_refused(card):
    card.setup.write_text(SETUP.replace('"correct horse battery"', '"""correct horse\nbattery"""'))
    with pytest.raises(ProvisionError, match="could not be removed"):
        run(card)


def test_a_missing_setup_file_says_where_it_was_looked_for(card, capsys):
    assert main(["provision", "--setup", str(card.setup), "--config-dir", str(card.config_dir), "--data-dir",
                 str(card.data_dir), "--no-hostname"]) == 2
    assert f"no setup file {card.setup}" in capsys.readouterr().err


def test_the_command_line_provisions_without_touching_the_hostname(card, capsys):
    card.setup.write_text(SETUP)
    assert main(["provision", "--setup", str(card.setup), "--config-dir", str(card.config_dir), "--data-dir",
                 str(card.data_dir), "--account", ME, "--no-hostname"]) == 0
    assert "created the screen's admin account 'sister'" in capsys.readouterr().err
    assert (card.data_dir / "webui.db").stat().st_uid == os.getuid()
