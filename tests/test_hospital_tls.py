"""TLS to the hospital engine's nodes: certificates made by the tooling, each node's configuration, and a real
three-node cluster on loopback serving TLS alone, whose routes verify each other against the hospital CA; a bed's
alarm confirmed by its station end to end over it, and clients that do not trust the CA, or do not speak TLS,
refused."""

import asyncio
import json
import shutil
import socket
import ssl
import stat
import subprocess
import tomllib

import pytest
from hospital_engine import logged_in, running_cluster
from mqtt_broker import wait_until

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.events import as_event
from appliance.cli import main
from appliance.errors import ConfigError
from appliance.hospital.bedlink import engine_ward_link
from appliance.hospital.certs import make_certificates
from appliance.hospital.description import description_text, hospital_from_mapping, load_hospital
from appliance.hospital.engine import connect
from appliance.hospital.install import install
from appliance.hospital.nodeconfig import ADMIN, read_password, write_node_configs
from appliance.hospital.tls import TlsFolder, client_context
from appliance.service.config_sections import engine_settings
from appliance.store.outbox import Outbox
from appliance.ward.applied import AppliedJournal
from appliance.ward.engine_station import EngineStation

DESCRIPTION = """
[hospital]
cluster = "st-mary"
store_dir = "/var/lib/appliance-hospital/store"

[[node]]
name = "n1"
host = "10.20.0.11"

[[node]]
name = "n2"
host = "engine2.st-mary.example"

[[node]]
name = "n3"
host = "10.20.0.13"

[[ward]]
name = "ward3"
beds = ["w3-bed01"]
stations = ["ward3-station"]

[tls]
dir = "tls"
"""


def tls_hospital(folder):
    return hospital_from_mapping(tomllib.loads(DESCRIPTION), folder)


def openssl(*arguments) -> str:
    return subprocess.run(["openssl", *arguments], capture_output=True, text=True, check=True).stdout


def test_the_certs_command_makes_a_ca_and_a_certificate_naming_each_nodes_host_once(tmp_path, capsys):
    (tmp_path / "hospital.toml").write_text(DESCRIPTION)
    assert main(["hospital", "certs", "--description", str(tmp_path / "hospital.toml")]) == 0
    assert "made: ca.crt, ca.key, n1.crt, n1.key, n2.crt, n2.key, n3.crt, n3.key" in capsys.readouterr().out
    folder = tmp_path / "tls"
    for name in ("ca", "n1", "n2", "n3"):
        assert stat.S_IMODE((folder / f"{name}.key").stat().st_mode) == 0o600
    for node, named in (("n1", "IP Address:10.20.0.11"), ("n2", "DNS:engine2.st-mary.example"),
                        ("n3", "IP Address:10.20.0.13")):
        assert openssl("verify", "-CAfile", str(folder / "ca.crt"), str(folder / f"{node}.crt")).strip() \
            == f"{folder / node}.crt: OK"
        text = openssl("x509", "-in", str(folder / f"{node}.crt"), "-noout", "-ext",
                       "subjectAltName,extendedKeyUsage")
        assert named in text and "TLS Web Server Authentication, TLS Web Client Authentication" in text
    before = (folder / "n1.crt").read_bytes()
    assert main(["hospital", "certs", "--description", str(tmp_path / "hospital.toml")]) == 0
    assert "made: none, all were there" in capsys.readouterr().out
    assert (folder / "n1.crt").read_bytes() == before


def test_a_node_certificate_needs_the_ca_key_and_a_description_with_tls(tmp_path):
    hospital = tls_hospital(tmp_path)
    (tmp_path / "tls").mkdir()
    (tmp_path / "tls" / "ca.crt").write_text("the hospital's own CA\n")
    with pytest.raises(ConfigError, match=r"n1\.crt does not exist, and this folder has no key for ca\.crt"):
        make_certificates(hospital)
    with pytest.raises(ConfigError, match=r"no \[tls\] table"):
        make_certificates(hospital_from_mapping(tomllib.loads(DESCRIPTION.replace("[tls]\ndir", "# "))))


def test_each_node_serves_tls_and_its_routes_verify_the_others_against_the_hospital_ca(tmp_path):
    hospital = hospital_from_mapping(tomllib.loads(DESCRIPTION.replace('host = "10.20.0.11"',
                                                                       'host = "10.20.0.11"\nmqtt_port = 1883')),
                                     tmp_path)
    assert hospital.ca_file == tmp_path / "tls" / "ca.crt"
    assert load_hospital_text(tmp_path, description_text(hospital)) == hospital
    make_certificates(hospital)
    text = write_node_configs(hospital, tmp_path / "config").files["n1"].read_text()
    folder = tmp_path / "tls"
    node_tls = f'tls {{\n  cert_file: "{folder}/n1.crt"\n  key_file: "{folder}/n1.key"\n  timeout: 5\n'
    assert f"\n{node_tls}}}\n" in text                                          # the client listener
    assert "\n".join("  " + line for line in node_tls.splitlines()) \
        + f'\n    ca_file: "{folder}/ca.crt"\n    verify: true\n  }}\n}}\n' in text   # the routes, both ways
    mqtt = text[text.index("mqtt {"):text.index("accounts {")]
    assert f'    cert_file: "{folder}/n1.crt"' in mqtt


