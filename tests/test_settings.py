"""Patient and bed settings: checked like the configuration, kept in settings.toml, audited, applied to the monitor."""

import numpy as np
import pytest

from appliance.core.pressure import KPA_PER_MMHG
from appliance.errors import ConfigError
from appliance.service import settings
from appliance.service.assemble import assemble
from appliance.service.config import config_from_mapping
from appliance.service.daemon import MonitorDaemon
from appliance.service.live import read_live
from appliance.store import Store
from webui import create_app
from webui_client import client_as, set_up, token


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


def commands(tmp_path) -> list[dict]:
    with Store.open(tmp_path / "appliance.db") as store:
        return store.commands_since(0)


def audits(app) -> list[tuple[str, str, str]]:
    return [(e["user"], e["action"], e["detail"]) for e in app.extensions["users"].audit_log()]


def post(client, path, **fields):
    return client.post(path, data={"csrf_token": token(client, "/settings"), **fields})


# Who may do what.

def test_anonymous_requests_are_sent_to_log_in_and_change_nothing(app, tmp_path):
    set_up(app.test_client())
    client = app.test_client()
    assert "/login" in client.get("/settings").headers["Location"]
    assert client.get("/api/settings").status_code == 401
    answer = client.post("/settings/patient", data={"csrf_token": token(client), "threshold_mmhg": "40"})
    assert answer.status_code == 302 and "/login" in answer.headers["Location"]
    assert not (tmp_path / "settings.toml").exists() and commands(tmp_path) == []


def test_a_change_without_the_csrf_token_is_refused(app, tmp_path):
    client = client_as(app, "nurse")
    answer = client.post("/settings/patient", data={"threshold_mmhg": "40"})
    assert answer.status_code == 400 and "CSRF" in answer.get_data(as_text=True)
    assert not (tmp_path / "settings.toml").exists() and commands(tmp_path) == []


def test_a_nurse_changes_patient_settings_but_not_the_bed(app, tmp_path):
    nurse = client_as(app, "nurse")
    assert post(nurse, "/settings/patient", threshold_mmhg="40").status_code == 303
    before = audits(app)
    answer = post(nurse, "/settings/bed", bed_id="ward3-bed12")
    assert answer.status_code == 403 and "engineer" in answer.get_data(as_text=True)
    assert settings.read_settings(tmp_path / "settings.toml") == {"alerts": {"threshold_mmhg": 40}}
    assert len(commands(tmp_path)) == 1 and audits(app) == before
    page = nurse.get("/settings").get_data(as_text=True)
    assert 'action="/settings/patient"' in page and "Save bed settings" not in page


# Bad values: 400 naming the field and what it may be; nothing written, queued or audited.

@pytest.mark.parametrize("path, fields, message", [
    ("/settings/patient", {"threshold_mmhg": "forty"}, "threshold_mmhg must be a number, got 'forty'"),
    ("/settings/patient", {"threshold_mmhg": "5"}, "threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 5"),
    ("/settings/patient", {"threshold_mmhg": ""}, "threshold_mmhg must be a number, got ''"),
    ("/settings/patient", {"alarm_dose": "9"}, "alarm_dose must be from 0.05 to 1 (its safe range), got 9"),
    ("/settings/patient", {"turn_interval_min": "10"},
     "turn_interval_min must be from 15 to 240 min (its safe range), got 10"),
    ("/settings/patient", {"escalate_after_min": "nan"}, "escalate_after_min must be a number, got nan"),
    ("/settings/patient", {"curve": "made-up"}, "curve must be one of reswick-rogers, linder-ganz, got 'made-up'"),
    ("/settings/patient", {"recovery": "forget"}, "recovery must be one of reset, decay, got 'forget'"),
    ("/settings/patient", {"colour": "red"}, "unknown field 'colour'; patient settings are threshold_mmhg, curve"),
    ("/settings/patient", {"bed_id": "ward3-bed12"}, "unknown field 'bed_id'"),
    ("/settings/bed", {"bed_id": ""}, "bed_id must be non-empty text, got ''"),
    ("/settings/bed", {"bed_id": "bed 12"}, "bed_id must be 1-64 characters without spaces"),
    ("/settings/bed", {"layout": "grid-99x99"},
     "layout must be one of circular-16, square-16, grid-4x4, grid-8x16, grid-16x32, ktc-32, got 'grid-99x99'"),
])
def test_a_bad_value_is_refused_naming_the_field_and_nothing_changes(app, tmp_path, path, fields, message):
    client = client_as(app, "engineer")
    before = audits(app)
    answer = post(client, path, **fields)
    assert answer.status_code == 400
    assert message in answer.get_data(as_text=True).replace("&#39;", "'")
    assert not (tmp_path / "settings.toml").exists()
    assert commands(tmp_path) == [] and audits(app) == before


