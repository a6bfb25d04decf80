"""Nurses at the ward station act on a bed: acknowledge an alarm, record a turn. On a real Mosquitto
(tests/mqtt_broker.py) and a real monitor daemon: every command is applied once however often it arrives (QoS 1
repeats, resends after a reconnect, a restart of either end), the bed answers, and the station's journal holds
who asked what and what became of it."""

import json
import re
import time

import paho.mqtt.client as mqtt
import pytest
from mqtt_broker import subscribed_station, wait_until
from test_ward import ward_daemon

from appliance.alerts.ward_commands import WardCommand, new_command, parse_command, parse_result
from appliance.alerts.ward_mqtt import mqtt_ward_link, release
from appliance.store import Store
from appliance.store.outbox import Outbox
from appliance.ward.journal import CommandJournal

BED = "ward-bed"


@pytest.fixture
def repeater(broker):
    """Publishes a command as the station would, as often as a test likes (QoS 1 repeats), or any payload on
    any topic."""
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-repeater")
    client.connect("127.0.0.1", broker.port)
    client.loop_start()

    def send(command, topic=None):
        payload = command if topic else command.to_payload()
        client.publish(topic or f"appliance/{command.bed_id}/command", payload, qos=1).wait_for_publish(5)
    yield send
    release(client)


def bed_link(broker, tmp_path):
    link = mqtt_ward_link("127.0.0.1", broker.port, BED, Outbox(tmp_path / "outbox.db"), client_id=f"{BED}-link",
                    summary_interval_s=0.05, resend_after_s=0.5)
    assert wait_until(lambda: link.status()["connected"])
    return link


def start_bed(small_mat_calibration, tmp_path, broker):
    """The monitor with its ward link; the same store (so the same applied ids) at every start."""
    return ward_daemon(small_mat_calibration, tmp_path, [bed_link(broker, tmp_path)])


def step_until(daemon, condition, frames=60):
    for _ in range(frames):
        if condition():
            return True
        daemon.step()
        time.sleep(0.05)
    return condition()


def pressure_alarm(daemon):
    assert step_until(daemon, lambda: any(a.key.startswith("pressure:") for a in daemon.pipeline.engine.alarms()),
                      100), "no pressure alarm"
    return next(a for a in daemon.pipeline.engine.alarms() if a.key.startswith("pressure:"))


def logged(tmp_path, kind):
    with Store.open(tmp_path / "1.db") as store:
        return [e for e in store.events_since(float("-inf")) if e["kind"] == kind]


def test_a_command_delivered_three_times_is_applied_once_and_its_answer_reaches_the_station(
        small_mat_calibration, tmp_path, broker, repeater):
    journal = CommandJournal(tmp_path / "journal.db")
    with subscribed_station(broker.port, client_id="test-station", journal=journal, resend_after_s=0.2) as station:
        daemon = start_bed(small_mat_calibration, tmp_path, broker)
        try:
            alarm = pressure_alarm(daemon)
            sent = station.commands.send(BED, "acknowledge", {"alarm_id": alarm.alarm_id}, "nurse.smith")
            assert sent["state"] == "pending" and sent["user"] == "nurse.smith"
            command = journal.pending()[0]
            repeater(command)
            repeater(command)                       # as QoS 1 may: the same id twice more
            assert wait_until(lambda: daemon.ward_link.commands_received >= 3)
            assert step_until(daemon, lambda: journal.get(command.id)["state"] == "done")
            repeater(command)                       # after it was applied
            assert wait_until(lambda: daemon.ward_link.commands_received >= 4)
            daemon.step()
        finally:
            daemon.close()
        acknowledged = logged(tmp_path, "acknowledged")
        assert [(e["alarm_id"], e["user"]) for e in acknowledged] == [(alarm.alarm_id, "ward:nurse.smith")]
        entry = journal.get(command.id)
        assert (entry["bed_id"], entry["kind"], entry["args"], entry["user"]) == \
            (BED, "acknowledge", {"alarm_id": alarm.alarm_id}, "nurse.smith")
        assert entry["issued_at"] <= entry["answered_at"] and entry["sends"] >= 1
        with Store.open(tmp_path / "1.db") as store:
            kept = store.ward_command(command.id)
        assert (kept["state"], kept["user"], kept["kind"]) == ("done", "ward:nurse.smith", "acknowledge")
        assert wait_until(lambda: bed_alarm(station, alarm.alarm_id)["acknowledged_by"] == "ward:nurse.smith")


def bed_alarm(station, alarm_id):
    bed = next((b for b in station.beds() if b["bed_id"] == BED), {"alarms": []})
    return next((a for a in bed["alarms"] if a["alarm_id"] == alarm_id), {"acknowledged_by": None})


