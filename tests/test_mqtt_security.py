"""The ward's broker with passwords and TLS: a real Mosquitto that refuses anonymous and plain connections, a bed
that logs in over TLS, and the configuration that names the password file and the CA."""

import shutil
import subprocess

import pytest
from mqtt_broker import Broker, wait_until

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.events import as_event
from appliance.alerts.ward_mqtt import mqtt_ward_link
from appliance.errors import ConfigError
from appliance.service.config import config_from_mapping
from appliance.store.outbox import Outbox
from appliance.ward.station import WardStation

BED_PASSWORD, STATION_PASSWORD = "bed twelve secret", "station secret"


def make_certificates(folder):
    """A throw-away CA and a server certificate for localhost signed by it."""
    def openssl(*args):
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)
    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.crt", "-days", "1",
            "-subj", "/CN=ward test CA")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
            "-subj", "/CN=localhost")
    (folder / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", "server.crt", "-days", "1", "-extfile", "san.ext")


@pytest.fixture
def secure_broker(tmp_path):
    make_certificates(tmp_path)
    passwords = tmp_path / "passwords"
    subprocess.run(["mosquitto_passwd", "-c", "-b", str(passwords), "ward3-bed12", BED_PASSWORD], check=True,
                   capture_output=True)
    subprocess.run(["mosquitto_passwd", "-b", str(passwords), "ward-station", STATION_PASSWORD], check=True,
                   capture_output=True)
    broker = Broker(f"cafile {tmp_path / 'ca.crt'}\ncertfile {tmp_path / 'server.crt'}\n"
                    f"keyfile {tmp_path / 'server.key'}\nallow_anonymous false\npassword_file {passwords}\n",
                    folder=tmp_path)
    broker.start()
    yield broker, tmp_path / "ca.crt"
    broker.stop()


def alarm():
    return as_event(AlarmEvent(time_s=60.0, kind="raised", alarm_id=1, key="pressure:sacrum", category="clinical",
                               priority="medium", message="sustained pressure at the sacrum"))


def station(broker, ca, password=STATION_PASSWORD, **options):
    return WardStation("localhost", broker.port, client_id="secure-station", username="ward-station",
                       password=password, tls={"ca_certs": str(ca)}, **options)


def test_a_bed_logged_in_over_tls_reaches_the_station(secure_broker, tmp_path):
    broker, ca = secure_broker
    ward = station(broker, ca)
    assert ward.wait_subscribed(10)
    bed = mqtt_ward_link("localhost", broker.port, "ward3-bed12", Outbox(tmp_path / "outbox.db"),
                   client_id="appliance-ward3-bed12", username="ward3-bed12", password=BED_PASSWORD, ca_file=ca)
    try:
        bed.notify(alarm())
        assert wait_until(lambda: any(b["bed_id"] == "ward3-bed12" and b["alarms"] for b in ward.beds()), 10)
        assert wait_until(lambda: bed.delivery(1) == "ward station")
    finally:
        bed.close()
        ward.close()


@pytest.mark.parametrize("how", ["wrong password", "no password", "no TLS"])
def test_a_bed_without_the_right_login_or_tls_is_refused_and_its_alarm_is_kept(secure_broker, tmp_path, how):
    broker, ca = secure_broker
    ward = station(broker, ca)
    assert ward.wait_subscribed(10)
    login = {"wrong password": {"username": "ward3-bed12", "password": "guess", "ca_file": ca},
             "no password": {"ca_file": ca},
             "no TLS": {"username": "ward3-bed12", "password": BED_PASSWORD}}[how]
    bed = mqtt_ward_link("localhost", broker.port, "ward3-bed12", Outbox(tmp_path / "outbox.db"),
                   client_id="appliance-ward3-bed12", confirm_timeout_s=1.0, **login)
    try:
        bed.notify(alarm())
        assert wait_until(lambda: "technical:ward-link" in bed.conditions(), 15)    # said at the bed
        assert [e.event["key"] for e in bed.outbox.pending()] == ["pressure:sacrum"]  # kept, not lost
        assert bed.delivery(1) == "bed" and ward.beds() == []
    finally:
        bed.close()
        ward.close()


def test_a_station_with_a_wrong_password_never_subscribes(secure_broker):
    broker, ca = secure_broker
    ward = station(broker, ca, password="guess")
    try:
        assert not ward.wait_subscribed(3)
    finally:
        ward.close()


def test_the_configuration_names_the_password_file_and_ca_and_checks_them(tmp_path, ca_certificate):
    (tmp_path / "password").write_text(BED_PASSWORD + "\n")
    shutil.copy(ca_certificate, tmp_path / "ca.crt")
    (tmp_path / "not-a-ca.crt").write_text("a CA")
    config = config_from_mapping({"notify": {"mqtt": {"host": "broker.ward", "port": 8883, "username": "ward3-bed12",
                                                      "password_file": "password", "ca_file": "ca.crt"}}},
                                 base=tmp_path)
    assert config.mqtt.password() == BED_PASSWORD and config.mqtt.ca_file == tmp_path / "ca.crt"
    for table, message in (({"password_file": "password"}, "password_file needs a username"),
                           ({"username": "bed", "password_file": "nope"}, f"password_file: no file {tmp_path}/nope"),
                           ({"ca_file": "missing.crt"}, "ca_file: no file"),
                           ({"ca_file": "not-a-ca.crt"}, "not-a-ca.crt holds no certificate TLS can load"),
                           ({"user": "bed"}, "user")):
        with pytest.raises(ConfigError, match=message):
            config_from_mapping({"notify": {"mqtt": {"host": "broker.ward", **table}}}, base=tmp_path)
    (tmp_path / "password").write_text("")
    with pytest.raises(ConfigError, match="cannot read a password"):
        config.mqtt.password()
