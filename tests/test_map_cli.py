"""``appliance sim map``: pressure maps through the whole chain of the virtual bed, and every bad input refused."""

import re
import struct

import numpy as np
import pytest

from appliance.calibration import calibration_loads, pressure_calibration
from appliance.cli import main
from appliance.core.model_cache import ModelSetup, cached_model
from appliance.core.named_layouts import get_layout
from appliance.core.pressure import save_pressure_calibration
from appliance.core.protocols import default_protocol
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import empty_mat

LANDSCAPE = "grid-2x4@100x200"          # 200 mm along x, 100 mm down: the bed turns a map onto it, as on a bed


def square_map(size_mm: float, pitch_mm: float, x_mm: float, y_mm: float, side_mm: float, mmhg: float) -> np.ndarray:
    """A map ``size_mm`` wide (or (width, height)) of ``pitch_mm`` sensels holding one square load at (x, y)."""
    width, height = (size_mm, size_mm) if np.isscalar(size_mm) else size_mm
    xs = (np.arange(round(width / pitch_mm)) + 0.5) * pitch_mm
    ys = (np.arange(round(height / pitch_mm)) + 0.5) * pitch_mm
    inside = (np.abs(ys[:, None] - y_mm) < side_mm / 2) & (np.abs(xs[None, :] - x_mm) < side_mm / 2)
    return np.where(inside, mmhg, 0.0)


def write_map(path, values) -> str:
    np.savetxt(path, values, delimiter=",", fmt="%g")
    return str(path)


