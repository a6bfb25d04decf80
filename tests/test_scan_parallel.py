"""The scan engine on the emulated parallel board: steps, auto-ranging per drive, faults, adaptive frames."""

import functools

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.protocols import protocol_for
from appliance.drivers.adaptive import AdaptivePlan
from appliance.drivers.backend import emulated_board, open_front_end
from appliance.drivers.emulated.board import EmulatedBoard
from appliance.drivers.emulated.parallel import settle_time_s
from appliance.drivers.emulated.parallel_board import EmulatedParallelBoard
from appliance.drivers.emulated.sensor import ForwardSensor
from appliance.drivers.profile import board_profile
from appliance.drivers.scan import UNUSABLE, Flag, ScanEngine
from appliance.drivers.selftest import run_self_test
from appliance.errors import ConfigError, ProtocolInvalid, ScanError
from conftest import sensor_readings

LAYOUT = get_layout("grid-4x8")
PROTOCOL = protocol_for(LAYOUT, "rows", reach=2)
GRID = {"grid": {"rows": 4, "cols": 8}}


@functools.lru_cache(maxsize=4)
def mat(sheet_s: float = 0.02):
    return ForwardSensor.of_layout(LAYOUT, sheet_conductance_s=sheet_s)


def parallel(sensor=None, seed=0, **overrides):
    board = emulated_board(board_profile({"profile": "parallel", **GRID, **overrides}), sensor or mat(), seed=seed)
    return board, open_front_end(board, board.profile)


def test_the_board_follows_the_profiles_chain():
    assert type(parallel()[0]) is EmulatedParallelBoard
    assert type(emulated_board(board_profile({}), mat())) is EmulatedBoard
    with pytest.raises(ConfigError, match="parallel front end: its emulated board is EmulatedParallelBoard"):
        EmulatedBoard(board_profile({"profile": "parallel", **GRID}), mat())


def errors_in_accuracy(frame, front_end, sensor, *, measured=False):
    expected = sensor_readings(sensor, frame.protocol, frame.drive_current_a)
    accuracy = front_end.profile.accuracy
    volts = frame.measured_volts if measured else frame.volts
    return np.abs(volts - expected) / (accuracy.relative * np.abs(expected) + accuracy.absolute_v)


def test_frames_match_the_sensor_within_the_stated_accuracy():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL)
    cold, planned = engine.scan(), engine.scan()
    for frame in (cold, planned):
        assert frame.usable.all() and frame.conditions == ()
        assert np.max(errors_in_accuracy(frame, fe, mat())) <= 1.0
        expected = sensor_readings(mat(), PROTOCOL, frame.drive_current_a)
        big = np.abs(expected) > 1e-4
        assert np.array_equal(np.sign(frame.volts[big]), np.sign(expected[big]))
    assert planned.duration_s < cold.duration_s / 2          # no probing, no contact check, settling hidden


def test_each_drive_is_one_step_one_switch_transfer_and_one_sample_instant():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL)
    engine.scan()
    board.log.clear()
    frame = engine.scan()
    switch_frames = [t for t in board.log if t.kind == "spi" and t.target == "/dev/spidev0.1"]
    assert len(switch_frames) == len(PROTOCOL.drives) + 1      # one per drive, and all off for the zero
    convst = [t for t in board.log if t.kind == "gpio" and t.target == "GPIO17" and t.sent == b"\x01"]
    assert len(convst) == len(PROTOCOL.drives) + 1
    for d in range(len(PROTOCOL.drives)):
        assert len(set(frame.time_s[PROTOCOL.drive_index == d])) == 1


