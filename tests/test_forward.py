"""Forward models: reciprocity, conservation, accuracy against an exact solution,
convergence, symmetry, agreement between the two models, hard cases and bad input."""

import math
from itertools import pairwise

import numpy as np
import pytest

from appliance.core.fem import build_fem_model, relative_contact_impedance
from appliance.core.forward import electrode_currents, simulate, solve_electrodes
from appliance.core.layouts import Layout, RectElectrode, RectSheet
from appliance.core.mesh import MeshSpec, mesh_layout
from appliance.core.named_layouts import get_layout
from appliance.core.network import build_network_model, network_for_layout
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import Protocol, default_protocol
from appliance.errors import ModelInputInvalid, ProtocolInvalid

from conftest import PERIPHERAL_AND_GRID


def driven_currents(model, drives):
    eye = np.eye(model.n_electrodes)
    return eye[:, drives[:, 0] - 1] - eye[:, drives[:, 1] - 1]


def check_solution(model, sigma, protocol, residual=1e-10, current=1e-10, reciprocity=1e-9):
    """The three properties every solve must have; returns the readings."""
    fields = solve_electrodes(model, sigma)
    v = fields.readings(protocol)
    assert np.all(np.isfinite(v))
    assert fields.relative_residual < residual
    potentials = fields.drive_potentials(protocol.drives)
    error = np.abs(electrode_currents(model, sigma, potentials) - driven_currents(model, protocol.drives)).max()
    assert error < current, f"current not conserved: {error:.2e} A of 1 A"
    pairs = protocol.reciprocal_pairs()
    if len(pairs):
        mismatch = np.abs(v[pairs[:, 0]] - v[pairs[:, 1]]).max() / np.abs(v).max()
        assert mismatch < reciprocity, f"reciprocity off by {mismatch:.2e}"
    return v


def placements(layout, rng):
    """Centre, over electrode 6 and its surroundings, from electrode 1's centre inwards (half on
    its face), and three random spots and sizes: (x, y, side) in mm."""
    w, h = layout.sheet.size_mm
    e6, e1 = layout.centroids_mm()[5], layout.centroids_mm()[0]
    inwards = (np.array([w / 2, h / 2]) - e1) / np.linalg.norm(np.array([w / 2, h / 2]) - e1)
    touching = e1 + inwards * 6.0
    fixed = [(w / 2, h / 2, 18.0), (e6[0], e6[1], 18.0), (touching[0], touching[1], 12.0)]
    random = [(rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.9) * h, rng.uniform(4.0, 30.0)) for _ in range(3)]
    return fixed + random


@pytest.mark.parametrize("kind", ["fem", "network"])
@pytest.mark.parametrize("name", PERIPHERAL_AND_GRID)
@pytest.mark.parametrize("contrast", [1e-3, 1e-1, 1e1, 1e3])
def test_reciprocity_conservation_and_residual(models, name, kind, contrast, rng):
    layout = get_layout(name)
    model, protocol = models[name, kind], default_protocol(layout)
    for x, y, side in placements(layout, rng):
        sigma = conductivity(model, [Inclusion("rect", x, y, side, side, contrast)])
        check_solution(model, sigma, protocol)


def strip_layout(length=100.0, width=10.0, pad=10.0):
    """A long strip with an electrode across each end: the exact solution is one-dimensional."""
    return Layout("strip", RectSheet(length, width),
                  (RectElectrode(1, pad / 2, width / 2, pad, width),
                   RectElectrode(2, length - pad / 2, width / 2, pad, width)))


def strip_resistance(z_ohm_m2, sigma, length=100.0, width=10.0, pad=10.0):
    """Exact two-terminal resistance: the gap in series with two distributed contacts.

    Under a face the contact current obeys w'' = w / (z sigma), so each face adds
    lambda coth(pad / lambda) / (sigma W) with lambda = sqrt(z sigma) (in mm).
    """
    lam = math.sqrt(z_ohm_m2 * 1e6 * sigma)
    return (length - 2 * pad) / (sigma * width) + 2 * lam / math.tanh(pad / lam) / (sigma * width)


@pytest.mark.parametrize("z", [1e-6, 1e-5, 1e-4])
def test_fem_matches_the_exact_strip_solution_at_second_order(z):
    layout = strip_layout()
    errors, sizes = [], []
    for h in (2.0, 1.0, 0.5):
        mesh = mesh_layout(layout, spec=MeshSpec(h, h, 1.01))
        model = build_fem_model(layout, mesh, contact_impedance_ohm_m2=z)
        fields = solve_electrodes(model, np.full(model.n_elements, 2.0))
        volts = fields.readings(Protocol(np.array([[1, 2, 1, 2]]), 2))[0]
        errors.append(abs(volts / strip_resistance(z, 2.0) - 1))
        sizes.append(h)
    order = np.polyfit(np.log(sizes), np.log(errors), 1)[0]
    assert errors[-1] < 2e-3
    assert order > 1.8, f"observed order {order:.2f}, errors {errors}"


