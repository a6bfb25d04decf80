"""Scenarios that play pressure map files (and PmatData at a given sensel size) in order, on time, through the
monitor."""

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from appliance.cli import main
from appliance.core.pressure import save_pressure_calibration
from appliance.errors import ConfigError, DataFileInvalid
from appliance.sim.body import MatGrid
from appliance.sim.field import KPA_PER_MMHG
from appliance.sim.map_scenes import load_map, place_map
from appliance.sim.recordings import PMAT_SENSEL_MM, force_n, pmat_scene
from appliance.sim.scenes import load_scene

SMALL = MatGrid(100.0, 100.0, 2.0)
SCENE = "[scene]\nwidth_mm = 100\nheight_mm = 100\npitch_mm = 2\n"
PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"
needs_pmat = pytest.mark.skipif(not PMAT.is_dir(), reason=f"PmatData recordings not present at {PMAT}")


def square(x_mm: float, y_mm: float, mmhg: float = 80.0, side_mm: float = 20.0, pitch_mm: float = 5.0) -> np.ndarray:
    """A 100 mm map of ``pitch_mm`` sensels with one square load centred at (x, y)."""
    c = (np.arange(round(100 / pitch_mm)) + 0.5) * pitch_mm
    inside = (np.abs(c[:, None] - y_mm) < side_mm / 2) & (np.abs(c[None, :] - x_mm) < side_mm / 2)
    return np.where(inside, mmhg, 0.0)


def write_maps(folder: Path, **maps) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, values in maps.items():
        np.savetxt(folder / f"{name}.csv", values, delimiter=",", fmt="%g")


def scenario(folder: Path, segment: str, head: str = SCENE, name: str = "maps.toml") -> Path:
    path = folder / name
    path.write_text(f"{head}\n[[recording]]\n{segment}\n", encoding="utf-8")
    return path


def test_maps_play_in_order_each_held_then_the_last_held_longer(tmp_path):
    write_maps(tmp_path, a=square(70, 30), b=square(25, 75), c=square(50, 50, 40))
    scene = load_scene(scenario(tmp_path, 'source = "maps"\nfiles = ["a.csv", "b.csv", "c.csv"]\npitch_mm = 5\n'
                                          'each_s = 10\nhold_s = 5'))
    placed = {n: place_map(load_map(tmp_path / f"{n}.csv"), 5.0, SMALL, n).kpa for n in "abc"}
    assert scene.duration_s == 35.0 and scene.grid == SMALL
    for t, expected in ((0.0, "a"), (9.99, "a"), (10.0, "b"), (19.99, "b"), (20.0, "c"), (29.99, "c"), (35.0, "c")):
        assert np.array_equal(scene.pressure_at(t).pressure_kpa, placed[expected]), t
    assert not scene.changes(0.0, 9.9) and not scene.changes(20.0, 35.0)
    assert scene.changes(9.9, 10.1) and scene.changes(19.9, 20.1)
    x0, y0, x1, y1 = scene.change_box_mm(9.9, 10.1)                   # both squares' places, nothing else
    assert (x0, y0, x1, y1) == (14.0, 20.0, 80.0, 86.0)
    info = scene.info["segments"][0]
    assert info["start_s"] == 0.0 and info["each_s"] == 10.0 and info["pitch_mm"] == 5.0
    assert [Path(f).name for f in info["files"]] == ["a.csv", "b.csv", "c.csv"]
    assert force_n(scene.pressure_at(0.0).pressure_kpa, 2.0) == pytest.approx(80 * KPA_PER_MMHG * 0.02**2 * 1e3)


def test_a_rate_plays_each_map_for_one_over_the_rate_and_segments_follow_each_other(tmp_path):
    write_maps(tmp_path / "maps", a=square(50, 50), b=square(25, 75))
    path = tmp_path / "night.toml"
    path.write_text(SCENE + 'duration_s = 60\n\n[[recording]]\nsource = "maps"\nfiles = ["maps/a.csv", "maps/b.csv"]\n'
                            'pitch_mm = 5\nrate_hz = 4\nhold_s = 1\n\n[[recording]]\nsource = "maps"\n'
                            'files = ["maps/a.csv"]\npitch_mm = 10\neach_s = 30\n', encoding="utf-8")
    scene = load_scene(path)
    assert scene.duration_s == 60.0
    assert [s["start_s"] for s in scene.info["segments"]] == [0.0, 1.5]
    assert list(scene.times_s) == [0.0, 0.25, 1.5]
    b = place_map(load_map(tmp_path / "maps" / "b.csv"), 5.0, SMALL, "b").kpa
    assert np.array_equal(scene.pressure_at(1.4).pressure_kpa, b)      # the last map of the first, held 1 s
    wide = scene.pressure_at(1.5).pressure_kpa                           # a at 10 mm: twice as wide
    assert force_n(wide, 2.0) == pytest.approx(4 * force_n(scene.pressure_at(0.0).pressure_kpa, 2.0))


