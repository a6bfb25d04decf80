"""What a model keeps in memory for the sets of missing readings a night's electrode faults ask for: a
factored set is an exact low-rank update of the full set's factor, the sets kept are bounded in bytes,
the most recently used kept, and a set that cannot be imaged is refused by name."""

import functools

import numpy as np
import pytest

import appliance.core.model_cache as model_cache
import appliance.core.reconstruct as reconstruct
from appliance.core.named_layouts import get_layout
from appliance.core.model_cache import ModelSetup, build_model, kept_bytes, return_freed_memory
from appliance.core.protocols import default_protocol
from appliance.core.reconstruct import ReconstructionOptions, readings_using, without_readings
from appliance.errors import ConfigError, ReconstructionError

LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)


def missing(*electrodes):
    return readings_using(PROTOCOL, electrodes)


def frame_and_reference(model, electrodes):
    reference = model.reconstructor.linear.reference
    frame = reference * (1 + 0.01 * np.random.default_rng(4).normal(size=len(reference)))
    frame[missing(*electrodes)] = np.nan
    return frame, reference


@functools.cache
def built(kind):
    """grid-4x4 as built (its R whole), or factored with the algorithm ``kind``."""
    if kind == "dense":
        return build_model(ModelSetup(LAYOUT, PROTOCOL, density=0.5))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(reconstruct, "DENSE_LIMIT", 0)
        return build_model(ModelSetup(LAYOUT, PROTOCOL, ReconstructionOptions(kind), density=0.5))


@pytest.fixture(params=["greit", "gn-laplace"])
def factored(request):
    return built(request.param)


@pytest.fixture(params=["dense", "gn-laplace"])
def model(request):
    return built(request.param)


def kept_lambda_image(model, r, frame, reference):
    """The image of N' + lambda P solved outright: the system a factored set of missing readings keeps."""
    full = model.reconstructor.normal_form
    jacobian = model.reconstructor.linear.jacobian[r.usable]
    weights = full.weights[r.usable]
    normal = (jacobian.T * weights) @ jacobian
    x = np.linalg.solve(normal + full.lam * full.prior, jacobian.T @ (weights * (frame - reference)[r.usable]))
    return (x if full.left is None else full.left @ x) / r.scale(reference)


@pytest.mark.parametrize("electrodes,update", [([1], True), ([7], True), ([1, 6], False), ([2, 5, 11], False)])
def test_a_factored_set_images_as_its_system_solved_outright_and_keeps_no_pixel_square_matrix(
        factored, electrodes, update):
    """One electrode (80 to 114 of 448 readings on 256 pixels) updates the full set's factor; two or three
    would make an update larger than a factor of the set's own, which it then keeps."""
    factored._dropped.clear()
    full = factored.reconstructor.normal_form
    r = factored.for_readings(missing(*electrodes))
    form = r.normal_form
    assert form.base is full and form.normal is full.normal and form.prior is full.prior
    assert (form.update is not None) == update
    k, n = int(missing(*electrodes).sum()), len(full.normal)
    if update:
        c, (s, _) = form.update
        assert c.shape == (n, k) and s.shape == (k, k)
        assert kept_bytes(r) == 8 * (n * k + k * k + len(PROTOCOL)) + len(PROTOCOL)
    else:
        assert kept_bytes(r) == 8 * (n * n + len(PROTOCOL)) + len(PROTOCOL)      # its factor, weights and mask
    frame, reference = frame_and_reference(factored, electrodes)
    expected = kept_lambda_image(factored, r, frame, reference)
    assert np.abs(r.pixels(frame, reference) - expected).max() <= 1e-10 * np.abs(expected).max()


def test_a_set_taken_from_a_set_is_the_set_taken_from_the_full_one(factored):
    one = without_readings(factored.reconstructor, missing(3))
    both = without_readings(one, missing(9))
    direct = without_readings(factored.reconstructor, missing(3, 9))
    assert both.normal_form.base is factored.reconstructor.normal_form
    assert np.array_equal(both.usable, direct.usable)
    frame, reference = frame_and_reference(factored, [3, 9])
    assert np.array_equal(both.pixels(frame, reference), direct.pixels(frame, reference))
    assert both.achieved_noise_figure == direct.achieved_noise_figure


