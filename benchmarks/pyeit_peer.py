"""pyEIT 1.2.4 as a peer: its JAC, BP and GREIT on our sheet, electrodes, protocol and frames.

The main entry point is :func:`run_pyeit`. The helpers it is built from (:func:`build_mesh`,
:func:`build_protocol`, :func:`protocol_readings`, :func:`forward_readings`, :func:`check_protocol`)
are public so that tests and benchmarks can simulate data with pyEIT's own forward model.

Conventions. Our coordinates are millimetres from the sheet's top-left corner, x right, y down.
pyEIT works in a frame centred on the sheet, scaled so that the sheet spans about [-1, 1], with y
up: ``u = (x - xc) * scale``, ``v = -(y - yc) * scale``. pyEIT models point electrodes at mesh
nodes, without contact impedance.

Notes
-----
pyEIT 1.2.4 needs the same number of measurements for every excitation. A protocol with a varying
count per drive is padded (each short excitation repeats its last pair) and ``keep_ba`` marks the
real readings, in pyEIT's order: ``forward_vector[protocol.keep_ba]`` is our reading vector. The
1.2.4 solvers ignore ``keep_ba``, so the solver classes here drop the padded rows from the Jacobian
(or the back-projection matrix) just before pyEIT forms its reconstruction matrix; the matrices are
then exactly what pyEIT would compute for our protocol, and ``solve`` takes our reading vectors.
"""

from __future__ import annotations

import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import pyeit.mesh as pyeit_mesh
from pyeit.eit.bp import BP
from pyeit.eit.fem import EITForward
from pyeit.eit.greit import GREIT
from pyeit.eit.jac import JAC
from pyeit.eit.protocol import PyEITProtocol
from pyeit.mesh import shape

#: Solver settings, as in the reference measurements (eit-anchors.md, section 1).
SETTINGS = {
    "jac": {"setup": {"p": 0.5, "lamb": 0.01, "method": "kotre", "perm": 1, "jac_normalized": True},
            "normalize": True},
    "bp": {"setup": {"weight": "none"}, "normalize": True},
    "greit": {"setup": {"p": 0.5, "lamb": 0.01, "n": 32, "s": 20, "ratio": 0.1, "perm": 1,
                        "jac_normalized": True},
              "normalize": True},
}

# Area per element over h0**2 for pyEIT's uniform distmesh (0.44 to 0.46 in the reference runs).
_ELEMENT_AREA_OVER_H0_SQUARED = 0.45


@contextmanager
def _quiet_pyeit():
    """Silence pyEIT's warning that the protocol uses fewer electrodes than the mesh has."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The mesh use")
        yield


# --------------------------------------------------------------------------------------------
# Geometry and mesh
# --------------------------------------------------------------------------------------------


@dataclass
class PyeitModel:
    """A pyEIT mesh of our sheet, with the map between our millimetres and pyEIT's frame.

    Attributes
    ----------
    mesh : pyeit.mesh.PyEITMesh
        The mesh; electrode ``i`` (0-based) is node ``mesh.el_pos[i] == i``.
    sheet : tuple
        Our sheet description, ``("disc", r)`` or ``("rect", w, h)``.
    centre_mm : ndarray, shape (2,)
        The sheet centre in our coordinates.
    scale : float
        pyEIT units per millimetre.
    half_extent : ndarray, shape (2,)
        Half width and half height of the sheet in pyEIT units.
    h0 : float
        The distmesh edge length used.
    seed : int
        The numpy seed the mesh was built with.
    mesh_s : float
        Wall time of the last (kept) mesh build, in seconds.
    attempts : list of tuple
        ``(h0, n_elements)`` of every mesh built while matching the target size.
    max_electrode_node_distance_mm : float
        Largest distance from an electrode to the nearest mesh node, in mm.
    """

    mesh: object
    sheet: tuple
    centre_mm: np.ndarray
    scale: float
    half_extent: np.ndarray
    h0: float
    seed: int
    mesh_s: float
    attempts: list = field(default_factory=list)
    max_electrode_node_distance_mm: float = np.nan

    def to_pyeit(self, points_mm):
        """Map points from our millimetres (y down) to pyEIT's frame (y up).

        Parameters
        ----------
        points_mm : array_like, shape (p, 2)

        Returns
        -------
        ndarray, shape (p, 2)
        """
        points = np.asarray(points_mm, dtype=float).reshape(-1, 2) - self.centre_mm
        return np.column_stack([points[:, 0], -points[:, 1]]) * self.scale

    def to_mm(self, points):
        """Map points from pyEIT's frame back to our millimetres (inverse of :meth:`to_pyeit`).

        Parameters
        ----------
        points : array_like, shape (p, 2) or (p, 3)

        Returns
        -------
        ndarray, shape (p, 2)
        """
        points = np.asarray(points, dtype=float)[:, :2] / self.scale
        return np.column_stack([points[:, 0], -points[:, 1]]) + self.centre_mm

    @property
    def area(self) -> float:
        """Sheet area in pyEIT units squared."""
        if self.sheet[0] == "disc":
            return float(np.pi)
        return float(4.0 * self.half_extent[0] * self.half_extent[1])


def _sheet_frame(sheet):
    """Centre (mm), scale (units/mm) and half extents (units) of a sheet."""
    kind = sheet[0]
    if kind == "disc":
        radius = float(sheet[1])
        return np.array([radius, radius]), 1.0 / radius, np.array([1.0, 1.0])
    if kind == "rect":
        width, height = float(sheet[1]), float(sheet[2])
        scale = 2.0 / max(width, height)
        return np.array([width / 2, height / 2]), scale, np.array([width, height]) * scale / 2
    raise ValueError(f"unknown sheet {sheet!r}: expected ('disc', r) or ('rect', w, h)")


def _distance_function(sheet, half_extent):
    """pyEIT signed distance function of the sheet, in pyEIT's frame."""
    if sheet[0] == "disc":
        return shape.circle
    p1, p2 = -half_extent, half_extent

    def rectangle(pts):
        return shape.rectangle(pts, p1=p1, p2=p2)

    return rectangle


