"""The analogue parts' rails and detectors: each profile's compliance comes from its rails, and every way a
profile can ask its parts for what they cannot do is refused naming the part and the voltages."""

import math

import pytest

from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
from appliance.drivers.rails import multiplexer_peak_v
from appliance.errors import AnalogueMismatch, ConfigError


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_every_built_in_profile_drives_no_further_than_its_multiplexers_pass(name):
    profile = board_profile({"profile": name})
    assert 0 < profile.excitation.compliance_v * math.sqrt(2) <= multiplexer_peak_v(profile)


def test_the_serial_boards_compliance_is_what_their_rails_give_and_the_bed_keeps_its_clamp():
    # ADG725 on +/-2.5 V, the source on the same rails less 0.3 V of headroom: 2.2 V peak.
    assert board_profile({"profile": "reference"}).excitation.compliance_v == pytest.approx(2.2 / math.sqrt(2))
    assert board_profile({"profile": "parallel"}).excitation.compliance_v == 5.0


def test_a_source_on_wider_rails_than_its_multiplexers_is_refused_naming_both():
    with pytest.raises(AnalogueMismatch) as caught:
        board_profile({"profile": "reference", "supply": {"current_source": [-12.0, 12.0]}})
    text = str(caught.value)
    assert "ADG725 multiplexers" in text and "-2.5/+2.5 V" in text and "8.27 V rms (11.70 V peak)" in text


def test_a_stated_compliance_the_multiplexers_cannot_pass_is_refused():
    """The old reference profile: a 5 V rms source behind multiplexers that pass 1.77 V rms."""
    with pytest.raises(AnalogueMismatch, match=r"compliance 5\.00 V rms \(7\.07 V peak\) exceeds what the ADG731 "
                                               r"multiplexers pass on -2\.5/\+2\.5 V \(2\.50 V peak, 1\.77 V rms\)"):
        board_profile({"profile": "reference-32", "supply": {"current_source": [-12.0, 12.0]},
                       "excitation": {"compliance_v": 5.0}})


def test_a_compliance_beyond_the_sources_own_rails_is_refused():
    with pytest.raises(AnalogueMismatch, match=r"compliance_v = 5 V rms \(7\.07 V peak\) is beyond what the current "
                                               r"source on -2\.5/\+2\.5 V can drive \(2\.20 V peak"):
        board_profile({"profile": "reference", "excitation": {"compliance_v": 5.0}})


def test_a_clamp_inside_every_rail_is_taken_as_the_compliance():
    profile = board_profile({"profile": "reference", "excitation": {"compliance_v": 1.0}})
    assert profile.excitation.compliance_v == 1.0


@pytest.mark.parametrize(("name", "supply", "message"), [
    ("reference", {"multiplexers": [-5.0, 5.0]}, r"ADG725 multiplexers on -5/\+5 V \(10 V between the rails\) are "
                                                 r"outside the 1\.8 to 5\.5 V"),
    ("parallel", {"multiplexers": [-2.5, 2.5]}, r"ADG1414 drive switches on -2\.5/\+2\.5 V .* outside the 10 to 30 V"),
    ("ad5933", {"amplifiers": [-18.0, 18.0]}, r"AD8251 amplifiers on -18/\+18 V .* outside the 10 to 30 V"),
])
def test_a_part_on_rails_it_is_not_specified_for_is_refused(name, supply, message):
    with pytest.raises(AnalogueMismatch, match=message):
        board_profile({"profile": name, "supply": supply})


def test_rails_that_are_not_a_negative_and_a_positive_volt_pair_are_refused():
    with pytest.raises(AnalogueMismatch, match=r"\[board.supply\] multiplexers = \[2.5, -2.5\]"):
        board_profile({"profile": "reference", "supply": {"multiplexers": [2.5, -2.5]}})
    with pytest.raises(ConfigError, match="two numbers"):
        board_profile({"profile": "reference", "supply": {"amplifiers": [12.0]}})


def test_a_source_with_no_room_to_drive_is_refused():
    with pytest.raises(AnalogueMismatch, match="cannot drive at all"):
        board_profile({"profile": "reference", "supply": {"source_headroom_v": 3.0}})


@pytest.mark.parametrize("claimed", ["synchronous", "dft"])
def test_an_rms_chain_claimed_phase_sensitive_is_refused_naming_the_ad8436(claimed):
    with pytest.raises(AnalogueMismatch, match="AD8436 RMS-to-DC converter gives the magnitude.*not phase-sensitive"):
        board_profile({"profile": "reference", "measurement": {"detector": claimed}})


def test_a_phase_sensitive_chain_described_as_rms_is_refused():
    with pytest.raises(AnalogueMismatch, match="the parallel chain's detector reports 'synchronous'"):
        board_profile({"profile": "parallel", "measurement": {"detector": "rms"}})


@pytest.mark.parametrize(("name", "detector"), [("reference", "rms"), ("reference-32", "rms"), ("ad5933", "dft"),
                                                ("parallel", "synchronous")])
def test_each_chain_states_what_its_detector_reports(name, detector):
    assert board_profile({"profile": name}).measurement.detector == detector
    assert board_profile({"profile": name, "measurement": {"detector": detector}}).measurement.detector == detector


def test_selftest_check_refuses_the_profile_before_any_hardware(tmp_path, capsys):
    from appliance.cli import main

    config = tmp_path / "monitor.toml"
    config.write_text('[board]\nprofile = "reference"\n[board.supply]\ncurrent_source = [-12.0, 12.0]\n')
    assert main(["selftest", "--check", "--config", str(config)]) == 2
    assert "exceeds what the ADG725 multiplexers pass" in capsys.readouterr().err