def test_the_json_api_answers_a_bad_value_in_json(app, tmp_path):
    client = client_as(app, "nurse")
    answer = client.post("/settings/patient", json={"turn_interval_min": 1000},
                         headers={"X-CSRF-Token": token(client, "/settings")})
    assert answer.status_code == 400
    assert answer.get_json() == {"error": "patient settings not changed: [alerts]: turn_interval_min must be from "
                                          "15 to 240 min (its safe range), got 1000"}
    assert not (tmp_path / "settings.toml").exists() and commands(tmp_path) == []


# Good changes.

def test_a_change_is_written_queued_once_and_audited_old_to_new(app, tmp_path):
    client = client_as(app, "nurse")
    form = {"threshold_mmhg": "40", "curve": "reswick-rogers", "alarm_dose": "1", "recovery": "reset",
            "turn_interval_min": "90", "escalate_after_min": "15"}              # the whole form, two fields changed
    answer = client.post("/settings/patient", data={**form, "csrf_token": token(client, "/settings")},
                         follow_redirects=True)
    text = answer.get_data(as_text=True).replace("&gt;", ">")
    assert "patient settings changed: threshold_mmhg 32 -> 40, turn_interval_min 120 -> 90" in text
    assert settings.read_settings(tmp_path / "settings.toml") == {"alerts": {"threshold_mmhg": 40,
                                                                             "turn_interval_min": 90}}
    [command] = commands(tmp_path)
    assert (command["kind"], command["user"], command["state"]) == ("apply-settings", "nurse.test", "pending")
    assert command["args"] == {"alerts": {"threshold_mmhg": 40, "turn_interval_min": 90}}
    assert audits(app)[0] == ("nurse.test", "changed settings",
                              f"threshold_mmhg 32 -> 40, turn_interval_min 120 -> 90 (command {command['id']})")
    shown = client.get("/api/settings").get_json()["settings"]["alerts"]
    assert shown["threshold_mmhg"] == {"value": 40, "source": "settings file"}
    assert shown["curve"] == {"value": "reswick-rogers", "source": "default"}

    before = audits(app)
    again = client.post("/settings/patient", data={**form, "csrf_token": token(client, "/settings")},
                        follow_redirects=True)
    assert "nothing changed in the patient settings" in again.get_data(as_text=True)
    assert len(commands(tmp_path)) == 1 and audits(app) == before


def test_an_engineer_changes_the_bed_and_is_told_the_layout_waits_for_a_restart(app, tmp_path):
    client = client_as(app, "engineer")
    answer = post(client, "/settings/bed", bed_id="ward3-bed12", layout="grid-4x4")
    assert answer.status_code == 303
    page = client.get("/settings").get_data(as_text=True).replace("&gt;", ">")
    assert f"layout {config_from_mapping({}).layout} -> grid-4x4" in page
    assert "applies when the monitor restarts" in page
    [command] = commands(tmp_path)
    assert command["args"] == {"monitor": {"bed_id": "ward3-bed12", "layout": "grid-4x4"}}
    assert settings.read_settings(tmp_path / "settings.toml")["monitor"] == command["args"]["monitor"]


# The file: kept across restarts, laid over the configuration, refused when broken.