def test_a_step_converts_only_after_the_low_pass_has_settled():
    profile = board_profile({"profile": "parallel"})
    assert settle_time_s(profile.measurement.lowpass_hz, 1e-5) <= profile.timing.drive_settle_s
    worst = {}
    for settle_s in (profile.timing.drive_settle_s, 1e-6):       # 1e-6: the planted bug, no wait
        board, fe = parallel(timing={"drive_settle_s": settle_s})
        engine = ScanEngine(fe, PROTOCOL, contact_check=False)
        engine.scan()
        worst[settle_s] = np.max(errors_in_accuracy(engine.scan(), fe, mat(), measured=True))
    assert worst[profile.timing.drive_settle_s] <= 1.0 and worst[1e-6] > 10


def test_ranges_are_chosen_per_drive_and_readings_beyond_the_wide_one_saturate():
    board, fe = parallel(mat(0.02))
    engine = ScanEngine(fe, PROTOCOL)
    engine.scan()
    assert set(engine.scan().range_index.tolist()) == {1}          # every drive fits +/-5 V
    board, fe = parallel(mat(0.0015))                                # 13 times the readings
    engine = ScanEngine(fe, PROTOCOL, contact_check=False)
    engine.scan()
    frame = engine.scan()
    expected = sensor_readings(mat(0.0015), PROTOCOL, frame.drive_current_a)
    wide = fe.ranges[0].full_scale_input_v
    saturated = (frame.flags & int(Flag.SATURATED)) != 0
    assert saturated.any() and np.all(np.abs(expected[saturated]) > 0.9 * wide)
    assert np.isnan(frame.volts[saturated]).all()
    assert any("over range even at the lowest gain" in str(c) for c in frame.conditions)
    ok = ~saturated
    assert set(frame.range_index[ok].tolist()) == {0, 1}
    drive_peak = np.array([np.abs(expected[PROTOCOL.drive_index == d]).max() for d in PROTOCOL.drive_index])
    needs_wide = drive_peak > fe.profile.measurement.range_headroom * fe.ranges[1].full_scale_input_v * 1.02
    assert np.all(frame.range_index[ok & needs_wide] == 0)
    assert np.max(errors_in_accuracy(frame, fe, mat(0.0015))[ok]) <= 1.0


def test_a_transient_spi_error_is_retried_and_a_persistent_one_flags_that_drive_only():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL, contact_check=False)
    engine.scan()
    board.faults.fail_next("/dev/spidev1.0", 1, after=20)       # past the zero's read-out, into the steps
    frame = engine.scan()
    assert frame.usable.all() and frame.conditions == ()
    board.faults.fail_next("/dev/spidev1.0", 3, after=20)
    frame = engine.scan()
    bad = (frame.flags & int(Flag.BUS_ERROR)) != 0
    assert bad.any() and len(set(PROTOCOL.drive_index[bad].tolist())) == 1
    assert frame.usable[~bad].all()
    assert any("failed 3 times" in str(c) for c in frame.conditions)


def test_a_stuck_converter_is_named_and_its_readings_dropped():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL, contact_check=False)
    engine.scan()
    board.adcs[2].stuck_code = 1234
    frame = engine.scan()
    stuck = (frame.flags & int(Flag.STUCK)) != 0
    adc_of_reading = fe.cmap.adc_index[engine.channels, 0]
    assert np.array_equal(stuck, adc_of_reading == 2)
    assert np.isnan(frame.volts[stuck]).all() and frame.usable[~stuck].all()
    assert [str(c) for c in frame.conditions] == [
        "AD7606 2 on /dev/spidev1.0 (decoder output 2): returned code 1234 for every reading it converted: stuck"]


def test_an_open_electrode_is_found_by_the_contact_check_and_left_out():
    board, fe = parallel()
    board.chain.open_electrodes.add(11)
    frame = ScanEngine(fe, PROTOCOL).scan()
    assert frame.contact.open_electrodes == {11}
    touches = (PROTOCOL.readings == 11).any(axis=1)
    assert np.all((frame.flags[touches] & int(Flag.OPEN_ELECTRODE)) != 0)
    assert frame.usable[~touches].all()
    assert [str(c) for c in frame.conditions] == ["electrode 11: open or lost contact: its readings are left out"]