def _fixed_points(sheet, half_extent, electrodes, h0):
    """Electrodes first (so electrode i is node i), then any rectangle corner not already taken."""
    if sheet[0] == "disc":
        return electrodes
    a, b = half_extent
    corners = np.array([[-a, -b], [a, -b], [a, b], [-a, b]])
    gaps = np.linalg.norm(corners[:, None, :] - electrodes[None, :, :], axis=2).min(axis=1)
    return np.vstack([electrodes, corners[gaps > 0.25 * h0]])


def _drop_unused_nodes(mesh, n_el):
    """Remove nodes that belong to no element (they would make the FEM matrix singular)."""
    used = np.zeros(mesh.n_nodes, dtype=bool)
    used[mesh.element.ravel()] = True
    if not used[:n_el].all():
        missing = np.flatnonzero(~used[:n_el]) + 1
        raise RuntimeError(f"electrodes {missing.tolist()} are on no pyEIT element")
    if used.all():
        return mesh
    new_index = np.cumsum(used) - 1
    return pyeit_mesh.PyEITMesh(node=mesh.node[used], element=new_index[mesh.element],
                                el_pos=np.arange(n_el), ref_node=0)


def _distmesh(fd, p_fix, bbox, h0, n_el, seed):
    """One seeded pyEIT distmesh build; restores numpy's global random state afterwards."""
    state = np.random.get_state()
    try:
        np.random.seed(seed)
        start = time.perf_counter()
        mesh = pyeit_mesh.create(n_el, fd=fd, fh=shape.area_uniform, h0=h0, p_fix=p_fix, bbox=bbox)
        seconds = time.perf_counter() - start
    finally:
        np.random.set_state(state)
    return _drop_unused_nodes(mesh, n_el), seconds


