"""Reconstruction: accuracy on grid-4x4, stability, broken electrodes, bad input, the factored form
of large mats (per-frame cost is measured by benchmarks/reconstruction.py)."""

import numpy as np
import pytest
from scipy import ndimage

from appliance.core.fem import build_fem_model
from appliance.core.forward import simulate
from appliance.core.model_cache import ModelSetup, build_model
from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import default_protocol
from appliance.core.reconstruct import (
    ALGORITHMS, ReconstructionOptions, build_reconstructor, readings_using, without_readings,
)
from appliance.core.regularisation import NoiseModel
from appliance.errors import ConfigError, ReconstructionError


LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)
NOISE_01 = NoiseModel(relative=0.0, absolute=1e-3)
"""0.1 % of the rms reading on every reading: the noise the accuracy tests add."""


@pytest.fixture(scope="module")
def truth():
    """The sheet simulated on a mesh four times finer, and differently built, from the model's."""
    model = build_fem_model(LAYOUT, density=4)
    return model, simulate(model, np.ones(model.n_elements), PROTOCOL)


@pytest.fixture(scope="module")
def product():
    """The reconstruction model as the appliance builds it, with the tests' noise declared."""
    return build_model(ModelSetup(LAYOUT, PROTOCOL, ReconstructionOptions(noise=NOISE_01)))


def load_frame(truth, loads, rng=None, noise=1e-3):
    model, reference = truth
    sigma = conductivity(model, [Inclusion("rect", x, y, 20.0, 20.0, 0.6) for x, y in loads])
    v = simulate(model, sigma, PROTOCOL)
    if rng is not None:
        v = v + rng.normal(0.0, noise * np.sqrt(np.mean(reference**2)), v.shape)
    return v


def centroid(image, grid):
    """Centre of the quarter-amplitude set of the pressed (negative) change, mm."""
    value = -np.nan_to_num(image.ravel())
    weight = np.where(value >= 0.25 * value.max(), value, 0.0)
    return weight @ grid.centres_mm / weight.sum()


def test_pressed_region_is_negative_where_it_was_pressed(product, truth):
    image, _ = product.reconstruct(load_frame(truth, [(30, 70)]), truth[1])
    r, c = np.unravel_index(np.nanargmin(image), image.shape)
    assert image[r, c] < -0.2
    assert abs((c + 0.5) * 6.25 - 30) < 6.25 and abs((r + 0.5) * 6.25 - 70) < 6.25


def test_accuracy_for_20_mm_loads_with_0_1_percent_noise(product, truth):
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(40):
        x, y = rng.uniform(12, 88, 2)
        image, _ = product.reconstruct(load_frame(truth, [(x, y)], rng), truth[1])
        errors.append(np.linalg.norm(centroid(image, product.reconstructor.grid) - (x, y)))
    median, p95 = np.median(errors), np.percentile(errors, 95)
    print(f"centroid error: median {median:.2f} mm, 95th percentile {p95:.2f} mm")
    assert median <= 1.0 and p95 <= 3.0


