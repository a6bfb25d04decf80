"""Scenario files: the built-in scenarios, electrode faults on the virtual front end, and recorded segments."""

import os
from pathlib import Path

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.drivers.scan import Flag, TechnicalCondition, saturation_condition
from appliance.errors import ConfigError, DataFileInvalid
from appliance.sim.bed import VirtualBed
from appliance.sim.body import G_M_S2, total_force_n
from appliance.sim.frontend import VirtualFrontEnd
from appliance.sim.loads import empty_mat
from appliance.sim.recordings import pmat_scene
from appliance.sim.scene_base import ElectrodeFault
from appliance.sim.scenes import builtin_scenes, load_scene, scene_from_mapping

GRID = get_layout("grid-4x4")
PROTOCOL = default_protocol(GRID)
PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"
needs_pmat = pytest.mark.skipif(not PMAT.is_dir(), reason=f"PmatData recordings not present at {PMAT}")


def test_every_builtin_scenario_loads_and_lays_a_plausible_force():
    names = builtin_scenes()
    assert {"supine-unturned", "turn-schedule", "restless", "turned-every-2h", "heel-only", "electrode-fault"} \
        <= set(names)
    for name in names:
        scene = load_scene(name)
        weight_n = scene.subject.weight_kg * G_M_S2
        for t in (0.0, scene.duration_s / 3, scene.duration_s):
            assert 0.0 <= total_force_n(scene.pressure_at(t)) <= weight_n * (1 + 1e-9), (name, t)


def test_turned_every_2h_cycles_left_supine_right_supine_for_a_day():
    scene = load_scene("turned-every-2h")
    assert scene.duration_s == 86400.0 and scene.faults == ()
    turns = [(step.start_s, step.end_s - step.start_s, step.after.posture) for step in scene.steps[1:]]
    assert [t for t, _, _ in turns] == [7200.0 * k for k in range(1, 12)]
    assert {span for _, span, _ in turns} == {20.0}
    assert [p for _, _, p in turns[:5]] == ["left-30", "supine", "right-30", "supine", "left-30"]


def test_electrode_fault_scenario_turns_and_loses_electrode_5_for_two_hours():
    scene = load_scene("electrode-fault")
    assert scene.duration_s == 28800.0
    assert scene.faults == (ElectrodeFault(3600.0, 5, False), ElectrodeFault(10800.0, 5, True))
    assert [step.after.posture for step in scene.steps] == ["supine", "left-30", "supine", "right-30"]


def empty_front_end(interval_s: float) -> VirtualFrontEnd:
    return VirtualFrontEnd(VirtualBed(GRID, empty_mat(GRID)), PROTOCOL, frame_interval_s=interval_s)


def test_the_front_end_plays_a_fault_schedule():
    front_end = empty_front_end(1800.0)
    front_end.schedule_faults(load_scene("electrode-fault").faults)
    touches_5 = (PROTOCOL.readings == 5).any(axis=1)
    for t in np.arange(0.0, 14400.0, 1800.0):
        frame = front_end.acquire()
        lost = 3600.0 <= t < 10800.0
        open_flag = (frame.flags & int(Flag.OPEN_ELECTRODE)) != 0
        assert np.array_equal(open_flag, touches_5 if lost else np.zeros_like(touches_5)), t
        assert np.isnan(frame.volts[touches_5]).all() == lost, t
        assert any(c.part == "electrode 5" for c in frame.conditions) == lost, t


def test_a_new_schedule_replaces_the_old_and_reconnects_every_electrode():
    front_end = empty_front_end(60.0)
    front_end.disconnect(3)
    front_end.schedule_faults([ElectrodeFault(0.0, 7, False), ElectrodeFault(120.0, 7, True)])
    front_end.schedule_faults([ElectrodeFault(60.0, 2, False)])
    parts = [{c.part for c in front_end.acquire().conditions} for _ in range(3)]
    assert parts == [set(), {"electrode 2"}, {"electrode 2"}]
    front_end.reconnect(2)
    assert not front_end.acquire().conditions
    with pytest.raises(ValueError, match="electrode 17 is not on this 16-electrode mat"):
        front_end.schedule_faults([ElectrodeFault(0.0, 17, False)])


