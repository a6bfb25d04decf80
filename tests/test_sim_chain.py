"""The frame-at-once analogue chain gives what a settled scan of the emulated chips gives."""

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion
from appliance.core.protocols import default_protocol, protocol_for
from appliance.drivers.backend import emulated_board, open_front_end
from appliance.drivers.emulated.sensor import ForwardSensor
from appliance.drivers.profile import board_profile
from appliance.drivers.scan import Flag, ScanEngine
from appliance.sim.chain import FrameChain, ParallelFrameChain
from conftest import sensor_of

PROTOCOL = default_protocol(get_layout("grid-4x4"))


def scanned(profile, sensor, seed=0):
    board = emulated_board(board_profile({"profile": profile}), sensor, seed=seed)
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


@pytest.mark.parametrize(("profile", "detector"), [("reference", "rms"), ("ad5933", "synchronous")])
def test_with_unequal_contacts_a_scan_reports_what_the_profiles_detector_does(profile, detector):
    """Contacts within +/-30 % of 30 ohm behind 1 nF inputs put quadrature into the differential: the RMS
    board's scan gives its magnitude, the AD5933 board's its in-phase part, each as the frame chain does."""
    import dataclasses

    from appliance.drivers.emulated.electrode_interface import ElectrodeContact, detect, reading_phasors

    table = {"profile": profile, "measurement": {"input_capacitance_f": 1e-9}}
    contact = ElectrodeContact.uniform(16, resistance_ohm=30.0, capacitance_f=0.0, spread=0.3)
    sensor = dataclasses.replace(sensor_of("grid-4x4"), contact=contact)
    board = emulated_board(board_profile(table), sensor, seed=0)
    engine = ScanEngine(open_front_end(board, board.profile), PROTOCOL)
    engine.scan()
    frame = engine.scan()
    chain = FrameChain(board_profile(table), seed=0, contact=contact)
    volts, _ = chain.readings(sensor.transfer, PROTOCOL)
    usable = np.isfinite(frame.volts)
    assert usable.sum() > 400
    accuracy = chain.profile.accuracy
    allowed = 2 * (accuracy.relative * np.abs(frame.volts) + accuracy.absolute_v)
    assert np.all(np.abs(volts - frame.volts)[usable] <= allowed[usable])
    x, m = chain.profile.excitation, chain.profile.measurement
    phasors = reading_phasors(sensor.transfer, PROTOCOL.readings - 1, chain.current_a, contact, x.frequency_hz,
                              m.input_capacitance_f, x.compliance_v)[0]
    other = detect(phasors, "synchronous" if detector == "rms" else "rms")
    assert (np.abs(frame.volts - other) > allowed)[usable].sum() >= 5, "the other detector's view is told apart"


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


# --- the parallel chain -------------------------------------------------------------------------------------

SMALL = get_layout("grid-4x8")
SMALL_PROTOCOL = protocol_for(SMALL, "rows")
SMALL_GRID = {"profile": "parallel", "grid": {"rows": 4, "cols": 8}}


def settled_parallel_scan(profile, sensor, protocol, *, seed, frames=9):
    """A steady frame of the emulated parallel board (after enough frames for the zero's running mean)."""
    board = emulated_board(profile, sensor, seed=seed)
    engine = ScanEngine(open_front_end(board, profile), protocol, contact_check=False)
    for _ in range(frames):
        frame = engine.scan()
    return frame, board


def compare_parallel(profile, sensor, protocol, seed, frames=9):
    """The shortcut against the transfer-level scan: readings within the noise of the two, the same ranges, and
    the same flags wherever a reading is not within that noise of the low-signal floor."""
    frame, board = settled_parallel_scan(profile, sensor, protocol, seed=seed, frames=frames)
    chain = FrameChain(profile, seed=seed)
    assert isinstance(chain, ParallelFrameChain)
    assert np.array_equal(chain.errors.channel_gain, board.errors.channel_gain)      # one board, drawn once
    volts, flags = chain.readings(sensor.transfer, protocol)
    ideal = chain.ideal(sensor.transfer, protocol)
    r = chain.drive_ranges(ideal, protocol)
    assert np.array_equal(r, frame.range_index)
    lsb = np.array([rng.second_stage for rng in chain.ranges])[r] / 32768
    e = chain.errors
    sigma = np.sqrt(2) * np.hypot(np.hypot(e.adc_noise_lsb * lsb, lsb / np.sqrt(12)), e.input_noise_v * chain.gain)
    sigma = np.hypot(sigma, 5 / 32768 * e.adc_noise_lsb) / chain.gain        # and the two zeros' noise
    both = np.isfinite(volts) & np.isfinite(frame.volts)
    assert np.array_equal(np.isfinite(volts), np.isfinite(frame.volts))
    assert np.all(np.abs(volts - frame.volts)[both] <= 5 * sigma[both] + 1e-3 * np.abs(ideal[both]))
    clear = np.abs(np.abs(ideal) - profile.measurement.sign_floor_v) > 5 * sigma
    assert np.array_equal(flags[clear], frame.flags[clear])
    return frame, flags