def test_paths_resolve_from_the_scenario_file_wherever_it_is_run_from(tmp_path, monkeypatch):
    write_maps(tmp_path / "ward" / "maps", a=square(70, 30))
    scenario(tmp_path / "ward", 'source = "maps"\nfiles = ["maps/a.csv"]\npitch_mm = 5\neach_s = 60')
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    scene = load_scene("../ward/maps.toml")
    assert scene.duration_s == 60.0 and scene.pressure_at(30.0).peak_kpa == pytest.approx(80 * KPA_PER_MMHG)


@needs_pmat
def test_pmatdata_plays_at_a_given_sensel_size_before_maps(tmp_path):
    write_maps(tmp_path, a=np.full((38, 18), 20.0))                    # 900 x 1900 mm of 50 mm sensels
    folder = os.path.relpath(PMAT, tmp_path)
    path = tmp_path / "mixed.toml"
    path.write_text(f'[scene]\npitch_mm = 20\n\n[[recording]]\nsource = "pmatdata"\ndir = "{folder}"\nsubject = 1\n'
                    f'posture = 1\nhold_s = 10\npitch_mm = 25.4\n\n[[recording]]\nsource = "maps"\nfiles = ["a.csv"]\n'
                    f'pitch_mm = 50\neach_s = 100\n', encoding="utf-8")
    scene = load_scene(path)
    inch = pmat_scene(PMAT, 1, 1, scene.grid, sensel_mm=25.4)
    usual = pmat_scene(PMAT, 1, 1, scene.grid)
    first, second = scene.info["segments"]
    assert first["sensel_mm"] == 25.4 and usual.info["sensel_mm"] == PMAT_SENSEL_MM
    assert np.array_equal(scene.pressure_at(0.0).pressure_kpa, inch.pressure_at(0.0).pressure_kpa)
    assert not np.allclose(inch.pressure_at(0.0).pressure_kpa, usual.pressure_at(0.0).pressure_kpa)
    assert second["start_s"] == inch.duration_s + 10 and scene.duration_s == second["start_s"] + 100
    assert second["share_off_mat"] == [0.0]


@pytest.mark.parametrize("segment, message", [
    ('files = ["a.csv"]\neach_s = 10', r"recording 1 is missing 'pitch_mm' \(the maps' sensel pitch\)"),
    ('files = ["a.csv"]\npitch_mm = 0\neach_s = 10', r"recording 1: pitch_mm must be a sensel pitch from 1 to 100 mm"),
    ('files = ["a.csv"]\npitch_mm = "5"\neach_s = 10', r"recording 1: pitch_mm must be a sensel pitch .*got '5'"),
    ('files = ["a.csv"]\npitch_mm = 5', r"recording 1: give how long each map is held, each_s, or the rate"),
    ('files = ["a.csv"]\npitch_mm = 5\neach_s = 1\nrate_hz = 1', r"recording 1: give how long each map is held"),
    ('files = ["a.csv"]\npitch_mm = 5\neach_s = 0', r"recording 1: each_s must be positive, got 0"),
    ('files = ["a.csv"]\npitch_mm = 5\nrate_hz = -2', r"recording 1: rate_hz must be positive, got -2"),
    ('files = ["a.csv"]\npitch_mm = 5\neach_s = 1\nhold_s = -1', r"recording 1: hold_s must not be negative"),
    ('files = "a.csv"\npitch_mm = 5\neach_s = 1', r"recording 1: files must be a list of pressure map files"),
    ('files = []\npitch_mm = 5\neach_s = 1', r"recording 1: files must be a list"),
    ('files = ["a.csv", "gone.csv"]\npitch_mm = 5\neach_s = 1', r"recording 1: pressure map .*gone.csv does not exist"),
    ('files = ["bad.csv"]\npitch_mm = 5\neach_s = 1',
     r"recording 1: pressure map .*bad.csv, line 2 \(row 1, column 0\): -1 mmHg is negative"),
    ('files = ["high.csv"]\npitch_mm = 5\neach_s = 1',
     r"recording 1: pressure map .*high.csv, row 0, column 1: 500 mmHg is beyond what the mat model accepts"),
    ('files = ["zero.csv"]\npitch_mm = 5\neach_s = 1', r"recording 1: pressure map .*zero.csv lays no force on the "
                                                        r"100 x 100 mm mat"),
    ('files = ["a.csv"]\npitch_mm = 5\neach_s = 1\nspeed = 2', r"recording 1: unknown field 'speed'"),
])
def test_bad_map_segments_are_refused_naming_the_file_segment_and_field(tmp_path, segment, message):
    write_maps(tmp_path, a=square(70, 30), zero=np.zeros((3, 3)))
    (tmp_path / "bad.csv").write_text("0,1\n-1,2\n")
    (tmp_path / "high.csv").write_text("0,500\n1,2\n")
    path = scenario(tmp_path, 'source = "maps"\n' + segment)
    with pytest.raises((ConfigError, DataFileInvalid), match=rf"scenario file .*maps.toml: {message}"):
        load_scene(path)


