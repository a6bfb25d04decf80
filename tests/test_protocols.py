"""Protocols: counts, the rules of each kind, reciprocity pairs, CSV files."""

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.protocols import (
    Protocol, adjacent_protocol, default_protocol, distributed_protocol, load_protocol, opposite_protocol,
    protocol_for, protocol_to_csv, skip_protocol,
)
from appliance.errors import DataFileInvalid, ProtocolInvalid


def touches_drive(protocol):
    r = protocol.readings
    return np.array([bool({a, b} & {c, d}) for a, b, c, d in r.tolist()])


def test_adjacent_protocol_has_208_readings_13_per_drive():
    p = adjacent_protocol(16)
    assert len(p) == 208 and len(p.drives) == 16
    assert np.all(np.bincount(p.drive_index) == 13)
    assert not touches_drive(p).any()
    assert p.readings[:3].tolist() == [[1, 2, 3, 4], [1, 2, 4, 5], [1, 2, 5, 6]]


def test_distributed_protocol_is_the_thesis_448():
    p = distributed_protocol(4, 4)
    assert len(p) == 448 and len(p.drives) == 24
    per_drive = np.bincount(p.drive_index)
    assert sorted(set(per_drive.tolist())) == [17, 18, 19, 20]
    assert not touches_drive(p).any()
    # Appendix B, projection 1 (electrodes 1-2) reads these 20 pairs, in any order.
    first = {tuple(r[2:]) for r in p.readings[p.drive_index == 0].tolist()}
    assert first == {(3, 4), (5, 6), (6, 7), (7, 8), (9, 10), (10, 11), (11, 12), (13, 14), (14, 15), (15, 16),
                     (5, 9), (9, 13), (6, 10), (10, 14), (3, 7), (7, 11), (11, 15), (4, 8), (8, 12), (12, 16)}


@pytest.mark.parametrize("protocol", [adjacent_protocol(16), distributed_protocol(4, 4),
                                      distributed_protocol(8, 16, reach=2)])
def test_every_reading_has_its_reciprocal(protocol):
    pairs = protocol.reciprocal_pairs()
    assert len(pairs) * 2 == len(protocol)
    r = protocol.readings
    assert np.array_equal(r[pairs[:, 0], :2], r[pairs[:, 1], 2:])


def test_opposite_and_skip_protocols():
    p = opposite_protocol(16)
    assert len(p.drives) == 8 and len(p) == 8 * 12
    assert all(abs(a - b) == 8 for a, b in p.drives.tolist())
    s = skip_protocol(16, 2, 0)
    assert len(s.drives) == 16 and np.all((s.drives[:, 1] - s.drives[:, 0]) % 16 == 3)
    assert not touches_drive(s).any()
    with pytest.raises(ProtocolInvalid, match="skips must be between 0 and 14"):
        skip_protocol(16, 15)


def test_local_protocol_limits_reach_and_keeps_large_mats_practical():
    full = distributed_protocol(4, 4)
    assert np.array_equal(distributed_protocol(4, 4, reach=3).readings, full.readings)
    near = distributed_protocol(4, 4, reach=1)
    assert 0 < len(near) < len(full)
    assert default_protocol(get_layout("grid-4x8@100x200")).name == "local-2", "a serial board's 32 electrodes"
    bed = default_protocol(get_layout("grid-16x32"))
    assert bed.name == "local-2-rows" and len(bed.drives) == 976, "more than a serial board: the parallel one's"
    assert len(bed) < 16000, "a 512-electrode frame must stay some ten thousand readings"
    assert len(bed) < 976 * 496 / 30


def test_rows_protocol_measures_only_along_the_rows():
    rows = protocol_for(get_layout("grid-4x8@100x200"), "rows", reach=2)
    local = protocol_for(get_layout("grid-4x8@100x200"), "local", reach=2)
    a, b, c, d = (rows.readings - 1).T
    assert np.all(d - c == 1) and np.all(c // 8 == d // 8), "every measuring pair lies along a row"
    assert np.array_equal(rows.drives, local.drives), "drives along rows and columns, as before"
    kept = {tuple(r) for r in local.readings.tolist() if (r[3] - r[2] == 1)}
    assert {tuple(r) for r in rows.readings.tolist()} == kept
    assert rows.name == "local-2-rows"
    with pytest.raises(ProtocolInvalid, match="measuring pairs must be one of all, rows"):
        distributed_protocol(4, 4, measuring="diagonal")


def test_default_protocols_per_layout():
    assert len(default_protocol(get_layout("circular-16"))) == 208
    assert len(default_protocol(get_layout("square-16"))) == 208
    assert len(default_protocol(get_layout("grid-4x4"))) == 448


def test_grid_kinds_refuse_peripheral_layouts():
    with pytest.raises(ProtocolInvalid, match="needs a grid layout"):
        protocol_for(get_layout("circular-16"), "distributed")
    with pytest.raises(ProtocolInvalid, match="unknown protocol kind 'spiral'"):
        protocol_for(get_layout("grid-4x4"), "spiral")


def test_csv_round_trip(tmp_path):
    p = distributed_protocol(4, 4)
    path = tmp_path / "p.csv"
    path.write_text(protocol_to_csv(p))
    assert protocol_to_csv(p).splitlines()[0] == "drive_pos,drive_neg,meas_pos,meas_neg"
    assert np.array_equal(load_protocol(path, 16).readings, p.readings)


@pytest.mark.parametrize(("body", "error", "message"), [
    ("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,3,17\n", ProtocolInvalid, "line 2: electrode 17 does not exist"),
    ("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,3,4\n\n5,5,3,4\n", ProtocolInvalid,
     "line 4: drive pair uses electrode 5 twice"),
    ("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,3,3\n", ProtocolInvalid,
     "line 2: measuring pair uses electrode 3 twice"),
    ("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,x,4\n", DataFileInvalid, "line 2: electrode numbers must be integers"),
    ("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,3\n", DataFileInvalid, "line 2: expected 4 values, got 3"),
    ("a,b,c,d\n1,2,3,4\n", DataFileInvalid, "line 1: header must be drive_pos,drive_neg,meas_pos,meas_neg"),
    ("drive_pos,drive_neg,meas_pos,meas_neg\n", DataFileInvalid, "no readings"),
])
def test_bad_protocol_files_name_file_and_line(tmp_path, body, error, message):
    path = tmp_path / "bad.csv"
    path.write_text(body)
    with pytest.raises(error) as err:
        load_protocol(path, 16)
    assert message in str(err.value) and "bad.csv" in str(err.value)


def test_missing_protocol_file(tmp_path):
    with pytest.raises(DataFileInvalid, match="cannot be read"):
        load_protocol(tmp_path / "none.csv", 16)


def test_protocol_object_validates_its_rows():
    with pytest.raises(ProtocolInvalid, match="reading 2: drive pair uses electrode 4 twice"):
        Protocol(np.array([[1, 2, 3, 4], [4, 4, 1, 2]]), 8)
    with pytest.raises(ProtocolInvalid, match="rows of 4 electrode numbers"):
        Protocol(np.array([[1, 2, 3]]), 8)
