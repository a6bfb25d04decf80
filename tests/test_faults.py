"""Faults injected on the emulated board: each is detected, named, and the scan goes on where it can."""

import errno

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.drivers.backend import emulated_board, open_front_end
from appliance.drivers.profile import board_profile
from appliance.drivers.scan import Flag, ScanEngine
from appliance.drivers.selftest import run_self_test
from appliance.errors import ChipNotResponding, DeviceMissing, ScanError
from conftest import sensor_of, sensor_readings

PROTOCOL = default_protocol(get_layout("grid-4x4"))


def scan_with_fault_at(engine, reading_number, inject):
    """Scan once, calling ``inject()`` when ``reading_number`` readings have been taken."""
    def progress(done, total):
        if done == reading_number:
            inject()

    engine.progress = progress
    try:
        return engine.scan()
    finally:
        engine.progress = None


def usable_match_the_sensor(frame, front_end):
    expected = sensor_readings(sensor_of("grid-4x4"), PROTOCOL, frame.drive_current_a)
    ok = frame.usable
    accuracy = front_end.profile.accuracy
    assert np.all(np.abs(frame.volts[ok] - expected[ok]) <= accuracy.relative * np.abs(expected[ok])
                  + accuracy.absolute_v)


def test_a_transient_nack_is_retried_and_nothing_is_lost(emulated):
    board, front_end = emulated()
    engine = ScanEngine(front_end, PROTOCOL)
    frame = scan_with_fault_at(engine, 100, lambda: board.faults.fail_next("i2c1@0x48", 2))
    assert frame.usable.all() and frame.conditions == ()
    assert sum(1 for t in board.log if t.kind.endswith("-nack") and t.target == "i2c1@0x48") == 2
    usable_match_the_sensor(frame, front_end)


def test_a_persistent_nack_flags_that_reading_and_the_scan_goes_on(emulated):
    board, front_end = emulated()
    engine = ScanEngine(front_end, PROTOCOL, retries=3)
    frame = scan_with_fault_at(engine, 100, lambda: board.faults.fail_next("i2c1@0x48", 3))
    bad = (frame.flags & int(Flag.BUS_ERROR)) != 0
    assert bad.sum() == 1
    assert np.isnan(frame.volts[bad]).all() and frame.usable.sum() == len(PROTOCOL) - 1
    assert any("I2C bus 1 address 0x48" in str(c) and "failed 3 times" in str(c) for c in frame.conditions)
    usable_match_the_sensor(frame, front_end)


def test_an_spi_io_error_on_a_multiplexer_is_retried_then_flagged(emulated):
    board, front_end = emulated()
    engine = ScanEngine(front_end, PROTOCOL)
    engine.scan()
    frame = scan_with_fault_at(engine, 50, lambda: board.faults.fail_next("/dev/spidev1.0", 1, errno.EIO))
    assert frame.usable.all()
    frame = scan_with_fault_at(engine, 50, lambda: board.faults.fail_next("/dev/spidev1.0", 12, errno.EIO))
    flagged = (frame.flags & int(Flag.BUS_ERROR)) != 0
    assert 1 <= flagged.sum() <= 4 and frame.usable.sum() >= len(PROTOCOL) - 4
    assert any("/dev/spidev1.0" in str(c) for c in frame.conditions)
    usable_match_the_sensor(frame, front_end)


def test_a_device_file_missing_at_start_is_named():
    board = emulated_board(board_profile({}), sensor_of("grid-4x4"))
    board.faults.missing.add("/dev/spidev0.1")
    with pytest.raises(DeviceMissing, match=r"/dev/spidev0\.1"):
        open_front_end(board, board.profile)
    board.faults.missing.clear()
    open_front_end(board, board.profile)     # the failed open left no reservation behind


def test_a_stuck_adc_is_detected_and_no_reading_is_used(emulated):
    board, front_end = emulated()
    board.adc.stuck_code = 12345
    frame = ScanEngine(front_end, PROTOCOL).scan()
    assert not frame.usable.any()
    assert ((frame.flags & int(Flag.STUCK)) != 0).all()
    assert any("ADS1115 ADC at i2c1@0x48" in str(c) and "stuck" in str(c) for c in frame.conditions)
    report = run_self_test(front_end, 16)
    assert not report.passed
    assert any("stuck" in c.detail for c in report.checks if not c.ok)


def test_a_saturated_channel_is_flagged_and_the_rest_are_used(emulated):
    board, front_end = emulated()
    board.chain.pickup_v[7] = 0.05                       # interference on electrode 7's measuring input
    frame = ScanEngine(front_end, PROTOCOL, contact_check=False).scan()
    saturated = (frame.flags & int(Flag.SATURATED)) != 0
    uses_7 = (PROTOCOL.readings[:, 2:] == 7).any(axis=1)
    assert np.array_equal(saturated, uses_7)
    assert np.isnan(frame.volts[saturated]).all() and frame.usable[~uses_7].all()
    assert any("measuring electrode(s) most involved: 7" in str(c) for c in frame.conditions)
    usable_match_the_sensor(frame, front_end)


