"""The calibrate commands and reconstruct --pressure, run in-process on the virtual bed and the emulated board."""

import contextlib
import io
import json
import re
import sys

import numpy as np
import pytest

from appliance.calibration import Load, calibration_loads
from appliance.cli import main
from appliance.core.frames import frame_to_csv, load_calibration, load_frame
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.pressure import layout_fingerprint, load_pressure_calibration
from appliance.core.protocols import default_protocol
from appliance.sim.bed import VirtualBed
from appliance.sim.frontend import VirtualFrontEnd
from appliance.sim.loads import empty_mat, placer

LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)
QUICK = ["--positions", "1", "--pressures", "2,5,10,20"]          # 12 loads instead of 84
QUICK_LOADS = calibration_loads(LAYOUT, 1, (2.0, 5.0, 10.0, 20.0))


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, err


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A pressure calibration of grid-4x4 on the virtual bed, and what the command said."""
    folder = tmp_path_factory.mktemp("calibrated")
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["calibrate", "pressure", "--layout", "grid-4x4", "--out", str(folder / "cal.json"),
                     "--cache-dir", str(folder / "cache"), *QUICK])
    assert code == 0, err.getvalue()
    return folder, err.getvalue()


def write_frames(folder, load, *, temperature_c=24.0, seed=1):
    """Reference (empty mat, 24 C) and frame (``load`` on the mat at ``temperature_c``) from the virtual bed."""
    bed = VirtualBed(LAYOUT, empty_mat(LAYOUT),
                     temperature_c=lambda t: 24.0 if t < 0.5 else temperature_c)
    front_end = VirtualFrontEnd(bed, PROTOCOL, seed=seed)
    place = placer(bed)
    place(None)
    (folder / "ref.csv").write_text(frame_to_csv(PROTOCOL, front_end.acquire().volts))
    place(load)
    (folder / "frame.csv").write_text(frame_to_csv(PROTOCOL, front_end.acquire().volts))
    return folder


def reconstruct(capsys, calibrated, frames, out, *extra):
    folder, _ = calibrated
    return run(capsys, "reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "ref.csv"),
               "--frame", str(frames / "frame.csv"), "--out", str(out), "--cache-dir", str(folder / "cache"),
               "--pressure", str(folder / "cal.json"), *extra)


def test_a_virtual_bed_calibration_is_written_and_loads(calibrated):
    folder, err = calibrated
    calibration = load_pressure_calibration(folder / "cal.json")
    calibration.check_fits(LAYOUT, "greit", (16, 16))
    assert calibration.notes["loads"] == 12 and calibration.reference_temperature_c == pytest.approx(24.0)
    curve = calibration.curve
    assert curve.change[0] == 0 and curve.pressure[0] == 0 and np.all(np.diff(curve.pressure) >= 0)
    assert 15.0 <= curve.pressure[-1] <= 20.0 and curve.change[-1] > 0.5     # the 20 kPa loads thin it by half
    first, last = QUICK_LOADS[0], QUICK_LOADS[-1]
    assert f"load 1/12: {first.side_mm:g} mm square at ({first.x_mm:g}, {first.y_mm:g}) mm, 2.0 kPa" in err
    assert f"load 12/12: {last.side_mm:g} mm square at ({last.x_mm:g}, {last.y_mm:g}) mm, 20.0 kPa" in err
    assert "from 12 loads (virtual)" in err and "read 0 to" in err


def test_reconstruct_pressure_maps_a_known_load_in_kpa(capsys, calibrated, tmp_path):
    """A pressure between the calibration's, where it put its smallest load: read to within a quarter."""
    first = QUICK_LOADS[0]
    load = Load(first.x_mm, first.y_mm, first.side_mm, 7.5)
    frames = write_frames(tmp_path, load)
    code, err = reconstruct(capsys, calibrated, frames, tmp_path / "kpa.csv")
    assert code == 0, err
    kpa = np.loadtxt(tmp_path / "kpa.csv", delimiter=",")
    assert kpa.shape == (16, 16) and np.all(kpa >= 0)
    assert load.pixel_pressure(pixel_grid(LAYOUT)).flat[np.argmax(kpa)] > 0       # the peak lies under the load
    assert kpa.max() == pytest.approx(7.5, rel=0.25)
    report = err[err.index("peak"):].splitlines()
    assert report[0] == (f"peak {kpa.max():.1f} kPa ({kpa.max() / 0.133322:.0f} mmHg); "
                         "1 region(s) at or above 32 mmHg (4.27 kPa)")
    assert report[1].startswith(f"  peak {kpa.max():.1f} kPa")
    x, y = (float(v) for v in re.search(r"centred at \((\S+), (\S+)\) mm$", report[1]).groups())
    assert np.hypot(x - first.x_mm, y - first.y_mm) < 6.25                        # within a pixel