def test_the_file_survives_a_reload_and_overlays_only_what_it_holds(tmp_path):
    path = tmp_path / "settings.toml"
    saved = {"alerts": {"threshold_mmhg": 40, "curve": "linder-ganz", "turn_interval_min": 90.5},
             "monitor": {"bed_id": "ward3-bed\"12\"", "layout": "grid-4x4"}}
    settings.write_settings(path, saved)
    assert settings.read_settings(path) == saved
    assert list(tmp_path.iterdir()) == [path]                                 # no temporary file left behind
    ward = config_from_mapping({"monitor": {"bed_id": "ward3-bed1"},
                                "alerts": {"threshold_mmhg": 35, "alarm_dose": 0.8, "escalation_channel": "icu",
                                           "curve_points": [[60, 100], [600, 40]]}})
    config = settings.load_overlaid(ward, tmp_path)
    assert config.alerts.threshold_kpa == pytest.approx(40 * KPA_PER_MMHG)
    assert (config.alerts.curve, config.alerts.curve_points) == ("linder-ganz", None)
    assert config.alerts.turn_interval_s == 90.5 * 60
    assert (config.alerts.alarm_dose, config.alerts.escalation_channel) == (0.8, "icu")     # the ward's, kept
    assert (config.bed_id, config.layout) == ('ward3-bed"12"', "grid-4x4")
    assert settings.load_overlaid(ward, tmp_path / "elsewhere") == ward                     # no file: as it is


@pytest.mark.parametrize("text, message", [
    ("[alerts]\nthreshold_mmhg = [", "is not valid TOML"),
    ("[alerts]\nthreshold_mmhg = 5\n", "[alerts]: threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 5"),
    ("[alerts]\ncurve_points = [[60, 100]]\n", "[alerts]: unknown key 'curve_points'; allowed"),
    ("[board]\nname = \"x\"\n", "unknown table [board]"),
    ("alerts = 3\n", "[alerts] must be a table, got 3"),
])
def test_a_broken_settings_file_is_a_clear_error_naming_the_file(tmp_path, text, message):
    path = tmp_path / "settings.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        settings.load_overlaid(config_from_mapping({}), tmp_path)
    assert str(path) in str(error.value) and message in str(error.value)
    with pytest.raises(ConfigError, match="settings file"):                # before any model is built
        assemble(config_from_mapping({"monitor": {"data_dir": str(tmp_path)}}), say=lambda line: None)


def test_the_screen_shows_a_broken_file_and_refuses_to_change_over_it(app, tmp_path):
    (tmp_path / "settings.toml").write_text("[alerts]\nthreshold_mmhg = 5\n")
    client = client_as(app, "nurse")
    page = client.get("/settings")
    assert page.status_code == 200 and "threshold_mmhg must be from 20 to 60 mmHg" in page.get_data(as_text=True)
    answer = post(client, "/settings/patient", threshold_mmhg="40")
    assert answer.status_code == 409 and "fix or remove it" in answer.get_data(as_text=True)
    assert (tmp_path / "settings.toml").read_text() == "[alerts]\nthreshold_mmhg = 5\n" and commands(tmp_path) == []


# Safe ranges and the ward policy.

@pytest.mark.parametrize("fields, message", [
    ({"threshold_mmhg": "200"}, "threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 200"),
    ({"alarm_dose": "5"}, "alarm_dose must be from 0.05 to 1 (its safe range), got 5"),
    ({"turn_interval_min": "720"}, "turn_interval_min must be from 15 to 240 min (its safe range), got 720"),
    ({"relief_min": "60"}, "relief_min must be from 5 to 30 min (its safe range), got 60"),
    ({"turn_grace_min": "120"}, "turn_grace_min must be from 0 to 60 min (its safe range), got 120"),
    ({"reminder_repeat_min": "240"}, "reminder_repeat_min must be from 5 to 60 min (its safe range), got 240"),
    ({"escalate_after_min": "120"}, "escalate_after_min must be from 1 to 30 min (its safe range), got 120"),
])
def test_a_setting_that_would_blind_the_monitor_is_refused_naming_it_its_value_and_its_range(app, tmp_path,
                                                                                           fields, message):
    answer = post(client_as(app, "admin"), "/settings/patient", **fields)
    assert answer.status_code == 400 and message in answer.get_data(as_text=True)
    assert not (tmp_path / "settings.toml").exists() and commands(tmp_path) == []


def test_a_configuration_file_outside_the_safe_range_stops_the_monitor_at_start_with_exit_2(tmp_path, capsys):
    from appliance.cli import main

    path = tmp_path / "appliance.toml"
    path.write_text("[alerts]\nthreshold_mmhg = 200\n")
    assert main(["run", "--config", str(path), "--check-config"]) == 2
    assert "threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 200" in capsys.readouterr().err


