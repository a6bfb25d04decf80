"""Triangle meshes of a layout's sheet with every electrode face resolved exactly.

Both generators are conforming and aligned: the edges of each electrode face are
mesh edges, so the contact area of every electrode is exact, and the mesh keeps
the layout's symmetry (mirror and quarter-turn for the square layouts, rotation
by one electrode for the disc), so symmetric scenes give symmetric readings.
Elements are finest at electrode edges, where the current density peaks, and
grow geometrically away from them.

>>> from appliance.core.named_layouts import get_layout
>>> mesh = mesh_layout(get_layout("grid-4x4"))
>>> mesh.n_nodes > 1000, bool(mesh.areas_mm2.min() > 0)
(True, True)
>>> round(float(mesh.areas_mm2.sum()), 6)
10000.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from itertools import pairwise

import numpy as np

from appliance.core.layouts import DiscSheet, Layout, SectorElectrode, disc_of
from appliance.errors import LayoutInvalid


@dataclass(frozen=True)
class Mesh:
    """Linear-triangle mesh of a sheet.

    Attributes
    ----------
    nodes : ndarray, shape (n_nodes, 2)
        Node coordinates, mm (origin top-left, y down).
    triangles : ndarray, shape (n_triangles, 3)
        Node indices of each triangle, counter-clockwise in (x, y).
    contact : ndarray, shape (n_triangles,)
        Index (0-based) of the electrode whose face covers the triangle, -1 if none.
    """

    nodes: np.ndarray
    triangles: np.ndarray
    contact: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "nodes", np.ascontiguousarray(self.nodes, dtype=np.float64))
        object.__setattr__(self, "triangles", np.ascontiguousarray(self.triangles, dtype=np.int64))
        object.__setattr__(self, "contact", np.ascontiguousarray(self.contact, dtype=np.int64))

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @cached_property
    def areas_mm2(self) -> np.ndarray:
        """Triangle areas, shape (n_triangles,), mm^2."""
        p = self.nodes[self.triangles]
        d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])

    @cached_property
    def centroids_mm(self) -> np.ndarray:
        """Triangle centroids, shape (n_triangles, 2), mm."""
        return self.nodes[self.triangles].mean(axis=1)


@dataclass(frozen=True)
class MeshSpec:
    """How fine a mesh is.

    Element size is ``electrode_h_mm`` at electrode edges and grows with distance d
    from them as ``electrode_h_mm + (growth - 1) * d`` (about ``growth`` times per
    element) up to ``max_h_mm``.
    """

    electrode_h_mm: float
    max_h_mm: float
    growth: float = 1.3

    def __post_init__(self):
        if not (self.electrode_h_mm > 0 and self.max_h_mm >= self.electrode_h_mm and self.growth > 1):
            raise LayoutInvalid(
                f"mesh spec needs 0 < electrode_h_mm <= max_h_mm and growth > 1, got {self}"
            )


ELEMENTS_PER_ELECTRODE = 4
"""Default element edges across the narrowest electrode face (see benchmarks/forward.md)."""
MAX_H_OVER_ELECTRODE_H = 4
"""Default largest element edge, in element edges at the electrodes."""
GROWTH = 1.3
"""Default growth of element size per element away from electrode edges."""


def default_spec(layout: Layout, density: float = 1.0) -> MeshSpec:
    """The default mesh spec for ``layout``; ``density`` scales element count per axis.

    ``density=2`` halves every element edge (about four times the nodes): the
    whole size function is scaled, grading included.
    """
    if not density > 0:
        raise LayoutInvalid(f"mesh density must be positive, got {density}")
    h_el = _narrowest_electrode_mm(layout) / ELEMENTS_PER_ELECTRODE
    return MeshSpec(h_el / density, MAX_H_OVER_ELECTRODE_H * h_el / density, 1 + (GROWTH - 1) / density)


def mesh_layout(layout: Layout, density: float = 1.0, spec: MeshSpec | None = None) -> Mesh:
    """Mesh ``layout``'s sheet, electrode faces resolved; ``spec`` overrides ``density``."""
    spec = spec or default_spec(layout, density)
    if isinstance(layout.sheet, DiscSheet):
        nodes, triangles = _row_major(*_disc_mesh(layout, spec))
    else:
        nodes, triangles = _rect_mesh(layout, spec)
    mesh = Mesh(nodes, triangles, np.full(len(triangles), -1))
    contact = mesh.contact.copy()
    for index, electrode in enumerate(layout.electrodes):
        inside = electrode.contains(layout.sheet, mesh.centroids_mm)
        contact[inside] = index
    mesh = Mesh(mesh.nodes, mesh.triangles, contact)
    _check_faces_resolved(layout, mesh)
    return mesh