def build_mesh(sheet, electrodes_mm, target_elements, seed=0, tolerance=0.05, max_attempts=6):
    """Build a pyEIT distmesh of the sheet with a point electrode at every electrode centre.

    The edge length ``h0`` is first estimated from the sheet area, then corrected from the
    element count of each build (count ~ 1/h0**2) until the count is within ``tolerance`` of
    ``target_elements`` or ``max_attempts`` meshes have been built; the closest mesh is kept.

    Parameters
    ----------
    sheet : tuple
        ``("disc", radius_mm)`` (centre at (radius, radius)) or ``("rect", width_mm, height_mm)``.
    electrodes_mm : array_like, shape (L, 2)
        Electrode centres in our coordinates (mm, y down); on the boundary or inside the sheet.
    target_elements : int
        Wanted number of triangles.
    seed : int, optional
        Seed for numpy's global generator, which pyEIT's distmesh draws from (the global state
        is restored afterwards). With the uniform size function used here every draw is
        accepted, so in pyEIT 1.2.4 the mesh does not actually depend on the seed.
    tolerance : float, optional
        Relative element-count tolerance at which the search stops.
    max_attempts : int, optional
        Largest number of meshes built.

    Returns
    -------
    PyeitModel
    """
    centre, scale, half = _sheet_frame(sheet)
    model = PyeitModel(mesh=None, sheet=tuple(sheet), centre_mm=centre, scale=scale, half_extent=half,
                       h0=np.nan, seed=int(seed), mesh_s=np.nan)
    electrodes = model.to_pyeit(electrodes_mm)
    n_el = len(electrodes)
    if sheet[0] == "disc":
        outside = np.linalg.norm(electrodes, axis=1) - 1.0
    else:
        outside = np.max(np.abs(electrodes) - half, axis=1)
    if np.any(outside > 1e-6):
        bad = np.flatnonzero(outside > 1e-6) + 1
        raise ValueError(f"electrodes {bad.tolist()} lie outside the sheet")
    fd = _distance_function(sheet, half)
    bbox = np.array([-half, half])

    h0 = float(np.sqrt(model.area / (_ELEMENT_AREA_OVER_H0_SQUARED * target_elements)))
    best = None
    for _ in range(max_attempts):
        p_fix = _fixed_points(sheet, half, electrodes, h0)
        mesh, seconds = _distmesh(fd, p_fix, bbox, h0, n_el, seed)
        model.attempts.append((h0, mesh.n_elems))
        miss = abs(mesh.n_elems / target_elements - 1.0)
        if best is None or miss < best[0]:
            best = (miss, mesh, h0, seconds)
        if miss <= tolerance:
            break
        h0 = float(h0 * np.sqrt(mesh.n_elems / target_elements))
    _, model.mesh, model.h0, model.mesh_s = best

    nodes = model.mesh.node[:, :2]
    gaps = np.linalg.norm(nodes[None, :, :] - electrodes[:, None, :], axis=2).min(axis=1)
    own = np.linalg.norm(nodes[:n_el] - electrodes, axis=1)
    model.max_electrode_node_distance_mm = float(max(gaps.max(), own.max()) / scale)
    return model


# --------------------------------------------------------------------------------------------
# Protocol
# --------------------------------------------------------------------------------------------


def build_protocol(readings):
    """Express our protocol as a pyEIT 1.2.4 ``PyEITProtocol``.

    Each run of consecutive readings with the same drive pair becomes one excitation (``ex_mat``
    row ``[drive_pos, drive_neg]``, 0-based: pyEIT injects +1 at the first and -1 at the second);
    its readings become ``meas_mat`` rows ``[meas_pos, meas_neg]`` (pyEIT measures
    ``V[first] - V[second]``), in our order. Short excitations are padded by repeating their last
    pair, and ``keep_ba`` (length ``n_exc * n_meas``) is True exactly on the real readings.

    Parameters
    ----------
    readings : array_like of int, shape (n, 4)
        1-based ``(drive_pos, drive_neg, meas_pos, meas_neg)``.

    Returns
    -------
    pyeit.eit.protocol.PyEITProtocol
    """
    readings = np.asarray(readings, dtype=int)
    if readings.ndim != 2 or readings.shape[1] != 4 or len(readings) == 0:
        raise ValueError(f"readings must be an (n, 4) array, got shape {readings.shape}")
    if readings.min() < 1:
        raise ValueError("electrode numbers are 1-based")
    if np.any(readings[:, 0] == readings[:, 1]) or np.any(readings[:, 2] == readings[:, 3]):
        raise ValueError("a drive or measurement pair uses one electrode twice")
    zero = readings - 1
    starts = np.flatnonzero(np.r_[True, np.any(np.diff(zero[:, :2], axis=0) != 0, axis=1)])
    stops = np.r_[starts[1:], len(zero)]
    n_meas = int(np.max(stops - starts))
    ex_mat = zero[starts, :2].copy()
    meas_mat = np.empty((len(starts), n_meas, 2), dtype=int)
    keep = np.zeros((len(starts), n_meas), dtype=bool)
    for i, (start, stop) in enumerate(zip(starts, stops)):
        count = stop - start
        meas_mat[i, :count] = zero[start:stop, 2:]
        meas_mat[i, count:] = zero[stop - 1, 2:]
        keep[i, :count] = True
    return PyEITProtocol(ex_mat=ex_mat, meas_mat=meas_mat, keep_ba=keep.ravel())