def policy(client, **fields):
    return client.post("/settings/policy", data={"csrf_token": token(client, "/settings"), **fields})


def test_only_an_admin_sets_the_ward_policy_and_it_bounds_what_a_nurse_may_set(app, tmp_path):
    nurse, engineer, admin = (client_as(app, role) for role in ("nurse", "engineer", "admin"))
    for client in (nurse, engineer):
        assert policy(client, threshold_mmhg_low="20", threshold_mmhg_high="60").status_code == 403
    assert not (tmp_path / "settings.toml").exists()
    assert post(nurse, "/settings/patient", threshold_mmhg="45").status_code == 303     # the safe range allows it
    answer = policy(admin, threshold_mmhg_low="28", threshold_mmhg_high="40")
    assert answer.status_code == 400                                 # the 45 in use would lie outside the new policy
    assert "threshold_mmhg 45 is outside the ward policy 28-40 mmHg" in answer.get_data(as_text=True)
    assert post(nurse, "/settings/patient", threshold_mmhg="36").status_code == 303
    assert policy(admin, threshold_mmhg_low="28", threshold_mmhg_high="40", turn_interval_min_low="60",
                  turn_interval_min_high="180").status_code == 303
    assert settings.read_settings(tmp_path / "settings.toml")["policy"] == {"threshold_mmhg": [28, 40],
                                                                           "turn_interval_min": [60, 180]}
    who, action, detail = audits(app)[0]
    assert (who, action) == ("admin.test", "changed ward policy")
    assert detail == "threshold_mmhg 20-60 -> 28-40 mmHg, turn_interval_min 15-240 -> 60-180 min"
    assert isinstance(app.extensions["users"].audit_log()[0]["time_s"], float)
    refused = post(nurse, "/settings/patient", threshold_mmhg="45")
    assert refused.status_code == 400
    assert "threshold_mmhg 45 is outside the ward policy 28-40 mmHg" in refused.get_data(as_text=True)
    assert settings.read_settings(tmp_path / "settings.toml")["alerts"] == {"threshold_mmhg": 36}
    as_json = nurse.post("/settings/patient", json={"turn_interval_min": 200},
                         headers={"X-CSRF-Token": token(nurse, "/settings")})
    assert as_json.status_code == 400 and "turn_interval_min 200 is outside the ward policy 60-180 min" in \
        as_json.get_json()["error"]
    assert post(nurse, "/settings/patient", threshold_mmhg="40").status_code == 303
    assert nurse.get("/api/settings").get_json()["policy"]["threshold_mmhg"]["high"] == 40
    assert "28-40 mmHg" in nurse.get("/settings").get_data(as_text=True)


def test_a_policy_outside_the_safe_range_is_refused_and_a_file_cannot_carry_one(app, tmp_path):
    admin = client_as(app, "admin")
    answer = policy(admin, threshold_mmhg_low="10", threshold_mmhg_high="80")
    assert answer.status_code == 400
    assert "threshold_mmhg 10-80 mmHg is outside its safe range 20-60 mmHg" in answer.get_data(as_text=True)
    inverted = admin.post("/settings/policy", json={"alarm_dose": [1.0, 0.5]},
                          headers={"X-CSRF-Token": token(admin, "/settings")})
    assert inverted.status_code == 400 and "alarm_dose 1-0.5: low is above high" in inverted.get_json()["error"]
    assert not (tmp_path / "settings.toml").exists()
    loaded = upload(admin, b"[policy]\nthreshold_mmhg = [20, 60]\n")
    assert loaded.status_code == 400 and "the ward policy is set on this page by an admin" in \
        loaded.get_data(as_text=True)
    with pytest.raises(ConfigError, match=r"threshold_mmhg 50 is outside the ward policy 28-40 mmHg"):
        settings.check_settings({"alerts": {"threshold_mmhg": 50}, "policy": {"threshold_mmhg": [28, 40]}})


# The running monitor.

def running_monitor(small_mat_calibration, tmp_path, failing=()):
    """The small daemon (alarm at 5 % of the tolerance) taking settings commands, and its events."""
    from test_daemon import FlakySource, small_daemon

    daemon, events = small_daemon(small_mat_calibration, tmp_path, FlakySource(failing=failing), alarm_dose=0.05)
    settings.attach(daemon)
    return daemon, events


