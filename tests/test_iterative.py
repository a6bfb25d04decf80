"""Iterative Gauss-Newton: it restores the amplitude of large changes, and knows when it is needed."""

import numpy as np
import pytest

from appliance.core.fem import build_fem_model
from appliance.core.forward import simulate
from appliance.core.iterative import LOG_LIMIT, MISFIT_LIMIT, iterative_reconstruct, one_step_misfit
from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import default_protocol
from appliance.errors import ReconstructionError

from conftest import grid_truth_and_model

LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)


@pytest.fixture(scope="module")
def setting():
    return grid_truth_and_model(1e-3)


def frame(setting, contrast):
    truth, _, _ = setting
    return simulate(truth, conductivity(truth, [Inclusion("rect", 40, 55, 20, 20, contrast)]), PROTOCOL)


@pytest.mark.parametrize("contrast", [0.3, 0.1])
def test_iteration_restores_the_amplitude_of_a_large_change(setting, contrast):
    truth, reference, model = setting
    r = model.reconstructor
    v = frame(setting, contrast)
    areas = r.linear.areas_mm2
    true_integral = (contrast - 1) * 400.0
    one_step = r.pixels(v, reference)
    result = iterative_reconstruct(model.forward, r, v, reference)
    assert 2 <= result.iterations <= 12
    assert all(b < a for a, b in zip(result.misfit_history, result.misfit_history[1:]))
    assert abs(areas @ result.pixels / true_integral - 1) < 0.5 * abs(areas @ one_step / true_integral - 1)
    assert result.pixels.min() > -1.0 > one_step.min() or contrast > 0.2, "no negative conductivity"
    assert result.pixels.min() > -1.0


def test_one_step_misfit_decides(setting):
    truth, reference, model = setting
    small = one_step_misfit(model.forward, model.reconstructor, frame(setting, 0.95), reference)
    large = one_step_misfit(model.forward, model.reconstructor, frame(setting, 0.2), reference)
    assert small < MISFIT_LIMIT < large
    _, info_small = model.reconstruct(frame(setting, 0.95), reference)
    _, info_large = model.reconstruct(frame(setting, 0.2), reference)
    assert info_small["iterations"] == 0 and info_large["iterations"] > 0


def test_iterate_option_is_checked(setting):
    _, reference, model = setting
    with pytest.raises(ReconstructionError, match="iterate must be auto, always or never"):
        model.reconstruct(reference, reference, iterate="sometimes")


def test_a_foreign_forward_model_is_refused(setting):
    _, reference, model = setting
    with pytest.raises(ReconstructionError, match="not the one the reconstructor was built from"):
        iterative_reconstruct(build_fem_model(LAYOUT, density=2), model.reconstructor, reference, reference)


def test_near_insulating_data_never_ask_the_solver_for_an_impossible_sheet(setting):
    truth, reference, model = setting
    r = model.reconstructor
    v = simulate(truth, conductivity(truth, [Inclusion("rect", 20, 20, 60, 60, 1e-4)]), PROTOCOL)
    result = iterative_reconstruct(model.forward, r, v, reference)
    assert np.isfinite(result.pixels).all()
    assert result.pixels.min() >= np.expm1(-LOG_LIMIT) and result.pixels.max() <= np.expm1(LOG_LIMIT)
    assert result.pixels.min() < -0.9                     # it still finds the sheet nearly cut through