def protocol_readings(protocol):
    """Our (n, 4) 1-based readings back from a protocol made by :func:`build_protocol`.

    Parameters
    ----------
    protocol : pyeit.eit.protocol.PyEITProtocol

    Returns
    -------
    ndarray of int, shape (n, 4)
    """
    drives = np.repeat(protocol.ex_mat[:, None, :], protocol.n_meas, axis=1)
    full = np.concatenate([drives, protocol.meas_mat], axis=2).reshape(-1, 4)
    return full[np.asarray(protocol.keep_ba, dtype=bool)] + 1


def forward_readings(model, protocol, perm=1.0):
    """Readings in our order from pyEIT's own forward model (``EITForward.solve_eit``).

    Parameters
    ----------
    model : PyeitModel
    protocol : pyeit.eit.protocol.PyEITProtocol
        From :func:`build_protocol`.
    perm : float or ndarray, optional
        Conductivity per element (pyEIT's ``perm``).

    Returns
    -------
    ndarray, shape (n,)
    """
    with _quiet_pyeit():
        forward = EITForward(model.mesh, protocol)
        full = forward.solve_eit(perm)
    return np.real(full[np.asarray(protocol.keep_ba, dtype=bool)])


def _reciprocal_index(readings):
    """For each reading, the index and sign of its reciprocal reading, or -1 if absent."""
    lookup = {tuple(row): i for i, row in enumerate(readings.tolist())}
    index = np.full(len(readings), -1)
    sign = np.zeros(len(readings))
    for i, (a, b, c, d) in enumerate(readings.tolist()):
        for key, s in (((c, d, a, b), 1.0), ((d, c, b, a), 1.0), ((c, d, b, a), -1.0), ((d, c, a, b), -1.0)):
            j = lookup.get(key)
            if j is not None:
                index[i], sign[i] = j, s
                break
    return index, sign


def check_protocol(model, protocol, readings):
    """Check that pyEIT sees our protocol: count, round trip and reciprocity of homogeneous readings.

    Parameters
    ----------
    model : PyeitModel
    protocol : pyeit.eit.protocol.PyEITProtocol
    readings : array_like of int, shape (n, 4)

    Returns
    -------
    dict
        ``n_readings`` (what pyEIT's forward model returned after ``keep_ba``), ``n_expected``,
        ``round_trip`` (bool), ``n_exc``, ``n_meas_padded``, ``reciprocal_pairs`` (readings whose
        reciprocal is also in the protocol) and ``reciprocity_max_rel`` (largest
        ``|v_i - s v_j| / max|v|`` over them; NaN if there are none).
    """
    readings = np.asarray(readings, dtype=int)
    v = forward_readings(model, protocol)
    index, sign = _reciprocal_index(readings)
    has = index >= 0
    if has.any() and len(v) == len(readings):
        error = np.max(np.abs(v[has] - sign[has] * v[index[has]])) / np.max(np.abs(v))
    else:
        error = np.nan
    return {
        "n_readings": int(len(v)),
        "n_expected": int(len(readings)),
        "round_trip": bool(np.array_equal(protocol_readings(protocol), readings)),
        "n_exc": int(protocol.n_exc),
        "n_meas_padded": int(protocol.n_meas),
        "reciprocal_pairs": int(has.sum()),
        "reciprocity_max_rel": float(error),
    }


# --------------------------------------------------------------------------------------------
# Solvers restricted to the real readings
# --------------------------------------------------------------------------------------------


class _KeptJAC(JAC):
    """pyEIT's JAC with the padded protocol rows dropped before H is formed."""

    def __init__(self, mesh, protocol):
        super().__init__(mesh, protocol)
        self.keep = np.asarray(protocol.keep_ba, dtype=bool)

    def _compute_h(self, jac, p, lamb, method="kotre"):
        return super()._compute_h(jac[self.keep], p, lamb, method)


