"""The command line, run in-process: output formats and error messages."""

import csv
import io

import numpy as np
import pytest

from appliance.cli import main
from appliance.core.layout_files import layout_to_toml
from appliance.core.layouts import get_layout


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(("layout", "rows"), [("grid-4x4", 448), ("circular-16", 208), ("square-16", 208)])
def test_protocol_prints_header_and_rows(capsys, layout, rows):
    code, out, _ = run(capsys, "protocol", "--layout", layout)
    lines = out.splitlines()
    assert code == 0 and lines[0] == "drive_pos,drive_neg,meas_pos,meas_neg"
    assert len(lines) == rows + 1
    assert all(len(line.split(",")) == 4 for line in lines[1:])


def test_protocol_kinds(capsys):
    assert len(run(capsys, "protocol", "--layout", "circular-16", "--kind", "opposite")[1].splitlines()) == 97
    code, out, _ = run(capsys, "protocol", "--layout", "grid-4x4", "--kind", "local", "--reach", "1")
    assert code == 0 and 1 < len(out.splitlines()) < 449


def test_simulate_writes_a_frame(capsys, tmp_path):
    out_file = tmp_path / "frame.csv"
    code, out, err = run(capsys, "simulate", "--layout", "grid-4x4", "--inclusion", "rect:50,50,20,20,0.5",
                         "--current-ma", "2.5", "--out", str(out_file))
    assert code == 0 and out == ""
    assert "448 readings" in err and "24 drives" in err
    rows = list(csv.DictReader(io.StringIO(out_file.read_text())))
    assert len(rows) == 448 and list(rows[0]) == ["drive_pos", "drive_neg", "meas_pos", "meas_neg", "volts"]
    volts = np.array([float(r["volts"]) for r in rows])
    assert np.all(np.isfinite(volts)) and np.abs(volts).max() > 0


def test_simulate_scales_with_current_and_sees_the_inclusion(capsys):
    frames = {}
    for current, inclusion in (("1", []), ("2", []), ("1", ["--inclusion", "disc:50,50,30,0.2"])):
        code, out, _ = run(capsys, "simulate", "--layout", "square-16", "--model", "network",
                           "--current-ma", current, *inclusion)
        assert code == 0
        frames[current, bool(inclusion)] = np.loadtxt(io.StringIO(out), delimiter=",", skiprows=1)[:, 4]
    assert np.allclose(frames["2", False], 2 * frames["1", False])
    assert not np.allclose(frames["1", True], frames["1", False])


def test_simulate_with_a_protocol_file_and_a_custom_layout(capsys, tmp_path):
    layout_file = tmp_path / "mat.toml"
    layout_file.write_text(layout_to_toml(get_layout("grid-4x4")).replace('"grid-4x4"', '"my-mat"'))
    protocol_file = tmp_path / "p.csv"
    protocol_file.write_text("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,3,4\n6,7,10,11\n")
    code, out, _ = run(capsys, "simulate", "--layout", str(layout_file), "--protocol", str(protocol_file))
    assert code == 0 and len(out.splitlines()) == 3


@pytest.mark.parametrize(("args", "message"), [
    (["protocol", "--layout", "nope"], "unknown layout 'nope'"),
    (["protocol", "--layout", "circular-16", "--kind", "distributed"], "needs a grid layout"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "rect:1,2"], "use rect:X,Y,W,H,CONTRAST"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "disc:50,50,x,1"], "values must be numbers"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "rect:50,50,10,10,0"], "contrast must be positive"),
    (["simulate", "--layout", "grid-3x5@400x800", "--model", "network"], "do not fit one"),
])
def test_bad_input_exits_2_with_one_clear_line(capsys, args, message):
    code, out, err = run(capsys, *args)
    assert code == 2 and out == ""
    assert err.startswith("appliance: error: ") and message in err and err.count("\n") == 1


def test_layouts_and_layout_commands(capsys):
    code, out, _ = run(capsys, "layouts")
    assert code == 0 and "grid-4x4" in out and "grid-RxC" in out
    code, out, _ = run(capsys, "layout", "--layout", "square-16")
    assert code == 0 and out.startswith('name = "square-16"') and out.count("[[electrodes]]") == 16