def test_saturated_readings_raise_one_measuring_channel_condition():
    flags = np.zeros(len(PROTOCOL), dtype=np.int64)
    assert saturation_condition(flags, PROTOCOL) is None
    flags[[0, 1]] |= Flag.SATURATED
    condition = saturation_condition(flags, PROTOCOL)
    assert condition.part == "measuring channel" and condition.message.startswith("2 readings over range")
    front_end = empty_front_end(60.0)
    readings = front_end.chain.readings
    front_end.chain.readings = lambda transfer, protocol: (readings(transfer, protocol)[0], flags.copy())
    assert condition in front_end.acquire().conditions
    assert isinstance(condition, TechnicalCondition)


def recording_scenario(tmp_path: Path, *segments: str, extra: str = "") -> Path:
    folder = os.path.relpath(PMAT, tmp_path)
    path = tmp_path / "recorded.toml"
    path.write_text("[scene]\npitch_mm = 20\n" + extra + "".join(
        f'\n[[recording]]\nsource = "pmatdata"\ndir = "{folder}"\n{segment}\n' for segment in segments),
        encoding="utf-8")
    return path


@needs_pmat
def test_recorded_segments_play_one_after_the_other_and_hold_their_last_frame(tmp_path):
    path = recording_scenario(tmp_path, "subject = 1\nposture = 1\nhold_s = 30", "subject = 1\nposture = 2\nhold_s = 0",
                              extra="duration_s = 500\n\n[[fault]]\nat_s = 10\nelectrode = 3\nkind = 'disconnect'\n")
    scene = load_scene(path)
    first, second = (pmat_scene(PMAT, 1, posture, scene.grid) for posture in (1, 2))
    end_first = first.duration_s + 30
    assert scene.duration_s == 500.0 and scene.faults == (ElectrodeFault(10.0, 3, False),)
    assert [s["start_s"] for s in scene.info["segments"]] == [0.0, end_first]
    for t, expected in ((0.0, first.pressure_at(0.0)), (40.5, first.pressure_at(40.5)),
                        (end_first - 0.5, first.pressure_at(first.times_s[-1])),
                        (end_first + 3.2, second.pressure_at(3.2)),
                        (499.0, second.pressure_at(second.times_s[-1]))):
        assert np.array_equal(scene.pressure_at(t).pressure_kpa, expected.pressure_kpa), t
    assert not scene.changes(first.times_s[-1] + 0.5, end_first - 0.1), "held"
    assert scene.changes(end_first - 0.1, end_first + 0.1), "the second segment starts"


GOOD_SEGMENT = "subject = 1\nposture = 1\nhold_s = 0"


@needs_pmat
@pytest.mark.parametrize("segment, extra, message", [
    ("subject = 1\nposture = 18\nhold_s = 0", "", r"recording 2: posture must be a file number 1 to 17"),
    ("subject = 1\nposture = 1\nhold_s = -5", "", r"recording 2: hold_s must not be negative"),
    ("subject = '1'\nposture = 1\nhold_s = 0", "", r"recording 2: subject must be an integer"),
    ("subject = 1\nposture = 1", "", r"recording 2 is missing 'hold_s'"),
    ("subject = 1\nposture = 1\nhold_s = 0\nspeed = 2", "", r"recording 2: unknown field 'speed'"),
    ("subject = 99\nposture = 1\nhold_s = 0", "", r"recording 2: .*has no subject 99"),
    (GOOD_SEGMENT, "duration_s = 10\n", r"duration_s = 10 ends before the recordings"),
    (GOOD_SEGMENT, "weight_kg = 80\n", r"\[scene\]: unknown field 'weight_kg'"),
])
def test_bad_recorded_segments_are_refused_naming_the_segment_and_field(tmp_path, segment, extra, message):
    with pytest.raises((ConfigError, DataFileInvalid), match=message):
        load_scene(recording_scenario(tmp_path, GOOD_SEGMENT, segment, extra=extra))


def test_a_missing_data_folder_is_named_and_events_with_recordings_refused(tmp_path):
    path = tmp_path / "night.toml"
    path.write_text('[scene]\nduration_s = 60\n\n[[recording]]\nsource = "pmatdata"\ndir = "nowhere/pmat"\n'
                    'subject = 1\nposture = 1\nhold_s = 0\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"night.toml: recording 1: dir '.*nowhere/pmat' is not a folder"):
        load_scene(path)
    data = {"event": [{"at_s": 0, "kind": "lie-down"}], "recording": [{"source": "pmatdata"}]}
    with pytest.raises(ConfigError, match="either"):
        scene_from_mapping(data)
