"""The scan engine on the emulated boards: readings against the sensor, auto-ranging, ordering, frame time."""

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.drivers.scan import UNUSABLE, Flag, ScanEngine, average_frames
from conftest import sensor_of, sensor_readings

FULL_SCALE_FLOOR = 0.4   # after auto-ranging every reading uses at least this share of its range ...
ABSOLUTE_FLOOR = 0.2     # ... unless it is already at the most sensitive range, and never less than this


def check_against_sensor(frame, front_end, sensor):
    """Every reading usable, none saturated, within the profile's stated accuracy of the sensor."""
    expected = sensor_readings(sensor, frame.protocol, frame.drive_current_a)
    accuracy = front_end.profile.accuracy
    allowed = accuracy.relative * np.abs(expected) + accuracy.absolute_v
    assert frame.usable.all(), [str(c) for c in frame.conditions]
    assert not (frame.flags & int(Flag.SATURATED)).any()
    worst = np.max(np.abs(frame.volts - expected) / allowed)
    assert worst <= 1.0, f"worst reading off by {worst:.2f} of the stated accuracy"
    most_sensitive = frame.range_index == len(front_end.ranges) - 1
    assert np.all((frame.fraction >= FULL_SCALE_FLOOR) | most_sensitive), frame.fraction.min()
    assert frame.fraction.min() >= ABSOLUTE_FLOOR
    return worst


@pytest.mark.parametrize(("profile", "layout"), [("reference", "grid-4x4"), ("reference", "circular-16"),
                                                  ("ad5933", "grid-4x4"), ("ad5933", "circular-16")])
def test_frames_match_the_sensor_within_the_stated_accuracy(emulated, profile, layout):
    board, front_end = emulated(profile, layout)
    protocol = default_protocol(get_layout(layout))
    engine = ScanEngine(front_end, protocol)
    cold = engine.scan()          # ranging by probe
    planned = engine.scan()       # ranging from the first frame's plan
    for frame in (cold, planned):
        check_against_sensor(frame, front_end, sensor_of(layout))
        assert frame.conditions == ()
        assert frame.contact is not None and not frame.contact.open_electrodes
    assert planned.duration_s < cold.duration_s


def test_the_sign_of_every_reading_follows_the_sensor(emulated):
    board, front_end = emulated("reference", "grid-4x4")
    protocol = default_protocol(get_layout("grid-4x4"))
    frame = ScanEngine(front_end, protocol).scan()
    expected = sensor_readings(sensor_of("grid-4x4"), protocol, frame.drive_current_a)
    assert np.array_equal(np.sign(frame.volts), np.sign(expected))


@pytest.mark.parametrize(("profile", "target_s"), [("reference", 3.0), ("ad5933", 1.5)])
def test_frame_time_meets_the_target_and_ordering_saves_time(emulated, profile, target_s):
    protocol = default_protocol(get_layout("grid-4x4"))
    times = {}
    for order in ("optimised", "protocol"):
        board, front_end = emulated(profile)
        engine = ScanEngine(front_end, protocol, order=order)
        engine.scan()
        times[order] = engine.scan().duration_s
    assert times["optimised"] <= target_s, times
    assert times["optimised"] <= times["protocol"], times


def test_the_optimised_order_takes_each_drive_once_with_rising_levels(emulated):
    board, front_end = emulated()
    protocol = default_protocol(get_layout("grid-4x4"))
    engine = ScanEngine(front_end, protocol)
    engine.scan()
    order = engine.reading_order()
    drives = protocol.drive_index[order]
    blocks = drives[np.r_[True, drives[1:] != drives[:-1]]]
    assert len(blocks) == len(protocol.drives) == len(set(blocks.tolist()))
    level = engine._planned_output()[order]
    for d in set(blocks.tolist()):
        assert np.all(np.diff(level[drives == d]) >= 0)


def test_reading_before_the_rms_converter_settles_gives_the_wrong_value(emulated):
    board, front_end = emulated()
    front_end.start_excitation()
    first, second = (3, 4), (5, 6)              # 3.9 mV and 18 mV with current into 1 and out of 2
    front_end.set_range(0)

    def after(pair, wait_s):
        front_end.mux.select((1, 2), pair)
        board.clock.sleep(wait_s)
        return front_end.sample()

    settled = after(second, 0.05).volts
    after(first, 0.05)
    early = after(second, 0.0).volts
    assert abs(early / settled - 1) > 0.01
    level = (0, abs(after(first, 0.05).volts) / front_end.ranges[0].full_scale_input_v)
    target = (0, abs(settled) / front_end.ranges[0].full_scale_input_v)
    wait = front_end.settle_s(False, True, level, target)
    assert 1e-3 < wait < 5e-3
    assert abs(after(second, wait).volts / settled - 1) < 2e-4


def test_an_object_on_the_mat_changes_the_readings_as_the_sensor_predicts(emulated):
    inclusion = ("disc:50,50,30,0.3",)
    from appliance.cli_args import parse_inclusion

    inclusions = tuple(parse_inclusion(text) for text in inclusion)
    board, front_end = emulated("reference", "grid-4x4", inclusions=inclusions)
    protocol = default_protocol(get_layout("grid-4x4"))
    frame = ScanEngine(front_end, protocol).scan()
    worst = check_against_sensor(frame, front_end, sensor_of("grid-4x4", inclusions))
    assert worst <= 1.0
    plain = sensor_readings(sensor_of("grid-4x4"), protocol, frame.drive_current_a)
    assert np.max(np.abs(frame.volts - plain) / np.abs(plain)) > 0.05


def test_averaging_sets_reduces_the_noise(emulated):
    board, front_end = emulated()
    board.chain.errors.input_noise_v = 1e-6
    protocol = default_protocol(get_layout("grid-4x4"))
    engine = ScanEngine(front_end, protocol, contact_check=False)
    engine.scan()
    sets = np.array([engine.scan().measured_volts for _ in range(32)])
    single = sets.std(axis=0)
    averaged = sets.reshape(8, 4, -1).mean(axis=1).std(axis=0)
    assert average_frames([engine.scan() for _ in range(4)]).sets == 4
    assert 0.35 < np.median(averaged / single) < 0.65      # 1/sqrt(4) = 0.5 expected


def test_averaging_keeps_a_reading_usable_in_some_sets_and_drops_one_usable_in_none(emulated):
    board, front_end = emulated()
    protocol = default_protocol(get_layout("grid-4x4"))
    engine = ScanEngine(front_end, protocol, contact_check=False)
    first, second = engine.scan(), engine.scan()
    flags = second.flags.copy()
    flags[0] |= Flag.BUS_ERROR
    flags[1] |= Flag.SATURATED | Flag.LOW_SIGNAL
    volts = second.volts.copy()
    volts[:2] = np.nan
    from dataclasses import replace

    broken = replace(second, flags=flags, volts=volts)
    both_broken = replace(first, flags=flags, volts=volts.copy())
    mean = average_frames([first, broken])
    assert mean.volts[0] == first.volts[0] and mean.usable[0]
    assert mean.flags[1] & Flag.LOW_SIGNAL and mean.usable[1]
    none = average_frames([both_broken, broken])
    assert np.isnan(none.volts[0]) and none.flags[0] & UNUSABLE