def test_without_tls_no_listener_is_configured_for_it(tmp_path):
    hospital = hospital_from_mapping(tomllib.loads(DESCRIPTION.replace("[tls]\ndir", "# ")), tmp_path)
    assert hospital.tls is None and hospital.ca_file is None
    assert "tls" not in write_node_configs(hospital, tmp_path / "config").files["n1"].read_text()


@pytest.mark.parametrize("table, message", [
    ({"folder": "tls"}, "unknown key 'folder'"),
    ({"dir": 3}, "[tls]: 'dir' must be a non-empty string, got 3"),
    ("tls", "[tls] is missing or not a table"),
])
def test_a_bad_tls_table_is_refused_naming_what_is_wrong(table, message):
    with pytest.raises(ConfigError) as raised:
        hospital_from_mapping({**tomllib.loads(DESCRIPTION), "tls": table})
    assert message in str(raised.value)


def test_a_missing_tls_file_is_named(tmp_path):
    hospital = tls_hospital(tmp_path)
    make_certificates(hospital)
    (tmp_path / "tls" / "n2.key").unlink()
    with pytest.raises(ConfigError) as raised:
        write_node_configs(hospital, tmp_path / "config")
    assert f"[tls] {tmp_path / 'tls' / 'n2.key'} does not exist" in str(raised.value)
    (tmp_path / "tls" / "ca.crt").unlink()
    with pytest.raises(ConfigError, match=f"the hospital CA {tmp_path / 'tls' / 'ca.crt'}: not a readable"):
        client_context(tmp_path / "tls" / "ca.crt")
    with pytest.raises(ConfigError, match=r"\[tls\] .*ca\.crt does not exist"):
        install(hospital, tmp_path / "root", ["n1"], history=False)


def test_a_server_installs_the_ca_and_only_its_own_nodes_certificate_and_key(tmp_path):
    hospital = hospital_from_mapping(tomllib.loads(DESCRIPTION.replace("/var/lib/appliance-hospital/store",
                                                                       "/var/lib/appliance-hospital")), tmp_path)
    make_certificates(hospital)
    installed = install(hospital, tmp_path / "root", ["n2"], history=False)
    folder = installed.folder / "tls"
    assert sorted(path.name for path in folder.iterdir()) == ["ca.crt", "n2.crt", "n2.key"]
    assert stat.S_IMODE((folder / "n2.key").stat().st_mode) == 0o600
    assert (folder / "n2.key").read_bytes() == (tmp_path / "tls" / "n2.key").read_bytes()
    assert sorted(path.name for path in installed.folder.glob("*.conf")) == ["n2.conf"]
    assert f'key_file: "{folder}/n2.key"' in (installed.folder / "n2.conf").read_text()
    assert load_hospital(installed.folder / "hospital.toml").tls == TlsFolder(folder)


def test_a_beds_engine_table_takes_tls_only_with_the_hospital_ca(tmp_path, ca_certificate):
    (tmp_path / "password").write_text("secret\n")
    shutil.copy(ca_certificate, tmp_path / "ca.crt")
    (tmp_path / "not-a-ca.crt").write_text("a certificate\n")
    table = {"servers": ["tls://10.20.0.11:4222"], "ward": "ward3", "password_file": "password"}
    with pytest.raises(ConfigError, match="is tls://, but no ca_file names the hospital CA"):
        engine_settings(table, tmp_path)
    assert engine_settings({**table, "ca_file": "ca.crt"}, tmp_path).ca_file == tmp_path / "ca.crt"
    with pytest.raises(ConfigError, match=f"ca_file: no file {tmp_path / 'nothing.crt'}"):
        engine_settings({**table, "ca_file": "nothing.crt"}, tmp_path)
    with pytest.raises(ConfigError, match="not-a-ca.crt holds no certificate TLS can load"):
        engine_settings({**table, "ca_file": "not-a-ca.crt"}, tmp_path)


def load_hospital_text(folder, text):
    path = folder / "written.toml"
    path.write_text(text)
    return load_hospital(path)


# On a running cluster: one, shared by the tests below.

@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with running_cluster(tmp_path_factory.mktemp("tls-engine"), tls=True) as running:
        yield running


def test_the_cluster_forms_over_tls_and_the_streams_command_makes_replicated_streams(cluster, tmp_path, capsys):
    for node in cluster.hospital.nodes:
        varz = cluster.monitor(node.name, "varz")
        assert varz["tls_required"] is True
        assert (varz["cluster"]["tls_required"], varz["cluster"]["tls_verify"]) == (True, True)
        assert varz["jetstream"]["meta"]["cluster_size"] == 3
        assert cluster.monitor(node.name, "routez")["num_routes"] >= 2
    assert main(["hospital", "streams", "--description", str(write_description(cluster, tmp_path)), "--secrets",
                 str(cluster.configs.secrets_folder)]) == 0
    assert "event and confirmation streams with 3 replica(s) each: ALARMS_ward1" in capsys.readouterr().out


