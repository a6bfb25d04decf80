"""The command line, run in-process: output formats and error messages."""

import csv
import io

import numpy as np
import pytest

from appliance.cli import main
from appliance.core.layout_files import layout_to_toml
from appliance.core.named_layouts import get_layout


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


def test_scenarios_lists_every_built_in_scenario_a_line_each_that_run_accepts(capsys):
    from appliance.sim.scenes import builtin_scenes, load_scene

    code, out, _ = run(capsys, "scenarios")
    lines = out.splitlines()
    assert code == 0 and [line.split()[0] for line in lines] == list(builtin_scenes())
    assert all(len(line.split(None, 1)) == 2 for line in lines), "each with its description"
    assert "restless" in out and "turn-schedule" in out
    for name in builtin_scenes():
        load_scene(name)                        # each name listed is one --scenario takes


@pytest.fixture
def frames(tmp_path, capsys):
    """A reference and a frame with a pressed square, simulated on a finer mesh than the model's."""
    for name, extra in (("ref.csv", []), ("frame.csv", ["--inclusion", "rect:35,60,20,20,0.6"])):
        assert main(["simulate", "--layout", "grid-4x4", "--density", "2", "--current-ma", "2.5",
                     "--out", str(tmp_path / name), *extra]) == 0
    capsys.readouterr()
    return tmp_path


def reconstruct(capsys, frames, *extra):
    code = main(["reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "ref.csv"),
                 "--frame", str(frames / "frame.csv"), "--cache-dir", str(frames / "cache"), *extra])
    out, err = capsys.readouterr()
    return code, err


def test_reconstruct_writes_a_csv_image_with_the_load_where_it_was(capsys, frames):
    code, err = reconstruct(capsys, frames, "--out", str(frames / "img.csv"))
    assert code == 0 and "16 x 16 pixels" in err and "448 of 448 readings used" in err
    image = np.loadtxt(frames / "img.csv", delimiter=",")
    assert image.shape == (16, 16)
    r, c = np.unravel_index(np.argmin(image), image.shape)
    assert abs((c + 0.5) * 6.25 - 35) <= 6.25 and abs((r + 0.5) * 6.25 - 60) <= 6.25 and image.min() < -0.2
    code, err = reconstruct(capsys, frames, "--out", str(frames / "again.csv"))
    assert "model loaded" in err


def test_reconstruct_png_normalised_and_segmented(capsys, frames):
    code, _ = reconstruct(capsys, frames, "--out", str(frames / "img.png"), "--algorithm", "gn-laplace",
                          "--segment", str(frames / "seg.csv"))
    assert code == 0 and (frames / "img.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    labels = np.loadtxt(frames / "seg.csv", delimiter=",")
    assert labels.shape == (256, 256) and set(np.unique(labels)) <= {0, 1, 2}
    code, _ = reconstruct(capsys, frames, "--out", str(frames / "n.csv"), "--normalise")
    image = np.loadtxt(frames / "n.csv", delimiter=",")
    assert image.min() == 0 and image.max() == 100


def test_reconstruct_backprojection_with_an_experimental_calibration(capsys, frames):
    """The thesis's calibration, simulated: the rod at every pixel in turn, a frame each."""
    from appliance.core.fem import build_fem_model
    from appliance.core.forward import simulate
    from appliance.core.named_layouts import get_layout
    from appliance.core.phantoms import Inclusion, conductivity
    from appliance.core.protocols import default_protocol

    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    model = build_fem_model(layout, density=2)
    lines = ["pixel_row,pixel_col,drive_pos,drive_neg,meas_pos,meas_neg,volts"]
    for r in range(16):
        for c in range(16):
            rod = Inclusion("rect", (c + 0.5) * 6.25, (r + 0.5) * 6.25, 6.25, 6.25, 1e-3)
            v = simulate(model, conductivity(model, [rod]), protocol, current_a=2.5e-3)
            lines += [f"{r},{c},{a},{b},{m},{n},{x:.9e}" for (a, b, m, n), x in zip(protocol.readings.tolist(), v)]
    (frames / "cal.csv").write_text("\n".join(lines) + "\n")
    code, err = reconstruct(capsys, frames, "--out", str(frames / "bp.csv"), "--algorithm", "backprojection",
                            "--calibration", str(frames / "cal.csv"))
    assert code == 0, err
    image = np.loadtxt(frames / "bp.csv", delimiter=",")
    assert np.isfinite(image).all() and image.min() < 0


@pytest.mark.parametrize(("change", "message"), [
    (lambda text: text.rsplit("\n", 2)[0] + "\n", "447 readings, reference"),
    (lambda text: text.replace("1,2,3,4,", "1,2,3,4,x", 1), "line 2: reading"),
    (lambda text: text.replace("\n1,2,3,4,", "\n1,2,3,40,", 1), "line 2: electrode 40 does not exist"),
])
def test_reconstruct_refuses_bad_frames_naming_file_and_line(capsys, frames, change, message):
    text = (frames / "frame.csv").read_text()
    (frames / "frame.csv").write_text(change(text))
    code, err = reconstruct(capsys, frames, "--out", str(frames / "img.csv"))
    assert code == 2 and message in err and err.count("\n") == 1


def test_reconstruct_refuses_missing_files_and_mat_files_for_other_layouts(capsys, frames):
    code = main(["reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "none.csv"), "--frame",
                 str(frames / "frame.csv"), "--out", str(frames / "x.csv")])
    assert code == 2 and "none.csv: cannot be read" in capsys.readouterr().err
    code = main(["reconstruct", "--layout", "grid-4x4", "--reference", str(frames / "r.mat"), "--frame",
                 str(frames / "f.mat"), "--out", str(frames / "x.csv")])
    assert code == 2 and "use --layout ktc-32" in capsys.readouterr().err


def test_reconstruct_refuses_an_all_missing_frame(capsys, frames):
    lines = (frames / "frame.csv").read_text().splitlines()
    (frames / "frame.csv").write_text("\n".join([lines[0]] + [l.rsplit(",", 1)[0] + ",nan" for l in lines[1:]]))
    code, err = reconstruct(capsys, frames, "--out", str(frames / "img.csv"))
    assert code == 2 and "nothing can be reconstructed" in err


@pytest.mark.parametrize("error, status", [("DeviceMissing", 3), ("ChipNotResponding", 3), ("DataFileInvalid", 2)])
def test_hardware_that_does_not_answer_exits_3_and_a_refusal_2(capsys, monkeypatch, error, status):
    """The service manager starts the monitor again after 3 (a device not ready at boot), not after 2."""
    import appliance.cli
    import appliance.errors

    def fails(args):
        raise getattr(appliance.errors, error)("spidev0.0 did not answer")

    parser = appliance.cli._parser()
    monkeypatch.setattr(appliance.cli, "_parser", lambda: parser)
    monkeypatch.setattr(parser, "parse_args", lambda argv: type("Args", (), {"run": staticmethod(fails)})())
    assert main(["layouts"]) == status
    assert capsys.readouterr().err.strip() == "appliance: error: spidev0.0 did not answer"
