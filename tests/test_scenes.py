"""Scenes: timelines of the body on the mat, their change boxes, and scenario files."""

import copy

import numpy as np
import pytest

from appliance.errors import ConfigError, ModelInputInvalid
from appliance.sim.body import (G_M_S2, MatGrid, Placement, Subject, body_field, body_patches, outline_box_mm,
                                total_force_n)
from appliance.sim.scene_base import ElectrodeFault
from appliance.sim.scenes import builtin_scenes, load_scene, scene_from_mapping

LIE = {"at_s": 0, "kind": "lie-down", "posture": "supine", "x_mm": 450, "y_mm": 80}


FAULT = {"at_s": 60, "electrode": 5, "kind": "disconnect"}


def scenario(*events, **scene):
    return {"scene": {"duration_s": 600, **scene}, "event": [dict(LIE), *events]}


def test_builtin_scenarios_load_and_run():
    names = builtin_scenes()
    assert {"supine-still", "turn-schedule", "restless", "head-raised", "leaves-bed"} <= set(names)
    for name in names:
        scene = load_scene(name)
        weight_n = scene.subject.weight_kg * G_M_S2
        for t in np.linspace(0.0, scene.duration_s, 13):
            force = total_force_n(scene.pressure_at(t))
            assert -1e-9 <= force <= weight_n * (1 + 1e-9), f"{name} at {t:g} s: {force:.6g} N"
        assert scene.changes(0.0, scene.duration_s), name


def test_still_scene_does_not_change():
    scene = load_scene("supine-still")
    assert not scene.changes(60.0, 7000.0)
    assert scene.change_box_mm(60.0, 7000.0) is None
    assert scene.changes(0.0, 5.0), "the lie-down is a change"
    assert np.array_equal(scene.pressure_at(60.0).pressure_kpa, scene.pressure_at(7000.0).pressure_kpa)


def test_shift_changes_inside_a_sensible_box():
    scene = scene_from_mapping(scenario({"at_s": 100, "kind": "shift", "dx_mm": 30, "rotation_deg": 2,
                                         "transition_s": 2}))
    assert not scene.changes(20.0, 99.0)
    box = scene.change_box_mm(99.0, 103.0)
    assert box is not None
    before = outline_box_mm(Subject(), Placement(x_mm=450.0, y_mm=80.0))
    after = outline_box_mm(Subject(), Placement(x_mm=480.0, y_mm=80.0, rotation_deg=2.0))
    union = (min(before[0], after[0]), min(before[1], after[1]), max(before[2], after[2]), max(before[3], after[3]))
    assert union[0] - 10 <= box[0] and union[1] - 10 <= box[1], (box, union)
    assert box[2] <= union[2] + 10 and box[3] <= union[3] + 10, (box, union)
    assert box[2] - box[0] > 500 and box[3] - box[1] > 1500, f"the whole body moved: {box}"
    later = scene.pressure_at(200.0).pressure_kpa
    assert np.allclose(later, body_field(Subject(), Placement(x_mm=480.0, y_mm=80.0, rotation_deg=2.0)).pressure_kpa)


def test_turn_blends_and_ends_in_the_target_posture():
    scene = scene_from_mapping(scenario({"at_s": 100, "kind": "turn", "posture": "left-30", "transition_s": 20}))
    supine = body_field(Subject(), Placement("supine", 450.0, 80.0)).pressure_kpa
    left = body_field(Subject(), Placement("left-30", 450.0, 80.0)).pressure_kpa
    assert np.allclose(scene.pressure_at(110.0).pressure_kpa, 0.5 * (supine + left))
    assert np.allclose(scene.pressure_at(125.0).pressure_kpa, left)
    for t in (100.0, 105.0, 119.0, 500.0):
        assert abs(total_force_n(scene.pressure_at(t)) / (75 * G_M_S2) - 1) < 1e-9
    assert scene.changes(105.0, 106.0) and not scene.changes(121.0, 600.0)


