"""Noise model, priors and the lambda rules."""

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.regularisation import (
    NoiseModel, choose_lambda, expected_error, laplacian, minimise_lambda, noise_figure, prior_matrix,
)
from appliance.errors import ConfigError


def test_noise_model_parts_add_in_quadrature():
    v = np.array([3.0, -4.0, 0.0])
    rms = np.sqrt(25 / 3)
    std = NoiseModel(relative=0.01, absolute=0.001).std(v)
    assert std == pytest.approx(np.hypot(0.01 * v, 0.001 * rms))
    assert std[2] > 0, "a reading near zero keeps a finite weight"
    with pytest.raises(ConfigError, match="non-negative parts"):
        NoiseModel(relative=0.0, absolute=0.0)


def test_laplacian_of_a_grid():
    lap = laplacian(pixel_grid(get_layout("grid-4x4"), 4, 4)).toarray()
    assert np.allclose(lap, lap.T) and np.allclose(lap.sum(axis=1), 0)
    assert sorted(set(np.diag(lap).tolist())) == [2.0, 3.0, 4.0]
    disc = laplacian(pixel_grid(get_layout("circular-16")))
    assert disc.shape[0] == pixel_grid(get_layout("circular-16")).n_inside


@pytest.mark.parametrize("kind", ["tikhonov", "noser", "laplace"])
def test_priors_are_scaled_to_the_data_term(kind):
    grid = pixel_grid(get_layout("grid-4x4"), 4, 4)
    normal = np.diag(np.linspace(1, 5, 16)) * 1e6
    p = prior_matrix(kind, normal, grid)
    assert np.trace(p) == pytest.approx(np.trace(normal))
    assert np.allclose(p, p.T)
    with pytest.raises(ConfigError, match="unknown prior"):
        prior_matrix("wavelet", normal, grid)


def test_lambda_rules_find_known_optima():
    """A toy problem where the expected-error optimum and the noise figure are known in closed form."""
    rng = np.random.default_rng(3)
    j = rng.normal(size=(40, 10))
    std = np.full(40, 0.1)
    build = lambda lam: np.linalg.solve(j.T @ j + lam * np.eye(10), j.T)          # noqa: E731
    targets = np.eye(10) * 0.5
    cost = lambda r: expected_error(r, j, std, targets, targets, np.ones(10))      # noqa: E731
    best = minimise_lambda(lambda lam: cost(build(lam)))
    grid = np.logspace(-6, 3, 400)
    brute = grid[np.argmin([cost(build(g)) for g in grid])]
    assert best == pytest.approx(brute, rel=0.05)
    figure = lambda r: noise_figure(r, j, std, targets[:, 0], np.ones(10))          # noqa: E731
    lam, achieved = choose_lambda(build, figure, 0.5)
    assert achieved == pytest.approx(0.5, rel=1e-3)
    assert figure(build(lam / 10)) > 0.5 > figure(build(lam * 10))


def test_expected_error_rule_regularises_more_for_more_noise():
    rng = np.random.default_rng(4)
    j = rng.normal(size=(40, 10))
    build = lambda lam: np.linalg.solve(j.T @ j + lam * np.eye(10), j.T)          # noqa: E731
    targets = np.eye(10) * 0.5
    lams = [minimise_lambda(lambda lam, s=s: expected_error(build(lam), j, np.full(40, s), targets, targets,
                                                             np.ones(10))) for s in (0.01, 0.1, 1.0)]
    assert lams[0] < lams[1] < lams[2]


@pytest.mark.parametrize("kind", ["tikhonov", "noser", "laplace"])
def test_spectral_expected_error_equals_the_direct_one(kind):
    from appliance.core.regularisation import ExpectedErrorSpectrum

    rng = np.random.default_rng(5)
    grid = pixel_grid(get_layout("grid-4x4"), 4, 4)
    j = rng.normal(size=(30, 16))
    std = rng.uniform(0.05, 0.2, 30)
    jw = j.T / std**2
    normal = jw @ j
    prior = prior_matrix(kind, normal, grid)
    targets = np.eye(16)[:, :6] * -0.4
    blur = np.full((16, 16), 0.02) + np.eye(16) * 0.7
    areas = rng.uniform(0.5, 1.5, 16)
    for left in (None, blur):
        desired = targets if left is None else left @ targets
        spectrum = ExpectedErrorSpectrum(normal, prior, targets, desired, areas, left)
        for lam in (1e-8, 1e-3, 10.0):
            r = np.linalg.solve(normal + lam * prior, jw)
            r = r if left is None else left @ r
            assert spectrum(lam) == pytest.approx(expected_error(r, j, std, targets, desired, areas), rel=1e-8)