def _narrowest_electrode_mm(layout: Layout) -> float:
    """The electrode dimension the elements must resolve: the arc of a rim sector (its depth,
    which may be a thin stand-in for a wall electrode, gets its own ring of elements)."""
    sizes = []
    for e in layout.electrodes:
        if isinstance(e, SectorElectrode):
            sizes.append(math.radians(e.width_deg) * disc_of(layout.sheet).radius_mm)
        else:
            sizes.append(min(e.width_mm, e.height_mm))
    return min(sizes)


def _check_faces_resolved(layout: Layout, mesh: Mesh) -> None:
    """Every electrode face must be covered by triangles to 1e-9 of its area."""
    covered = np.bincount(mesh.contact[mesh.contact >= 0], weights=mesh.areas_mm2[mesh.contact >= 0],
                          minlength=layout.n_electrodes)
    for e, area in zip(layout.electrodes, covered):
        if isinstance(e, SectorElectrode):
            continue  # a polygonal rim approximates a curved face; its error is measured in the tests
        exact = e.area_mm2
        if abs(area - exact) > 1e-9 * exact:
            raise LayoutInvalid(f"mesh does not resolve electrode {e.number}: {area:.6g} of {exact:.6g} mm^2")


# ---------------------------------------------------------------------------
# Rectangular sheets: graded tensor grid, alternating diagonals

def _rect_mesh(layout: Layout, spec: MeshSpec) -> tuple[np.ndarray, np.ndarray]:
    width, height = layout.sheet.size_mm
    xs = graded_axis(width, [v for e in layout.rectangles for v in e.bounds_mm[0::2]], spec)
    ys = graded_axis(height, [v for e in layout.rectangles for v in e.bounds_mm[1::2]], spec)
    nx, ny = len(xs), len(ys)
    gx, gy = np.meshgrid(xs, ys)
    nodes = np.column_stack([gx.ravel(), gy.ravel()])
    i_grid, j_grid = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    i, j = i_grid.ravel(), j_grid.ravel()
    n00 = j * nx + i
    n10, n01, n11 = n00 + 1, n00 + nx, n00 + nx + 1
    even = (i + j) % 2 == 0
    first = np.where(even[:, None], np.column_stack([n00, n10, n11]), np.column_stack([n00, n10, n01]))
    second = np.where(even[:, None], np.column_stack([n00, n11, n01]), np.column_stack([n10, n11, n01]))
    return nodes, _counter_clockwise(nodes, np.vstack([first, second]))


def graded_axis(length: float, edges: list[float], spec: MeshSpec) -> np.ndarray:
    """Node positions on [0, length]: every electrode edge is a node, spacing
    ``spec.electrode_h_mm`` at those edges growing by ``spec.growth`` up to ``spec.max_h_mm``.

    The result is mirror-symmetric when the edges are, and has an even number of
    cells then, so that alternating diagonals keep the mirror symmetry.
    """
    marks = np.unique(np.clip(np.concatenate([[0.0, length], np.asarray(edges, dtype=float)]), 0.0, length))
    marks = marks[np.concatenate([[True], np.diff(marks) > 1e-9 * length])]
    marks[-1] = length
    inner = np.asarray(edges, dtype=float)
    points = [marks[:1]]
    for a, b in pairwise(marks):
        t = np.linspace(a, b, 257)
        if inner.size:
            dist = np.min(np.abs(t[:, None] - inner[None, :]), axis=1)
            h = np.minimum(spec.max_h_mm, spec.electrode_h_mm + (spec.growth - 1) * dist)
        else:
            h = np.full_like(t, spec.max_h_mm)
        s = np.concatenate([[0.0], np.cumsum(np.diff(t) * 0.5 * (1 / h[1:] + 1 / h[:-1]))])
        n = max(1, math.ceil(s[-1] - 1e-9))
        points.append(np.interp(np.arange(1, n + 1) * s[-1] / n, s, t))
        points[-1][-1] = b
    axis = np.concatenate(points)
    mirrored = length - axis[::-1]
    if len(axis) == len(mirrored) and np.allclose(axis, mirrored, atol=1e-9 * length):
        axis = 0.5 * (axis + mirrored)
        if (len(axis) - 1) % 2:
            mid = (len(axis) - 1) // 2
            axis = np.insert(axis, mid + 1, 0.5 * (axis[mid] + axis[mid + 1]))
    return axis


# ---------------------------------------------------------------------------
# Discs: concentric rings, rim rings aligned with the electrode sectors