def test_the_monitor_applies_a_change_at_its_next_frame_and_carries_doses_and_alarms_over(small_mat_calibration,
                                                                                        tmp_path):
    daemon, events = running_monitor(small_mat_calibration, tmp_path, failing={6})   # frame 6: no map, dose held
    app = create_app(tmp_path, secure_cookies=False, TESTING=True)
    nurse = client_as(app, "nurse")
    assert nurse.get("/api/settings").get_json()["settings"]["alerts"]["alarm_dose"] == {"value": 0.05,
                                                                                         "source": "monitor"}
    daemon.run(6)
    before = daemon.pipeline.state()
    open_before = {a.alarm_id: a.key for a in daemon.pipeline.engine.alarms()}
    assert np.max(before["dose"]["cells"]["dose"]) > 0.05 and open_before                 # a dose and an alarm to keep
    answer = post(nurse, "/settings/patient", threshold_mmhg="40", curve="linder-ganz", recovery="decay",
                  turn_interval_min="30", escalate_after_min="5")
    assert answer.status_code == 303
    assert daemon.pipeline.settings.turn_interval_s == 7200.0                    # not before the next frame
    daemon.run(1)
    s = daemon.pipeline.settings
    assert (s.turn_interval_s, s.escalate_after_s, s.curve, s.recovery) == (1800.0, 300.0, "linder-ganz", "decay")
    assert s.threshold_kpa == pytest.approx(40 * KPA_PER_MMHG) and s.alarm_dose == 0.05
    assert daemon.config.alerts == s and daemon.pipeline.turns.interval_s == 1800.0
    after = daemon.pipeline.state()
    assert after["dose"]["cells"]["dose"] == before["dose"]["cells"]["dose"]       # carried over, not reset
    assert after["dose"]["cells"]["relieved_s"] == before["dose"]["cells"]["relieved_s"]
    assert (after["dose"]["cells"]["curve"], after["dose"]["cells"]["recovery"]) == ("linder-ganz", "decay")
    assert after["dose"]["cells"]["relief_kpa"] == pytest.approx(40 * KPA_PER_MMHG)
    assert after["turns"]["last_turn_s"] == before["turns"]["last_turn_s"]
    assert open_before.items() <= {a.alarm_id: a.key for a in daemon.pipeline.engine.alarms()}.items()
    [command] = commands(tmp_path)
    assert command["state"] == "done"
    assert command["result"] == ("applied threshold_mmhg 32 -> 40, curve reswick-rogers -> linder-ganz, recovery "
                                 "reset -> decay, turn_interval_min 120 -> 30, escalate_after_min 15 -> 5")
    daemon.run(2)                                                               # the new settings run on
    daemon.close()
    assert read_live(tmp_path / "live.json")["turn"]["interval_s"] == 1800.0
    shown = nurse.get("/api/settings").get_json()["settings"]["alerts"]
    assert shown["turn_interval_min"] == {"value": 30, "source": "settings file"}
    assert shown["alarm_dose"] == {"value": 0.05, "source": "monitor"}
    assert not [e for e in events if e.kind == "ended" and e.alarm_id in open_before]


def test_an_open_pressure_alarm_outlives_a_change_of_settings_until_the_site_is_relieved(small_mat_calibration,
                                                                                         tmp_path):
    daemon, events = running_monitor(small_mat_calibration, tmp_path)
    while not daemon.pipeline.engine.alarms("clinical"):
        daemon.run(1)
    [alarm] = daemon.pipeline.engine.alarms("clinical")
    assert alarm.key.startswith("pressure:") and daemon.pipeline.dose.doses()["mat"] < 1.0
    # The 45 mmHg load is below a 60 mmHg threshold, and the dose far below a whole tolerance: by the new
    # rules alone the site is relieved and its dose decays, and the alarm would end at the next frame.
    _, result = settings.apply_settings(daemon, daemon.source.now(), {"alerts": {
        "threshold_mmhg": 60, "alarm_dose": 1.0, "recovery": "decay", "relief_min": 30}})
    assert result.startswith("applied threshold_mmhg 32 -> 60")
    daemon.run(1)
    assert [a.alarm_id for a in daemon.pipeline.engine.alarms("clinical")] == [alarm.alarm_id]
    assert daemon.pipeline.state()["held"] == ["mat"]
    daemon.run(3)                                            # relieved for the 30 min relief: it ends as usual
    daemon.close()
    assert [e.alarm_id for e in events if e.kind == "ended"] == [alarm.alarm_id]
    assert daemon.pipeline.state()["held"] == []


