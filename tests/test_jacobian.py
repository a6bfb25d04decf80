"""The adjoint Jacobian against finite differences, on both models."""

import numpy as np
import pytest

from appliance.core.fem import build_fem_model
from appliance.core.forward import simulate
from appliance.core.jacobian import jacobian, pixel_jacobian
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol

from conftest import PERIPHERAL_AND_GRID


@pytest.mark.parametrize("kind", ["fem", "network"])
@pytest.mark.parametrize("name", PERIPHERAL_AND_GRID)
def test_adjoint_jacobian_matches_central_differences(models, name, kind, rng):
    model = models[name, kind]
    protocol = default_protocol(get_layout(name))
    sigma = rng.uniform(0.3, 3.0, model.n_elements)
    j = jacobian(model, sigma, protocol)
    free = np.flatnonzero(~model.fixed_elements)
    for e in rng.choice(free, 4, replace=False):
        h = 1e-5 * sigma[e]
        up, down = sigma.copy(), sigma.copy()
        up[e] += h
        down[e] -= h
        fd = (simulate(model, up, protocol) - simulate(model, down, protocol)) / (2 * h)
        assert np.abs(fd - j[:, e]).max() <= 1e-4 * np.abs(j[:, e]).max() + 1e-12


def test_relative_jacobian_scales_by_conductivity(models, rng):
    model = models["grid-4x4", "fem"]
    protocol = default_protocol(get_layout("grid-4x4"))
    sigma = rng.uniform(0.5, 2.0, model.n_elements)
    assert np.allclose(jacobian(model, sigma, protocol, relative=True),
                       jacobian(model, sigma, protocol) * sigma[None, :], rtol=1e-12, atol=0)


def test_metal_elements_have_no_sensitivity(models):
    model = models["grid-4x4", "network"]
    j = jacobian(model, np.ones(model.n_elements), default_protocol(get_layout("grid-4x4")), relative=True)
    assert np.all(j[:, model.fixed_elements] == 0) and np.abs(j).max() > 0


def test_uniform_scaling_sums_to_minus_the_readings():
    """With ideal contacts, scaling every conductivity by (1 + t) scales every reading by
    1 / (1 + t): the relative Jacobian's rows sum to minus the readings (Euler's theorem)."""
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    fem = build_fem_model(layout, contact_impedance_ohm_m2=1e-9 * 6.25**2 * 1e-6)
    j = jacobian(fem, np.ones(fem.n_elements), protocol, relative=True)
    v = simulate(fem, np.ones(fem.n_elements), protocol)
    assert np.abs(j.sum(axis=1) + v).max() < 1e-6 * np.abs(v).max()


@pytest.mark.parametrize("kind", ["fem", "network"])
def test_the_pixel_jacobian_is_the_element_jacobian_summed_onto_pixels(models, kind, rng):
    from appliance.core.pixels import element_pixel_map, pixel_grid

    layout = get_layout("grid-4x4")
    model = models["grid-4x4", kind]
    protocol = default_protocol(layout)
    sigma = rng.uniform(0.3, 3.0, model.n_elements)
    mapping = element_pixel_map(model, pixel_grid(layout, 5, 7)) if kind == "fem" else \
        element_pixel_map(model, pixel_grid(layout))
    expected = jacobian(model, sigma, protocol, relative=True) @ mapping
    got = pixel_jacobian(model, sigma, protocol, mapping, relative=True)
    assert np.abs(got - expected).max() <= 1e-10 * np.abs(expected).max()


def test_the_pixel_jacobian_refuses_a_mapping_of_another_model(models):
    import scipy.sparse as sp

    model = models["grid-4x4", "fem"]
    with pytest.raises(ValueError, match="one row per element"):
        pixel_jacobian(model, np.ones(model.n_elements), default_protocol(get_layout("grid-4x4")),
                       sp.identity(model.n_elements + 1))