class _KeptBP(BP):
    """pyEIT's BP with the padded protocol rows dropped from the smear matrix."""

    def __init__(self, mesh, protocol):
        super().__init__(mesh, protocol)
        self.keep = np.asarray(protocol.keep_ba, dtype=bool)

    def _compute_h(self, b_matrix):
        return super()._compute_h(b_matrix[self.keep])


class _KeptGREIT(GREIT):
    """pyEIT's GREIT with the padded protocol rows dropped before H is formed."""

    def __init__(self, mesh, protocol):
        super().__init__(mesh, protocol)
        self.keep = np.asarray(protocol.keep_ba, dtype=bool)

    def _compute_h(self, jac, w_mat):
        return super()._compute_h(jac[self.keep], w_mat)


_SOLVERS = {"jac": _KeptJAC, "bp": _KeptBP, "greit": _KeptGREIT}


# --------------------------------------------------------------------------------------------
# Sampling images at our pixels
# --------------------------------------------------------------------------------------------


def locate(model, points_mm, chunk_elements=500_000):
    """Find the pyEIT triangle containing each point, with barycentric coordinates.

    Parameters
    ----------
    model : PyeitModel
    points_mm : array_like, shape (p, 2)
        Points in our coordinates.
    chunk_elements : int, optional
        Bound on points x triangles handled at once (memory).

    Returns
    -------
    element : ndarray of int, shape (p,)
        Index of the containing triangle (the first one for points on a shared edge), -1 outside.
    weights : ndarray, shape (p, 3)
        Barycentric coordinates of the point in that triangle (NaN outside).
    """
    points = model.to_pyeit(points_mm)
    nodes = model.mesh.node[:, :2]
    tri = model.mesh.element
    a = nodes[tri[:, 0]]
    edges = np.stack([nodes[tri[:, 1]] - a, nodes[tri[:, 2]] - a], axis=2)  # columns: b - a, c - a
    det = edges[:, 0, 0] * edges[:, 1, 1] - edges[:, 0, 1] * edges[:, 1, 0]
    good = np.abs(det) > 1e-14
    inverse = np.full_like(edges, np.nan)
    inverse[good, 0, 0] = edges[good, 1, 1] / det[good]
    inverse[good, 0, 1] = -edges[good, 0, 1] / det[good]
    inverse[good, 1, 0] = -edges[good, 1, 0] / det[good]
    inverse[good, 1, 1] = edges[good, 0, 0] / det[good]

    element = np.full(len(points), -1)
    weights = np.full((len(points), 3), np.nan)
    step = max(1, chunk_elements // max(1, len(tri)))
    eps = 1e-10
    for start in range(0, len(points), step):
        block = points[start:start + step]
        local = np.einsum("eij,pej->pei", inverse, block[:, None, :] - a[None, :, :])
        l0 = 1.0 - local[..., 0] - local[..., 1]
        inside = (local[..., 0] >= -eps) & (local[..., 1] >= -eps) & (l0 >= -eps)
        found = inside.any(axis=1)
        first = np.argmax(inside, axis=1)
        rows = np.flatnonzero(found)
        element[start + rows] = first[rows]
        chosen = local[rows, first[rows]]
        weights[start + rows] = np.column_stack([1.0 - chosen.sum(axis=1), chosen])
    return element, weights


def _sample_elements(values, element):
    """Element values at located points (NaN outside). ``values`` has shape (k, n_elems)."""
    out = np.full((values.shape[0], len(element)), np.nan)
    inside = element >= 0
    out[:, inside] = values[:, element[inside]]
    return out


def _sample_nodes(values, tri, element, weights):
    """Linear interpolation of node values at located points. ``values``: (k, n_nodes)."""
    out = np.full((values.shape[0], len(element)), np.nan)
    inside = element >= 0
    corners = tri[element[inside]]  # (q, 3)
    out[:, inside] = np.einsum("kqc,qc->kq", values[:, corners], weights[inside])
    return out


def _sample_grid(values, xg, yg, mask, points):
    """Bilinear interpolation on pyEIT's GREIT grid, at its true sample coordinates.

    Grid samples outside GREIT's mask are treated as missing; the bilinear weights are
    renormalised over the valid corners of the cell (clamped at the grid's last row/column).
    """
    n_y, n_x = xg.shape
    xv, yv = xg[0, :], yg[:, 0]
    grid = values.reshape(values.shape[0], n_y, n_x).astype(float).copy()
    grid[:, mask.reshape(n_y, n_x)] = np.nan
    fx = (points[:, 0] - xv[0]) / (xv[1] - xv[0])
    fy = (points[:, 1] - yv[0]) / (yv[1] - yv[0])
    ix = np.clip(np.floor(fx).astype(int), 0, n_x - 2)
    iy = np.clip(np.floor(fy).astype(int), 0, n_y - 2)
    tx = np.clip(fx - ix, 0.0, 1.0)
    ty = np.clip(fy - iy, 0.0, 1.0)
    total = np.zeros((values.shape[0], len(points)))
    weight = np.zeros_like(total)
    for dy, wy in ((0, 1.0 - ty), (1, ty)):
        for dx, wx in ((0, 1.0 - tx), (1, tx)):
            corner = grid[:, iy + dy, ix + dx]
            w = np.maximum(wy * wx, 1e-12) * ~np.isnan(corner)
            total += w * np.nan_to_num(corner)
            weight += w
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > 0, total / weight, np.nan)


