"""The contact fit: its sensitivities, what it recovers and what it cannot, when it is taken, what it buys the
reconstruction under mismatch, its cache, and bad input."""

import numpy as np
import pytest

from appliance.core.contact_fit import ContactPrior, contact_sensitivity, fit_contacts
from appliance.core.fem import build_fem_model, with_contact_impedance
from appliance.core.forward import simulate
from appliance.core.mesh import mesh_layout
from appliance.core.model_cache import ModelSetup, build_model, cached_model
from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import default_protocol
from appliance.core.reconstruct import ReconstructionOptions, readings_using
from appliance.core.regularisation import NoiseModel
from appliance.errors import ConfigError, ModelInputInvalid, ReconstructionError

LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)
MESH = mesh_layout(LAYOUT)
NOISE = NoiseModel(relative=0.0, absolute=1e-3)
SALINE_S = 8.7e-3
"""The saline mat's sheet conductance (1.25 S/m over 6.95 mm): 1e-4 ohm m^2 contacts are near ideal on it."""
CURRENT_A = 2.5e-3


@pytest.fixture(scope="module")
def base():
    return build_fem_model(LAYOUT, MESH)


def measured(base, contact_ohm_m2, sheet_s, seed=0, drop=None):
    """The empty mat's readings in volts at 2.5 mA: the model's own mesh, contacts ``contact_ohm_m2`` on a uniform
    sheet of ``sheet_s`` siemens, 0.1 % noise."""
    truth = with_contact_impedance(base, MESH, contact_ohm_m2)
    v = simulate(truth, np.full(base.n_elements, sheet_s), PROTOCOL, CURRENT_A)
    v = v + np.random.default_rng(seed).normal(0.0, 1e-3 * np.sqrt(np.mean(v**2)), v.shape)
    return v if drop is None else np.where(drop, np.nan, v)


def test_other_contacts_are_the_model_a_fresh_build_gives(base):
    z = 1e-6 * np.random.default_rng(1).uniform(0.5, 1.5, 16)
    changed, built = with_contact_impedance(base, MESH, z), build_fem_model(LAYOUT, MESH, contact_impedance_ohm_m2=z)
    assert np.allclose(changed.system.fixed, built.system.fixed, rtol=1e-14, atol=0.0)
    sigma = np.ones(base.n_elements)
    assert np.allclose(simulate(changed, sigma, PROTOCOL), simulate(built, sigma, PROTOCOL), rtol=1e-12, atol=0.0)
    with pytest.raises(ModelInputInvalid, match="one value or one per electrode"):
        with_contact_impedance(base, MESH, np.ones(3))


def test_sensitivity_to_each_contact_matches_finite_differences(base):
    z = 1e-6 * np.random.default_rng(2).uniform(0.5, 1.5, 16)
    d = contact_sensitivity(base, MESH, PROTOCOL, z)
    sigma = np.ones(base.n_elements)
    for electrode in (0, 5):                                 # a corner and an interior electrode
        step = np.exp(1e-4 * (np.arange(16) == electrode))
        fd = (simulate(with_contact_impedance(base, MESH, z * step), sigma, PROTOCOL)
              - simulate(with_contact_impedance(base, MESH, z / step), sigma, PROTOCOL)) / 2e-4
        assert np.abs(fd - d[:, electrode]).max() < 1e-5 * np.abs(fd).max()


def test_fit_recovers_each_contact_and_the_sheet_conductance(base):
    """Near-ideal contacts (the saline mat's regime) on a sheet 20 % above the saline value, read at 2.5 mA: the
    conductance within 0.5 %, every contact within three of its stated standard deviations, the four interior
    electrodes (which shunt most) within 10 % and half of all within 5 %."""
    sheet = 1.2 * SALINE_S
    z = 1e-4 * np.random.default_rng(3).uniform(0.5, 1.5, 16)
    fit = fit_contacts(base, MESH, PROTOCOL, measured(base, z, sheet), 1e-4, NOISE)
    assert fit.accepted and fit.determined >= 12            # the corners shunt little: the prior helps there
    assert fit.sheet_conductance_s(CURRENT_A) == pytest.approx(sheet, rel=5e-3)
    error = np.log(fit.contact_impedance_ohm_m2(CURRENT_A) / z)
    assert np.all(np.abs(error) <= 3 * fit.sd_log_contact)
    assert np.abs(error[[5, 6, 9, 10]]).max() < 0.1 and np.median(np.abs(error)) < 0.05
    assert fit.misfit < 1.0 < fit.misfit_nominal


