"""The model cache: keys follow every input, files round-trip, damage is rebuilt."""

import numpy as np

from appliance.core.model_cache import ModelSetup, cached_model, default_cache_dir, load_model
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol, opposite_protocol
from appliance.core.reconstruct import ReconstructionOptions
from appliance.core.regularisation import NoiseModel

LAYOUT = get_layout("circular-16")
SETUP = ModelSetup(LAYOUT, default_protocol(LAYOUT))


def test_key_changes_with_every_input():
    keys = {SETUP.key(),
            ModelSetup(get_layout("square-16"), default_protocol(LAYOUT)).key(),
            ModelSetup(LAYOUT, opposite_protocol(16)).key(),
            ModelSetup(LAYOUT, default_protocol(LAYOUT), ReconstructionOptions("gn-noser")).key(),
            ModelSetup(LAYOUT, default_protocol(LAYOUT), ReconstructionOptions(noise=NoiseModel(2e-3))).key(),
            ModelSetup(LAYOUT, default_protocol(LAYOUT), density=2.0).key(),
            ModelSetup(LAYOUT, default_protocol(LAYOUT), pixels=(20, 20)).key(),
            ModelSetup(LAYOUT, default_protocol(LAYOUT), contact_impedance_ohm_m2=1e-3).key(),
            ModelSetup(LAYOUT, default_protocol(LAYOUT), fitted_contact_ohm_m2=(1e-6,) * 16).key()}
    assert len(keys) == 9
    # whether frames are imaged with a fitted model changes nothing built: fitted models have keys of their own
    assert SETUP.key() == ModelSetup(LAYOUT, default_protocol(LAYOUT), contact_fit="relinearise").key()
    assert SETUP.key() == ModelSetup(get_layout("circular-16"), default_protocol(LAYOUT)).key()


def test_built_then_loaded_without_building_and_identical(tmp_path, monkeypatch):
    progress = []
    built, loaded = cached_model(SETUP, tmp_path, lambda step, share: progress.append(share))
    assert not loaded and progress[0] == 0.0 and progress[-1] == 1.0

    def no_build(*args):
        raise AssertionError("a cached model was built again")
    monkeypatch.setattr("appliance.core.model_cache.build_model", no_build)
    again, loaded = cached_model(SETUP, tmp_path)
    assert loaded
    assert np.array_equal(again.reconstructor.matrix, built.reconstructor.matrix)
    assert again.reconstructor.lam == built.reconstructor.lam
    assert not list(tmp_path.glob("*.tmp")), "the atomic write leaves no temporary file"
    ref = built.reconstructor.linear.reference
    frame = ref * (1 + 0.01 * np.sin(np.arange(len(ref))))
    assert np.allclose(again.reconstruct(frame, ref)[0], built.reconstruct(frame, ref)[0], equal_nan=True)


def test_a_damaged_or_foreign_file_is_rebuilt(tmp_path):
    cached_model(SETUP, tmp_path)
    path = next(tmp_path.glob("model-*.npz"))
    path.write_bytes(b"not a model")
    model, loaded = cached_model(SETUP, tmp_path)
    assert not loaded and model.reconstructor.matrix.shape[1] == 208
    other = ModelSetup(LAYOUT, opposite_protocol(16))
    try:
        load_model(path, other)
    except ValueError as exc:
        assert "another setup" in str(exc)
    else:
        raise AssertionError("a model of another setup was accepted")


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("APPLIANCE_CACHE_DIR", str(tmp_path / "c"))
    assert default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("APPLIANCE_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert default_cache_dir() == tmp_path / "x" / "appliance"


def test_a_large_mat_model_is_saved_and_loaded_in_its_factored_form(tmp_path, monkeypatch):
    import appliance.core.reconstruct as reconstruct

    monkeypatch.setattr(reconstruct, "DENSE_LIMIT", 0)
    layout = get_layout("grid-4x4")
    setup = ModelSetup(layout, default_protocol(layout), density=0.5)
    built, loaded = cached_model(setup, tmp_path)
    again, loaded_again = cached_model(setup, tmp_path)
    assert not loaded and loaded_again
    assert built.reconstructor.matrix is None and again.reconstructor.matrix is None
    frame = np.random.default_rng(2).normal(size=len(setup.protocol))
    reference = built.reconstructor.linear.reference
    assert np.allclose(again.reconstructor.pixels(frame, reference), built.reconstructor.pixels(frame, reference))