def test_two_loads_35_mm_apart_are_two_regions(product, truth):
    rng = np.random.default_rng(12)
    for (x1, y1), (x2, y2) in [((30, 50), (65, 50)), ((40, 30), (40, 65)), ((25, 25), (50, 50))]:
        image, _ = product.reconstruct(load_frame(truth, [(x1, y1), (x2, y2)], rng), truth[1])
        value = -np.nan_to_num(image)
        labels, count = ndimage.label(value >= 0.25 * value.max())
        assert count == 2, f"loads at {(x1, y1)} and {(x2, y2)} gave {count} regions"
        at = [labels[int(y // 6.25), int(x // 6.25)] for x, y in ((x1, y1), (x2, y2))]
        assert at[0] != at[1] and min(at) > 0


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_every_algorithm_images_a_load_with_the_right_sign(product, truth, algorithm):
    r = build_reconstructor(product.reconstructor.linear, ReconstructionOptions(algorithm, noise=NOISE_01))
    image = r.reconstruct(load_frame(truth, [(60, 40)]), truth[1])
    assert np.isfinite(image).sum() == 256
    assert np.nanmin(image) < -0.1 and abs(np.nanmin(image)) > np.nanmax(image)


@pytest.mark.parametrize("lam", np.logspace(-12, 2, 8))
def test_any_lambda_from_1e_minus_12_up_gives_a_finite_image(product, truth, lam):
    rng = np.random.default_rng(13)
    for algorithm in ("greit", "gn-laplace", "gn-tikhonov", "gn-noser"):
        r = build_reconstructor(product.reconstructor.linear, ReconstructionOptions(algorithm), lam=lam)
        assert np.all(np.isfinite(r.pixels(load_frame(truth, [(50, 50)], rng), truth[1])))


def test_float32_frames_give_the_float64_image(product, truth):
    v, ref = load_frame(truth, [(45, 55)]), truth[1]
    x64 = product.reconstructor.pixels(v, ref)
    x32 = product.reconstructor.pixels(v.astype(np.float32), ref.astype(np.float32))
    assert np.abs(x32 - x64).max() <= 1e-4 * np.abs(x64).max()


def test_ten_percent_noise_gives_a_bounded_image(product, truth):
    """Readings 10 % (of the rms reading) noisy, a hundred times what the model was built for.

    The bound: each pixel's error stays within 6 of its predicted standard deviations
    (R's rows times the noise), and the image's rms error within 1.5 times the predicted
    rms (about 0.5 here, against changes of -0.4): the noise passes through the matrix
    by exactly the amount it promises and nothing blows up.
    """
    r = product.reconstructor
    rng = np.random.default_rng(14)
    clean, ref = load_frame(truth, [(50, 50)]), truth[1]
    x0 = r.pixels(clean, ref)
    sd = 0.1 * np.sqrt(np.mean(ref**2))
    predicted = np.sqrt((r.matrix**2).sum(axis=1)) * sd / r.scale(ref)
    for _ in range(20):
        error = r.pixels(clean + rng.normal(0.0, sd, clean.shape), ref) - x0
        assert np.all(np.isfinite(error))
        assert np.abs(error / predicted).max() < 6.0
        assert np.sqrt(np.mean(error**2)) < 1.5 * np.sqrt(np.mean(predicted**2))


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_reference_readings_at_or_near_zero_do_not_blow_up_the_image(product, truth, algorithm):
    r = build_reconstructor(product.reconstructor.linear, ReconstructionOptions(algorithm, noise=NOISE_01))
    v, ref = load_frame(truth, [(40, 40)]), truth[1].copy()
    normal = r.pixels(v, ref)
    small = np.argsort(np.abs(ref))[:8]
    for value in (0.0, 1e-15):
        ref_small, v_small = ref.copy(), v.copy()
        ref_small[small] = value
        v_small[small] = v[small] - ref[small] + value
        x = r.pixels(v_small, ref_small)
        assert np.all(np.isfinite(x)) and np.abs(x - normal).max() <= 0.05 * np.abs(normal).max()


def test_any_one_electrode_removed(product, truth):
    rng = np.random.default_rng(15)
    errors = []
    for electrode in range(1, 17):
        drop = readings_using(PROTOCOL, [electrode])
        r = without_readings(product.reconstructor, drop)
        assert not r.usable[drop].any() and np.all(r.matrix[:, drop] == 0)
        for _ in range(4):
            x, y = rng.uniform(12, 88, 2)
            v = load_frame(truth, [(x, y)], rng)
            v[drop] = np.nan
            image, info = product.reconstruct(v, truth[1])
            assert info["usable_readings"] == int((~drop).sum())
            errors.append(np.linalg.norm(centroid(image, r.grid) - (x, y)))
    assert np.median(errors) <= 3.0


def test_too_few_readings_is_refused(product, truth):
    v = np.full(len(PROTOCOL), np.nan)
    with pytest.raises(ReconstructionError, match="readings are usable: nothing can be reconstructed"):
        product.reconstruct(v, truth[1])


def test_a_reference_from_another_layout_is_refused(product):
    """The 448-reading protocol read on the square-16 mat: valid electrode numbers, wrong sheet."""
    other = build_fem_model(get_layout("square-16"))
    reference = simulate(other, np.ones(other.n_elements), PROTOCOL)
    with pytest.raises(ReconstructionError, match="correlate .* with this layout's model"):
        product.reconstruct(reference * 1.01, reference)


def test_every_frame_checks_its_reference_though_the_last_fit_is_kept(product, truth):
    """The reference's fit is remembered between frames; a different reference (or the same array changed
    in place, or flattened, or holding a NaN the frame does not) is fitted and checked anew, and the
    correlation is Pearson's."""
    r = product.reconstructor
    reference = truth[1].copy()
    frame = load_frame(truth, [(50, 50)])
    assert r.check_reference(reference) == pytest.approx(np.corrcoef(reference, r.linear.reference)[0, 1],
                                                         abs=1e-12)
    model_reference = r.linear.reference
    assert r.scale(reference) == pytest.approx(reference @ model_reference / (model_reference @ model_reference),
                                               rel=1e-12)
    first = product.reconstruct(frame, reference, iterate="never")[0]
    assert np.allclose(product.reconstruct(frame, reference, iterate="never")[0], first, equal_nan=True)
    reference[:] = np.random.default_rng(3).permutation(reference)       # mis-wired: the same values elsewhere
    with pytest.raises(ReconstructionError, match="correlate .* with this layout's model"):
        product.reconstruct(frame, reference, iterate="never")
    with pytest.raises(ReconstructionError, match="correlate .* with this layout's model"):
        r.check_reference(np.full_like(reference, 1e-3))
    with pytest.raises(ReconstructionError, match="correlate nan"):
        r.check_reference(np.where(np.arange(reference.size) == 5, np.nan, truth[1]))
    with pytest.raises(ReconstructionError, match="fitted scale"):
        r.scale(-truth[1])


def test_bad_options_are_refused():
    with pytest.raises(ConfigError, match="unknown algorithm 'sart'"):
        ReconstructionOptions("sart")
    with pytest.raises(ConfigError, match="unknown lambda rule"):
        ReconstructionOptions(lambda_rule="guess")


@pytest.mark.parametrize("algorithm,rule", [("gn-laplace", "expected-error"), ("greit", "expected-error"),
                                            ("gn-tikhonov", "noise-figure")])
def test_the_factored_form_of_a_large_mat_images_as_the_matrix_does(product, truth, algorithm, rule, monkeypatch):
    import appliance.core.reconstruct as reconstruct

    linear = product.reconstructor.linear
    options = ReconstructionOptions(algorithm=algorithm, noise=NoiseModel(1e-2, 1e-3), lambda_rule=rule)
    chosen = build_reconstructor(linear, options).lam
    dense = build_reconstructor(linear, options, lam=1e-2)       # well conditioned, to compare to rounding
    monkeypatch.setattr(reconstruct, "DENSE_LIMIT", 0)
    assert build_reconstructor(linear, options).lam == pytest.approx(chosen, rel=1e-6)
    factored = build_reconstructor(linear, options, lam=1e-2)
    assert dense.normal_form is None and factored.matrix is None
    assert factored.achieved_noise_figure == pytest.approx(dense.achieved_noise_figure, rel=1e-6)
    v = load_frame(truth, [(30, 70)], np.random.default_rng(3))
    assert np.allclose(factored.pixels(v, truth[1]), dense.pixels(v, truth[1]), rtol=1e-7, atol=1e-10)
    drop = readings_using(PROTOCOL, [6])
    v[drop] = np.nan
    factored = without_readings(factored, drop)
    # The factored set keeps lambda P; a dense rebuild scales the prior with the readings left, by
    # c = trace(N') / trace(N), so at lambda / c it solves the same system.
    normal = factored.normal_form.normal
    kept = linear.jacobian[factored.usable]
    c = np.einsum("rp,r,rp->", kept, factored.normal_form.weights[factored.usable], kept) / np.trace(normal)
    assert 0.5 < c < 0.99                                        # the prior would shrink, and not by nothing
    monkeypatch.setattr(reconstruct, "DENSE_LIMIT", 6_000_000)
    dense = build_reconstructor(linear, options, factored.usable, lam=1e-2 / c)
    assert factored.achieved_noise_figure == pytest.approx(dense.achieved_noise_figure, rel=1e-6)
    assert np.allclose(factored.pixels(v, truth[1]), dense.pixels(v, truth[1]), rtol=1e-7, atol=1e-10)


def test_a_jacobian_kept_in_single_precision_moves_the_images_by_a_thousandth_of_the_noise(
        product, truth, monkeypatch):
    """A bed-size J is kept in float32 (half the memory and half the bytes a frame reads); on this mat,
    made to keep it so, the factored images, noise figure and a set of missing readings move by rounding
    only: under a thousandth of what the readings' noise (1e-3) moves them."""
    import appliance.core.reconstruct as reconstruct
    from appliance.core.reconstruct import LinearModel

    double = product.reconstructor.linear
    assert double.jacobian.dtype == np.float64                   # a small mat keeps double precision
    monkeypatch.setattr(reconstruct, "DENSE_LIMIT", 0)
    monkeypatch.setattr(reconstruct, "SINGLE_PRECISION_LIMIT", 0)
    single = LinearModel(double.protocol, double.grid, double.jacobian, double.reference, double.areas_mm2,
                         double.mapping)
    assert single.jacobian.dtype == np.float32
    options = ReconstructionOptions(algorithm="greit", noise=NoiseModel(1e-2, 1e-3))
    exact, rounded = (build_reconstructor(linear, options, lam=1e-2) for linear in (double, single))
    assert rounded.achieved_noise_figure == pytest.approx(exact.achieved_noise_figure, rel=1e-5)
    clean, noisy = load_frame(truth, [(30, 70)]), load_frame(truth, [(30, 70)], np.random.default_rng(3))
    for drop in (None, readings_using(PROTOCOL, [6])):
        if drop is not None:
            clean[drop] = noisy[drop] = np.nan
            exact, rounded = (without_readings(r, drop) for r in (exact, rounded))
        image = exact.pixels(noisy, truth[1])
        noise = np.max(np.abs(image - exact.pixels(clean, truth[1])))
        rounding = np.max(np.abs(rounded.pixels(noisy, truth[1]) - image))
        assert 0 < rounding <= 1e-3 * noise