@pytest.mark.parametrize("electrode", [1, 8, 14])
def test_the_contact_check_blames_the_open_electrode_not_its_partner(electrode):
    board, fe = parallel()
    board.chain.open_electrodes.add(electrode)
    assert run_self_test(fe, 32).contact.open_electrodes == {electrode}


def test_between_contact_checks_an_open_electrode_still_never_passes_silently():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL)
    engine.scan()                                   # contact check on the first frame, then every tenth
    board.chain.open_electrodes.add(11)
    frame = engine.scan()
    assert frame.contact.open_electrodes == frozenset()
    touches = (PROTOCOL.readings == 11).any(axis=1)
    assert np.all((frame.flags[touches] & int(UNUSABLE)) != 0)
    assert frame.usable[~touches].all()
    assert any("drive pair" in str(c) or "measuring electrode(s) most involved: 11" in str(c)
               for c in frame.conditions)
    for _ in range(8):
        engine.scan()
    assert engine.scan().contact.open_electrodes == {11}          # the tenth frame checks again


def test_a_channel_whose_gain_is_wrong_breaks_reciprocity():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL, contact_check=False)
    engine.scan()
    board.errors.channel_gain[fe.cmap.channel_of(10, 11)[0]] += 0.05
    board.chain.power_on()
    frame = engine.scan()
    flagged = (frame.flags & int(Flag.RECIPROCITY)) != 0
    assert flagged.any()
    pairs = PROTOCOL.reciprocal_pairs()
    involved = {tuple(sorted(r)) for r in PROTOCOL.readings[flagged][:, 2:].tolist()}
    involved |= {tuple(sorted(r)) for r in PROTOCOL.readings[flagged][:, :2].tolist()}
    assert (10, 11) in involved and len(pairs) > 0


def test_offsets_are_measured_with_the_source_off_and_removed():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL, contact_check=False)
    for _ in range(8):
        engine.scan()
    error_v = np.abs(fe.offset_v - board.errors.offset_v)
    assert np.max(error_v) < 0.3 * np.max(np.abs(board.errors.offset_v))


def test_adaptive_frames_take_the_coarse_pass_and_fine_drives_near_the_load_and_hold_the_rest():
    board, fe = parallel()
    engine = ScanEngine(fe, PROTOCOL, contact_check=False)
    first = engine.scan(loaded=[2])                     # the first frame is a full pass whatever the caller asks
    assert (first.flags & int(Flag.HELD) == 0).all()
    full = engine.scan()
    adaptive = engine.scan(loaded=[2])
    plan = AdaptivePlan(PROTOCOL, 4, 8)
    taken = np.isin(PROTOCOL.drive_index, plan.drives_for([2]))
    held = (adaptive.flags & int(Flag.HELD)) != 0
    assert np.array_equal(held, ~taken) and held.any() and taken.any()
    assert np.isnan(adaptive.time_s[held]).all() and np.isfinite(adaptive.time_s[taken]).all()
    assert np.array_equal(adaptive.volts[held], full.volts[held]) and adaptive.usable.all()
    fine = ~np.isin(np.arange(len(PROTOCOL.drives)), plan.coarse)
    assert 0 < np.isin(np.flatnonzero(fine), plan.drives_for([2])).sum() < fine.sum()
    assert adaptive.duration_s < 0.8 * full.duration_s
    coarse = engine.scan(loaded=[])
    assert coarse.duration_s < adaptive.duration_s


def test_the_parallel_front_end_refuses_what_it_cannot_read():
    board, fe = parallel()
    with pytest.raises(ProtocolInvalid, match="only horizontally adjacent"):
        ScanEngine(fe, protocol_for(LAYOUT, "local", reach=2))
    with pytest.raises(ConfigError, match="4 x 8 grid"):
        ScanEngine(fe, protocol_for(get_layout("grid-4x4"), "rows"))
    board = emulated_board(board_profile({}), ForwardSensor.of_layout(get_layout("grid-4x4")))
    engine = ScanEngine(open_front_end(board, board.profile), protocol_for(get_layout("grid-4x4"), "rows"),
                        contact_check=False)
    engine.scan()
    with pytest.raises(ConfigError, match="adaptive frames need"):
        engine.scan(loaded=[1])