def _disc_mesh(layout: Layout, spec: MeshSpec) -> tuple[np.ndarray, np.ndarray]:
    radius = disc_of(layout.sheet).radius_mm
    n_el = layout.n_electrodes
    rim_angles = _rim_angles(layout, spec)
    depth = max(e.depth_mm for e in layout.sectors)
    band_steps = max(1, math.ceil(depth / spec.electrode_h_mm - 1e-9))
    radii = list(radius - depth * np.arange(band_steps + 1) / band_steps)
    step = spec.electrode_h_mm
    while True:
        step = min(spec.max_h_mm, step * spec.growth)
        nxt = radii[-1] - step
        if nxt < 0.5 * step:
            break
        radii.append(nxt)
    offset = math.radians(layout.sectors[0].angle_deg)
    rings = []
    for r in radii:
        if r >= radius - depth - 1e-9:
            angles = rim_angles
        else:
            count = n_el * max(1, round(2 * math.pi * r / _local_h(radius - r, spec) / n_el))
            angles = offset + 2 * np.pi * np.arange(count) / count
        rings.append((r, np.asarray(angles)))
    ring_nodes = [np.array([[radius, radius]])]
    starts = []
    count = 1
    for r, angles in rings:
        starts.append(count)
        ring_nodes.append(np.column_stack([radius + r * np.sin(angles), radius - r * np.cos(angles)]))
        count += len(angles)
    nodes = np.vstack(ring_nodes)
    triangles = []
    for k in range(len(rings) - 1):
        triangles.append(_zip_rings(rings[k + 1][1], starts[k + 1], rings[k][1], starts[k]))
    inner_angles, inner_start = rings[-1][1], starts[-1]
    m = len(inner_angles)
    fan = np.column_stack([np.zeros(m, dtype=int), inner_start + (np.arange(m) + 1) % m, inner_start + np.arange(m)])
    triangles.append(fan)
    return nodes, _counter_clockwise(nodes, np.vstack(triangles))


def _local_h(dist_from_rim: float, spec: MeshSpec) -> float:
    return min(spec.max_h_mm, spec.electrode_h_mm + (spec.growth - 1) * dist_from_rim)


def _rim_angles(layout: Layout, spec: MeshSpec) -> np.ndarray:
    """Angles (radians, clockwise from top) of the rim nodes, electrode edges included."""
    radius = disc_of(layout.sheet).radius_mm
    edges = sorted(((e.angle_deg - e.width_deg / 2) % 360.0, (e.angle_deg + e.width_deg / 2) % 360.0)
                   for e in layout.sectors)
    edge_deg = []
    for start, end in edges:
        edge_deg += [start, end if end > start else end + 360.0]
    marks = np.radians(np.array(edge_deg))
    first = marks[0]
    marks = np.concatenate([marks, [first + 2 * np.pi]])
    angles = []
    electrode_arc = True
    for a, b in pairwise(marks):
        arc_mm = (b - a) * radius
        if electrode_arc:
            n = max(1, math.ceil(arc_mm / spec.electrode_h_mm - 1e-9))
            angles.append(a + (b - a) * np.arange(n) / n)
        else:
            axis = graded_axis(arc_mm, [0.0, arc_mm], spec)
            angles.append(a + axis[:-1] / radius)
        electrode_arc = not electrode_arc
    return np.concatenate(angles)


def _zip_rings(inner: np.ndarray, inner_start: int, outer: np.ndarray, outer_start: int) -> np.ndarray:
    """Triangulate the strip between two closed rings of nodes (angles in radians).

    Walks both rings by increasing angle from the outer ring's first node,
    always advancing on the ring whose next node comes first; on a tie (to 1e-9
    rad) the outer ring advances, so that the strip is as symmetric as the rings.
    """
    m, n = len(inner), len(outer)
    two_pi, eps = 2 * np.pi, 1e-9
    inner_rel = (inner - outer[0]) % two_pi
    inner_rel[inner_rel > two_pi - eps] = 0.0
    outer_rel = (outer - outer[0]) % two_pi
    # Start from the inner node strictly before the outer ring's first node, where
    # the walk would stand on reaching it from anywhere else.
    io = np.roll(np.argsort(inner_rel, kind="stable"), 1)
    oo = np.argsort(outer_rel, kind="stable")
    a = inner_rel[io]
    a[0] -= two_pi
    a = np.append(a, a[0] + two_pi)
    b = np.append(outer_rel[oo], two_pi)
    ii, oi = inner_start + io, outer_start + oo
    i = j = 0
    tris = []
    while i < m or j < n:
        if j == n or (i < m and a[i + 1] < b[j + 1] - eps):
            tris.append((ii[i % m], ii[(i + 1) % m], oi[j % n]))
            i += 1
        else:
            tris.append((ii[i % m], oi[(j + 1) % n], oi[j % n]))
            j += 1
    return np.array(tris)


def _row_major(nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Renumber nodes top to bottom, left to right.

    The fill-reducing ordering breaks ties by the initial numbering; from a
    ring-by-ring numbering it yields a factor as sparse but three times slower
    to compute than from a row-major one (measured on the disc meshes).
    """
    order = np.lexsort((nodes[:, 0], np.round(nodes[:, 1], 9)))
    new = np.empty_like(order)
    new[order] = np.arange(len(order))
    return nodes[order], new[triangles]


def _counter_clockwise(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    p = nodes[triangles]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    flip = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] < 0
    triangles = triangles.copy()
    triangles[flip] = triangles[flip][:, [0, 2, 1]]
    return triangles