def test_fit_says_what_the_readings_cannot_determine(base):
    """Poor contacts (the model's nominal at unit conductance): a contact barely moves four-electrode readings,
    so the prior holds them; the scale is still fixed."""
    z = 1e-4 * np.random.default_rng(4).uniform(0.5, 1.5, 16)
    fit = fit_contacts(base, MESH, PROTOCOL, measured(base, z, 1.0), 1e-4, NOISE)
    near = fit_contacts(base, MESH, PROTOCOL, measured(base, z, SALINE_S), 1e-4, NOISE)
    assert fit.determined < near.determined
    assert np.median(fit.sd_log_contact) > 5 * np.median(near.sd_log_contact)
    assert fit.sheet_conductance_s(CURRENT_A) == pytest.approx(1.0, rel=5e-3)


def test_fit_with_a_broken_electrode(base):
    """Electrode 6's readings missing: the rest are fitted as before, its own only through what it shunts."""
    z = 1e-4 * np.random.default_rng(5).uniform(0.5, 1.5, 16)
    drop = readings_using(PROTOCOL, [6])
    fit = fit_contacts(base, MESH, PROTOCOL, measured(base, z, SALINE_S, drop=drop), 1e-4, NOISE)
    assert fit.usable.sum() == (~drop).sum()
    assert fit.sheet_conductance_s(CURRENT_A) == pytest.approx(SALINE_S, rel=5e-3)
    error = np.abs(np.log(fit.contact_impedance_ohm_m2(CURRENT_A) / z))
    assert np.all(error <= 3 * fit.sd_log_contact)
    others = np.delete(fit.sd_log_contact, 5)
    assert fit.sd_log_contact[5] > np.median(others)


def test_a_reference_the_model_cannot_explain_keeps_the_nominal_model():
    """A load left on the mat while the reference was taken: no homogeneous sheet explains it."""
    model = build_model(ModelSetup(LAYOUT, PROTOCOL, ReconstructionOptions(noise=NOISE), contact_fit="relinearise"))
    truth = build_fem_model(LAYOUT, density=2)
    loaded = simulate(truth, conductivity(truth, [Inclusion("rect", 40, 60, 30, 30, 0.5)]), PROTOCOL)
    chosen = model.for_reference(loaded)
    assert not chosen.contact_fit.accepted and chosen.contact_fit.misfit > 4
    assert chosen.setup.fitted_contact_ohm_m2 is None


def test_with_the_fit_regions_are_placed_where_without_it_they_are_not():
    """Near-ideal contacts (0.1 ohm cm^2 on the saline mat, +-50 %) on a finer, independent model, 40 loads: the
    model at its nominal (poor) contact misplaces pressed regions by 0.66 to 0.83 mm (median, over six noise
    seeds), the model relinearised at the fit by 0.39 to 0.58 mm."""
    options = ReconstructionOptions(noise=NOISE)
    nominal = build_model(ModelSetup(LAYOUT, PROTOCOL, options, contact_fit="off"))
    fitting = build_model(ModelSetup(LAYOUT, PROTOCOL, options, contact_fit="relinearise"))
    truth = build_fem_model(LAYOUT, density=2, contact_impedance_ohm_m2=1e-7 * np.random.default_rng(1).uniform(
        0.5, 1.5, 16))
    rng = np.random.default_rng(0)
    clean = simulate(truth, np.ones(truth.n_elements), PROTOCOL)
    sd = 1e-3 * np.sqrt(np.mean(clean**2))
    reference = clean + rng.normal(0, sd, clean.shape)
    errors = {"nominal": [], "fitted": []}
    for x, y in rng.uniform(12, 88, (40, 2)):
        frame = simulate(truth, conductivity(truth, [Inclusion("rect", x, y, 20, 20, 0.6)]), PROTOCOL) + \
            rng.normal(0, sd, clean.shape)
        for name, model in (("nominal", nominal), ("fitted", fitting)):
            region = model.regions(frame, reference)[0]
            errors[name].append(np.hypot(region.x_mm - x, region.y_mm - y))
    assert fitting.for_reference(reference).setup.fitted_contact_ohm_m2 is not None
    print({name: f"{np.median(e):.2f} mm" for name, e in errors.items()})
    assert np.median(errors["fitted"]) <= 0.62 < np.median(errors["nominal"])


