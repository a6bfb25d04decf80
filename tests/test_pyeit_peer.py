"""pyEIT 1.2.4 as a peer (benchmarks/pyeit_peer.py): our protocol in pyEIT, and its images on simulated data."""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyeit")

BENCHMARKS = str(Path(__file__).resolve().parents[1] / "benchmarks")
if BENCHMARKS not in sys.path:
    sys.path.insert(0, BENCHMARKS)

import pyeit.eit.protocol as pyeit_protocol  # noqa: E402
from pyeit.mesh import set_perm  # noqa: E402
from pyeit.mesh.wrapper import PyEITAnomaly_Circle  # noqa: E402

import pyeit_peer  # noqa: E402

RADIUS = 50.0
SQUARE = ("rect", 100.0, 100.0)


def rim_electrodes(radius=RADIUS, n=16):
    """n electrodes on the rim, clockwise from the top (our y points down)."""
    angle = 2 * np.pi * np.arange(n) / n
    return np.column_stack([radius + radius * np.sin(angle), radius - radius * np.cos(angle)])


def adjacent_protocol(n=16):
    """Drive k, k+1; read V(m) - V(m+1) for every adjacent pair not touching the drive (1-based)."""
    rows = []
    for k in range(n):
        a, b = k, (k + 1) % n
        for m in range(n):
            c, d = m, (m + 1) % n
            if not {a, b} & {c, d}:
                rows.append((a + 1, b + 1, c + 1, d + 1))
    return np.array(rows)


def grid_electrodes():
    """4 x 4 interior grid on the 100 mm square, numbered row-major from the top left."""
    ticks = np.array([12.5, 37.5, 62.5, 87.5])
    x, y = np.meshgrid(ticks, ticks)
    return np.column_stack([x.ravel(), y.ravel()])


def grid_protocol():
    """Every horizontally/vertically adjacent pair drives; every adjacent pair sharing no electrode is read."""
    index = np.arange(1, 17).reshape(4, 4)
    pairs = [(index[r, c], index[r, c + 1]) for r in range(4) for c in range(3)]
    pairs += [(index[r, c], index[r + 1, c]) for c in range(4) for r in range(3)]
    return np.array([(a, b, c, d) for a, b in pairs for c, d in pairs if not {a, b} & {c, d}])


def simulate(sheet, electrodes, readings, centre_mm, radius_mm, target=1200):
    """Reference and one frame from pyEIT's forward model, on a finer mesh than the reconstruction's."""
    truth = pyeit_peer.build_mesh(sheet, electrodes, target)
    protocol = pyeit_peer.build_protocol(readings)
    anomaly = PyEITAnomaly_Circle(center=truth.to_pyeit([centre_mm])[0], r=radius_mm * truth.scale, perm=10.0)
    perm = set_perm(truth.mesh, anomaly, background=1.0).perm
    return pyeit_peer.forward_readings(truth, protocol), pyeit_peer.forward_readings(truth, protocol, perm)


def pixel_grid(width, step=2.5):
    ticks = np.arange(step / 2, width, step)
    x, y = np.meshgrid(ticks, ticks)
    return np.column_stack([x.ravel(), y.ravel()])


def assert_peak(images, pixels, centre_mm, tolerance_mm):
    image = images[0]
    peak = np.nanargmax(image)
    assert np.hypot(*(pixels[peak] - centre_mm)) < tolerance_mm
    assert np.nanmax(image) > 0 and np.nanmax(image) > -np.nanmin(image)  # conductive comes out positive


def test_adjacent_protocol_is_pyeits_own_with_our_measurement_sign():
    readings = adjacent_protocol()
    assert readings.shape == (208, 4)
    ours = pyeit_peer.build_protocol(readings)
    std = pyeit_protocol.create(16, dist_exc=1, step_meas=1, parser_meas="std")
    assert np.array_equal(ours.ex_mat, std.ex_mat)
    assert np.array_equal(ours.meas_mat, std.meas_mat[..., ::-1])  # we read V(m) - V(m+1)
    assert ours.keep_ba.all() and np.array_equal(pyeit_peer.protocol_readings(ours), readings)