def test_a_new_bed_id_shows_at_once_and_a_new_layout_waits_for_a_restart(small_mat_calibration, tmp_path):
    daemon, _ = running_monitor(small_mat_calibration, tmp_path)
    app = create_app(tmp_path, secure_cookies=False, TESTING=True)
    engineer = client_as(app, "engineer")
    daemon.run(2)
    pipeline = daemon.pipeline
    assert post(engineer, "/settings/bed", bed_id="ward3-bed12", layout="grid-8x16").status_code == 303
    daemon.run(1)
    daemon.close()
    assert (daemon.config.bed_id, daemon.config.layout) == ("ward3-bed12", "grid-4x4")
    assert daemon.pipeline is pipeline                                          # no patient setting changed
    assert read_live(tmp_path / "live.json")["bed_id"] == "ward3-bed12"
    [command] = commands(tmp_path)
    assert command["state"] == "done"
    assert command["result"] == ("applied bed_id " + config_from_mapping({}).bed_id + " -> ward3-bed12; "
                                 "layout grid-4x4 -> grid-8x16 applies when the monitor restarts")
    state = engineer.get("/api/settings").get_json()
    assert (state["running_layout"], state["restart_pending"]) == ("grid-4x4", True)
    assert "the monitor still runs\n  grid-4x4" in engineer.get("/settings").get_data(as_text=True)


def test_a_restart_resumes_the_doses_under_settings_changed_while_the_monitor_was_down(small_mat_calibration,
                                                                                      tmp_path):
    from test_daemon import FlakySource

    daemon, _ = running_monitor(small_mat_calibration, tmp_path)
    daemon.run(6)
    before = daemon.pipeline.state()
    daemon.close()
    settings.write_settings(tmp_path / "settings.toml", {"alerts": {"threshold_mmhg": 40, "curve": "linder-ganz",
                                                                    "recovery": "decay"}})
    model, calibration = small_mat_calibration
    config = settings.load_overlaid(daemon.config, tmp_path)               # as assemble() does
    restarted = MonitorDaemon(config, FlakySource(failing=()), model, calibration,
                              Store.open(tmp_path / "appliance.db"), say=lambda line: None)
    settings.attach(restarted)
    restarted.start()
    after = restarted.pipeline.state()
    restarted.close()
    assert restarted.resumed_from_s == before["last_time_s"]                  # resumed, not started afresh
    assert after["dose"]["cells"]["dose"] == before["dose"]["cells"]["dose"]
    assert np.max(after["dose"]["cells"]["dose"]) > 0
    assert (after["dose"]["cells"]["curve"], after["dose"]["cells"]["recovery"]) == ("linder-ganz", "decay")
    assert after["alarms"] == before["alarms"]


@pytest.mark.parametrize("args, reason", [
    ({"alerts": {"threshold_mmhg": 5}}, "[alerts]: threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 5"),
    ({"alerts": {"escalation_channel": "icu"}}, "[alerts]: unknown key 'escalation_channel'"),
    ({"monitor": {"data_dir": "/tmp"}}, "[monitor]: unknown key 'data_dir'"),
    ({"board": {}}, "unknown table [board]"),
    ({"alerts": [40]}, "[alerts] must be a table"),
])
def test_a_bad_command_queued_directly_is_refused_with_the_reason_and_changes_nothing(small_mat_calibration,
                                                                                     tmp_path, args, reason):
    daemon, _ = running_monitor(small_mat_calibration, tmp_path)
    daemon.run(2)
    pipeline, config = daemon.pipeline, daemon.config
    with Store.open(tmp_path / "appliance.db") as screen:
        command = screen.queue_command("apply-settings", args, "someone")
    daemon.run(1)
    daemon.close()
    assert daemon.pipeline is pipeline and daemon.config == config
    with Store.open(tmp_path / "appliance.db") as store:
        refused = store.command(command)
        assert refused["state"] == "refused" and reason in refused["result"]
        assert store.load_state("settings") == settings.published(config)


