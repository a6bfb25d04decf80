"""The hospital description and the node configurations written from it (appliance.hospital): every bad input
named, passwords kept across runs, and a bed added to a running engine by a reload, without a restart."""

import asyncio
import dataclasses
import json
import os
import signal
import socket
import stat
import subprocess
import sys

import pytest
from hospital_engine import logged_in, make_streams, running_cluster
from mqtt_broker import wait_until

from appliance.cli import main
from appliance.errors import ConfigError
from appliance.hospital.description import Ward, description_text, hospital_from_mapping, load_hospital
from appliance.hospital.engine import BedPublisher, connect
from appliance.hospital.nodeconfig import read_password, write_node_configs

DESCRIPTION = """
[hospital]
cluster = "st-mary"
store_dir = "store"

[[node]]
name = "n1"
host = "10.20.0.11"
mqtt_port = 1883

[[node]]
name = "n2"
host = "10.20.0.12"

[[node]]
name = "n3"
host = "10.20.0.13"

[[ward]]
name = "ward3"
beds = ["w3-bed01", "w3-bed02"]
stations = ["ward3-station"]
"""


def description(**changes):
    data = {"hospital": {"cluster": "st-mary", "store_dir": "/var/lib/h"},
            "node": [{"name": f"n{i}", "host": "127.0.0.1", "client_port": 4220 + i, "cluster_port": 6220 + i,
                      "monitor_port": 8220 + i} for i in (1, 2, 3)],
            "ward": [{"name": "ward3", "beds": ["b1", "b2"], "stations": ["s3"]}]}
    data.update(changes)
    return data


def test_the_description_file_is_read_with_its_defaults(tmp_path):
    hospital = load_hospital_text(tmp_path, DESCRIPTION)
    assert hospital.cluster == "st-mary" and hospital.replicas == 3
    assert hospital.store_dir == tmp_path / "store"
    assert [(n.name, n.client_port, n.cluster_port, n.monitor_port, n.mqtt_port) for n in hospital.nodes] == [
        ("n1", 4222, 6222, 8222, 1883), ("n2", 4222, 6222, 8222, None), ("n3", 4222, 6222, 8222, None)]
    assert hospital.wards == (Ward("ward3", ("w3-bed01", "w3-bed02"), ("ward3-station",)),)


@pytest.mark.parametrize("changes, message", [
    ({"wards": []}, "unknown key 'wards'"),
    ({"ward": []}, "no [[ward]] tables"),
    ({"hospital": {"cluster": "st mary", "store_dir": "/s"}}, "[hospital] cluster 'st mary'"),
    ({"hospital": {"cluster": "x", "store_dir": "/s", "replicas": 2}}, "replicas must be 1 or 3, got 2"),
    ({"node": [{"name": "n1", "host": "a"}]}, "replicas = 3 needs at least 3 [[node]] tables, got 1"),
    ({"node": [{"name": "n1", "host": "a"}, {"name": "n1", "host": "b"}, {"name": "n3", "host": "c"}]},
     "node name 'n1' is given twice"),
    ({"node": [{"name": "n1", "host": "a"}, {"name": "n2", "host": "a"}, {"name": "n3", "host": "c"}]},
     "host and port ('a', 4222) is given twice"),
    ({"node": [{"name": "n1", "host": "a", "client_port": 70000}, {"name": "n2", "host": "b"},
               {"name": "n3", "host": "c"}]}, "client_port must be a port from 1 to 65535, got 70000"),
    ({"ward": [{"name": "w", "beds": ["bed.1"], "stations": ["s"]}]}, "bed id 'bed.1'"),
    ({"ward": [{"name": "w", "beds": ["b"], "stations": []}]}, "'stations' must be a non-empty list"),
    ({"ward": [{"name": "w1", "beds": ["b"], "stations": ["s1"]}, {"name": "w2", "beds": ["b"], "stations": ["s2"]}]},
     "bed id or station 'b' is given twice"),
])
def test_a_bad_description_is_refused_naming_what_is_wrong(changes, message):
    with pytest.raises(ConfigError) as raised:
        hospital_from_mapping(description(**changes))
    assert message in str(raised.value)


def test_each_node_gets_fsync_routes_to_the_others_and_every_user_a_kept_password(tmp_path):
    hospital = hospital_from_mapping(description())
    first = write_node_configs(hospital, tmp_path / "out")
    assert sorted(first.added) == ["b1", "b2", "hospital-admin", "hospital-history", "s3"]
    text = first.files["n1"].read_text()
    assert "sync_interval: always" in text
    assert "@127.0.0.1:6222" in text and "@127.0.0.1:6223" in text and "@127.0.0.1:6221" not in text
    assert "mqtt {" not in text
    assert stat.S_IMODE(first.files["n1"].stat().st_mode) == 0o600
    assert stat.S_IMODE(first.secrets_folder.stat().st_mode) == 0o700
    password = read_password(first.secrets_folder, "b1")
    assert f'{{user: "b1", password: "{password}"' in text

    fewer = hospital_from_mapping(description(ward=[{"name": "ward3", "beds": ["b1", "b4"], "stations": ["s3"]}]))
    second = write_node_configs(fewer, tmp_path / "out")
    assert second.added == ("b4",) and second.removed == ("b2",)
    assert read_password(second.secrets_folder, "b1") == password
    assert '"b2"' not in second.files["n2"].read_text()


def test_a_bed_or_station_cannot_be_named_as_the_administrator(tmp_path):
    hospital = hospital_from_mapping(description(ward=[{"name": "w", "beds": ["hospital-admin"], "stations": ["s"]}]))
    with pytest.raises(ConfigError, match="'hospital-admin' is the engine's administrator"):
        write_node_configs(hospital, tmp_path / "out")


