"""Finite-element model of the sheet with the complete electrode model (CEM).

The sheet is meshed with linear triangles; each electrode touches the sheet over
its whole face through a contact impedance z (ohm m^2), so the current it feeds
in at a point is (U - u) / z per unit area. With u the sheet potential and U the
electrode potentials, the CEM system is

    [A(sigma) + M/z    -C/z ] [u]   [0]
    [  -C^T/z         |E|/z ] [U] = [I]

where M is the mass matrix over the electrode faces and C their load vectors.
It becomes badly conditioned as z -> 0 (every 1/z term grows). We solve it in
the variables v = u - U_l on the nodes of face l (u elsewhere) and U. That is an
exact change of variables; afterwards 1/z appears only in the mass term on v:

    [A + M/z     A P  ] [v]   [0]
    [P^T A     P^T A P] [U] = [I]

(P maps each electrode potential to its face nodes). The system stays well
scaled from z = 1e-9 to 1e0 in relative units, and the electrode voltages are
unknowns of their own, read off without any cancellation. The last electrode is
grounded (its unknown removed), which makes the system positive definite.

>>> from appliance.core.named_layouts import get_layout
>>> model = build_fem_model(get_layout("circular-16"))
>>> model.kind, model.n_electrodes
('fem', 16)
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from appliance.core.assembly import build_assembler, offset_potentials, offset_variables
from appliance.core.forward import ForwardModel, with_fill_reducing_order
from appliance.core.layouts import Layout
from appliance.core.mesh import Mesh, mesh_layout
from appliance.errors import LayoutInvalid, ModelInputInvalid

DEFAULT_CONTACT_IMPEDANCE_OHM_M2 = 1e-4
"""Electrode-liquid contact impedance: about 1 ohm cm^2, the order of stainless steel in
saline at the thesis's 17.5 kHz; refined by calibration against measurements."""

_MM2_PER_M2 = 1e6
_LOCAL_MASS = (np.full((3, 3), 1.0) + np.eye(3)) / 12.0
"""A linear triangle's mass matrix over its area."""


def triangle_gradients(mesh: Mesh) -> np.ndarray:
    """Gradients of the three hat functions on each triangle, shape (n_triangles, 3, 2), 1/mm."""
    p = mesh.nodes[mesh.triangles]
    x, y = p[:, :, 0], p[:, :, 1]
    twice_area = 2 * mesh.areas_mm2
    bx = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1)
    by = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1)
    return np.stack([bx, by], axis=2) / twice_area[:, None, None]


def unit_stiffness(mesh: Mesh) -> np.ndarray:
    """Each triangle's stiffness matrix at unit sheet conductance, shape (n_triangles, 3, 3)."""
    g = triangle_gradients(mesh)
    return mesh.areas_mm2[:, None, None] * np.einsum("tik,tjk->tij", g, g)


def _face_mass(mesh: Mesh, conductance_per_mm2: np.ndarray, size: int) -> sp.coo_matrix:
    """Sum over electrode faces of (1/z) * mass matrix, on the first unknowns of a size x size system."""
    rows, cols, data = _face_entries(mesh, conductance_per_mm2, np.arange(mesh.n_nodes))
    return sp.coo_matrix((data, (rows, cols)), shape=(size, size))


def _face_entries(mesh: Mesh, conductance_per_mm2: np.ndarray, unknown_of_node: np.ndarray):
    """Rows, columns and values of (1/z) * mass over every electrode face, nodes numbered by ``unknown_of_node``."""
    on_face = np.flatnonzero(mesh.contact >= 0)
    tri = unknown_of_node[mesh.triangles[on_face]]
    scale = mesh.areas_mm2[on_face] * conductance_per_mm2[mesh.contact[on_face]]
    rows = np.repeat(tri, 3, axis=1).ravel()
    cols = np.tile(tri, (1, 3)).ravel()
    return rows, cols, (scale[:, None, None] * _LOCAL_MASS[None]).ravel()


