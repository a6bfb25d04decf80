"""The ward broker's logins and ACL (appliance.ward.broker) on a real Mosquitto: each bed logs in with its own
generated password and publishes only as itself, so no bed can hide another's alarms with a spoofed summary;
the station reads every bed and confirms, and cannot speak for a bed; a new bed gets in on SIGHUP.

"Does not arrive" is shown by a message that does arrive after the forbidden one, on the same path: Mosquitto
routes each publish before it acknowledges it, so one that was let through would have come first.
"""

import json
import os
import queue
import signal
import stat
import threading

import paho.mqtt.client as mqtt
import pytest
from mqtt_broker import Broker, free_port, subscribed_station, wait_until
from test_mqtt_security import make_certificates
from ward_payloads import alarm, summary

from appliance.alerts.events import Event
from appliance.alerts.ward_mqtt import mqtt_ward_link
from appliance.cli import main
from appliance.errors import ConfigError
from appliance.service.config import config_from_mapping
from appliance.store.outbox import Outbox
from appliance.ward.broker import Listener, write_ward_broker
from appliance.ward.config import ward_config_from_mapping
from appliance.ward.station import WardStation

BED1, BED2, BED3 = "ward3-bed1", "ward3-bed2", "ward3-bed3"
STATION = "ward3-station"


class Client:
    """A paho client logged in as ``user`` (None: anonymous): whether the broker let it in, and what it got."""

    def __init__(self, port, user, password, client_id=None, ca=None):
        self.received = []                   # (topic, payload), in order
        self._answers = queue.Queue()
        self._subscribed = threading.Event()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id or f"test-{user}")
        if user is not None:
            self.client.username_pw_set(user, password)
        if ca is not None:
            self.client.tls_set(ca_certs=str(ca))
        self.client.on_connect = lambda client, userdata, flags, code, properties: self._answers.put(code)
        self.client.on_subscribe = lambda *args: self._subscribed.set()
        self.client.on_message = lambda client, userdata, m: self.received.append((m.topic, m.payload.decode()))
        self.client.connect("localhost" if ca else "127.0.0.1", port)
        self.client.loop_start()
        self.accepted = not self._answers.get(timeout=10).is_failure

    def subscribe(self, *topics):
        self._subscribed.clear()
        self.client.subscribe([(topic, 1) for topic in topics])
        assert self._subscribed.wait(10)

    def publish(self, topic, payload, retain=False):
        """Publish at QoS 1 and wait for the broker's acknowledgement: it has routed (or dropped) it by then."""
        info = self.client.publish(topic, payload if isinstance(payload, str) else json.dumps(payload), qos=1,
                                   retain=retain)
        info.wait_for_publish(10)
        assert info.is_published()

    def close(self):
        self.client.disconnect()
        self.client.loop_stop()


def connects(port, user, password, ca=None) -> bool:
    client = Client(port, user, password, client_id=f"probe-{user}", ca=ca)
    client.close()
    return client.accepted


def secret(files, user) -> str:
    return (files.secrets_folder / f"{user}.password").read_text().splitlines()[0]


def mode(path):
    return stat.S_IMODE(path.stat().st_mode)


def topic(bed_id, kind):
    return f"appliance/{bed_id}/{kind}"


def bed(station, bed_id):
    return next((b for b in station.beds() if b["bed_id"] == bed_id), None)


def station_login(files, client_id):
    return {"username": STATION, "password": secret(files, STATION), "client_id": client_id}


@pytest.fixture
def ward(tmp_path):
    """Two beds and a station, and a Mosquitto whose own configuration sets the persistence folder and
    includes the generated snippet, as Debian's /etc/mosquitto/mosquitto.conf does conf.d."""
    files = write_ward_broker(tmp_path / "ward", [BED1, BED2], [STATION])
    broker = Broker(f"persistence true\npersistence_location {tmp_path}/\ninclude_dir {tmp_path / 'ward'}\n",
                    folder=tmp_path)
    broker.start()
    yield broker, files
    broker.stop()


@pytest.fixture
def clients():
    """Every Client a test opens, closed after it."""
    opened = []

    def open_client(*args, **options):
        opened.append(Client(*args, **options))
        return opened[-1]

    yield open_client
    for client in opened:
        client.close()