def test_fitted_models_are_cached_and_a_close_fit_keeps_its_linearisation(tmp_path, base):
    setup = ModelSetup(LAYOUT, PROTOCOL, ReconstructionOptions(noise=NOISE), contact_fit="relinearise")
    model, _ = cached_model(setup, tmp_path)
    reference = measured(base, 1e-4 * np.random.default_rng(6).uniform(0.5, 1.5, 16), SALINE_S)
    steps = []
    fitted = model.for_reference(reference, lambda step, share: steps.append(step))
    assert steps and fitted.setup.fitted_contact_ohm_m2 is not None
    assert model.for_reference(reference) is fitted                              # once per reference
    assert len(list(tmp_path.glob("model-*-fitted-*.npz"))) == 1
    again, _ = cached_model(setup, tmp_path)                                      # a restart: same fit, loaded
    steps.clear()
    restored = again.for_reference(reference, lambda step, share: steps.append(step))
    assert not steps and restored.setup == fitted.setup
    other = measured(base, 1e-4 * np.random.default_rng(6).uniform(0.5, 1.5, 16), SALINE_S, seed=1)
    close = again.for_reference(other, lambda step, share: steps.append(step))    # another reference of that mat
    assert not steps and close.setup == fitted.setup and close.contact_fit is not restored.contact_fit
    frame = reference * (1 + 0.01 * np.sin(np.arange(len(reference))))
    assert np.allclose(model.reconstruct(frame, reference)[0], restored.reconstruct(frame, reference)[0],
                       equal_nan=True)


def test_bad_references_are_refused(base):
    reference = measured(base, 1e-4, SALINE_S)
    with pytest.raises(ReconstructionError, match="has 447 readings, the protocol 448"):
        fit_contacts(base, MESH, PROTOCOL, reference[:-1], 1e-4, NOISE)
    with pytest.raises(ReconstructionError, match=r"reading 3 \(.*\) is infinite"):
        fit_contacts(base, MESH, PROTOCOL, np.where(np.arange(448) == 2, np.inf, reference), 1e-4, NOISE)
    with pytest.raises(ReconstructionError, match="only 0 of 448 reference readings are usable"):
        fit_contacts(base, MESH, PROTOCOL, np.full(448, np.nan), 1e-4, NOISE)
    with pytest.raises(ReconstructionError, match="fitted scale -"):
        fit_contacts(base, MESH, PROTOCOL, -reference, 1e-4, NOISE)               # leads reversed
    with pytest.raises(ConfigError, match="contact prior"):
        ContactPrior(spread_log=0.0)
    model = build_model(ModelSetup(LAYOUT, PROTOCOL))
    with pytest.raises(ReconstructionError, match="correlate"):
        model.for_reference(-reference)
    with pytest.raises(ConfigError, match="unknown contact fit 'always'"):
        ModelSetup(LAYOUT, PROTOCOL, contact_fit="always")


def test_by_default_the_sensors_track_their_contacts_and_the_beds_do_not(base):
    """grid-4x4 fits every reference and reports it, imaging with the nominal linearisation; a bed does nothing."""
    model = build_model(ModelSetup(LAYOUT, PROTOCOL))
    reference = measured(base, 1e-4 * np.random.default_rng(8).uniform(0.5, 1.5, 16), SALINE_S)
    tracked = model.for_reference(reference)
    assert tracked.contact_fit.accepted and tracked.setup.fitted_contact_ohm_m2 is None
    assert tracked.reconstructor is model.reconstructor
    assert 0.005 < np.median(tracked.contact_fit.contact_ohm_m2 / 1e-4) < 0.015       # 1e-4 x 8.7 mS: near ideal
    bed = get_layout("grid-8x16")
    assert ModelSetup(bed, default_protocol(bed)).contact_fit_mode == "off"
