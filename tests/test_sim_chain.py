"""The frame-at-once analogue chain gives what a settled scan of the emulated chips gives."""

import numpy as np
import pytest

from appliance.core.layouts import get_layout
from appliance.core.phantoms import Inclusion
from appliance.core.protocols import default_protocol
from appliance.drivers.emulated.board import EmulatedBoard
from appliance.drivers.frontend import open_front_end
from appliance.drivers.profile import board_profile
from appliance.drivers.scan import Flag, ScanEngine
from appliance.sim.chain import FrameChain
from conftest import sensor_of

PROTOCOL = default_protocol(get_layout("grid-4x4"))


def scanned(profile, sensor, seed=0):
    board = EmulatedBoard(board_profile({"profile": profile}), sensor, seed=seed)
    engine = ScanEngine(open_front_end(board, board.profile), PROTOCOL)
    engine.scan()
    return engine.scan()


@pytest.mark.parametrize("profile", ["reference", "ad5933"])
def test_ranges_currents_and_readings_agree_with_a_scan(profile):
    sensor = sensor_of("grid-4x4")
    frame = scanned(profile, sensor)
    chain = FrameChain(board_profile({"profile": profile}), seed=0)
    volts, flags = chain.readings(sensor.transfer, PROTOCOL)
    assert chain.current_a == pytest.approx(frame.drive_current_a, rel=1e-12)
    assert np.array_equal(chain.ranges_for(chain.ideal(sensor.transfer, PROTOCOL)), frame.range_index)
    accuracy = chain.profile.accuracy
    allowed = 2 * (accuracy.relative * np.abs(frame.volts) + accuracy.absolute_v)
    assert np.all(np.abs(volts - frame.volts) <= allowed)
    assert not flags.any()


def test_saturation_is_flagged_where_a_scan_flags_it():
    sensor = sensor_of("grid-4x4", (Inclusion("disc", 50, 50, 50, 50, 1e-3),))
    frame = scanned("reference", sensor)
    volts, flags = FrameChain(board_profile({}), seed=0).readings(sensor.transfer, PROTOCOL)
    assert np.array_equal((flags & int(Flag.SATURATED)) != 0, (frame.flags & int(Flag.SATURATED)) != 0)
    assert np.isnan(volts[(flags & int(Flag.SATURATED)) != 0]).all()


def test_noise_is_of_the_chips_size_and_independent_between_frames():
    sensor = sensor_of("grid-4x4")
    chain = FrameChain(board_profile({}), seed=3)
    chain.errors.input_noise_v = 2e-6
    frames = np.array([chain.readings(sensor.transfer, PROTOCOL)[0] for _ in range(40)])
    spread = frames.std(axis=0)
    gain = 100 * chain.gain[chain.ranges_for(chain.ideal(sensor.transfer, PROTOCOL))]
    expected = chain.errors.output_noise_v(gain, np.abs(frames.mean(axis=0)) * gain) / gain
    ratio = np.median(spread / expected)
    assert 0.8 < ratio < 1.25, ratio
    assert abs(np.corrcoef(frames[:-1, 0], frames[1:, 0])[0, 1]) < 0.5