def test_a_turn_sent_while_the_bed_is_down_and_across_a_station_restart_is_applied_once_when_it_is_back(
        small_mat_calibration, tmp_path, broker, repeater):
    journal = CommandJournal(tmp_path / "journal.db")
    daemon = start_bed(small_mat_calibration, tmp_path, broker)
    daemon.step()
    daemon.close()                                           # the bed is down
    with subscribed_station(broker.port, client_id="test-station", journal=journal, resend_after_s=0.2) as station:
        command_id = station.commands.send(BED, "record-turn", {}, "nurse.smith")["id"]
        assert wait_until(lambda: journal.get(command_id)["sends"] >= 2)      # resent, and nobody answers
    assert journal.get(command_id)["state"] == "pending"                      # kept over the station's restart
    turns_before = len(logged(tmp_path, "recorded"))
    with subscribed_station(broker.port, client_id="test-station", journal=journal, resend_after_s=0.2):
        daemon = start_bed(small_mat_calibration, tmp_path, broker)
        try:
            assert step_until(daemon, lambda: journal.get(command_id)["state"] == "done")
            entry = journal.get(command_id)
            command = WardCommand(**{k: entry[k] for k in WardCommand.__dataclass_fields__})
        finally:
            daemon.close()
    daemon = start_bed(small_mat_calibration, tmp_path, broker)               # the bed restarts: a copy comes late
    try:
        repeater(command)
        assert wait_until(lambda: daemon.ward_link.commands_received >= 1)
        daemon.step()
        daemon.step()
    finally:
        daemon.close()
    recorded = logged(tmp_path, "recorded")[turns_before:]
    assert [e["user"] for e in recorded] == ["ward:nurse.smith"]


def test_a_command_whose_bed_stays_away_expires_and_the_bed_refuses_a_late_copy(
        small_mat_calibration, tmp_path, broker, repeater):
    journal = CommandJournal(tmp_path / "journal.db")
    with subscribed_station(broker.port, client_id="test-station", journal=journal, resend_after_s=0.2,
                            command_expiry_s=0.5) as station:
        command_id = station.commands.send(BED, "record-turn", {}, "nurse.smith")["id"]
        assert wait_until(lambda: journal.get(command_id)["state"] == "expired")
        assert "no answer from the bed in time" in journal.get(command_id)["result"]
        late = new_command(BED, "record-turn", {}, "nurse.smith", "test-station", time.time() - 60, 30)
        journal.add(late)                                    # as if the station had sent it a minute ago
        daemon = start_bed(small_mat_calibration, tmp_path, broker)
        try:
            repeater(late)
            assert step_until(daemon, lambda: journal.get(late.id)["state"] == "refused")
            assert journal.get(command_id)["state"] == "expired"     # never sent again once given up
        finally:
            daemon.close()
    assert re.match(r"expired: record-turn from ward:nurse.smith came 3\d s after it expired",
                    journal.get(late.id)["result"])
    assert [e for e in logged(tmp_path, "recorded") if e["user"] == "ward:nurse.smith"] == []


def test_an_alarm_that_has_ended_is_refused_with_the_reason(small_mat_calibration, tmp_path, broker):
    journal = CommandJournal(tmp_path / "journal.db")
    with subscribed_station(broker.port, client_id="test-station", journal=journal, resend_after_s=0.2) as station:
        daemon = start_bed(small_mat_calibration, tmp_path, broker)
        try:
            command_id = station.commands.send(BED, "acknowledge", {"alarm_id": 999}, "nurse.smith")["id"]
            assert step_until(daemon, lambda: journal.get(command_id)["state"] == "refused")
        finally:
            daemon.close()
    assert journal.get(command_id)["result"] == "alarm 999 is unknown or has already ended"


@pytest.mark.parametrize(("change", "message"), [
    ({"kind": "discharge"}, "kind must be one of acknowledge, record-turn, got 'discharge'"),
    ({"args": {"alarm_id": "3"}}, "acknowledge takes args {alarm_id: a positive integer}"),
    ({"id": "1"}, "command id must be 32 lower-case hex digits, got '1'"),
    ({"bed_id": "bed-2"}, "is for bed 'bed-2', not 'ward-bed'"),
    ({"expires_at": 0.0}, "expires_at (0.0) must come after issued_at"),
    ({"user": ""}, "user must be 1-64 printable characters"),
    ({"extra": 1}, "unknown ['extra']"),
])
def test_a_bad_command_is_refused_naming_what_is_wrong(change, message):
    good = json.loads(new_command(BED, "acknowledge", {"alarm_id": 3}, "nurse.smith", "st", 100.0, 60.0)
                      .to_payload())
    assert parse_command(json.dumps(good).encode(), BED).args == {"alarm_id": 3}
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[").replace("]", r"\]").replace("{", r"\{").replace("}", r"\}")):
        parse_command(json.dumps({**good, **change}).encode(), BED)


def test_a_bad_answer_is_refused_and_the_station_counts_it(broker, tmp_path, repeater):
    with pytest.raises(ValueError, match="state of done, refused"):
        parse_result(json.dumps({"id": "a" * 32, "state": "maybe", "result": "", "answered_at": 1.0}).encode())
    with subscribed_station(broker.port, client_id="test-station",
                            journal=CommandJournal(tmp_path / "journal.db")) as station:
        repeater("not json", f"appliance/{BED}/command-result")
        assert wait_until(lambda: station.bad_payloads == 1)