def test_the_parallel_shortcut_matches_the_transfer_level_scan_on_a_small_grid():
    profile = board_profile(SMALL_GRID)
    frame, flags = compare_parallel(profile, sensor_of("grid-4x8"), SMALL_PROTOCOL, seed=4)
    assert frame.usable.all()


def test_the_parallel_shortcut_matches_the_scan_through_capacitive_contacts():
    """200 ohm parallel 10 nF contacts (+/-30 %): both keep the in-phase part, which the contacts move; the
    scan's reciprocity check finds the pairs the contacts made disagree."""
    import dataclasses

    from appliance.drivers.emulated.electrode_interface import ElectrodeContact

    contact = ElectrodeContact.uniform(32, resistance_ohm=200.0, capacitance_f=1e-8, spread=0.3)
    plain = sensor_of("grid-4x8")
    profile = board_profile(SMALL_GRID)
    frame, _ = settled_parallel_scan(profile, dataclasses.replace(plain, contact=contact), SMALL_PROTOCOL, seed=4)
    volts, _ = FrameChain(profile, seed=4, contact=contact).readings(plain.transfer, SMALL_PROTOCOL)
    usable = np.isfinite(frame.volts)
    assert np.array_equal(~usable, (frame.flags & int(Flag.RECIPROCITY)) != 0)
    assert usable.sum() > len(SMALL_PROTOCOL) / 3
    accuracy = profile.accuracy
    allowed = 2 * (accuracy.relative * np.abs(volts) + accuracy.absolute_v)
    assert np.all(np.abs(volts - frame.volts)[usable] <= allowed[usable])
    without = FrameChain(profile, seed=4).ideal(plain.transfer, SMALL_PROTOCOL)
    assert np.max(np.abs(volts - without)) > 0.01 * np.max(np.abs(without)), "the contacts move the readings"


def test_the_parallel_shortcut_saturates_where_the_scan_does():
    sensor = ForwardSensor.of_layout(SMALL, sheet_conductance_s=0.0015)
    frame, flags = compare_parallel(board_profile(SMALL_GRID), sensor, SMALL_PROTOCOL, seed=5)
    saturated = (flags & int(Flag.SATURATED)) != 0
    assert saturated.any() and np.array_equal(saturated, (frame.flags & int(Flag.SATURATED)) != 0)


def test_the_parallel_shortcut_matches_the_scan_on_the_bed_for_a_subset_of_steps():
    from appliance.core.fem import build_fem_model
    from appliance.core.protocols import Protocol
    from appliance.sim.bed import BED_MAT_PARAMETERS as mat
    from appliance.sim.transfer import TransferSolver

    layout = get_layout("grid-16x32")
    full = protocol_for(layout, "rows", reach=2)
    subset = np.isin(full.drive_index, np.arange(0, len(full.drives), 9))       # 109 of the 976 drives
    protocol = Protocol(full.readings[subset], full.n_electrodes, "rows-subset")
    assert len(set(full.drive_index[subset].tolist())) == 109
    sheet = mat.rest_depth_mm * 1e-3 * mat.conductivity_s_per_m
    model = build_fem_model(layout)
    sensor = ForwardSensor(TransferSolver(model).transfer(np.full(model.n_elements, sheet)))
    frame, flags = compare_parallel(board_profile({"profile": "parallel"}), sensor, protocol, seed=6, frames=3)
    assert frame.usable.all() and not (flags & int(Flag.LOW_SIGNAL)).any()