def test_a_bed_and_the_station_log_in_with_their_generated_passwords_and_others_are_refused(ward, tmp_path):
    broker, files = ward
    station_config = ward_config_from_mapping(
        {"broker": {"host": "127.0.0.1", "port": broker.port, "username": STATION,
                    "password_file": str(files.secrets_folder / f"{STATION}.password")},
         "station": {"client_id": "ward3-station"}})
    bed_config = config_from_mapping(
        {"monitor": {"bed_id": BED1},
         "notify": {"mqtt": {"host": "127.0.0.1", "port": broker.port, "username": BED1,
                             "password_file": str(files.secrets_folder / f"{BED1}.password")}}})
    with WardStation.from_config(station_config) as station:
        assert station.wait_subscribed(10)
        notifier = mqtt_ward_link("127.0.0.1", broker.port, BED1, Outbox(tmp_path / "outbox.db"),
                            client_id=f"appliance-{BED1}", username=BED1, password=bed_config.mqtt.password())
        try:
            notifier.notify(alarm(1))
            notifier.notify(Event(20.0, "episode", "admitted", message="admitted p1"))
            assert wait_until(lambda: notifier.confirmed == 2)             # confirmed by the station, end to end
            notifier.summarise(summary(BED1, alarms=[(1, "high")]))
            assert wait_until(lambda: bed(station, BED1) and bed(station, BED1)["summary"] is not None)
        finally:
            notifier.close()
        assert wait_until(lambda: bed(station, BED1)["status"] == "offline")       # its own, on a clean close
        seen = bed(station, BED1)
        assert [(e["type"], e["kind"]) for e in seen["events"]] == [("alarm", "raised"), ("episode", "admitted")]
        assert [a["alarm_id"] for a in seen["alarms"]] == [1]
    assert not connects(broker.port, BED1, "guess")
    assert not connects(broker.port, BED1, secret(files, BED2))
    assert not connects(broker.port, None, None)


def test_a_bed_cannot_hide_another_beds_alarms_with_a_spoofed_summary(ward, clients):
    broker, files = ward
    bed1, bed2 = (clients(broker.port, b, secret(files, b)) for b in (BED1, BED2))
    with subscribed_station(broker.port, **station_login(files, "station")) as station:
        bed2.publish(topic(BED2, "summary"), summary(BED2, time_s=100.0, alarms=[(1, "high")]), retain=True)
        assert wait_until(lambda: bed(station, BED2) is not None)
        bed1.publish(topic(BED2, "summary"), summary(BED2, time_s=200.0), retain=True)      # "all quiet"
        bed1.publish(topic(BED2, "alarm"), alarm(1, kind="ended", time_s=150.0).to_dict())
        bed1.publish(topic(BED1, "summary"), summary(BED1), retain=True)                     # after them
        assert wait_until(lambda: bed(station, BED1) is not None)
        shown = bed(station, BED2)
        assert shown["summary"]["time_s"] == 100.0 and [a["alarm_id"] for a in shown["alarms"]] == [1]
        assert shown["events"] == [] and station.bad_payloads == 0
    with subscribed_station(broker.port, **station_login(files, "station-started-later")) as later:
        assert wait_until(lambda: bed(later, BED1) is not None and bed(later, BED2) is not None)
        assert bed(later, BED2)["summary"]["time_s"] == 100.0       # the retained copy is still bed 2's own


def test_a_bed_reads_only_its_own_confirmations_and_cannot_write_them(ward, clients):
    broker, files = ward
    bed1, bed2 = (clients(broker.port, b, secret(files, b)) for b in (BED1, BED2))
    station = clients(broker.port, STATION, secret(files, STATION), client_id="station-confirms")
    bed1.subscribe(topic(BED2, "summary"), topic(BED2, "alarm"), topic(BED2, "confirm"), topic(BED1, "confirm"),
                   "appliance/#")
    bed2.publish(topic(BED2, "summary"), summary(BED2))
    bed2.publish(topic(BED2, "alarm"), alarm(1).to_dict())
    station.publish(topic(BED2, "confirm"), "bed 2's confirmation")
    bed1.publish(topic(BED1, "confirm"), "confirmed by the bed itself")
    bed1.publish(topic(BED2, "confirm"), "confirmed for bed 2 by bed 1")
    station.publish(topic(BED1, "confirm"), "confirmed by the station")
    assert wait_until(lambda: bed1.received)
    assert set(bed1.received) == {(topic(BED1, "confirm"), "confirmed by the station")}   # once per subscription


