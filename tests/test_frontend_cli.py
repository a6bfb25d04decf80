"""Board profiles, board selection, and the acquire / selftest commands, run in-process."""

import warnings

import numpy as np
import pytest

from appliance.cli import main
from appliance.core.frames import load_frame
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol, protocol_to_csv
from appliance.drivers.backend import EmulationFallbackWarning, open_board
from appliance.drivers.profile import board_profile, board_table_from_file
from appliance.errors import ConfigError, DeviceMissing
from conftest import sensor_of, sensor_readings


@pytest.mark.parametrize(("table", "message"), [
    ({"profile": "nope"}, "not built in"),
    ({"gpio": {"buzzer": "GPIO5"}}, "buzzer and gain_a0 both use GPIO5"),
    ({"timing": {"drive_settle": 1.0}}, "unknown key 'drive_settle'"),
    ({"i2c": {"adc": 0x90}}, "not a 7-bit I2C address"),
    ({"timing": {"drive_settle_s": -1.0}}, "must be positive"),
    ({"spi": {"dds": {"bus": 0, "chip_select": 1, "max_speed_hz": 1000}}}, "both use spi0.1"),
    ({"channels": 32}, "does not match the adg725"),
])
def test_bad_board_tables_are_refused_with_the_key_named(table, message):
    with pytest.raises(ConfigError, match=message):
        board_profile(table)


def test_a_table_overrides_one_key_of_a_builtin_profile(tmp_path):
    path = tmp_path / "appliance.toml"
    path.write_text('[board]\nprofile = "ad5933"\n[board.timing]\ndrive_settle_s = 0.002\n')
    profile = board_profile(board_table_from_file(path))
    assert profile.name == "ad5933" and profile.timing.drive_settle_s == 0.002
    assert profile.timing.measure_settle_s == board_profile({"profile": "ad5933"}).timing.measure_settle_s


def test_the_real_board_without_hardware_names_the_missing_device():
    with pytest.raises(DeviceMissing, match="/dev/i2c-1"):
        open_board({"backend": "linux"})


def test_auto_falls_back_to_emulation_loudly():
    with pytest.warns(EmulationFallbackWarning, match="EMULATED"):
        board, profile = open_board({"backend": "auto"}, sensor=lambda: sensor_of("grid-4x4"))
    assert type(board).__name__ == "EmulatedBoard"
    with pytest.raises(ConfigError, match="backend"):
        open_board({"backend": "serial"})


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_acquire_writes_a_frame_the_sensor_agrees_with(tmp_path, capsys):
    path = tmp_path / "frame.csv"
    code, out, err = run(capsys, "acquire", "--emulated", "--layout", "grid-4x4", "--out", str(path))
    assert code == 0, err
    frame = load_frame(path, 16)
    expected = sensor_readings(sensor_of("grid-4x4"), default_protocol(get_layout("grid-4x4")), 0.004 * 64 / 127)
    assert np.all(np.abs(frame.volts - expected) <= 0.005 * np.abs(expected) + 2e-6)
    quality = (tmp_path / "frame.quality.csv").read_text().splitlines()
    assert quality[0].startswith("# sets=1 drive_current_a=2.015748e-03")
    assert quality[0].endswith("temperature_c=24.00")
    assert quality[1].startswith("drive_pos,drive_neg,meas_pos,meas_neg,measured_volts,flags,range")
    assert len(quality) == 2 + 448
    assert "448 of 448 readings usable" in err and "emulated board time" in err


def test_acquire_a_timed_series_and_an_average(tmp_path, capsys):
    code, out, err = run(capsys, "acquire", "--emulated", "--layout", "circular-16", "--series", "3",
                         "--interval", "5", "--average", "2", "--out", str(tmp_path / "run.csv"))
    assert code == 0, err
    for k in (1, 2, 3):
        assert load_frame(tmp_path / f"run-{k:03d}.csv", 16).volts.shape == (208,)
        assert (tmp_path / f"run-{k:03d}.quality.csv").read_text().startswith("# sets=2 ")
    assert "set 3/3" in err


def test_acquire_with_a_protocol_file(tmp_path, capsys):
    protocol = default_protocol(get_layout("grid-4x4"))
    short = type(protocol)(protocol.readings[:40], 16, "short")
    (tmp_path / "p.csv").write_text(protocol_to_csv(short))
    code, out, err = run(capsys, "acquire", "--emulated", "--protocol", str(tmp_path / "p.csv"), "--out",
                         str(tmp_path / "f.csv"))
    assert code == 0 and load_frame(tmp_path / "f.csv", 16).volts.shape == (40,)


def test_acquired_frames_reconstruct_the_object_where_it_is(tmp_path, capsys):
    assert run(capsys, "acquire", "--emulated", "--out", str(tmp_path / "ref.csv"))[0] == 0
    assert run(capsys, "acquire", "--emulated", "--inclusion", "disc:70,30,20,3.0",
               "--out", str(tmp_path / "obj.csv"))[0] == 0
    code, out, err = run(capsys, "reconstruct", "--layout", "grid-4x4", "--reference", str(tmp_path / "ref.csv"),
                         "--frame", str(tmp_path / "obj.csv"), "--out", str(tmp_path / "image.csv"),
                         "--cache-dir", str(tmp_path / "cache"))
    assert code == 0, err
    image = np.genfromtxt(tmp_path / "image.csv", delimiter=",")
    row, col = np.unravel_index(np.nanargmax(image), image.shape)
    pitch = 100.0 / image.shape[0]
    assert abs((col + 0.5) * pitch - 70) < 15 and abs((row + 0.5) * pitch - 30) < 15


def test_selftest_passes_on_the_emulated_board(capsys):
    code, out, err = run(capsys, "selftest", "--emulated")
    assert code == 0, out
    assert "MCP9808 thermometer" in out and "24.00 degC" in out and "open electrodes: none" in out
    assert "self-test passed" in out


def test_real_board_commands_without_hardware_fail_in_one_line(tmp_path, capsys):
    code, out, err = run(capsys, "acquire", "--out", str(tmp_path / "f.csv"))
    assert code == 3 and err.count("\n") == 1 and "/dev/i2c-1" in err          # hardware that did not answer
    code, out, err = run(capsys, "acquire", "--inclusion", "disc:50,50,20,2", "--out", str(tmp_path / "f.csv"))
    assert code == 2 and "add --emulated" in err
    with pytest.raises(SystemExit, match="^2$"):                                  # refused as it parses
        run(capsys, "acquire", "--emulated", "--series", "61", "--out", str(tmp_path / "f.csv"))
    assert "--series" in capsys.readouterr().err
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, out, err = run(capsys, "selftest", "--emulated", "--layout", "grid-8x16")
    assert code == 2 and "128 electrodes" in err and "16" in err
