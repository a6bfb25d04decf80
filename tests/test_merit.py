"""Figures of merit: the formulas, the sign rule of Q, where each layout is sensitive."""

import numpy as np
import pytest

from appliance.core.forward import simulate
from appliance.core.merit import calibration_sensitivity, fractional_change, sensitivity_profile, visibility
from appliance.core.network import build_network_model, thesis_phantom
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import adjacent_protocol, distributed_protocol
from appliance.errors import ModelInputInvalid

PROTOCOLS = {"A": adjacent_protocol(16), "B": adjacent_protocol(16), "C": distributed_protocol(4, 4)}


def test_formulas_on_hand_numbers():
    reference = np.array([2.0, -4.0])
    volts = np.array([3.0, -2.0])
    assert fractional_change(volts, reference) == pytest.approx((0.5 - 0.5) / 2)
    assert visibility(volts, reference) == pytest.approx((1 / 5 - 2 / 6) / 2)


def test_undefined_ratios_are_refused():
    with pytest.raises(ModelInputInvalid, match="reference reading is zero"):
        fractional_change(np.array([1.0]), np.array([0.0]))
    with pytest.raises(ModelInputInvalid, match="both zero"):
        visibility(np.array([0.0]), np.array([0.0]))
    with pytest.raises(ModelInputInvalid, match="matching non-empty vectors"):
        visibility(np.ones(3), np.ones(2))


@pytest.mark.parametrize("letter", ["A", "B", "C"])
def test_sign_rule_of_visibility(letter):
    """Q > 0 for an anomaly less conductive than the background, Q < 0 for a more conductive one."""
    model = build_network_model(thesis_phantom(letter))
    protocol = PROTOCOLS[letter]
    reference = simulate(model, np.ones(model.n_elements), protocol)
    for contrast in (1e-3, 0.5, 0.9):
        sigma = conductivity(model, [Inclusion("rect", 50, 50, 30, 30, contrast)])
        q = visibility(simulate(model, sigma, protocol), reference)
        assert 0 < q < 1
        assert fractional_change(simulate(model, sigma, protocol), reference) > 0
    for contrast in (1.1, 2.0, 1e3):
        sigma = conductivity(model, [Inclusion("rect", 50, 50, 30, 30, contrast)])
        assert -1 < visibility(simulate(model, sigma, protocol), reference) < 0


def profile(letter, n=9):
    """The thesis's sensitivity on an n x n set of positions over the sheet."""
    model = build_network_model(thesis_phantom(letter))
    step = 100 / n
    centres = [((i + 0.5) * step, (j + 0.5) * step) for j in range(n) for i in range(n)]
    s = calibration_sensitivity(model, PROTOCOLS[letter], np.array(centres), step, contrast=1e-3)
    assert s.shape == (n * n, len(PROTOCOLS[letter]))
    return sensitivity_profile(s).reshape(n, n)


def test_distributed_layout_is_most_sensitive_at_the_centre_peripheral_at_the_edge():
    c, b = profile("C"), profile("B")
    assert c[4, 4] == c.max(), "C peaks at the centre"
    assert c[4, 4] > 2 * c[4, 0] and c[4, 4] > 5 * c[0, 0], "C: the centre beats the edge and the corner"
    assert b[2, 0] > 3 * b[4, 4] and b[4, 4] < 0.1 * b.max(), "B: the edge beats the centre"
    assert c.max() > b.max()


def test_image_figures_of_a_perfect_and_a_shifted_image():
    """A 3 x 3-pixel target imaged exactly, then one pixel off, on a 10 x 10 grid of 1 mm pixels."""
    from appliance.core.merit import image_figures

    r, c = np.divmod(np.arange(100), 10)
    centres = np.column_stack([c + 0.5, r + 0.5])
    areas = np.ones(100)
    target = ((np.abs(c - 6) <= 1) & (np.abs(r - 4) <= 1)) * -0.4
    f = image_figures(target, centres, areas, (6.5, 4.5), 9.0, -0.4, (5.0, 5.0))
    assert f.amplitude_response == pytest.approx(1.0) and f.centroid_error_mm == pytest.approx(0.0)
    assert f.position_error_mm == pytest.approx(0.0) and f.ringing == 0.0
    assert f.resolution == pytest.approx(0.3) and f.shape_deformation == 0.0   # a square fits its disc here
    elongated = ((np.abs(c - 5) <= 3) & (r == 4)) * -0.4
    assert image_figures(elongated, centres, areas, (5.5, 4.5), 7.0, -0.4, (5.0, 5.0)).shape_deformation > 0.5
    shifted = np.roll(target.reshape(10, 10), 1, axis=1).ravel() + 0.1 * (c < 2)   # ringing: opposite sign
    g = image_figures(shifted, centres, areas, (6.5, 4.5), 9.0, -0.4, (5.0, 5.0))
    assert g.centroid_error_mm == pytest.approx(1.0) and g.position_error_mm < 0
    assert g.ringing == pytest.approx(2.0 / 3.6)
