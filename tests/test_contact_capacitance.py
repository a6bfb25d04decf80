"""Contacts of R parallel C: what an RMS detector reports against a phase-sensitive one, and the source's
compliance on the complex drive impedance."""

import math

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion
from appliance.core.protocols import default_protocol
from appliance.drivers.emulated.electrode_interface import ElectrodeContact, detect, reading_phasors
from appliance.drivers.emulated.sensor import ForwardSensor
from appliance.drivers.profile import board_profile
from appliance.drivers.scan import Flag
from appliance.errors import ModelInputInvalid
from appliance.sim.chain import FrameChain

LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)


@pytest.fixture(scope="module")
def transfers():
    return (ForwardSensor.of_layout(LAYOUT).transfer,
            ForwardSensor.of_layout(LAYOUT, inclusions=[Inclusion("disc", 50, 50, 20, 20, 0.5)]).transfer)


def sheet_readings(z, current):
    a, b, c, d = (PROTOCOL.readings - 1).T
    return current * (z[c, a] - z[c, b] - z[d, a] + z[d, b])


def test_contacts_of_no_impedance_leave_the_sheets_readings(transfers):
    profile = board_profile({"profile": "reference"})
    plain = FrameChain(profile, seed=3)
    touching = FrameChain(profile, seed=3, contact=ElectrodeContact.uniform(16, resistance_ohm=0.0, capacitance_f=1e-6))
    assert np.allclose(touching.ideal(transfers[0], PROTOCOL), plain.ideal(transfers[0], PROTOCOL), rtol=1e-12)
    assert np.allclose(plain.ideal(transfers[0], PROTOCOL), sheet_readings(transfers[0], plain.current_a))


def test_capacitive_contacts_corrupt_an_rms_detectors_change_and_not_a_phase_sensitive_ones(transfers):
    """200 ohm parallel 10 nF contacts (+/-30 %) at 17.5 kHz behind 100 pF inputs: the quadrature the unequal
    contacts make of the common-mode voltage goes into the magnitude; the in-phase part keeps the change."""
    profile = board_profile({"profile": "reference"})
    contact = ElectrodeContact.uniform(16, resistance_ohm=200.0, capacitance_f=1e-8, spread=0.3,
                                       rng=np.random.default_rng(7))
    current, x = profile.excitation.current_a, profile.excitation
    true_change = sheet_readings(transfers[1], current) - sheet_readings(transfers[0], current)
    change = {}
    for detector in ("rms", "synchronous"):
        got = [detect(reading_phasors(z, PROTOCOL.readings - 1, current, contact, x.frequency_hz,
                                      profile.measurement.input_capacitance_f, x.compliance_v)[0], detector)
               for z in transfers]
        change[detector] = np.linalg.norm(got[1] - got[0] - true_change) / np.linalg.norm(true_change)
    assert change["rms"] > 0.05, change
    assert change["synchronous"] < 0.005, change
    assert change["rms"] > 50 * change["synchronous"]


def test_an_rms_detector_reads_the_magnitude_and_a_synchronous_one_the_in_phase_part():
    phasors = np.array([3 + 4j, -3 + 4j])
    assert detect(phasors, "rms").tolist() == [5.0, -5.0]
    assert detect(phasors, "synchronous").tolist() == [3.0, -3.0]
    assert detect(phasors, "synchronous", math.radians(1.0))[0] == pytest.approx(3 * math.cos(math.radians(1))
                                                                                  + 4 * math.sin(math.radians(1)))
    with pytest.raises(ValueError, match="unknown detector"):
        detect(phasors, "peak")


def test_a_capacitive_contact_lowers_what_the_contact_check_sees():
    """A dry pad (10 kohm) coupled through 10 nF reads a few hundred ohm at 17.5 kHz: under a 600 ohm limit."""
    z = np.array([[40.0, 10.0], [10.0, 40.0]])
    contact = ElectrodeContact(np.array([1e4, 10.0]), np.array([1e-8, 1e-6]))
    phasor, _, _ = reading_phasors(z, np.array([[0, 1, 0, 1]]), 3.2e-5, contact, 17500.0, 1e-10, 1.5)
    assert abs(phasor[0]) / 3.2e-5 < 1000 < 1e4


def test_drives_beyond_compliance_deliver_less_current_and_are_flagged(transfers):
    profile = board_profile({"profile": "reference"})
    chain = FrameChain(profile, seed=1)
    wet = chain.ideal(transfers[0], PROTOCOL)
    assert not chain.at_compliance.any()
    # Contacts of 2 kohm put every drive's voltage (4 kohm at 2 mA: 8 V) beyond the 1.56 V rms compliance.
    dry = FrameChain(profile, seed=1, contact=ElectrodeContact.uniform(16, resistance_ohm=2000.0, capacitance_f=0.0))
    volts, flags = dry.readings(transfers[0], PROTOCOL)
    assert dry.at_compliance.all()
    assert np.all(flags & int(Flag.COMPLIANCE))
    ratio = np.abs(dry.ideal(transfers[0], PROTOCOL) / wet)
    assert np.median(ratio) < profile.excitation.compliance_v / (chain.current_a * 4000) * 1.2


def test_the_parallel_chain_passes_quadrature_only_through_its_phase_error(transfers):
    from appliance.core.protocols import protocol_for
    from appliance.drivers.emulated.parallel import SWITCH_OHM, ParallelErrors

    profile = board_profile({"profile": "parallel", "grid": {"rows": 4, "cols": 4}})
    protocol = protocol_for(LAYOUT, "rows")
    contact = ElectrodeContact.uniform(16, resistance_ohm=200.0, capacitance_f=0.0, spread=0.3)
    n = 12                                          # 4 rows x 3 pairs

    def readings(phase_error_deg):
        errors = ParallelErrors(channel_gain=np.zeros(n), offset_v=np.zeros(n), quadrature=np.zeros(n),
                                phase_error_rad=math.radians(phase_error_deg), input_noise_v=0.0, adc_noise_lsb=0.0)
        chain = FrameChain(profile, seed=2, contact=contact, errors=errors)
        volts, _ = chain.readings(transfers[0], protocol)
        return volts, chain

    exact, chain = readings(0.0)
    phasors = reading_phasors(transfers[0], protocol.readings - 1, chain.current_a, contact, 50000.0, 30e-12, 5.0,
                              2 * SWITCH_OHM)[0]
    assert np.allclose(chain.quadrature_v, phasors.imag)
    lsb = 5.0 / 32768 / chain.gain
    assert np.all(np.abs(exact - phasors.real) <= lsb), "the in-phase part, to a code"
    assert np.max(np.abs(np.abs(phasors) - np.abs(phasors.real))) > 10 * lsb, "the magnitude would differ"
    tilted, _ = readings(5.0)
    expected = phasors.real * math.cos(math.radians(5)) + phasors.imag * math.sin(math.radians(5))
    assert np.all(np.abs(tilted - expected) <= 2 * lsb)


def test_contact_values_must_be_one_finite_non_negative_value_per_electrode():
    with pytest.raises(ModelInputInvalid, match="resistance_ohm"):
        ElectrodeContact(np.array([1.0, -1.0]), np.zeros(2))
    contact = ElectrodeContact(np.ones(3), np.zeros(3))
    with pytest.raises(ModelInputInvalid, match="3 electrodes on a mat of 16"):
        reading_phasors(np.eye(16), np.array([[0, 1, 2, 3]]), 1e-3, contact, 1e4, 0.0, 1.0)
