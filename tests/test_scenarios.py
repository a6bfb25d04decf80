"""The whole monitor daemon on the virtual bed under a simulated clock, one map per simulated minute:
the built-in scenarios raise the alarms a nurse needs and no others, and ``appliance sim run`` records them."""

import json
from pathlib import Path

import pytest

from appliance.alerts.anatomy import posture_group
from appliance.cli import main
from appliance.service.assemble import assemble
from appliance.service.config import config_from_mapping
from appliance.sim.scenes import load_scene

MINUTE = 60.0
PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"


def replay(name, tmp_path, model_cache, hours=None, **monitor):
    """Every event of scenario ``name`` through the daemon, and each frame's dose per site."""
    config = config_from_mapping({"monitor": {"frame_interval_s": MINUTE, "data_dir": str(tmp_path),
                                              "cache_dir": str(model_cache), **monitor},
                                  "virtual": {"scenario": name, "speed": 0}})
    events, frames = [], []

    def on_map(pressure_map):
        frames.append((pressure_map.time_s, daemon.pipeline.dose.doses(), pressure_map))

    daemon = assemble(config, say=lambda text: None, on_event=events.append, on_map=on_map, live=False)
    duration = load_scene(name).duration_s if hours is None else hours * 3600
    try:
        daemon.run(int(duration / MINUTE) + 1)
    finally:
        daemon.close()
    return events, frames


def raised(events, prefix=""):
    return [e for e in events if e.kind == "raised" and e.key.startswith(prefix)]


def test_supine_unturned_raises_the_sacral_alarm_in_the_frame_its_dose_crosses(tmp_path, bed_monitoring,
                                                                              model_cache):
    events, frames = replay("supine-unturned", tmp_path, model_cache)
    sacral = raised(events, "pressure:sacrum")
    assert len(sacral) == 1 and sacral[0].site == "sacrum" and sacral[0].posture == "supine"
    crossing = next(t for t, doses, _ in frames if doses["sacrum"] >= 1.0)
    assert sacral[0].time_s == crossing                        # within one frame: the very frame
    assert 2 * 3600 <= sacral[0].time_s <= 12 * 3600
    assert 700 <= sacral[0].x_mm <= 1100 and 350 <= sacral[0].y_mm <= 550    # the pelvis, on the midline
    assert [e.kind for e in events if e.key == sacral[0].key] == ["raised", "escalated"]   # nobody answered


def test_turned_every_two_hours_for_a_day_raises_no_pressure_alarm(tmp_path, bed_monitoring, model_cache):
    events, frames = replay("turned-every-2h", tmp_path, model_cache)
    assert frames[-1][0] == 24 * 3600
    assert not raised(events, "pressure:")
    turns = [e.kind for e in events if e.type == "turn" and e.kind in ("lay-down", "repositioned")]
    assert turns == ["lay-down"] + ["repositioned"] * 11
    assert not raised(events, "technical:") and not raised(events, "turn:overdue")


def test_heels_alone_on_the_mat_are_no_body_but_their_load_still_alarms_where_it_lies(tmp_path, bed_monitoring,
                                                                                       model_cache):
    """Two heels weigh far less than a person: no site can be named from anatomy (the body model would call
    them anything), so the load is dosed as one unidentified site and its alarm says where it lies."""
    events, frames = replay("heel-only", tmp_path, model_cache)
    alarms = raised(events, "pressure:")
    assert [(e.site, e.posture) for e in alarms] == [("unidentified", "out-of-bed")]
    assert alarms[0].x_mm >= 1600                                # at the foot end, where the heels lie
    crossing = next(t for t, doses, _ in frames if doses["unidentified"] >= 1.0)
    assert alarms[0].time_s == crossing <= 12 * 3600
    assert not raised(events, "technical:")                    # a few saturated heel readings are no fault


def test_an_electrode_lost_mid_run_is_a_technical_alarm_and_monitoring_goes_on(tmp_path, bed_monitoring,
                                                                             model_cache):
    events, frames = replay("electrode-fault", tmp_path, model_cache, hours=4)
    technical = raised(events, "technical:")
    assert [(e.key, e.category) for e in technical] == [("technical:electrode:5", "technical")]
    assert 3600 <= technical[0].time_s <= 3600 + 2 * MINUTE    # within 3 frames of the lead coming off
    ended = [e for e in events if e.kind == "ended" and e.key == "technical:electrode:5"]
    assert ended and 10800 <= ended[0].time_s <= 10800 + 2 * MINUTE
    during = [m for t, _, m in frames if 3600 < t < 10800]
    assert len(during) == 119                                  # a map every minute without the electrode
    before = [m for t, _, m in frames if 600 < t < 3600]
    assert all(m.usable_readings < before[0].usable_readings for m in during)
    assert all(m.regions for m in during)                      # the patient is still mapped
    assert not raised(events, "pressure:")