def sim_map(capsys, *args):
    code = main(["sim", "map", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def centre_of_peak(mmhg: np.ndarray, width_mm: float, height_mm: float) -> tuple[float, float]:
    """The centre (x, y) in mm of the highest pixel of a map covering a ``width_mm`` x ``height_mm`` mat."""
    i, j = np.unravel_index(np.nanargmax(mmhg), mmhg.shape)
    return (j + 0.5) * width_mm / mmhg.shape[1], (i + 0.5) * height_mm / mmhg.shape[0]


@pytest.fixture(scope="module")
def small(small_mat_calibration, model_cache, tmp_path_factory):
    """grid-4x4's calibration as a file, and the session's model cache: the arguments every run here shares."""
    _, calibration = small_mat_calibration
    path = tmp_path_factory.mktemp("calibration") / "grid-4x4.json"
    save_pressure_calibration(path, calibration)
    return ["--layout", "grid-4x4", "--calibration", path, "--cache-dir", model_cache]


@pytest.fixture(scope="module")
def landscape(model_cache, tmp_path_factory):
    """A calibration of the landscape mat with a reduced load set, as a file, and the arguments to use it."""
    layout = get_layout(LANDSCAPE)
    model, _ = cached_model(ModelSetup(layout, default_protocol(layout)), model_cache)
    source = VirtualBedSource(layout, empty_mat(layout), default_protocol(layout), seed=2)
    calibration = pressure_calibration(source.acquire, source.place, model,
                                       calibration_loads(layout, positions=1, pressures_kpa=(2, 5, 10, 20)))
    path = tmp_path_factory.mktemp("calibration") / "landscape.json"
    save_pressure_calibration(path, calibration)
    return ["--layout", LANDSCAPE, "--calibration", path, "--cache-dir", model_cache]


def test_each_square_comes_out_at_its_load_and_nowhere_far_from_it(small, tmp_path, capsys):
    loads = {"a": (70.0, 30.0), "b": (25.0, 75.0)}
    args = []
    for name, (x, y) in loads.items():
        args += ["--map", write_map(tmp_path / f"{name}.csv", square_map(100, 5, x, y, 20, 80)),
                 "--out", tmp_path / f"{name}-out.csv"]
    code, out, err = sim_map(capsys, *args, "--pitch-mm", "5", *small)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 2
    for line, (name, (x, y)) in zip(lines, loads.items()):
        assert re.search(rf"{name}.csv \(20 x 20 sensels of 5 mm, all on the mat\): peak 80 mmHg centred at "
                         rf"\({x:.0f}, {y:.0f}\) mm in, \d+ mmHg centred at \(\d+, \d+\) mm out", line), line
        image = np.loadtxt(tmp_path / f"{name}-out.csv", delimiter=",")
        assert image.shape == (16, 16)                               # the reconstruction's pixel grid
        px, py = centre_of_peak(image, 100, 100)
        assert np.hypot(px - x, py - y) < 10, (name, px, py)
        assert 40 < image.max() < 160                                 # 80 mmHg, through a calibrated 4-electrode mat
        yy, xx = np.mgrid[0:16, 0:16] * 6.25 + 3.125
        far = np.hypot(xx - x, yy - y) > 45
        assert image[far].max() < 0.25 * image.max(), name


def test_a_map_is_turned_onto_a_landscape_mat_and_written_back_as_given(landscape, tmp_path, capsys):
    """Rows head to foot along the mat's long side: a load near the head end, at the left, comes out there."""
    given = square_map((100, 200), 4, 30, 50, 24, 100)             # 25 x 50 sensels, rows along the 200 mm
    code, out, err = sim_map(capsys, "--map", write_map(tmp_path / "m.csv", given), "--pitch-mm", "4",
                             "--out", tmp_path / "m-out.csv", *landscape)
    assert code == 0, err
    image = np.loadtxt(tmp_path / "m-out.csv", delimiter=",")
    assert image.shape == (32, 16)                                   # the 16 x 32 pixel grid, turned back
    px, py = centre_of_peak(image, 100, 200)
    assert np.hypot(px - 30, py - 50) < 15, (px, py)
    assert "centred at (30, 50) mm in" in out


def test_a_map_larger_than_the_mat_loses_what_falls_off_and_says_how_much(small, tmp_path, capsys):
    given = np.full((24, 24), 10.0)                                  # 120 mm of 10 mmHg on the 100 mm mat
    code, out, err = sim_map(capsys, "--map", write_map(tmp_path / "big.csv", given), "--pitch-mm", "5",
                             "--out", tmp_path / "big.png", *small)
    assert code == 0, err
    assert f"{1 - 100**2 / 120**2:.1%} of its force off the mat" in out
    png = (tmp_path / "big.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", png[16:24]) == (16 * 16, 16 * 16)   # width, height: 16 pixels, 16 times enlarged


def test_one_pitch_per_map_and_comment_lines(small, tmp_path, capsys):
    path = tmp_path / "c.csv"
    path.write_text("# 10 x 10 sensels, 10 mm\n# mmHg\n" + "\n".join(
        ",".join(f"{v:g}" for v in row) for row in square_map(100, 10, 50, 50, 40, 60)) + "\n")
    fine = write_map(tmp_path / "f.csv", square_map(100, 2.5, 50, 50, 40, 60))
    code, out, err = sim_map(capsys, "--map", path, "--pitch-mm", "10", "--out", tmp_path / "c-out.csv",
                             "--map", fine, "--pitch-mm", "2.5", "--out", tmp_path / "f-out.csv", *small)
    assert code == 0, err
    assert "(10 x 10 sensels of 10 mm" in out and "(40 x 40 sensels of 2.5 mm" in out
    coarse, fine = (np.loadtxt(tmp_path / f"{n}-out.csv", delimiter=",") for n in "cf")
    assert np.abs(coarse - fine).max() < 0.15 * coarse.max()        # the same load, however finely sampled


@pytest.mark.slow
def test_the_default_bed_mat_maps_a_load_at_the_head_end_on_the_left(bed_monitoring, model_cache, tmp_path, capsys):
    """The monitor's own mat (turned: its long side runs along x), its calibration found where the monitor keeps it."""
    given = square_map((900, 1900), 25, 200, 400, 140, 90)          # 36 x 76 sensels of 25 mm
    code, out, err = sim_map(capsys, "--map", write_map(tmp_path / "bed.csv", given), "--pitch-mm", "25",
                             "--out", tmp_path / "bed-out.csv", "--cache-dir", model_cache)
    assert code == 0, err
    assert "pressure calibration loaded from" in err
    image = np.loadtxt(tmp_path / "bed-out.csv", delimiter=",")
    assert image.shape == (64, 30)                                  # 30 mm pixels, head end at row 0
    px, py = centre_of_peak(image, 900, 1900)
    assert np.hypot(px - 200, py - 400) < 60, (px, py)              # within about two pixels (30 mm)
    yy, xx = (np.mgrid[0:64, 0:30] + 0.5) * np.array([1900 / 64, 900 / 30])[:, None, None]
    assert image[np.hypot(xx - 200, yy - 400) > 500].max() < 0.3 * image.max()


GOOD = "0,0,0\n0,50,0\n0,0,0\n"


@pytest.mark.parametrize("text, message", [
    ("0,1,2\n3,4\n5,6,7\n", r"m.csv, line 2: 2 values, but the first row has 3"),
    ("0,1,2\n", r"m.csv has 1 row\(s\) of 3 value\(s\); a map needs at least 2 rows and 2 columns"),
    ("1\n2\n3\n", r"m.csv has 3 row\(s\) of 1 value\(s\)"),
    ("", r"m.csv holds no values"),
    ("# only a comment\n\n", r"m.csv holds no values"),
    ("0,1\n2,x\n", r"m.csv, line 2 \(row 1, column 1\): 'x' is not a number"),
    ("0,1\n2,\n", r"m.csv, line 2 \(row 1, column 1\): '' is not a number"),
    ("0,nan\n2,3\n", r"line 1 \(row 0, column 1\): nan is not a finite pressure"),
    ("0,1\ninf,3\n", r"line 2 \(row 1, column 0\): inf is not a finite pressure"),
    ("0,1\n2,-3\n", r"line 2 \(row 1, column 1\): -3 mmHg is negative"),
    ("0,0\n0,0\n", r"m.csv lays no force on the 100 x 100 mm mat \(it is zero everywhere"),
    ("0,0\n0,400\n", r"m.csv, row 1, column 1: 400 mmHg is beyond what the mat model accepts \(375 mmHg, 50 kPa\)"),
])
def test_a_bad_map_is_refused_naming_the_problem(tmp_path, capsys, text, message):
    (tmp_path / "m.csv").write_text(text)
    assert_refused(capsys, tmp_path, message, "--map", tmp_path / "m.csv", "--pitch-mm", "10")


@pytest.mark.parametrize("pitch, message", [
    (None, r"--pitch-mm is missing: give the maps' sensel pitch in mm \(1 to 100\)"),
    ("0", r"--pitch-mm must be a sensel pitch from 1 to 100 mm \(pressure mats' sensels are .*unit slip\), got 0.0"),
    ("-5", r"--pitch-mm must be a sensel pitch from 1 to 100 mm .*got -5.0"),
    ("2850", r"--pitch-mm must be a sensel pitch from 1 to 100 mm .*got 2850.0"),
    ("nan", r"--pitch-mm must be a sensel pitch .*got nan"),
    ("wide", r"--pitch-mm must be a number of mm, got 'wide'"),
])
def test_a_missing_or_unusable_pitch_is_refused_with_the_range_accepted(tmp_path, capsys, pitch, message):
    (tmp_path / "m.csv").write_text(GOOD)
    args = ["--map", tmp_path / "m.csv"] + ([] if pitch is None else ["--pitch-mm", pitch])
    assert_refused(capsys, tmp_path, message, *args)


def test_a_map_whose_force_all_falls_off_the_mat_is_refused(tmp_path, capsys):
    (tmp_path / "m.csv").write_text("9,0,0\n0,0,0\n0,0,0\n")        # 300 mm of 100 mm sensels: the corner is off
    assert_refused(capsys, tmp_path, r"lays no force on the 100 x 100 mm mat \(all of it falls off: 3 x 3 sensels "
                                     r"of 100 mm, centred\)", "--map", tmp_path / "m.csv", "--pitch-mm", "100")


def test_missing_files_folders_and_unknown_outputs_are_refused(tmp_path, capsys):
    good = tmp_path / "m.csv"
    good.write_text(GOOD)
    pitch = ["--pitch-mm", "10"]
    assert_refused(capsys, tmp_path, r"pressure map .*nowhere.csv does not exist", "--map", tmp_path / "nowhere.csv",
                   *pitch)
    for out, message in ((tmp_path / "no" / "o.csv", r"output .*o.csv: the folder .*no does not exist"),
                         (tmp_path / "o.txt", r"output .*o.txt: the extension must be .csv \(mmHg on the pixel grid\) "
                                              r"or .png, got '.txt'"),
                         (tmp_path / "o", r"the extension must be .csv .* got 'none'"),
                         (good, r"--out .*m.csv is one of the input maps: it would be overwritten")):
        assert_refused(capsys, tmp_path, message, "--map", good, *pitch, out=out)
    assert_refused(capsys, tmp_path, r"give one --out per --map, in their order: 2 maps, 1 outputs",
                   "--map", good, "--map", good, *pitch)
    assert_refused(capsys, tmp_path, r"one --pitch-mm for all the maps or one per --map: 3 maps, 2 pitches",
                   "--map", good, "--map", good, "--map", good, *pitch, *pitch, "--out", tmp_path / "a.csv",
                   "--out", tmp_path / "b.csv", out=tmp_path / "c.csv")
    assert_refused(capsys, tmp_path, r"--out .*a.csv is given twice", "--map", good, "--map", good, *pitch,
                   "--out", tmp_path / "a.csv", out=tmp_path / "a.csv")
    assert_refused(capsys, tmp_path, r"give at least one --map", *pitch, out=None)
    assert good.read_text() == GOOD


def test_a_calibration_for_another_mat_is_refused_before_anything_is_built(small, tmp_path, capsys):
    calibration = small[small.index("--calibration") + 1]
    kept = calibration.read_bytes()
    (tmp_path / "m.csv").write_text(GOOD)
    for path, message in ((calibration, r"the pressure calibration was made for layout 'grid-4x4', not for "
                                        r"'grid-4x4@120x120'"),
                          (tmp_path / "none.json", r"pressure calibration .*none.json does not exist")):
        assert_refused(capsys, tmp_path, message, "--map", tmp_path / "m.csv", "--pitch-mm", "10",
                       "--calibration", path, layout="grid-4x4@120x120")
    assert calibration.read_bytes() == kept
    with pytest.raises(SystemExit, match="^2$"):                     # refused as it parses, with its range
        sim_map(capsys, "--map", tmp_path / "m.csv", "--pitch-mm", "10", "--seed", "-1", "--out", tmp_path / "o.csv")
    assert "--seed: takes a whole number from 0 to 4294967295, got '-1'" in capsys.readouterr().err


def assert_refused(capsys, tmp_path, message, *args, out="default", layout="grid-4x4"):
    """Exit 2, one line on stderr matching ``message``, and the existing output left exactly as it was."""
    existing = tmp_path / "existing.csv"
    existing.write_text("written before\n")
    outputs = [] if out is None else ["--out", existing if out == "default" else out]
    code, printed, err = sim_map(capsys, *args, *outputs, "--layout", layout, "--cache-dir", tmp_path / "cache")
    assert code == 2 and printed == ""
    assert len(err.strip().splitlines()) == 1, err
    assert re.search(message, err), err
    assert err.startswith("appliance: error: ")
    assert existing.read_text() == "written before\n"
    assert not (tmp_path / "cache").exists()                          # refused before anything was built