def test_leaving_the_bed_gives_zero_and_return_restores():
    scene = load_scene("leaves-bed")
    assert scene.pressure_at(3700.0).peak_kpa == 0.0
    assert scene.pressure_at(3602.5).peak_kpa > 0.0, "halfway through getting up"
    assert np.array_equal(scene.pressure_at(3000.0).pressure_kpa, scene.pressure_at(5000.0).pressure_kpa)
    assert scene.changes(3000.0, 5000.0), "left and came back: still a change"
    assert not scene.changes(3700.0, 4400.0)


def test_empty_before_the_first_event_and_times_checked():
    scene = scene_from_mapping({"scene": {"duration_s": 100}, "event": [dict(LIE, at_s=10, transition_s=0)]})
    assert scene.pressure_at(5.0).peak_kpa == 0.0 and scene.pressure_at(10.0).peak_kpa > 0.0
    with pytest.raises(ModelInputInvalid, match="outside the scene"):
        scene.pressure_at(101.0)
    with pytest.raises(ModelInputInvalid, match="backwards"):
        scene.changes(50.0, 40.0)


BAD = [
    ({"extra": 1}, "unknown field 'extra'"),
    ({"scene": {"pitch": 10}}, r"\[scene\]: unknown field 'pitch'"),
    ({"scene": {"surface": "water"}}, "surface"),
    ({"scene": {"weight_kg": -3}}, "weight_kg"),
    ({"event": [dict(LIE, speed=3)]}, r"event 1 \(lie-down\): unknown field 'speed'"),
    ({"event": [dict(LIE, kind="jump")]}, "event 1: kind must be one of"),
    ({"event": [dict(LIE, at_s=-1)]}, r"event 1 \(lie-down\): at_s must not be negative"),
    ({"event": [dict(LIE, at_s=100), {"at_s": 50, "kind": "leave"}]}, r"event 2 \(leave\): at_s = 50 comes before"),
    ({"event": [dict(LIE), {"at_s": 5, "kind": "turn", "posture": "left-30"}]}, r"event 2 \(turn\): at_s = 5"),
    ({"event": [dict(LIE, x_mm=1200)]}, r"event 1 \(lie-down\): x_mm = 1200 puts the body off"),
    ({"event": [dict(LIE, y_mm=-40)]}, r"event 1 \(lie-down\): y_mm = -40"),
    ({"event": [dict(LIE, x_mm=200)]}, r"event 1 \(lie-down\): .*off the 900 x 1900 mm mat"),
    ({"event": [dict(LIE), {"at_s": 60, "kind": "shift", "dx_mm": 600}]}, r"event 2 \(shift\): x_mm = 1050"),
    ({"event": [dict(LIE), {"at_s": 60, "kind": "lie-down"}]}, r"event 2 \(lie-down\): the bed is occupied"),
    ({"event": [{"at_s": 0, "kind": "turn", "posture": "left-30"}]}, r"event 1 \(turn\): the bed is empty"),
    ({"event": [dict(LIE), {"at_s": 60, "kind": "turn", "posture": "prone"}]}, r"event 2 \(turn\): posture"),
    ({"event": [dict(LIE), {"kind": "leave"}]}, r"event 2 \(leave\) is missing 'at_s'"),
    ({"event": [dict(LIE, x_mm="middle")]}, r"event 1 \(lie-down\): x_mm must be a finite number"),
    ({"event": [dict(LIE), {"at_s": 60, "kind": "still", "duration_s": 0}]}, r"event 2 \(still\): duration_s"),
    ({"scene": {"duration_s": 5}}, r"\[scene\] duration_s = 5 ends before"),
    ({"scene": {"sites": ["heel-left", "tail"]}}, r"\[scene\]: unknown site 'tail': use one of .*heel-right"),
    ({"scene": {"sites": []}}, r"\[scene\]: no site on the mat"),
    ({"scene": {"sites": "heel-left"}}, r"\[scene\] sites must be a list"),
    ({"fault": [FAULT, dict(FAULT, kind="break")]}, "fault 2: kind must be one of disconnect, reconnect"),
    ({"fault": [dict(FAULT, at_s=-1)]}, "fault 1: at_s must not be negative"),
    ({"fault": [dict(FAULT, wire=3)]}, "fault 1: unknown field 'wire'"),
    ({"fault": [dict(FAULT, electrode=0)]}, "fault 1: electrode must be an electrode number"),
    ({"fault": [dict(FAULT, electrode=2.0)]}, "fault 1: electrode must be"),
    ({"fault": [dict(FAULT, electrode=True)]}, "fault 1: electrode must be"),
    ({"fault": [{"electrode": 5, "kind": "disconnect"}]}, "fault 1 is missing 'at_s'"),
    ({"fault": [dict(FAULT, at_s=601)]}, "fault at 601 s comes after the scene's end"),
]