def test_the_config_command_writes_every_node(tmp_path, capsys):
    path = tmp_path / "hospital.toml"
    path.write_text(DESCRIPTION)
    assert main(["hospital", "config", "--description", str(path), "--out", str(tmp_path / "engine")]) == 0
    assert sorted(p.name for p in (tmp_path / "engine").glob("*.conf")) == ["n1.conf", "n2.conf", "n3.conf"]
    assert 'listen: "10.20.0.11:1883"' in (tmp_path / "engine" / "n1.conf").read_text()
    assert "added: hospital-admin, hospital-history, w3-bed01, w3-bed02, ward3-station" in capsys.readouterr().out
    path.write_text(DESCRIPTION.replace('"n3"', '"n 3"'))
    assert main(["hospital", "config", "--description", str(path), "--out", str(tmp_path / "engine")]) == 2
    assert "[[node]] number 3 name 'n 3'" in capsys.readouterr().err


def login_answer(node, user, password):
    """What ``node`` answers a CONNECT as ``user`` followed by a PING: PONG when it lets the user in."""
    with socket.create_connection((node.host, node.client_port), timeout=5) as connection:
        reader = connection.makefile("rb")
        assert reader.readline().startswith(b"INFO ")
        login = json.dumps({"user": user, "pass": password, "verbose": False, "pedantic": False})
        connection.sendall(f"CONNECT {login}\r\nPING\r\n".encode())
        return reader.readline().decode()


def test_a_bed_added_to_the_description_gets_in_on_reload_without_a_restart(tmp_path):
    with running_cluster(tmp_path) as cluster:
        asyncio.run(make_streams(cluster))
        pids = {name: process.pid for name, process in cluster.processes.items()}
        ward1 = cluster.hospital.wards[0]
        grown = dataclasses.replace(cluster.hospital, wards=(Ward(ward1.name, (*ward1.beds, "bed9"), ward1.stations),
                                                             *cluster.hospital.wards[1:]))
        before = read_password(cluster.configs.secrets_folder, "bed1")
        assert write_node_configs(grown, cluster.folder).added == ("bed9",)
        assert read_password(cluster.configs.secrets_folder, "bed1") == before

        password = read_password(cluster.configs.secrets_folder, "bed9")
        assert all(login_answer(node, "bed9", password).startswith("-ERR 'Authorization Violation'")
                   for node in cluster.hospital.nodes)         # not a user until the nodes read their files again
        for pid in pids.values():
            os.kill(pid, signal.SIGHUP)
        for node in cluster.hospital.nodes:
            assert wait_until(lambda node=node: login_answer(node, "bed9", password).startswith("PONG")), node.name

        async def bed9_publishes():
            async with logged_in(cluster, "bed9") as bed:
                return await BedPublisher(bed, "ward1", "bed9").send("alarm", 1, {"kind": "occiput"})

        ack = asyncio.run(bed9_publishes())
        assert ack.stream == "ALARMS_ward1" and ack.seq == 1
        assert {name: process.pid for name, process in cluster.processes.items()} == pids
        assert all(cluster.running(name) for name in pids)


def test_a_description_written_out_reads_back_the_same(tmp_path):
    hospital = load_hospital_text(tmp_path, DESCRIPTION)
    path = tmp_path / "again.toml"
    path.write_text(description_text(hospital))
    assert load_hospital(path) == hospital


def load_hospital_text(folder, text):
    path = folder / "hospital.toml"
    path.write_text(text)
    return load_hospital(path)


def test_start_local_runs_a_cluster_that_the_streams_command_and_a_bed_can_use_and_stops_it(tmp_path, capsys):
    folder = tmp_path / "local"
    with subprocess.Popen([sys.executable, "-m", "appliance", "hospital", "start-local", "--dir", str(folder),
                           "--beds", "2"], stdout=subprocess.PIPE, text=True) as command:
        try:
            hospital = _use_local_cluster(command, folder, capsys)
        finally:
            command.send_signal(signal.SIGTERM)
            assert command.wait(30) == 0
    for node in hospital.nodes:                                 # every node stopped with it
        with pytest.raises(OSError):
            socket.create_connection((node.host, node.client_port), timeout=1).close()


def _use_local_cluster(command, folder, capsys):
    """What start-local printed, its description and secrets used by the streams command and a bed."""
    lines = [command.stdout.readline() for _ in range(5)]
    assert lines[0].startswith("hospital engine: nats-server v2.15.1, 3 nodes on loopback, stream ALARMS_trial "
                               "with 3 replicas"), lines
    assert "Ctrl-C stops the cluster" in lines[4]
    hospital = load_hospital(folder / "hospital.toml")
    assert hospital.wards == (Ward("trial", ("bed01", "bed02"), ("trial-station",)),)
    secrets = folder / "config" / "secrets"
    assert main(["hospital", "streams", "--description", str(folder / "hospital.toml"), "--secrets",
                 str(secrets)]) == 0
    assert "1 ward(s), their event and confirmation streams with 3 replica(s) each: ALARMS_trial, CONFIRMS_trial" \
        in capsys.readouterr().out

    async def bed_publishes():
        connection = await connect([node.client_url for node in hospital.nodes], "bed02",
                                   read_password(secrets, "bed02"))
        try:
            return await BedPublisher(connection, "trial", "bed02").send("alarm", 1, {"kind": "sacrum"})
        finally:
            await connection.close()

    assert asyncio.run(bed_publishes()).stream == "ALARMS_trial"
    return hospital