def test_an_insulating_tear_saturates_readings_across_it():
    from appliance.core.phantoms import Inclusion

    tear = (Inclusion("disc", 50, 50, 50, 50, 1e-3),)     # a near-insulating hole between the electrodes
    sensor = sensor_of("grid-4x4", tear)
    board = emulated_board(board_profile({}), sensor)
    front_end = open_front_end(board, board.profile)
    frame = ScanEngine(front_end, PROTOCOL).scan()
    saturated = (frame.flags & int(Flag.SATURATED)) != 0
    assert saturated.sum() >= 4 and np.isnan(frame.volts[saturated]).all()
    assert frame.usable.sum() == len(PROTOCOL) - saturated.sum()
    expected = sensor_readings(sensor, PROTOCOL, frame.drive_current_a)
    assert np.all(np.abs(expected[saturated]) > 0.9 * front_end.ranges[0].full_scale_input_v)
    ok = frame.usable
    assert np.all(np.abs(frame.volts[ok] - expected[ok]) <= 0.005 * np.abs(expected[ok]) + 2e-6)


def test_an_open_electrode_is_found_by_the_contact_check_and_left_out(emulated):
    board, front_end = emulated()
    board.chain.open_electrodes.add(6)
    frame = ScanEngine(front_end, PROTOCOL).scan()
    assert frame.contact.open_electrodes == {6}
    uses_6 = (PROTOCOL.readings == 6).any(axis=1)
    assert np.array_equal((frame.flags & int(Flag.OPEN_ELECTRODE)) != 0, uses_6)
    assert frame.usable[~uses_6].all() and not frame.usable[uses_6].any()
    assert any(str(c).startswith("electrode 6:") for c in frame.conditions)
    usable_match_the_sensor(frame, front_end)


def test_an_open_electrode_without_the_contact_check_still_never_passes_silently(emulated):
    board, front_end = emulated()
    board.chain.open_electrodes.add(6)
    frame = ScanEngine(front_end, PROTOCOL, contact_check=False).scan()
    uses_6 = (PROTOCOL.readings == 6).any(axis=1)
    assert not frame.usable[uses_6].any() and frame.usable[~uses_6].all()
    assert sum(str(c).startswith("drive pair") and "6" in c.part for c in frame.conditions) == 4
    assert not any("stuck" in str(c) for c in frame.conditions)
    usable_match_the_sensor(frame, front_end)


def test_an_excitation_that_cannot_start_stops_the_scan_with_the_source_off(emulated):
    board, front_end = emulated()
    engine = ScanEngine(front_end, PROTOCOL, contact_check=False)
    board.faults.fail_next("/dev/spidev0.0", 3, errno.EIO)
    with pytest.raises(ScanError, match="excitation could not be started.*spidev0.0"):
        engine.scan()
    assert board.bank.driven[board.profile.gpio["source_enable"]] == 0
    assert engine.scan().usable.all()                   # the fault cleared: the next scan works


def test_an_adc_ready_line_that_never_fires_stops_the_scan_naming_chip_and_line_with_the_source_off(emulated):
    board, front_end = emulated()
    ready = board.profile.gpio["adc_ready"]
    chip = board.bank.sources.pop(ready)                 # the ALERT/RDY wire broken
    engine = ScanEngine(front_end, PROTOCOL, contact_check=False)
    with pytest.raises(ChipNotResponding, match=rf"ADS1115\(0x48\): ALERT/RDY on {ready} did not signal"):
        engine.scan()
    assert board.bank.driven[board.profile.gpio["source_enable"]] == 0
    board.bank.connect(ready, chip)
    assert engine.scan().usable.all()                   # mended: the next scan works


def test_the_ad5933_board_survives_a_nack_too(emulated):
    board, front_end = emulated("ad5933")
    engine = ScanEngine(front_end, PROTOCOL)
    frame = scan_with_fault_at(engine, 200, lambda: board.faults.fail_next("i2c1@0x0D", 2))
    assert frame.usable.all()


def test_a_thermometer_that_does_not_answer_is_reported_and_the_frame_is_still_taken(emulated):
    board, front_end = emulated()
    board.faults.fail_next("i2c1@0x18", 3)
    frame = ScanEngine(front_end, PROTOCOL).scan()
    assert frame.temperature_c is None and frame.usable.all()
    assert any(c.part == "thermometer" and "0x18" in c.message for c in frame.conditions)
    assert ScanEngine(front_end, PROTOCOL).scan().temperature_c == 24.0