def test_reconstruct_pressure_as_png(capsys, calibrated, tmp_path):
    frames = write_frames(tmp_path, Load(30, 70, 40, 10.0))
    code, err = reconstruct(capsys, calibrated, frames, tmp_path / "kpa.png")
    assert code == 0, err
    assert (tmp_path / "kpa.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_temperature_correction_undoes_a_cooler_frame(capsys, calibrated, tmp_path):
    """The empty mat 3 C cooler than its reference conducts 6 % less: uncorrected, the whole sheet reads as
    pressed; corrected to the calibration's temperature, almost none of it."""
    frames = write_frames(tmp_path, None, temperature_c=21.0)
    maps = {}
    for name, extra in (("cool", []), ("corrected", ["--temperature-c", "21"])):
        code, err = reconstruct(capsys, calibrated, frames, tmp_path / f"{name}.csv", *extra)
        assert code == 0, err
        maps[name] = np.loadtxt(tmp_path / f"{name}.csv", delimiter=",")
    assert (maps["cool"] > 0).mean() > 0.95 and maps["corrected"].mean() < 0.05 * maps["cool"].mean()


@pytest.mark.parametrize(("extra", "message"), [
    (["--layout", "grid-4x4@120x120"], "made for layout 'grid-4x4', not for 'grid-4x4@120x120'"),
    (["--algorithm", "gn-laplace"], "fitted to greit images of 16 x 16 pixels, not gn-laplace images"),
    (["--pixels", "8x8"], "not greit images of 8 x 8"),
    (["--normalise"], "use one or the other"),
])
def test_reconstruct_refuses_a_calibration_for_another_mat_or_reconstruction(capsys, calibrated, tmp_path,
                                                                             extra, message):
    frames = write_frames(tmp_path, Load(50, 50, 30, 5.0))
    code, err = reconstruct(capsys, calibrated, frames, tmp_path / "kpa.csv", *extra)
    assert code == 2 and message in err
    assert not (tmp_path / "kpa.csv").exists()


def test_a_calibration_for_another_layout_is_refused(capsys, calibrated, tmp_path):
    """Made for the disc, applied to the grid: both named, nothing written."""
    folder, _ = calibrated
    data = json.loads((folder / "cal.json").read_text())
    data.update(layout="circular-16", layout_sha256=layout_fingerprint(get_layout("circular-16")))
    (tmp_path / "disc.json").write_text(json.dumps(data))
    frames = write_frames(tmp_path, Load(50, 50, 30, 5.0))
    code, err = run(capsys, "reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "ref.csv"),
                    "--frame", str(frames / "frame.csv"), "--out", str(tmp_path / "kpa.csv"),
                    "--pressure", str(tmp_path / "disc.json"))
    assert code == 2 and "made for layout 'circular-16', not for 'grid-4x4'" in err
    assert not (tmp_path / "kpa.csv").exists()


def test_temperature_needs_a_pressure_calibration(capsys, tmp_path):
    frames = write_frames(tmp_path, Load(50, 50, 30, 5.0))
    code, err = run(capsys, "reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "ref.csv"),
                    "--frame", str(frames / "frame.csv"), "--out", str(tmp_path / "img.csv"),
                    "--temperature-c", "21")
    assert code == 2 and "add --pressure" in err


@pytest.fixture
def emulated_board(tmp_path):
    """A configuration whose [board] is the emulated one: the hardware path without hardware."""
    path = tmp_path / "appliance.toml"
    path.write_text('[board]\nbackend = "emulated"\n')
    return path


def test_the_operator_is_prompted_for_each_weight(capsys, monkeypatch, tmp_path, emulated_board):
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n" * 5))
    out = tmp_path / "cal.json"
    code, err = run(capsys, "calibrate", "pressure", "--layout", "grid-4x4", "--source", "hardware",
                    "--config", str(emulated_board), "--positions", "1", "--pressures", "5", "--out", str(out),
                    "--cache-dir", str(tmp_path / "cache"))
    assert code == 0, err
    prompts = [line for line in err.splitlines() if line.endswith("then press Enter")]
    squares = [f"the {load.side_mm:g} mm square centred at ({load.x_mm:g}, {load.y_mm:g}) mm"
               for load in calibration_loads(LAYOUT, 1, (5.0,))]
    assert prompts == ["Clear the mat, then press Enter",                  # 5 kPa on 9, 16 and 25 cm2
                       f"Put 459 g on {squares[0]}, then press Enter",
                       f"Put 816 g on {squares[1]}, then press Enter",
                       f"Put 1275 g on {squares[2]}, then press Enter",
                       "Clear the mat, then press Enter"]
    assert "load 3/3: 50 mm square" in err and "(hardware)" in err
    assert load_pressure_calibration(out).notes["loads"] == 3


def test_the_input_ending_aborts_and_writes_nothing(capsys, monkeypatch, tmp_path, emulated_board):
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n\n"))
    out = tmp_path / "cal.json"
    code, err = run(capsys, "calibrate", "pressure", "--layout", "grid-4x4", "--source", "hardware",
                    "--config", str(emulated_board), "--positions", "1", "--pressures", "5", "--out", str(out),
                    "--cache-dir", str(tmp_path / "cache"))
    assert code == 2 and "calibration aborted: the input ended at 'Put 816 g on the 40 mm square" in err
    assert err.count("then press Enter") == 3 and not out.exists()


def test_without_hardware_the_missing_device_is_named(capsys, tmp_path):
    """Exit status 3: hardware that did not answer, which a service manager retries (a refusal is 2)."""
    code, err = run(capsys, "calibrate", "sensitivity", "--layout", "grid-4x4", "--source", "hardware",
                    "--out", str(tmp_path / "cal.csv"))
    assert code == 3 and "/dev/" in err and not (tmp_path / "cal.csv").exists()


def test_sensitivity_round_trip_through_backprojection(capsys, tmp_path):
    """The thesis's calibration on the virtual bed, read back by reconstruct --calibration: a load shows
    in its own pixel."""
    code, err = run(capsys, "calibrate", "sensitivity", "--layout", "grid-4x4", "--pixels", "4x4",
                    "--out", str(tmp_path / "sens.csv"))
    assert code == 0, err
    assert "pixel 16/16: row 3, column 3" in err and "sensitivity of 16 pixels" in err
    frames = write_frames(tmp_path, Load(62.5, 37.5, 25, 10.0))      # the procedure's object on pixel (1, 2)
    reference, frame = (load_frame(frames / name, 16).volts for name in ("ref.csv", "frame.csv"))
    sensitivity = load_calibration(tmp_path / "sens.csv", PROTOCOL, pixel_grid(LAYOUT, 4, 4), reference)
    assert sensitivity.shape == (16, 448)
    assert np.isfinite(sensitivity).mean() > 0.9           # the rest: readings the front end flagged unusable
    change = frame - reference
    match = [np.corrcoef(row[both], change[both])[0, 1] for row in sensitivity
             for both in [np.isfinite(row) & np.isfinite(change)]]
    assert np.argmax(match) == 1 * 4 + 2 and max(match) > 0.99
    code, err = backproject(capsys, frames, tmp_path / "sens.csv")
    assert code == 0, err


def test_backprojection_with_the_virtual_beds_sensitivity_gives_an_image(capsys, tmp_path):
    code, err = run(capsys, "calibrate", "sensitivity", "--layout", "grid-4x4", "--pixels", "4x4",
                    "--out", str(tmp_path / "sens.csv"))
    assert code == 0, err
    frames = write_frames(tmp_path, Load(62.5, 37.5, 25, 10.0))
    code, err = backproject(capsys, frames, tmp_path / "sens.csv")
    assert code == 0, err
    image = np.loadtxt(frames / "bp.csv", delimiter=",")
    assert np.isfinite(image).all()


def backproject(capsys, frames, sensitivity):
    return run(capsys, "reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "ref.csv"),
               "--frame", str(frames / "frame.csv"), "--out", str(frames / "bp.csv"), "--pixels", "4x4",
               "--algorithm", "backprojection", "--calibration", str(sensitivity),
               "--cache-dir", str(frames / "cache"))


def test_the_emulated_board_measures_the_loads_on_the_virtual_bed(capsys, tmp_path):
    """The real scan path sees what the whole-frame chain sees: the same object, pixel by pixel."""
    for source in ("virtual", "emulated"):
        code, err = run(capsys, "calibrate", "sensitivity", "--layout", "grid-4x4", "--pixels", "2x2",
                        "--side-mm", "30", "--source", source, "--out", str(tmp_path / f"{source}.csv"))
        assert code == 0, err
    grid, raw = pixel_grid(LAYOUT, 2, 2), np.zeros(len(PROTOCOL))
    virtual, emulated = (load_calibration(tmp_path / f"{s}.csv", PROTOCOL, grid, raw)
                         for s in ("virtual", "emulated"))
    for k in (1, 2, 3):                    # the object moved from pixel (0, 0) to each other pixel
        v, e = virtual[k] - virtual[0], emulated[k] - emulated[0]
        both = np.isfinite(v) & np.isfinite(e)
        assert both.sum() > 350 and np.corrcoef(v[both], e[both])[0, 1] > 0.999
        assert np.sum(e[both] * v[both]) / np.sum(v[both] ** 2) == pytest.approx(1.0, abs=0.01)