@pytest.mark.parametrize("change, message", BAD, ids=[m[:30] for _, m in BAD])
def test_bad_scenarios_are_refused_naming_the_event_and_field(change, message):
    data = copy.deepcopy(scenario())
    for key, value in change.items():
        if key == "scene":
            data["scene"].update(value)
        else:
            data[key] = value
    with pytest.raises(ConfigError, match=message):
        scene_from_mapping(data)


def test_scenario_file_errors_name_the_file(tmp_path):
    path = tmp_path / "night.toml"
    path.write_text('[scene]\nduration_s = 60\n\n[[event]]\nat_s = -2\nkind = "lie-down"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"night.toml: event 1 \(lie-down\): at_s"):
        load_scene(path)
    with pytest.raises(ConfigError, match="does not exist"):
        load_scene(tmp_path / "missing.toml")
    path.write_text('[scene]\nwidth_mm = 1000\nheight_mm = 2000\npitch_mm = 20\nduration_s = 60\n\n'
                    '[[event]]\nat_s = 0\nkind = "lie-down"\nposture = "right-30"\n', encoding="utf-8")
    scene = load_scene(path)
    assert scene.grid == MatGrid(1000.0, 2000.0, 20.0) and scene.pressure_at(30.0).pressure_kpa.shape == (100, 50)


def _cell(patch, placement: Placement, pitch_mm: float = 10.0) -> tuple[int, int]:
    """(row, col) under a supine, unrotated patch's centre."""
    return int((placement.y_mm + patch.s) // pitch_mm), int((placement.x_mm + patch.u) // pitch_mm)


def test_heel_only_field_keeps_the_heels_at_their_whole_body_pressures():
    subject, placement = Subject(), Placement("supine").on(MatGrid(), Subject())
    heels = body_field(subject, placement, sites={"heel-left", "heel-right"}).pressure_kpa
    whole = body_field(subject, placement).pressure_kpa
    patches = {p.site: p for p in body_patches(subject, "supine")}
    for site in ("sacrum", "occiput", "scapula-left", "buttock-right"):
        assert heels[_cell(patches[site], placement)] == 0.0, site
    assert whole[_cell(patches["sacrum"], placement)] > 3.0
    for site in ("heel-left", "heel-right"):
        row, col = _cell(patches[site], placement)
        near = np.s_[row - 3:row + 4, col - 3:col + 4]
        assert heels[near].max() == pytest.approx(whole[near].max(), rel=0.01), site
    share = total_force_n(body_field(subject, placement, sites={"heel-left", "heel-right"})) / (75 * G_M_S2)
    assert 0.01 < share < 0.1, f"the heels carry a small share of the weight, not all of it: {share:.3f}"
    assert total_force_n(body_field(subject, placement)) == pytest.approx(75 * G_M_S2, rel=1e-12), \
        "the whole-body field is unchanged by an earlier field limited to some sites"


def test_heel_only_scenario_is_the_heel_field_all_night():
    scene = load_scene("heel-only")
    expected = body_field(scene.subject, Placement("supine"), sites={"heel-left", "heel-right"}).pressure_kpa
    assert scene.sites == {"heel-left", "heel-right"}
    assert np.array_equal(scene.pressure_at(3600.0).pressure_kpa, expected)
    assert not scene.changes(60.0, scene.duration_s)


def test_faults_are_parsed_and_sorted_by_time():
    data = scenario()
    data["fault"] = [{"at_s": 300, "electrode": 5, "kind": "reconnect"}, FAULT,
                     {"at_s": 300, "electrode": 7, "kind": "disconnect"}]
    scene = scene_from_mapping(data)
    assert scene.faults == (ElectrodeFault(60.0, 5, False), ElectrodeFault(300.0, 5, True),
                            ElectrodeFault(300.0, 7, False))
    assert load_scene("supine-still").faults == ()