def test_disc_images_peak_at_the_conductive_target():
    electrodes, readings = rim_electrodes(), adjacent_protocol()
    centre = np.array([72.0, 35.0])  # upper right (y down), 0.53 R from the centre
    reference, frame = simulate(("disc", RADIUS), electrodes, readings, centre, 0.12 * RADIUS)
    pixels = pixel_grid(2 * RADIUS)
    out = pyeit_peer.run_pyeit(("disc", RADIUS), electrodes, readings, reference, frame[None], pixels,
                               target_elements=500, frame_repeats=5)

    mesh = out["mesh"]
    assert abs(mesh["n_elements"] / 500 - 1) < 0.1 and mesh["max_electrode_node_distance_mm"] < 1e-9
    check = mesh["protocol"]
    assert check["n_readings"] == 208 and check["round_trip"] and check["reciprocal_pairs"] == 208
    assert check["reciprocity_max_rel"] < 1e-10
    outside = np.hypot(*(pixels - RADIUS).T) > RADIUS
    for name in ("jac", "bp", "greit"):
        result = out[name]
        assert result["images"].shape == (1, len(pixels))
        assert result["n_elements"] == mesh["n_elements"]
        assert result["setup_s"] > 0 and result["frame_s"] > 0
        assert np.isnan(result["images"][0, outside]).all()
        assert_peak(result["images"], pixels, centre, 0.25 * RADIUS)


def test_the_per_frame_solver_is_pyeits_greit_on_its_32_by_32_grid():
    """What the reconstruction benchmark times frame by frame: pyEIT's GREIT (n 32) against the reference,
    nothing for the reference itself, the same image from the same setup."""
    electrodes, readings = rim_electrodes(), adjacent_protocol()
    reference, frame = simulate(("disc", RADIUS), electrodes, readings, np.array([72.0, 35.0]), 0.12 * RADIUS)
    solve = pyeit_peer.pyeit_solver(("disc", RADIUS), electrodes, readings, reference, 500)
    image = np.real(solve(frame))
    assert image.shape == (32 * 32,) and np.isfinite(image).all() and np.abs(image).max() > 0
    assert np.abs(np.real(solve(reference))).max() == 0
    again = pyeit_peer.pyeit_solver(("disc", RADIUS), electrodes, readings, reference, 500)
    assert np.array_equal(np.real(again(frame)), image)


def test_grid_protocol_round_trips_and_is_reciprocal_in_pyeit():
    electrodes, readings = grid_electrodes(), grid_protocol()
    assert readings.shape == (448, 4)
    _, counts = np.unique(readings[:, :2], axis=0, return_counts=True)
    assert len(counts) == 24 and counts.min() == 17 and counts.max() == 20

    protocol = pyeit_peer.build_protocol(readings)
    assert protocol.meas_mat.shape == (24, 20, 2) and protocol.keep_ba.sum() == 448
    assert np.array_equal(pyeit_peer.protocol_readings(protocol), readings)

    model = pyeit_peer.build_mesh(SQUARE, electrodes, 500)
    assert model.max_electrode_node_distance_mm < 1e-9
    check = pyeit_peer.check_protocol(model, protocol, readings)
    assert check["n_readings"] == 448 and check["round_trip"]
    assert check["reciprocal_pairs"] == 448 and check["reciprocity_max_rel"] < 1e-10


def test_grid_images_jac_and_greit_find_the_target():
    electrodes, readings = grid_electrodes(), grid_protocol()
    centre = np.array([30.0, 70.0])  # lower left (y down)
    reference, frame = simulate(SQUARE, electrodes, readings, centre, 10.0)
    pixels = pixel_grid(100.0)
    out = pyeit_peer.run_pyeit(SQUARE, electrodes, readings, reference, frame[None], pixels,
                               target_elements=500, algorithms=("jac", "greit"), frame_repeats=5)
    assert set(out) == {"jac", "greit", "mesh"}
    for name in ("jac", "greit"):
        assert np.isfinite(out[name]["images"]).all()  # every pixel lies in the square
        assert_peak(out[name]["images"], pixels, centre, 0.25 * 50.0)


def test_located_points_map_back_to_themselves():
    model = pyeit_peer.build_mesh(("disc", RADIUS), rim_electrodes(), 300)
    points = np.array([[50.0, 50.0], [20.0, 70.0], [95.0, 50.0], [1.0, 1.0]])
    assert np.allclose(model.to_mm(model.to_pyeit(points)), points)
    element, weights = pyeit_peer.locate(model, points)
    assert element[-1] == -1 and np.isnan(weights[-1]).all()  # outside the disc
    nodes = model.mesh.node[:, :2][model.mesh.element[element[:3]]]
    assert np.allclose(np.einsum("pc,pcd->pd", weights[:3], nodes), model.to_pyeit(points[:3]))