def test_a_command_queued_directly_outside_the_ward_policy_is_refused_by_the_monitor(small_mat_calibration,
                                                                                       tmp_path):
    import dataclasses

    daemon, _ = running_monitor(small_mat_calibration, tmp_path)
    daemon.config = dataclasses.replace(daemon.config, data_dir=tmp_path)
    settings.write_settings(tmp_path / "settings.toml", {"policy": {"threshold_mmhg": [28, 40]}})
    pipeline = daemon.pipeline
    with pytest.raises(ConfigError, match="threshold_mmhg 50 is outside the ward policy 28-40 mmHg"):
        settings.apply_settings(daemon, 0.0, {"alerts": {"threshold_mmhg": 50}})
    assert daemon.pipeline is pipeline
    applied = settings.apply_settings(daemon, 0.0, {"alerts": {"threshold_mmhg": 36}})[1]
    assert applied == "applied threshold_mmhg 32 -> 36"
    daemon.close()


def test_a_command_restating_the_settings_changes_nothing(small_mat_calibration, tmp_path):
    daemon, _ = running_monitor(small_mat_calibration, tmp_path)
    pipeline, config = daemon.pipeline, daemon.config
    events, result = settings.apply_settings(daemon, 0.0, {"alerts": {"alarm_dose": 0.05, "threshold_mmhg": 32}})
    daemon.close()
    assert (events, result) == ([], "nothing changed")
    assert daemon.pipeline is pipeline and daemon.config is config


# Save and load as a file.

def upload(client, content: bytes, name="settings.toml"):
    import io

    return client.post("/settings/file", data={"csrf_token": token(client, "/settings"),
                                               "file": (io.BytesIO(content), name)},
                       content_type="multipart/form-data", follow_redirects=True)


def test_an_engineer_saves_the_settings_and_loads_them_back_changed(app, tmp_path):
    engineer = client_as(app, "engineer")
    saved = engineer.get("/settings/file")
    assert saved.status_code == 200 and "attachment" in saved.headers["Content-Disposition"]
    text = saved.get_data(as_text=True)
    (tmp_path / "kept.toml").write_text(text)
    assert settings.read_settings(tmp_path / "kept.toml")["alerts"]["turn_interval_min"] == 120   # a whole file
    answer = upload(engineer, text.replace("turn_interval_min = 120", "turn_interval_min = 60").encode())
    assert "settings loaded: turn_interval_min 120 -> 60" in answer.get_data(as_text=True).replace("&gt;", ">")
    assert settings.read_settings(tmp_path / "settings.toml") == {"alerts": {"turn_interval_min": 60}}
    [command] = commands(tmp_path)
    assert command["args"] == {"alerts": {"turn_interval_min": 60}}
    assert audits(app)[0][:2] == ("engineer.test", "loaded settings")
    again = upload(engineer, text.replace("turn_interval_min = 120", "turn_interval_min = 60").encode())
    assert "nothing changed" in again.get_data(as_text=True) and len(commands(tmp_path)) == 1


@pytest.mark.parametrize("content, message", [
    (b"[alerts]\nthreshold_mmhg = 5\n", "threshold_mmhg must be from 20 to 60 mmHg (its safe range), got 5"),
    (b"[alerts]\nbogus = 1\n", "bogus"),
    (b"[alerts\n", "settings file"),
    (b"", None),
])
def test_a_bad_settings_file_is_refused_and_nothing_changes(app, tmp_path, content, message):
    engineer = client_as(app, "engineer")
    before = audits(app)
    answer = upload(engineer, content) if content else engineer.post(
        "/settings/file", data={"csrf_token": token(engineer, "/settings")})
    text = answer.get_data(as_text=True)
    assert answer.status_code == 400 and "settings not loaded" in text
    assert message is None or message in text
    assert commands(tmp_path) == [] and audits(app) == before and not (tmp_path / "settings.toml").exists()


def test_a_nurse_may_neither_save_nor_load_the_settings_file(app, tmp_path):
    nurse = client_as(app, "nurse")
    assert nurse.get("/settings/file").status_code == 403
    assert upload(nurse, b"[alerts]\nturn_interval_min = 60\n").status_code == 403
    assert commands(tmp_path) == []