def test_mesh_convergence_of_electrode_voltages():
    """Readings on grid-4x4 converge as the mesh is refined; the order is reported."""
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    densities = (0.5, 1, 2, 4)

    def homogeneous(density):
        model = build_fem_model(layout, density=density)
        return simulate(model, np.ones(model.n_elements), protocol)

    readings = [homogeneous(d) for d in densities]
    reference = homogeneous(8)
    errors = [np.abs(v - reference).max() / np.abs(reference).max() for v in readings]
    order = np.polyfit(np.log(1 / np.array(densities)), np.log(errors), 1)[0]
    print(f"grid-4x4 reading errors {[f'{e:.2e}' for e in errors]}, observed order {order:.2f}")
    assert all(b < a for a, b in pairwise(errors))
    assert order > 1.5
    assert errors[1] < 1e-2, "the default mesh is within 1 % of the converged readings"


def test_homogeneous_disc_readings_turn_with_the_drive():
    layout = get_layout("circular-16")
    model = build_fem_model(layout)
    v = simulate(model, np.ones(model.n_elements), default_protocol(layout)).reshape(16, 13)
    assert np.abs(v - v[0]).max() < 1e-9 * np.abs(v).max()


def test_grid_readings_mirror():
    """Mirroring grid-4x4 left-right maps electrode (r, c) to (r, 3 - c) and every reading
    onto its mirror image, negated once for each pair whose order the mirror reverses."""
    layout = get_layout("grid-4x4")
    model = build_fem_model(layout)
    protocol = default_protocol(layout)
    v = simulate(model, np.ones(model.n_elements), protocol)
    index = {tuple(r): i for i, r in enumerate(protocol.readings.tolist())}

    def mirrored(a, b):
        a, b = (a - 1) // 4 * 4 + 3 - (a - 1) % 4 + 1, (b - 1) // 4 * 4 + 3 - (b - 1) % 4 + 1
        return ((a, b), 1) if a < b else ((b, a), -1)

    for i, (a, b, c, d) in enumerate(protocol.readings.tolist()):
        (drive, s1), (meas, s2) = mirrored(a, b), mirrored(c, d)
        assert s1 * s2 * v[index[drive + meas]] == pytest.approx(v[i], rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("name", PERIPHERAL_AND_GRID)
def test_fem_and_network_agree_on_the_homogeneous_sheet(models, name):
    protocol = default_protocol(get_layout(name))
    fem = simulate(models[name, "fem"], np.ones(models[name, "fem"].n_elements), protocol)
    net = simulate(models[name, "network"], np.ones(models[name, "network"].n_elements), protocol)
    correlation = np.corrcoef(fem, net)[0, 1]
    print(f"{name}: FEM/network correlation {correlation:.4f}")
    assert correlation >= 0.99


# ---------------------------------------------------------------------------
# Hard cases

@pytest.mark.parametrize("contrast", [1e-3, 1e3])
@pytest.mark.parametrize("kind", ["fem", "network"])
def test_extreme_contrast_touching_an_electrode(models, kind, contrast):
    """A ring of extreme contrast hugging electrode 6 of grid-4x4, the face itself left as it is."""
    layout = get_layout("grid-4x4")
    model = models["grid-4x4", kind]
    x, y = layout.centroids_mm()[5]
    ring = Inclusion("rect", x, y, 14.0, 14.0, contrast)
    face = Inclusion("rect", x, y, 6.25, 6.25, 1.0)
    check_solution(model, conductivity(model, [ring, face]), default_protocol(layout))


def test_network_with_electrode_conductance_1e4_over_extreme_contrast():
    layout = get_layout("square-16")
    model = build_network_model(network_for_layout(layout, 3), electrode_conductance=1e4)
    x, y = layout.centroids_mm()[0]
    for contrast in (1e-3, 1e3):
        sigma = conductivity(model, [Inclusion("rect", x + 8, y + 8, 16.0, 16.0, contrast)])
        check_solution(model, sigma, default_protocol(layout))


@pytest.mark.parametrize("z_relative", [1e-9, 1e-6, 1e-3, 1e0])
def test_contact_impedance_from_near_ideal_to_poor(z_relative):
    layout = get_layout("grid-4x4")
    area_m2 = 6.25**2 * 1e-6
    model = build_fem_model(layout, contact_impedance_ohm_m2=z_relative * area_m2)
    assert relative_contact_impedance(layout, z_relative * area_m2, 1.0) == pytest.approx(z_relative)
    sigma = conductivity(model, [Inclusion("rect", 40.0, 40.0, 20.0, 20.0, 1e-3)])
    check_solution(model, sigma, default_protocol(layout))


def test_near_ideal_contact_approaches_the_limit():
    """Shrinking z by 1000 changes the readings less and less: the z -> 0 limit is reached smoothly."""
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    mesh = mesh_layout(layout)
    area_m2 = 6.25**2 * 1e-6
    v = [simulate(m := build_fem_model(layout, mesh, contact_impedance_ohm_m2=z * area_m2),
                  np.ones(m.n_elements), protocol) for z in (1e-3, 1e-6, 1e-9)]
    step1 = np.abs(v[1] - v[0]).max() / np.abs(v[2]).max()
    step2 = np.abs(v[2] - v[1]).max() / np.abs(v[2]).max()
    assert step2 < step1 / 100


@pytest.fixture(scope="module")
def fine_grid_model():
    layout = get_layout("grid-4x4")
    mesh = mesh_layout(layout, density=8.5)
    assert mesh.n_nodes >= 100_000
    return layout, build_fem_model(layout, mesh)


def test_hundred_thousand_node_mesh(fine_grid_model):
    layout, model = fine_grid_model
    sigma = conductivity(model, [Inclusion("rect", 40.0, 55.0, 25.0, 20.0, 0.3)])
    check_solution(model, sigma, default_protocol(layout))


def test_extreme_contrast_on_the_finest_mesh_is_backward_stable(fine_grid_model):
    """Contrast 1e3 around an electrode on 1e5 nodes: ||b - Kx|| / ||b|| meets the float64
    floor eps * || |K| |x| || / ||b|| (about 2e-10 here: the electrode sits at 3.7 V while
    its surroundings differ from it by microvolts), so the solve is judged by its
    normwise backward error, which must be at rounding level."""
    layout, model = fine_grid_model
    x, y = layout.centroids_mm()[5]
    sigma = conductivity(model, [Inclusion("rect", x, y, 14.0, 14.0, 1e3)])
    protocol = default_protocol(layout)
    fields = solve_electrodes(model, sigma)
    K = model.system.matrix(sigma)
    b = model.electrodes.toarray()
    solved = np.abs(b).sum(axis=0) > 0             # the grounded electrode's column is not solved
    x, b = fields.solution[:, solved], b[:, solved]
    r = b - K @ x
    backward = np.linalg.norm(r, axis=0) / (abs(K) @ np.abs(x) + np.abs(b)).max(axis=0)
    assert backward.max() < 1e-14
    assert fields.relative_residual < 1e-9
    v = fields.readings(protocol)
    pairs = protocol.reciprocal_pairs()
    assert np.abs(v[pairs[:, 0]] - v[pairs[:, 1]]).max() < 1e-9 * np.abs(v).max()


# ---------------------------------------------------------------------------
# Bad input

@pytest.mark.parametrize(("value", "message"), [
    (0.0, "element 7 has 0.0"), (-1.0, "element 7 has -1.0"), (np.nan, "element 7 has nan"),
    (np.inf, "element 7 has inf"),
])
def test_non_positive_conductivity_is_refused(models, value, message):
    model = models["grid-4x4", "fem"]
    sigma = np.ones(model.n_elements)
    sigma[7] = value
    with pytest.raises(ModelInputInvalid, match="conductivity must be positive and finite") as err:
        simulate(model, sigma, default_protocol(get_layout("grid-4x4")))
    assert message in str(err.value)


def test_conductivity_of_wrong_length_is_refused(models):
    model = models["grid-4x4", "network"]
    with pytest.raises(ModelInputInvalid, match="one value per element \\(256\\)"):
        simulate(model, np.ones(10), default_protocol(get_layout("grid-4x4")))


def test_network_ignores_conductivity_given_to_its_metal_electrodes(models):
    model = models["grid-4x4", "network"]
    protocol = default_protocol(get_layout("grid-4x4"))
    sigma = np.ones(model.n_elements)
    sigma[model.fixed_elements] = -5.0
    assert np.allclose(simulate(model, sigma, protocol), simulate(model, np.ones(model.n_elements), protocol))


@pytest.mark.parametrize("z", [0.0, -1e-4, np.nan])
def test_bad_contact_impedance_is_refused(z):
    with pytest.raises(ModelInputInvalid, match="contact impedance of electrode 1 must be positive"):
        build_fem_model(get_layout("grid-4x4"), contact_impedance_ohm_m2=z)


def test_protocol_for_another_electrode_count_is_refused(models):
    with pytest.raises(ProtocolInvalid, match="is for 8 electrodes, the model has 16"):
        simulate(models["grid-4x4", "fem"], np.ones(models["grid-4x4", "fem"].n_elements),
                 Protocol(np.array([[1, 2, 3, 4]]), 8))