def face_mass_matrices(mesh: Mesh, n_electrodes: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """For each electrode, its face's nodes (sorted) and the mass matrix over them, mm^2.

    The face term of the system is this matrix over z (ohm mm^2) acting on u - U_l, so
    it is what differentiates the readings by each contact impedance.
    """
    out = []
    for l in range(n_electrodes):
        faces = np.flatnonzero(mesh.contact == l)
        nodes = np.unique(mesh.triangles[faces])
        local = np.searchsorted(nodes, mesh.triangles[faces])
        mass = np.zeros((len(nodes), len(nodes)))
        np.add.at(mass, (np.repeat(local, 3, axis=1).ravel(), np.tile(local, (1, 3)).ravel()),
                  (mesh.areas_mm2[faces, None, None] * _LOCAL_MASS[None]).ravel())
        out.append((nodes, mass))
    return tuple(out)


def build_fem_model(layout: Layout, mesh: Mesh | None = None, *, density: float = 1.0,
                    contact_impedance_ohm_m2: float | np.ndarray = DEFAULT_CONTACT_IMPEDANCE_OHM_M2
                    ) -> ForwardModel:
    """Build the CEM finite-element model of ``layout``.

    Parameters
    ----------
    layout : Layout
    mesh : Mesh, optional
        A mesh of ``layout``; by default :func:`mesh_layout` at ``density``.
    contact_impedance_ohm_m2 : float or ndarray of shape (n_electrodes,)
        Contact impedance of each electrode face, ohm m^2 (positive).

    Raises
    ------
    ModelInputInvalid
        A contact impedance is not positive and finite.
    LayoutInvalid
        The mesh does not give every electrode its own contact nodes.
    """
    mesh = mesh if mesh is not None else mesh_layout(layout, density)
    n_nodes, n_el = mesh.n_nodes, layout.n_electrodes
    z = _checked_contact(contact_impedance_ohm_m2, n_el)
    face_of_node, contact_nodes = _face_nodes(mesh, n_el)

    # Unknowns: v on every node, then U for electrodes 1..L; the last is grounded.
    n_unknowns = n_nodes + n_el
    local = unit_stiffness(mesh)
    tri = mesh.triangles
    base = np.where(face_of_node >= 0, n_nodes + face_of_node, -1)    # the U each node's potential carries
    dofs, expanded = offset_variables(tri, local, base[tri])
    keep = np.arange(n_unknowns - 1)
    system = build_assembler(n_unknowns, dofs, expanded, _face_mass(mesh, 1.0 / (z * _MM2_PER_M2), n_unknowns), keep)
    electrodes = sp.csc_matrix((np.ones(n_el - 1), (n_nodes + np.arange(n_el - 1), np.arange(n_el - 1))),
                               shape=(n_unknowns - 1, n_el))
    node_map = offset_potentials(base, n_unknowns, keep)
    return with_fill_reducing_order(ForwardModel(
        "fem", system, electrodes, mesh.centroids_mm, mesh.areas_mm2, np.zeros(mesh.n_triangles, dtype=bool),
        node_map, mesh.nodes, tri, local, contact_nodes))


def with_contact_impedance(model: ForwardModel, mesh: Mesh, contact_impedance_ohm_m2: float | np.ndarray
                           ) -> ForwardModel:
    """``model``, built by :func:`build_fem_model` on ``mesh``, at other contact impedances.

    Contact impedance enters only the faces' mass terms, which act on the face nodes'
    own offset unknowns; they are re-assembled onto the model's fixed sparsity pattern
    and numbering, so no ordering or factorisation is needed to make the new model
    (a fit that tries many contact impedances pays only for its solves).

    Raises
    ------
    ModelInputInvalid
        Not a finite-element model of ``mesh``, or a contact impedance not positive and finite.
    """
    if model.kind != "fem" or len(model.nodes_mm) != mesh.n_nodes or model.n_elements != mesh.n_triangles:
        raise ModelInputInvalid("contact impedance can only be changed on a finite-element model of the given mesh")
    z = _checked_contact(contact_impedance_ohm_m2, model.n_electrodes)
    system = model.system
    rows, cols, data = _face_entries(mesh, 1.0 / (z * _MM2_PER_M2), _own_unknowns(model))
    pattern = np.repeat(np.arange(system.n, dtype=np.int64), np.diff(system.indptr)) * system.n + system.indices
    keys = rows * system.n + cols
    slot = np.searchsorted(pattern, keys)
    if not np.array_equal(pattern[np.minimum(slot, len(pattern) - 1)], keys):
        raise ModelInputInvalid("the mesh's electrode faces do not match the model's sparsity pattern")
    fixed = np.bincount(slot, weights=data, minlength=system.nnz)
    return dataclasses.replace(model, system=dataclasses.replace(system, fixed=fixed))


def _own_unknowns(model: ForwardModel) -> np.ndarray:
    """The unknown holding each node's own potential (its offset from its electrode on a face)."""
    node_map = sp.csr_matrix(model.node_map)
    electrode_unknowns = sp.csc_matrix(model.electrodes).indices
    rows = np.repeat(np.arange(node_map.shape[0]), np.diff(node_map.indptr))
    own = ~np.isin(node_map.indices, electrode_unknowns)
    unknowns = np.full(node_map.shape[0], -1, dtype=np.int64)
    unknowns[rows[own]] = node_map.indices[own]
    return unknowns


def _checked_contact(contact_impedance_ohm_m2, n_electrodes: int) -> np.ndarray:
    z = np.asarray(contact_impedance_ohm_m2, dtype=float)
    if z.ndim > 1 or (z.ndim == 1 and len(z) != n_electrodes):
        raise ModelInputInvalid(f"contact impedance needs one value or one per electrode ({n_electrodes}), "
                                f"got shape {z.shape}")
    z = np.broadcast_to(z, (n_electrodes,))
    if not np.all(np.isfinite(z) & (z > 0)):
        bad = int(np.flatnonzero(~(np.isfinite(z) & (z > 0)))[0])
        raise ModelInputInvalid(f"contact impedance of electrode {bad + 1} must be positive and finite, "
                                f"got {float(z[bad])} ohm m^2")
    return z


def _face_nodes(mesh: Mesh, n_electrodes: int) -> tuple[np.ndarray, tuple]:
    """For each node the electrode whose face it lies on (-1 if none), and each face's nodes."""
    face_of_node = np.full(mesh.n_nodes, -1)
    contact_nodes = []
    for l in range(n_electrodes):
        nodes = np.unique(mesh.triangles[mesh.contact == l])
        if nodes.size == 0:
            raise LayoutInvalid(f"mesh has no triangle on electrode {l + 1}")
        clash = nodes[face_of_node[nodes] >= 0]
        if clash.size:
            raise LayoutInvalid(f"electrodes {face_of_node[clash[0]] + 1} and {l + 1} share mesh node "
                                f"{clash[0]}: refine the mesh or move them apart")
        face_of_node[nodes] = l
        contact_nodes.append(nodes)
    return face_of_node, tuple(contact_nodes)


def relative_contact_impedance(layout: Layout, contact_impedance_ohm_m2: float, sheet_conductance_s: float
                               ) -> float:
    """Contact resistance of the smallest electrode face over the sheet resistance per square.

    z_rel = z * sigma / A: 1e-9 is an almost ideal electrode, 1 a poor one.
    """
    area_m2 = min(layout.electrode_area_mm2(e) for e in layout.electrodes) / _MM2_PER_M2
    return contact_impedance_ohm_m2 * sheet_conductance_s / area_m2