# The ward screen's controls.

def test_a_nurse_acknowledges_from_the_ward_screen_audited_and_shown_pending_then_done(tmp_path, broker, beds):
    from test_ward_screen import ward, ward_app
    from ward_payloads import summary
    from webui_client import client_as, token

    journal = CommandJournal(tmp_path / "journal.db")
    with subscribed_station(broker.port, client_id="test-station", journal=journal, resend_after_s=0.2) as station:
        app = ward_app(tmp_path, station)
        nurse = client_as(app, "nurse", "nurse.smith")
        link = beds(BED)
        link.summarise(summary(BED, alarms=[(4, "high")]))
        assert wait_until(lambda: ward(nurse)["beds"] and ward(nurse)["beds"][0]["alarms"])
        csrf = {"X-CSRF-Token": token(nurse, "/ward"), "Accept": "application/json"}

        assert nurse.post(f"/ward/{BED}/alarms/4/acknowledge").status_code == 400          # no CSRF token
        refused = nurse.post(f"/ward/{BED}/alarms/5/acknowledge", headers=csrf)
        assert refused.status_code == 409 and "alarm 5 is not open at bed ward-bed" in refused.get_json()["message"]
        assert nurse.post("/ward/bed-99/turn", headers=csrf).status_code == 404
        answer = nurse.post(f"/ward/{BED}/alarms/4/acknowledge", headers=csrf)
        assert answer.status_code == 202, answer.get_data(as_text=True)
        command = answer.get_json()["command"]
        assert "applies it at its next frame" in answer.get_json()["message"]
        assert ward(nurse)["beds"][0]["commands"][0] | {"result": None} == \
            {"id": command["id"], "kind": "acknowledge", "args": {"alarm_id": 4}, "user": "nurse.smith",
             "issued_at": command["issued_at"], "state": "pending", "result": None}
        assert wait_until(lambda: link.commands_received == 1)
        (taken,) = link.take_commands()
        assert (taken.id, taken.bed_user) == (command["id"], "ward:nurse.smith")
        link.answer(taken.id, True, "1 event(s)")
        assert wait_until(lambda: ward(nurse)["beds"][0]["commands"][0]["state"] == "done")
        turn = nurse.post(f"/ward/{BED}/turn", data={"csrf_token": csrf["X-CSRF-Token"]})
        assert turn.status_code == 303                                  # a plain form goes back to the page
        assert [c["kind"] for c in ward(nurse)["beds"][0]["commands"]] == ["record-turn", "acknowledge"]
    audit = app.extensions["users"].audit_log()
    assert [(e["user"], e["action"]) for e in audit[:2]] == [("nurse.smith", "ward: record a turn"),
                                                             ("nurse.smith", "ward: acknowledge alarm 4 "
                                                                             "(pressure:sacrum)")]
    assert command["id"] in audit[1]["detail"] and BED in audit[1]["detail"]


def test_only_a_logged_in_user_may_act_and_a_watching_station_says_it_cannot(tmp_path, station, beds):
    from test_ward_screen import ward, ward_app
    from ward_payloads import summary
    from webui_client import client_as, token

    app = ward_app(tmp_path, station)                     # a station without a journal only watches
    nurse = client_as(app, "nurse")
    stranger = app.test_client()
    refused = stranger.post(f"/ward/{BED}/turn", data={"csrf_token": token(stranger)})
    assert refused.status_code == 302 and "/login" in refused.headers["Location"]
    beds(BED).summarise(summary(BED))
    assert wait_until(lambda: ward(nurse)["beds"])
    assert ward(nurse)["can_act"] is False
    answer = nurse.post(f"/ward/{BED}/turn", headers={"X-CSRF-Token": token(nurse, "/ward"),
                                                     "Accept": "application/json"})
    assert answer.status_code == 503 and "only watches the beds" in answer.get_json()["message"]


def test_a_command_no_bed_could_take_is_refused_at_the_station_and_not_journalled(tmp_path, broker, beds):
    from test_ward_screen import ward, ward_app
    from ward_payloads import summary
    from webui_client import client_as, token

    journal = CommandJournal(tmp_path / "journal.db")
    long_id = "b" * 70                                   # no bed may have it (the broker's logins allow 64)
    with subscribed_station(broker.port, client_id="test-station", journal=journal) as station:
        app = ward_app(tmp_path, station)
        nurse = client_as(app, "nurse")
        beds(long_id).summarise(summary(long_id))
        assert wait_until(lambda: ward(nurse)["beds"])
        answer = nurse.post(f"/ward/{long_id}/turn", headers={"X-CSRF-Token": token(nurse, "/ward"),
                                                             "Accept": "application/json"})
    assert answer.status_code == 400 and "bed_id must be 1-64 printable characters" in answer.get_json()["message"]
    assert journal.recent(0.0) == []