def test_a_beds_alarm_is_confirmed_by_its_station_over_tls(cluster, tmp_path):
    assert main(["hospital", "streams", "--description", str(write_description(cluster, tmp_path)), "--secrets",
                 str(cluster.configs.secrets_folder)]) == 0
    secrets, ca_file = cluster.configs.secrets_folder, cluster.hospital.ca_file
    station = EngineStation(cluster.urls, "ward1", "station1", read_password(secrets, "station1"),
                            AppliedJournal(tmp_path / "applied.db"), ca_file=ca_file)
    bed = engine_ward_link(cluster.urls, "ward1", "bed1", read_password(secrets, "bed1"),
                           Outbox(tmp_path / "outbox.db"), ca_file=ca_file)
    try:
        assert station.wait_subscribed(30)
        bed.notify(as_event(AlarmEvent(time_s=1.0, kind="raised", alarm_id=1, key="pressure:sacrum",
                                       category="clinical", priority="high", message="Sacrum dose over limit")))
        assert wait_until(lambda: getattr(bed.outbox.entry(1), "confirmed_by", None) == "station1", 30)
        assert station.journal.seqs("bed1") == [1] and station.confirmations_sent == 1
    finally:
        bed.close(timeout_s=2)
        station.close()
        station.journal.close()


def test_a_client_that_does_not_trust_the_hospital_ca_is_refused(cluster, tmp_path):
    other = hospital_from_mapping(tomllib.loads(DESCRIPTION.replace('dir = "tls"', 'dir = "other"')), tmp_path)
    make_certificates(other)                                    # another CA, whose nodes' certificates are valid

    async def refused(urls, ca_file):
        with pytest.raises(ssl.SSLCertVerificationError) as raised:
            await connect(urls, ADMIN, read_password(cluster.configs.secrets_folder, ADMIN), ca_file=ca_file)
        return raised.value.verify_message

    assert asyncio.run(refused(cluster.urls, other.ca_file)) == "unable to get local issuer certificate"
    assert asyncio.run(refused(cluster.urls, None)) == "unable to get local issuer certificate"   # the system's CAs
    misnamed = [url.replace("127.0.0.1", "localhost") for url in cluster.urls]    # the certificates name the address
    assert asyncio.run(refused(misnamed, cluster.hospital.ca_file)).startswith("Hostname mismatch")

    async def trusted():
        async with logged_in(cluster, ADMIN) as admin:
            return admin.connected_url.scheme

    assert asyncio.run(trusted()) == "tls"


def test_a_client_that_does_not_speak_tls_is_refused(cluster):
    node = cluster.hospital.nodes[0]
    password = read_password(cluster.configs.secrets_folder, ADMIN)
    with socket.create_connection((node.host, node.client_port), timeout=10) as plain:
        info = json.loads(plain.makefile("rb").readline().removeprefix(b"INFO "))
        assert info["tls_required"] is True
        plain.sendall(f'CONNECT {{"user":"{ADMIN}","pass":"{password}","verbose":false}}\r\nPING\r\n'.encode())
        said = read_until_closed(plain)
    assert b"PONG" not in said and b"+OK" not in said


def test_the_mqtt_port_speaks_tls_and_the_route_port_only_to_a_node_of_the_hospital_ca(cluster):
    node, tls = cluster.hospital.nodes[0], cluster.hospital.tls
    trusting = client_context(tls.ca_file)
    with socket.create_connection((node.host, node.mqtt_port), timeout=10) as raw, \
            trusting.wrap_socket(raw, server_hostname=node.host) as mqtt:
        assert mqtt.getpeercert()["subjectAltName"] == (("IP Address", "127.0.0.1"),)
    with socket.create_connection((node.host, node.cluster_port), timeout=10) as raw, \
            trusting.wrap_socket(raw, server_hostname=node.host) as stranger, \
            pytest.raises(ssl.SSLError, match="CERTIFICATE_REQUIRED"):
        stranger.recv(100)
    another_node = client_context(tls.ca_file)
    another_node.load_cert_chain(tls.cert_file("n2"), tls.key_file("n2"))
    with socket.create_connection((node.host, node.cluster_port), timeout=10) as raw, \
            another_node.wrap_socket(raw, server_hostname=node.host) as route:
        assert route.makefile("rb").readline().startswith(b"INFO {")


def read_until_closed(sock) -> bytes:
    said = b""
    while chunk := sock.recv(4096):
        said += chunk
    return said


def write_description(cluster, folder):
    path = folder / "hospital.toml"
    path.write_text(description_text(cluster.hospital))
    return path