def test_the_station_confirms_to_a_bed_but_cannot_publish_as_one(ward, clients):
    broker, files = ward
    bed1, bed2 = (clients(broker.port, b, secret(files, b)) for b in (BED1, BED2))
    bed1.subscribe(topic(BED1, "confirm"))
    station = clients(broker.port, STATION, secret(files, STATION), client_id="station-publisher")
    with subscribed_station(broker.port, **station_login(files, "station-watching")) as watching:
        bed2.publish(topic(BED2, "summary"), summary(BED2, alarms=[(1, "high")]), retain=True)
        assert wait_until(lambda: bed(watching, BED2) is not None)
        station.publish(topic(BED2, "summary"), summary(BED2, time_s=200.0), retain=True)
        station.publish(topic(BED2, "alarm"), alarm(1, kind="ended", time_s=150.0).to_dict())
        station.publish(topic(STATION, "summary"), summary(STATION, alarms=[(9, "high")]))   # its own name's topic
        station.publish(topic(STATION, "alarm"), alarm(9).to_dict())
        station.publish(topic(BED1, "confirm"), "alarm 1 seen at the station")
        bed1.publish(topic(BED1, "summary"), summary(BED1))
        assert wait_until(lambda: bed(watching, BED1) is not None)
        assert [b["bed_id"] for b in watching.beds()] == [BED2, BED1]
        assert bed(watching, BED2)["summary"]["time_s"] == 100.0 and bed(watching, BED2)["events"] == []
        assert wait_until(lambda: bed1.received)
        assert bed1.received == [(topic(BED1, "confirm"), "alarm 1 seen at the station")]


def test_only_the_station_commands_a_bed_and_only_that_bed_answers(ward, clients):
    broker, files = ward
    bed1, bed2 = (clients(broker.port, b, secret(files, b)) for b in (BED1, BED2))
    station = clients(broker.port, STATION, secret(files, STATION), client_id="station-commands")
    bed1.subscribe(topic(BED1, "command"), topic(BED2, "command"))
    station.subscribe(topic("+", "command-result"))
    bed2.publish(topic(BED1, "command"), "record a turn, says bed 2")
    bed1.publish(topic(BED1, "command"), "record a turn, says bed 1 itself")
    bed1.publish(topic(BED2, "command-result"), "done, says bed 1 for bed 2")
    station.publish(topic(BED2, "command"), "for bed 2")
    station.publish(topic(BED1, "command-result"), "done, says the station")
    station.publish(topic(BED1, "command"), "acknowledge, says the station")
    bed1.publish(topic(BED1, "command-result"), "done, says bed 1")
    assert wait_until(lambda: bed1.received and station.received)
    assert bed1.received == [(topic(BED1, "command"), "acknowledge, says the station")]
    assert station.received == [(topic(BED1, "command-result"), "done, says bed 1")]


def test_a_new_bed_gets_in_on_sighup_and_a_removed_one_is_refused_without_a_restart(ward, tmp_path, clients):
    broker, files = ward
    bed1_password, bed2_password = secret(files, BED1), secret(files, BED2)
    staying = clients(broker.port, BED1, bed1_password)
    assert not connects(broker.port, BED3, "not yet a bed")
    files = write_ward_broker(tmp_path / "ward", [BED1, BED3], [STATION])
    assert files.added == (BED3,) and files.kept == (BED1, STATION) and files.removed == (BED2,)
    assert secret(files, BED1) == bed1_password and not (files.secrets_folder / f"{BED2}.password").exists()
    running = broker.process
    running.send_signal(signal.SIGHUP)
    assert wait_until(lambda: connects(broker.port, BED3, secret(files, BED3)))
    assert not connects(broker.port, BED2, bed2_password)         # the same reload took bed 2 out
    assert connects(broker.port, BED1, bed1_password) and staying.client.is_connected()
    assert broker.process is running and running.poll() is None
    with subscribed_station(broker.port, **station_login(files, "station")) as station:
        clients(broker.port, BED3, secret(files, BED3)).publish(topic(BED3, "summary"), summary(BED3))
        assert wait_until(lambda: bed(station, BED3) is not None)


def test_the_files_are_the_owners_alone_and_a_rerun_keeps_every_password(tmp_path):
    files = write_ward_broker(tmp_path / "ward", [BED1, BED2], [STATION])
    assert mode(files.password_file) == mode(files.acl_file) == 0o600 and mode(files.secrets_folder) == 0o700
    assert {p.name: mode(p) for p in files.secrets_folder.iterdir()} == {
        f"{user}.password": 0o600 for user in (BED1, BED2, STATION)}
    assert mode(files.config_file) == 0o644           # no secret in it, and Mosquitto reads it on reload
    lines = files.password_file.read_text().splitlines()
    assert [line.split(":")[0] for line in lines] == [BED1, BED2, STATION]
    assert all(line.split(":", 1)[1].startswith("$7$101$") for line in lines)
    again = write_ward_broker(tmp_path / "ward", [BED1, BED2], [STATION])
    assert again.added == again.removed == () and files.password_file.read_text().splitlines() == lines


def test_a_password_whose_line_was_lost_is_taken_again_from_its_secret(ward, tmp_path):
    broker, files = ward
    kept = [line for line in files.password_file.read_text().splitlines() if not line.startswith(f"{BED2}:")]
    files.password_file.write_text("\n".join(kept) + "\n")
    files = write_ward_broker(tmp_path / "ward", [BED1, BED2], [STATION])
    assert files.added == () and BED2 in files.kept
    broker.stop()
    broker.start()                  # reads the new line: the one it had in memory took the same password
    assert connects(broker.port, BED2, secret(files, BED2))