def test_a_returning_set_is_served_from_the_cache_and_the_least_recently_used_goes_first(model, monkeypatch):
    """Electrodes 3, 5, 8, 9 and 12 each drive or measure 114 readings: their sets take the same bytes."""
    model._dropped.clear()
    first = model.for_readings(missing(3))
    monkeypatch.setattr(model_cache, "DROPPED_KEPT_BYTES", 2 * kept_bytes(first))      # two of them
    assert model.for_readings(missing(3)) is first
    model.for_readings(missing(5))
    assert model.for_readings(missing(3)) is first                       # used again: now the newest
    eight = model.for_readings(missing(8))                               # electrode 5's set goes, the oldest
    assert [id(r) for r in model._dropped.values()] == [id(first), id(eight)]
    model.for_readings(missing(9))
    model.for_readings(missing(12))
    again = model.for_readings(missing(3))                               # forgotten, built anew, the same
    assert again is not first
    frame, reference = frame_and_reference(model, [3])
    assert np.array_equal(again.pixels(frame, reference), first.pixels(frame, reference))


def test_the_sets_kept_never_exceed_their_budget_and_the_newest_is_kept_whatever_it_takes(model, monkeypatch):
    model._dropped.clear()
    budget = int(2.5 * kept_bytes(model.for_readings(missing(2))))
    monkeypatch.setattr(model_cache, "DROPPED_KEPT_BYTES", budget)
    for electrodes in ([4], [6], [8], [10, 12], [13], [1, 16], [3]):
        newest = model.for_readings(missing(*electrodes))
        kept = sum(map(kept_bytes, model._dropped.values()))
        assert kept <= budget or [id(r) for r in model._dropped.values()] == [id(newest)]
        assert next(reversed(model._dropped.values())) is newest
    monkeypatch.setattr(model_cache, "DROPPED_KEPT_BYTES", 0)
    newest = model.for_readings(missing(14))
    assert [id(r) for r in model._dropped.values()] == [id(newest)]


def test_a_set_that_cannot_be_imaged_is_refused_by_name(model):
    r = model.reconstructor
    with pytest.raises(ReconstructionError, match=f"only 0 of {len(PROTOCOL)} readings are usable"):
        model.for_readings(np.ones(len(PROTOCOL), dtype=bool))
    reference = r.linear.reference
    with pytest.raises(ReconstructionError, match="only 0 of"):
        model.reconstruct(np.full_like(reference, np.nan), reference)
    with pytest.raises(ConfigError, match=f"a mask of {len(PROTOCOL)} booleans, got bool of shape \\(10,\\)"):
        without_readings(r, np.zeros(10, dtype=bool))
    with pytest.raises(ConfigError, match="booleans, got int64"):
        without_readings(r, missing(3).astype(np.int64))


def test_the_build_reports_what_its_matrices_take():
    steps = []
    model = build_model(ModelSetup(LAYOUT, PROTOCOL, density=0.5), lambda step, share: steps.append(step))
    assert model.matrix_bytes() == 2 * 448 * 256 * 8 + 448                # J and R, and the usable mask
    assert steps[-1] == f"done: its matrices take {model.matrix_bytes() / 2**20:.1f} MiB"


def test_freed_memory_is_returned_only_where_the_c_library_is_glibc(monkeypatch):
    calls = []

    class Library:
        def malloc_trim(self, pad):
            calls.append(pad)
            return 1

    monkeypatch.setattr(model_cache.ctypes, "CDLL", lambda name: Library())
    monkeypatch.setattr(model_cache.platform, "libc_ver", lambda: ("glibc", "2.36"))
    return_freed_memory()
    assert calls == [0]
    monkeypatch.setattr(model_cache.platform, "libc_ver", lambda: ("musl", ""))
    return_freed_memory()
    assert calls == [0]