def test_sim_run_writes_every_event_as_a_json_line(tmp_path, bed_monitoring, model_cache, capsys):
    out = tmp_path / "events.jsonl"
    assert main(["sim", "run", "--scenario", "supine-unturned", "--hours", "9", "--out", str(out),
                 "--acknowledge-after-min", "5", "--cache-dir", str(model_cache)]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert all({"time_s", "type", "kind", "priority", "site", "posture", "x_mm", "y_mm"} <= set(line)
               for line in lines)
    kinds = [(line["type"], line["kind"], line["key"]) for line in lines]
    assert ("turn", "lay-down", None) in kinds
    sacral = [line for line in lines if (line["key"] or "").startswith("pressure:sacrum")]
    assert [line["kind"] for line in sacral] == ["raised", "acknowledged"]      # answered before escalation
    assert sacral[1]["user"] == "simulated-nurse" and sacral[1]["time_s"] - sacral[0]["time_s"] == 5 * MINUTE
    assert (sacral[0]["site"], sacral[0]["posture"], sacral[0]["priority"]) == ("sacrum", "supine", "medium")
    assert "541 frames (9 simulated h)" in capsys.readouterr().err


def test_sim_run_refuses_hours_beyond_the_scenario_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "events.jsonl"
    assert main(["sim", "run", "--scenario", "turn-schedule", "--hours", "9", "--out", str(out)]) != 0
    assert "scenario turn-schedule lasts 8 h; --hours 9 is longer" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.skipif(not PMAT.is_dir(), reason=f"PmatData recordings not present at {PMAT}")
def test_a_night_replayed_from_recorded_pressure_maps(tmp_path, bed_monitoring, model_cache):
    scenario = tmp_path / "recorded-night.toml"
    scenario.write_text(f'[scene]\ndescription = "PmatData S1 supine, then right side"\n'
                        f'[[recording]]\nsource = "pmatdata"\ndir = "{PMAT}"\nsubject = 1\nposture = 1\n'
                        f'hold_s = 3600\n[[recording]]\nsource = "pmatdata"\ndir = "{PMAT}"\nsubject = 1\n'
                        f'posture = 2\nhold_s = 3600\n')
    out = tmp_path / "events.jsonl"
    assert main(["sim", "run", "--scenario", str(scenario), "--hours", "2", "--out", str(out),
                 "--cache-dir", str(model_cache)]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert (lines[0]["type"], lines[0]["kind"], lines[0]["posture"], lines[0]["time_s"]) == \
        ("turn", "lay-down", "supine", 0.0)
    assert [(line["kind"], line["posture"]) for line in lines if line["type"] == "turn"][1:] == \
        [("repositioned", "right-90")]
    assert not [line for line in lines if (line["key"] or "").startswith(("technical:", "pressure:"))]


@pytest.mark.skipif(not PMAT.is_dir(), reason=f"PmatData recordings not present at {PMAT}")
def test_sim_replay_feeds_true_maps_to_the_alert_layer_and_names_an_unknown_posture(tmp_path, capsys):
    scenario = tmp_path / "unturned.toml"
    scenario.write_text(f'[scene]\n[[recording]]\nsource = "pmatdata"\ndir = "{PMAT}"\nsubject = 4\n'
                        f'posture = "supine"\nhold_s = 36000\n')
    out = tmp_path / "events.jsonl"
    assert main(["sim", "replay", "--scenario", str(scenario), "--hours", "10", "--out", str(out)]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    sacral = [line for line in lines if line["key"] == "pressure:sacrum" and line["kind"] == "raised"]
    assert len(sacral) == 1 and 700 <= sacral[0]["x_mm"] <= 1100
    assert posture_group(sacral[0]["posture"]) == "supine"      # S4 lying flat reads as the head raised (posture.md)
    assert [line["key"] for line in lines if line["kind"] == "raised"][:2] == ["turn:due", "turn:overdue:1"]
    assert "601 true maps (10 h)" in capsys.readouterr().err
    scenario.write_text(scenario.read_text().replace('"supine"', '"sideways"'))
    assert main(["sim", "replay", "--scenario", str(scenario), "--out", str(out)]) == 2
    assert "unknown posture 'sideways'" in capsys.readouterr().err