@pytest.mark.parametrize("source, shown", [('"tekscan"', "'tekscan'"), ('["maps"]', r"\['maps'\]")])
def test_an_unknown_source_names_those_there_are(tmp_path, source, shown):
    with pytest.raises(ConfigError, match=rf"recording 1: source must be one of pmatdata, maps, got {shown}"):
        load_scene(scenario(tmp_path, f"source = {source}"))


@pytest.fixture(scope="module")
def calibration_file(small_mat_calibration, tmp_path_factory):
    path = tmp_path_factory.mktemp("calibration") / "grid-4x4.json"
    save_pressure_calibration(path, small_mat_calibration[1])
    return path


def test_the_monitor_plays_the_maps_in_order_and_on_time(calibration_file, model_cache, tmp_path, capsys):
    """``appliance run --scenario``: two frames of each map at one frame a second, each load where it lies."""
    write_maps(tmp_path, a=square(70, 30), b=square(25, 75))
    path = scenario(tmp_path, 'source = "maps"\nfiles = ["a.csv", "b.csv"]\npitch_mm = 5\neach_s = 2')
    code = main(["run", "--scenario", str(path), "--layout", "grid-4x4", "--frames", "4", "--speed", "0",
                 "--calibration", str(calibration_file), "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(model_cache)])
    out, err = capsys.readouterr()
    assert code == 0, err
    frames = re.findall(r"^0:00:0(\d)  peak .* region\(s\) >= 32 mmHg: \d+ mmHg over \d+ cm2 at \((\d+), (\d+)\) mm",
                        out, flags=re.M)
    assert [int(t) for t, _, _ in frames] == [0, 1, 2, 3], out
    for (_, x, y), (tx, ty) in zip(frames, [(70, 30), (70, 30), (25, 75), (25, 75)]):
        assert np.hypot(int(x) - tx, int(y) - ty) < 10, frames


def test_sim_run_replays_a_map_scenario(calibration_file, model_cache, tmp_path, capsys):
    write_maps(tmp_path, a=square(70, 30, mmhg=300))
    path = scenario(tmp_path, 'source = "maps"\nfiles = ["a.csv"]\npitch_mm = 5\neach_s = 18000')
    config = tmp_path / "monitor.toml"
    config.write_text(f'[monitor]\nlayout = "grid-4x4"\ncalibration = "{calibration_file}"\n'
                      f'cache_dir = "{model_cache}"\n', encoding="utf-8")
    code = main(["sim", "run", "--scenario", str(path), "--config", str(config), "--hours", "5", "--interval", "600",
                 "--out", str(tmp_path / "events.jsonl")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "31 frames (5 simulated h)" in err
    events = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    raised = [e for e in events if e["type"] == "alarm" and e["kind"] == "raised" and e["category"] == "clinical"]
    assert raised and all(e["time_s"] > 0 for e in raised)           # read at ~130 mmHg (the small mat saturates): ~4 h
