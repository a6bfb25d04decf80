"""Frame and calibration files: round trips and errors that name the file and the line."""

import numpy as np
import pytest

from appliance.core.frames import check_same_protocol, frame_to_csv, load_calibration, load_frame
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.protocols import adjacent_protocol, default_protocol
from appliance.errors import DataFileInvalid, ProtocolInvalid

PROTOCOL = adjacent_protocol(16)


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_round_trip_with_missing_readings(tmp_path):
    volts = np.linspace(-1, 1, 208)
    volts[[3, 50]] = np.nan
    frame = load_frame(write(tmp_path, "f.csv", frame_to_csv(PROTOCOL, volts)), 16)
    assert np.array_equal(frame.protocol.readings, PROTOCOL.readings)
    assert np.allclose(frame.volts, volts, equal_nan=True, rtol=1e-9)


@pytest.mark.parametrize(("body", "error", "message"), [
    ("a,b\n", DataFileInvalid, "line 1: header must be"),
    ("drive_pos,drive_neg,meas_pos,meas_neg,volts\n1,2,3,4,0.1\n1,2,4,5,abc\n", DataFileInvalid,
     "line 3: reading 'abc' is not a number"),
    ("drive_pos,drive_neg,meas_pos,meas_neg,volts\n1,2,3,4\n", DataFileInvalid, "line 2: expected 5 values"),
    ("drive_pos,drive_neg,meas_pos,meas_neg,volts\n1,2,x,4,0.1\n", DataFileInvalid, "line 2: electrode numbers"),
    ("drive_pos,drive_neg,meas_pos,meas_neg,volts\n1,2,3,4,inf\n", DataFileInvalid, "line 2: reading 'inf'"),
    ("drive_pos,drive_neg,meas_pos,meas_neg,volts\n1,2,3,40,0.1\n", ProtocolInvalid, "line 2: electrode 40 does not"),
    ("drive_pos,drive_neg,meas_pos,meas_neg,volts\n", DataFileInvalid, "no readings"),
])
def test_bad_frames_name_file_and_line(tmp_path, body, error, message):
    with pytest.raises(error) as err:
        load_frame(write(tmp_path, "bad.csv", body), 16)
    assert message in str(err.value) and "bad.csv" in str(err.value)


def test_missing_frame_file(tmp_path):
    with pytest.raises(DataFileInvalid, match="cannot be read"):
        load_frame(tmp_path / "none.csv", 16)


def test_frames_of_different_protocols_are_refused(tmp_path):
    a = load_frame(write(tmp_path, "a.csv", frame_to_csv(PROTOCOL, np.ones(208))), 16)
    short = load_frame(write(tmp_path, "b.csv", frame_to_csv(PROTOCOL, np.ones(208)).rsplit("\n", 2)[0] + "\n"), 16)
    with pytest.raises(ProtocolInvalid, match="207 readings, reference a.csv has 208"):
        check_same_protocol(short, a, "reference a.csv")
    swapped = frame_to_csv(PROTOCOL, np.ones(208)).replace("\n1,2,4,5,", "\n1,2,5,4,", 1)
    c = load_frame(write(tmp_path, "c.csv", swapped), 16)
    with pytest.raises(ProtocolInvalid, match=r"reading 2 is \(1, 2, 5, 4\), reference a.csv has \(1, 2, 4, 5\)"):
        check_same_protocol(c, a, "reference a.csv")


def test_calibration_file(tmp_path):
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    grid = pixel_grid(layout, 2, 2)
    reference = np.linspace(1, 2, len(protocol))
    lines = ["pixel_row,pixel_col,drive_pos,drive_neg,meas_pos,meas_neg,volts"]
    for r in range(2):
        for c in range(2):
            for k, (a, b, m, n) in enumerate(protocol.readings.tolist()):
                lines.append(f"{r},{c},{a},{b},{m},{n},{reference[k] + 0.01 * (r * 2 + c + 1)}")
    s = load_calibration(write(tmp_path, "cal.csv", "\n".join(lines)), protocol, grid, reference)
    assert s.shape == (4, 448) and np.allclose(s[:, 0], [0.01, 0.02, 0.03, 0.04])
    with pytest.raises(DataFileInvalid, match=r"pixel \(1, 1\) is not calibrated"):
        load_calibration(write(tmp_path, "short.csv", "\n".join(lines[:1 + 3 * 448])), protocol, grid, reference)
    bad = lines[:2] + ["5,0," + lines[2].split(",", 2)[2]]
    with pytest.raises(DataFileInvalid, match=r"line 3: pixel \(5, 0\) is outside the 2 x 2 grid"):
        load_calibration(write(tmp_path, "far.csv", "\n".join(bad)), protocol, grid, reference)