def test_converters_that_never_finish_stop_the_scan():
    board, fe = parallel()
    del board.bank.sources[board.profile.gpio["adc_busy"]]
    with pytest.raises(ScanError, match="converters do not respond"):
        ScanEngine(fe, PROTOCOL, contact_check=False).scan()


def test_the_self_test_passes_and_checks_the_switch_chain():
    board, fe = parallel()
    report = run_self_test(fe, 32)
    assert report.passed, report.text()
    parts = {c.part: c for c in report.checks}
    assert "8 chips shift a pattern through and back" in parts["ADG1414 drive switches"].detail
    assert parts["AD7606 ranges"].ok and parts["converters with the source off"].ok
    board.adcs[0].stuck_code = 77
    report = run_self_test(fe, 32)
    assert not report.passed and "stuck" in report.text()


def test_the_parallel_profile_without_its_hardware_names_the_missing_device(monkeypatch):
    """On a Pi 4B's facts (this machine's own board is unknown, so the mainline name GPIO_GCLK could not be
    placed on it), the profile fits, and opening it names the first device node that is not there."""
    from appliance.drivers.backend import open_board
    from appliance.drivers.boards import HOST_BOARDS
    from appliance.errors import DeviceMissing

    monkeypatch.setattr("appliance.drivers.board_check.running_host", lambda: HOST_BOARDS["pi4b"])
    with pytest.raises(DeviceMissing, match="/dev/i2c-1"):
        open_board({"profile": "parallel", "backend": "linux"})


def test_the_adaptive_plan_takes_fine_drives_only_near_loaded_electrodes():
    layout = get_layout("grid-16x32")
    protocol = protocol_for(layout, "rows", reach=2)
    plan = AdaptivePlan(protocol, 16, 32, radius=2)
    assert len(plan.coarse) == 16 * 31 and len(plan.fine) == 15 * 32
    taken = plan.drives_for([5 * 32 + 10 + 1])                      # row 5, column 10
    fine = np.setdiff1d(taken, plan.coarse)
    rows, cols = np.divmod(protocol.drives[fine] - 1, 32)
    near = (np.abs(rows - 5) <= 2) & (np.abs(cols - 10) <= 2)
    assert near.any(axis=1).all() and len(fine) == 6 * 5             # vertical pairs touching the 5 x 5 block
    assert np.array_equal(plan.drives_for([]), plan.coarse)
    with pytest.raises(ConfigError, match="loaded electrode 513"):
        plan.drives_for([513])


@pytest.mark.parametrize(("table", "message"), [
    ({"grid": {"rows": 16, "cols": 64}}, "128 ADCs need 7 decoder address lines"),
    ({"measurement": {"adc_oversampling": 3}}, "adc_oversampling must be one of"),
    ({"measurement": {"adc_tile_rows": 3}}, "must divide the 8 channels"),
    ({"grid": {"rows": 4, "cols": 1}}, "at least 1 row and 2 columns"),
    ({"contact": {"every_frames": 0}}, "every_frames must be at least 1"),
    ({"gpio": {"adc_convst": "GPIO_GCLK"}}, "both use GPIO_GCLK"),
])
def test_bad_parallel_profiles_are_refused_naming_the_key(table, message):
    with pytest.raises(ConfigError, match=message):
        board_profile({"profile": "parallel", **table})


def test_a_grid_on_a_serial_profile_is_refused():
    with pytest.raises(ConfigError, match=r"\[board.grid\] belongs to a parallel front end"):
        board_profile({"profile": "reference", "grid": {"rows": 4, "cols": 4}})