def test_the_snippets_tls_listener_and_persistence_folder_work_on_their_own(tmp_path):
    make_certificates(tmp_path)
    port = free_port()
    (tmp_path / "db").mkdir()
    files = write_ward_broker(tmp_path / "ward", [BED1], [STATION], persistence_location=tmp_path / "db",
                              listener=Listener(port, tmp_path / "server.crt", tmp_path / "server.key"))
    assert f"persistence_location {tmp_path / 'db'}/\n" in files.config_file.read_text()
    broker = Broker(f"include_dir {tmp_path / 'ward'}\n", folder=tmp_path)
    broker.start(port)
    try:
        assert connects(port, BED1, secret(files, BED1), ca=tmp_path / "ca.crt")
        assert not connects(port, BED1, "guess", ca=tmp_path / "ca.crt")
    finally:
        broker.stop()
    assert (tmp_path / "db" / "mosquitto.db").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="giving files to another user needs root")
def test_the_broker_files_go_to_the_brokers_user_and_stay_its_own_on_a_rerun(tmp_path):
    """Mosquitto reads them as its own user after dropping root, at start and on every reload."""
    files = write_ward_broker(tmp_path / "ward", [BED1], [STATION], broker_user="nobody")
    nobody = os.stat(files.password_file).st_uid
    assert nobody != 0 and os.stat(files.acl_file).st_uid == nobody
    assert os.stat(files.secrets_folder).st_uid == os.stat(files.secrets_folder / f"{BED1}.password").st_uid == 0
    files = write_ward_broker(tmp_path / "ward", [BED1, BED2], [STATION])
    assert os.stat(files.password_file).st_uid == os.stat(files.acl_file).st_uid == nobody


@pytest.mark.parametrize(("beds", "stations", "options", "named"), [
    ([], [STATION], {}, "no beds"),
    ([BED1], [], {}, "no station"),
    (["ward3/bed1"], [STATION], {}, "'ward3/bed1'"),
    (["bed+"], [STATION], {}, "'bed+'"),
    (["bed#"], [STATION], {}, "'bed#'"),
    (["bed 1"], [STATION], {}, "'bed 1'"),
    (["bed\x001"], [STATION], {}, "'bed\\x001'"),
    (["bed:1"], [STATION], {}, "'bed:1'"),
    ([""], [STATION], {}, "bed id ''"),
    (["b" * 65], [STATION], {}, "b" * 65),
    ([BED1, BED1], [STATION], {}, f"{BED1!r} is given twice"),
    ([BED1], ["station one"], {}, "station 'station one'"),
    ([BED1], [BED1], {}, f"station {BED1!r} is also a bed id"),
    ([BED1], [STATION], {"topic_prefix": "ward/+"}, "'ward/+'"),
    ([BED1], [STATION], {"topic_prefix": "ward//3"}, "'ward//3'"),
    ([BED1], [STATION], {"topic_prefix": "%u"}, "'%u'"),
    ([BED1], [STATION], {"listener": Listener(0)}, "--listener"),
    ([BED1], [STATION], {"listener": Listener(8883, certfile="server.crt")}, "--keyfile"),
    ([BED1], [STATION], {"broker_user": "no-such-account"}, "'no-such-account'"),
])
def test_bad_beds_stations_and_settings_are_refused_naming_the_value_before_anything_is_written(
        tmp_path, beds, stations, options, named):
    with pytest.raises(ConfigError) as refused:
        write_ward_broker(tmp_path / "ward", beds, stations, **options)
    assert named in str(refused.value)
    assert not (tmp_path / "ward").exists()



def test_the_command_writes_the_files_for_the_beds_given_and_says_how_to_reload(tmp_path, capsys):
    (tmp_path / "beds.txt").write_text(f"# ward 3\n{BED2}\n\n{BED3}\n")
    argv = ["ward-broker", "--out", str(tmp_path / "ward"), "--bed", BED1, "--beds-file", str(tmp_path / "beds.txt"),
            "--station", STATION]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"added: {BED1}, {BED2}, {BED3}, {STATION};" in out
    assert out.splitlines()[-1].endswith("systemctl reload mosquitto")
    users = [line.split(":")[0] for line in (tmp_path / "ward" / "passwords").read_text().splitlines()]
    assert users == [BED1, BED2, BED3, STATION]
    assert main(argv[:5] + ["--station", STATION]) == 0
    assert f"kept: {BED1}, {STATION}; removed: {BED2}, {BED3}" in capsys.readouterr().out