# --------------------------------------------------------------------------------------------
# Main entry point
# --------------------------------------------------------------------------------------------


def pyeit_solver(sheet, electrodes_mm, readings, reference, target_elements, algorithm="greit", seed=0):
    """pyEIT's ``algorithm`` set up as :func:`run_pyeit` sets it up, as a function of one frame: what a
    caller times beside its own per-frame path, frame by frame.

    Returns ``frame -> solver.solve(frame, reference)`` with :data:`SETTINGS`' normalisation, called as
    :func:`run_pyeit` times it (nothing wrapped around the call).
    """
    readings = np.asarray(readings, dtype=int)
    reference = np.asarray(reference, dtype=float).ravel()
    model = build_mesh(sheet, np.asarray(electrodes_mm, dtype=float).reshape(-1, 2), target_elements, seed=seed)
    settings = SETTINGS[algorithm]
    with _quiet_pyeit():
        solver = _SOLVERS[algorithm](model.mesh, build_protocol(readings))
        solver.setup(**settings["setup"])

    def solve(frame):
        return solver.solve(frame, reference, normalize=settings["normalize"])

    return solve


def run_pyeit(sheet, electrodes_mm, readings, reference, frames, pixel_centres_mm, target_elements,
              algorithms=("jac", "bp", "greit"), frame_repeats=1000, seed=0):
    """Reconstruct our frames with pyEIT 1.2.4's JAC, BP and GREIT, timed, on our pixels.

    Sign convention: pyEIT's, kept as is. ``solve`` returns ``-H dv`` with ``dv`` normalised
    by ``|v0|`` (JAC, GREIT) or ``sign(v0)`` (BP), so a region MORE conductive than the
    reference comes out POSITIVE. Units are pyEIT's (arbitrary, solver-dependent).

    Parameters
    ----------
    sheet : tuple
        ``("disc", radius_mm)``, centre at (radius, radius), or ``("rect", width_mm, height_mm)``.
    electrodes_mm : array_like, shape (L, 2)
        Electrode centres, mm from the top-left corner, y down; on the boundary or inside.
    readings : array_like of int, shape (n, 4)
        1-based ``(drive_pos, drive_neg, meas_pos, meas_neg)``; current enters at ``drive_pos``,
        a reading is ``V(meas_pos) - V(meas_neg)``. The count per drive may vary.
    reference : array_like, shape (n,)
        Homogeneous (reference) readings.
    frames : array_like, shape (k, n) or (n,)
        Readings to reconstruct, in the same order.
    pixel_centres_mm : array_like, shape (p, 2)
        Points (our coordinates) at which every image is reported.
    target_elements : int
        Wanted number of triangles in pyEIT's mesh (matched within about 5 %, see
        :func:`build_mesh`).
    algorithms : sequence of str, optional
        Any of ``"jac"``, ``"bp"``, ``"greit"``, run with :data:`SETTINGS`.
    frame_repeats : int, optional
        Number of timed ``solve`` calls on the first frame; ``frame_s`` is their median.
    seed : int, optional
        Seed for pyEIT's distmesh (see :func:`build_mesh`).

    Returns
    -------
    dict
        For each algorithm, ``{"setup_s", "frame_s", "images", "n_elements", "n_values"}``:
        setup wall time (solver construction with FEM assembly, Jacobian or smear matrix and
        ``H``), median per-frame ``solve`` time, images of shape (k, p) (NaN at points outside
        pyEIT's mesh), the mesh's triangle count, and the length of pyEIT's own image vector
        (elements for JAC, nodes for BP, grid points for GREIT). Key ``"mesh"`` holds
        ``n_nodes``, ``n_elements``, ``h0``, ``seed``, ``mesh_s``, ``attempts``,
        ``max_electrode_node_distance_mm``, ``target_elements`` and ``protocol`` (the result of
        :func:`check_protocol`).

    Raises
    ------
    ValueError
        On inconsistent shapes or unknown algorithms.
    RuntimeError
        If pyEIT does not reproduce our protocol (count, round trip or reciprocity).

    Notes
    -----
    Per-image sampling: JAC's element values are taken from the triangle containing each pixel,
    BP's node values are interpolated linearly in it, GREIT's grid is sampled bilinearly at its
    true sample coordinates (``xg``, ``yg``; pyEIT 1.2.4 puts them on cell corners). Timings
    depend on the BLAS thread count; the reference measurements pinned BLAS to one thread.
    """
    readings = np.asarray(readings, dtype=int)
    reference = np.asarray(reference, dtype=float).ravel()
    frames = np.atleast_2d(np.asarray(frames, dtype=float))
    pixels = np.asarray(pixel_centres_mm, dtype=float).reshape(-1, 2)
    electrodes = np.asarray(electrodes_mm, dtype=float).reshape(-1, 2)
    n = len(readings)
    if reference.shape != (n,) or frames.shape[1] != n:
        raise ValueError(f"{n} readings, but reference has shape {reference.shape} and frames "
                         f"{frames.shape}")
    if readings.max() > len(electrodes):
        raise ValueError(f"readings use electrode {readings.max()} of {len(electrodes)}")
    unknown = set(algorithms) - set(_SOLVERS)
    if unknown:
        raise ValueError(f"unknown algorithms {sorted(unknown)}; choose from {sorted(_SOLVERS)}")

    model = build_mesh(sheet, electrodes, target_elements, seed=seed)
    protocol = build_protocol(readings)
    check = check_protocol(model, protocol, readings)
    reciprocity_failed = check["reciprocal_pairs"] > 0 and not check["reciprocity_max_rel"] <= 1e-8
    if check["n_readings"] != n or not check["round_trip"] or reciprocity_failed:
        raise RuntimeError(f"pyEIT does not reproduce the protocol: {check}")

    mesh = model.mesh
    element, weights = locate(model, pixels)
    points = model.to_pyeit(pixels)
    out = {}
    for name in algorithms:
        settings = SETTINGS[name]
        with _quiet_pyeit():
            start = time.perf_counter()
            solver = _SOLVERS[name](mesh, protocol)
            solver.setup(**settings["setup"])
            setup_s = time.perf_counter() - start

            def solve(v1, solver=solver, normalize=settings["normalize"]):
                return solver.solve(v1, reference, normalize=normalize)

            solve(frames[0])
            times = np.empty(max(1, int(frame_repeats)))
            for i in range(len(times)):
                start = time.perf_counter()
                solve(frames[0])
                times[i] = time.perf_counter() - start
            raw = np.real(np.atleast_2d(solve(frames).T))  # (k, n_values)

        if name == "jac":
            images = _sample_elements(raw, element)
        elif name == "bp":
            images = _sample_nodes(raw, mesh.element, element, weights)
        else:
            images = _sample_grid(raw, solver.xg, solver.yg, solver.mask, points)
            images[:, element < 0] = np.nan
        out[name] = {
            "setup_s": float(setup_s),
            "frame_s": float(np.median(times)),
            "images": images,
            "n_elements": int(mesh.n_elems),
            "n_values": int(raw.shape[1]),
        }
    out["mesh"] = {
        "n_nodes": int(mesh.n_nodes),
        "n_elements": int(mesh.n_elems),
        "target_elements": int(target_elements),
        "h0": float(model.h0),
        "seed": int(seed),
        "mesh_s": float(model.mesh_s),
        "attempts": [(float(h), int(e)) for h, e in model.attempts],
        "max_electrode_node_distance_mm": model.max_electrode_node_distance_mm,
        "protocol": check,
    }
    return out
