"""Meshes: valid, conforming, electrode faces resolved, symmetric, density honoured."""

import math

import numpy as np
import pytest

from appliance.core.layouts import SectorElectrode

from appliance.core.mesh import MeshSpec, mesh_layout
from appliance.core.named_layouts import get_layout
from appliance.errors import LayoutInvalid


def edges_of(mesh):
    e = np.sort(np.vstack([mesh.triangles[:, [0, 1]], mesh.triangles[:, [1, 2]], mesh.triangles[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(e, axis=0, return_counts=True)
    return unique, counts


@pytest.mark.parametrize("name", ["circular-16", "square-16", "grid-4x4", "grid-8x16"])
def test_mesh_is_a_valid_conforming_triangulation(name):
    layout = get_layout(name)
    mesh = mesh_layout(layout)
    assert np.all(mesh.areas_mm2 > 0), "every triangle counter-clockwise and non-degenerate"
    edges, counts = edges_of(mesh)
    assert counts.max() == 2, "no edge shared by more than two triangles"
    assert mesh.n_nodes - len(edges) + mesh.n_triangles == 1, "Euler characteristic of a disc"
    boundary = np.unique(edges[counts == 1])
    p = mesh.nodes[boundary]
    if name == "circular-16":
        assert np.allclose(np.hypot(p[:, 0] - 50, p[:, 1] - 50), 50)
    else:
        w, h = layout.sheet.size_mm
        on_edge = np.isclose(p[:, 0], 0) | np.isclose(p[:, 0], w) | np.isclose(p[:, 1], 0) | np.isclose(p[:, 1], h)
        assert on_edge.all()
    assert len(np.unique(mesh.triangles)) == mesh.n_nodes, "no unused node"


@pytest.mark.parametrize("name", ["square-16", "grid-4x4", "grid-8x16"])
def test_rectangular_faces_and_sheet_are_covered_exactly(name):
    layout = get_layout(name)
    mesh = mesh_layout(layout)
    assert mesh.areas_mm2.sum() == pytest.approx(layout.sheet.area_mm2, rel=1e-12)
    for index, e in enumerate(layout.electrodes):
        assert mesh.areas_mm2[mesh.contact == index].sum() == pytest.approx(e.area_mm2, rel=1e-12)


def test_disc_faces_converge_to_their_curved_area():
    layout = get_layout("circular-16")
    errors = []
    for density in (1, 2, 4):
        mesh = mesh_layout(layout, density)
        exact = layout.electrode_area_mm2(layout.electrodes[0])
        errors.append(abs(mesh.areas_mm2[mesh.contact == 0].sum() - exact) / exact)
        assert mesh.areas_mm2.sum() == pytest.approx(math.pi * 50**2, rel=2e-3 / density**2)
    assert errors[0] < 1e-3 and errors[1] < errors[0] / 3 and errors[2] < errors[1] / 3


def test_square_meshes_keep_the_layout_symmetry():
    for name in ("square-16", "grid-4x4"):
        mesh = mesh_layout(get_layout(name))
        key = {tuple(np.round(p, 9)) for p in mesh.nodes}
        mirrored = {tuple(np.round([100 - x, y], 9)) for x, y in mesh.nodes}
        transposed = {tuple(np.round([y, x], 9)) for x, y in mesh.nodes}
        assert key == mirrored == transposed
        tri_key = {tuple(sorted(tuple(np.round(mesh.nodes[v], 9)) for v in t)) for t in mesh.triangles}
        tri_mirror = {tuple(sorted(tuple(np.round([100 - mesh.nodes[v][0], mesh.nodes[v][1]], 9)) for v in t))
                      for t in mesh.triangles}
        assert tri_key == tri_mirror, "alternating diagonals mirror onto themselves"


def test_disc_mesh_turns_onto_itself_by_one_electrode():
    mesh = mesh_layout(get_layout("circular-16"))
    phi = math.radians(22.5)
    x, y = mesh.nodes[:, 0] - 50, mesh.nodes[:, 1] - 50
    turned = np.column_stack([50 + x * math.cos(phi) - y * math.sin(phi), 50 + x * math.sin(phi) + y * math.cos(phi)])
    key = {tuple(np.round(p, 7)) for p in mesh.nodes}
    assert {tuple(np.round(p, 7)) for p in turned} == key


def test_density_scales_the_node_count():
    layout = get_layout("grid-4x4")
    n1, n2 = mesh_layout(layout, 1).n_nodes, mesh_layout(layout, 2).n_nodes
    assert 3.0 < n2 / n1 < 4.5


def test_electrode_edges_are_mesh_lines_even_when_finer_spec_given():
    layout = get_layout("grid-4x4")
    mesh = mesh_layout(layout, spec=MeshSpec(0.5, 2.0, 1.2))
    for e in layout.electrodes:
        x0, y0, x1, y1 = e.bounds_mm
        assert np.isclose(mesh.nodes[:, 0], x0).any() and np.isclose(mesh.nodes[:, 1], y1).any()


@pytest.mark.parametrize("bad", [dict(density=0), dict(density=-1)])
def test_bad_density_is_refused(bad):
    with pytest.raises(LayoutInvalid, match="density must be positive"):
        mesh_layout(get_layout("grid-4x4"), **bad)


def test_bad_spec_is_refused():
    with pytest.raises(LayoutInvalid, match="mesh spec"):
        MeshSpec(2.0, 1.0)


def test_sector_faces_assigned_to_their_electrode():
    layout = get_layout("circular-16")
    mesh = mesh_layout(layout)
    for index, e in enumerate(layout.electrodes):
        assert isinstance(e, SectorElectrode)
        inside = e.contains(layout.sheet, mesh.centroids_mm[mesh.contact == index])
        assert inside.all() and (mesh.contact == index).sum() >= 8
