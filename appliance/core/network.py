"""The thesis's resistor-network model of the sheet (section 5.4, Appendix B).

The sheet is a grid of square elements; each element is four edge resistors and
two diagonal ones, all 1 ohm at unit conductivity (Fig. 5.4.4), so its matrix is
3 on the diagonal and -1 elsewhere. An electrode is an element of conductance
10,000: current is fed in at its four corner nodes, and its voltage is the mean
of them. Elements are numbered row-major over the cells that exist, nodes
row-major over the corners in use, each element's corners in the order top-left,
top-right, bottom-right, bottom-left, exactly as in the thesis.

The thesis grounded all four nodes of the sink electrode and injected 1 A at
each node of the source, which needs a new matrix per sink. We feed the current
into and out of the electrode's nodes symmetrically and ground one node, so one
factorisation serves every drive and reciprocity holds exactly;
:func:`appendix_b_electrode_volts` keeps the thesis's own procedure for
comparison (the two differ by about 1e-4, see tests/test_network.py).

>>> grid = thesis_phantom("C")
>>> grid.n_cells, grid.n_nodes
(256, 289)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from appliance.core.assembly import build_assembler, offset_potentials, offset_variables
from appliance.core.forward import ForwardModel, with_fill_reducing_order
from appliance.core.layouts import DiscSheet, Layout, RectElectrode, disc_of
from appliance.errors import LayoutInvalid

ELECTRODE_CONDUCTANCE = 1e4
"""Relative conductance of an electrode element (section 5.4)."""

ELEMENT_MATRIX = np.full((4, 4), -1.0) + 4.0 * np.eye(4)
"""G_ele of section 5.4: four edge and two diagonal 1-ohm resistors between the four corners."""


@dataclass(frozen=True)
class NetworkGrid:
    """Which cells of a rows x cols grid exist, their size, and the electrode cells.

    Attributes
    ----------
    mask : ndarray of bool, shape (rows, cols)
    cell_mm : float
        Side of one element.
    electrode_cells : tuple of tuple of int
        For electrodes 1..L, the elements (0-based, row-major over existing cells)
        that make up each; the thesis's electrodes are one element each.
    """

    mask: np.ndarray
    cell_mm: float
    electrode_cells: tuple

    def __post_init__(self):
        object.__setattr__(self, "mask", np.asarray(self.mask, dtype=bool))
        cells = [c for e in self.electrode_cells for c in e]
        for number, e in enumerate(self.electrode_cells, start=1):
            if not e:
                raise LayoutInvalid(f"electrode {number} has no network element")
            bad = [c for c in e if not 0 <= c < self.n_cells]
            if bad:
                raise LayoutInvalid(f"electrode {number}: element {bad[0]} is not one of the "
                                    f"{self.n_cells} elements")
        if len(set(cells)) != len(cells):
            raise LayoutInvalid("two electrodes share one network element")

    @property
    def n_electrodes(self) -> int:
        return len(self.electrode_cells)

    @property
    def n_cells(self) -> int:
        return int(self.mask.sum())

    @cached_property
    def cell_rc(self) -> np.ndarray:
        """(row, column) of each element, shape (n_cells, 2)."""
        return np.argwhere(self.mask)

    @cached_property
    def _corner_numbers(self) -> np.ndarray:
        rows, cols = self.mask.shape
        used = np.zeros((rows + 1, cols + 1), dtype=bool)
        for dr in (0, 1):
            for dc in (0, 1):
                used[dr:dr + rows, dc:dc + cols] |= self.mask
        numbers = np.full(used.shape, -1)
        numbers[used] = np.arange(used.sum())
        return numbers

    @property
    def n_nodes(self) -> int:
        return int((self._corner_numbers >= 0).sum())

    @cached_property
    def topology(self) -> np.ndarray:
        """Nodes of each element: top-left, top-right, bottom-right, bottom-left; shape (n_cells, 4)."""
        r, c = self.cell_rc[:, 0], self.cell_rc[:, 1]
        n = self._corner_numbers
        return np.column_stack([n[r, c], n[r, c + 1], n[r + 1, c + 1], n[r + 1, c]])

    @property
    def centroids_mm(self) -> np.ndarray:
        return (self.cell_rc[:, ::-1] + 0.5) * self.cell_mm

    @property
    def nodes_mm(self) -> np.ndarray:
        """Corner coordinates, in node order, shape (n_nodes, 2)."""
        rc = np.argwhere(self._corner_numbers >= 0)
        order = self._corner_numbers[rc[:, 0], rc[:, 1]]
        coords = np.empty((len(rc), 2))
        coords[order] = rc[:, ::-1] * self.cell_mm
        return coords

    @property
    def areas_mm2(self) -> np.ndarray:
        return np.full(self.n_cells, self.cell_mm**2)


def conductance_matrix(grid: NetworkGrid, conductance: np.ndarray) -> sp.csr_matrix:
    """G_sys of the network with element conductances ``conductance`` (n_cells,), ungrounded."""
    return conductance_matrix_of(grid.n_nodes, grid.topology, np.asarray(conductance, dtype=float))


def conductance_matrix_of(n_nodes: int, topology: np.ndarray, conductance) -> sp.csr_matrix:
    """Sum of G_ele over the elements ``topology`` (n, 4) scaled by ``conductance``."""
    n = len(topology)
    a = build_assembler(n_nodes, topology, np.broadcast_to(ELEMENT_MATRIX, (n, 4, 4)))
    return a.matrix(np.broadcast_to(np.asarray(conductance, dtype=float), (n,)))


def build_network_model(grid: NetworkGrid, electrode_conductance: float = ELECTRODE_CONDUCTANCE) -> ForwardModel:
    """A forward model of ``grid``: electrodes are metal elements, fed evenly at their corner nodes.

    Each electrode's nodes are written as offsets from one master node (its
    highest-numbered), so the 1e4 conductance acts only on the small offsets; the
    last node, never an offset, is grounded.
    """
    n_nodes, topo = grid.n_nodes, grid.topology
    metal = np.zeros(grid.n_cells, dtype=bool)
    metal[[c for cells in grid.electrode_cells for c in cells]] = True
    contact_nodes = tuple(np.unique(topo[list(cells)]) for cells in grid.electrode_cells)
    master = np.full(n_nodes, -1)
    for nodes in contact_nodes:
        master[nodes[:-1]] = nodes[-1]
    local = np.broadcast_to(ELEMENT_MATRIX, (grid.n_cells, 4, 4))
    dofs, expanded = offset_variables(topo, local, master[topo])
    metal_part = build_assembler(n_nodes, dofs[metal], expanded[metal] * electrode_conductance)
    sheet_dofs = np.where(metal[:, None], -1, dofs)
    keep = np.arange(n_nodes - 1)
    system = build_assembler(n_nodes, sheet_dofs, expanded, metal_part.matrix(np.ones(int(metal.sum()))), keep)

    # A unit current spread evenly over the n nodes of electrode l: 1/n on each
    # offset, and all of it on the master, whose potential every node carries.
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    weights: list[np.ndarray] = []
    for l, nodes in enumerate(contact_nodes):
        rows += [nodes[:-1], nodes[-1:]]
        cols += [np.full(len(nodes), l)]
        weights += [np.full(len(nodes) - 1, 1.0 / len(nodes)), np.ones(1)]
    spread = sp.csc_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(n_nodes, grid.n_electrodes))
    node_map = offset_potentials(master, n_nodes, keep)
    return with_fill_reducing_order(ForwardModel(
        "network", system, sp.csc_matrix(spread[keep]), grid.centroids_mm, grid.areas_mm2, metal, node_map,
        grid.nodes_mm, topo, np.array(local), contact_nodes))


def appendix_b_electrode_volts(grid: NetworkGrid, conductance: np.ndarray, source: int, sink: int,
                               electrode_conductance: float = ELECTRODE_CONDUCTANCE) -> np.ndarray:
    """Electrode voltages by the thesis's own procedure (Appendix B), for checking.

    Electrode elements get ``electrode_conductance``; the sink electrode's four
    nodes are set to 0 V and 1 A is injected at each of the source's four nodes;
    an electrode's voltage is the mean of its nodes. ``source`` and ``sink`` are
    electrode numbers (1-based). Returns shape (n_electrodes,).
    """
    g = np.array(conductance, dtype=float)
    g[[c for cells in grid.electrode_cells for c in cells]] = electrode_conductance
    gsys = conductance_matrix(grid, g).tocsc()
    topo = grid.topology
    nodes = [np.unique(topo[list(cells)]) for cells in grid.electrode_cells]
    current = np.zeros(grid.n_nodes)
    current[nodes[source - 1]] = 1.0
    free = np.setdiff1d(np.arange(grid.n_nodes), nodes[sink - 1])
    v = np.zeros(grid.n_nodes)
    v[free] = spla.spsolve(gsys[free][:, free], current[free])
    return np.array([v[n].mean() for n in nodes])


# ---------------------------------------------------------------------------
# The thesis's phantoms and the networks of our layouts

_PHANTOM_A_ROWS = (7, 11, 13, 15, 15, 17, 17, 17, 17, 17, 17, 17, 15, 15, 13, 11, 7)
_THESIS_ELECTRODES = {
    "A": (4, 7, 31, 78, 129, 180, 223, 241, 238, 235, 211, 164, 113, 62, 19, 1),
    "B": (1, 5, 9, 13, 17, 85, 153, 221, 289, 285, 281, 277, 273, 205, 137, 69),
    "C": (1, 6, 11, 16, 81, 86, 91, 96, 161, 166, 171, 176, 241, 246, 251, 256),
}
"""Electrode element numbers (1-based, as printed in Appendix B) of electrodes 1..16 in our numbering."""


def thesis_phantom(letter: str, size_mm: float = 100.0) -> NetworkGrid:
    """Phantom A (circle, 241 elements), B (square, 289) or C (4 x 4 grid, 256) of chapter 5."""
    if letter == "A":
        mask = np.zeros((17, 17), dtype=bool)
        for r, width in enumerate(_PHANTOM_A_ROWS):
            start = (17 - width) // 2
            mask[r, start:start + width] = True
    elif letter in ("B", "C"):
        n = 17 if letter == "B" else 16
        mask = np.ones((n, n), dtype=bool)
    else:
        raise LayoutInvalid(f"the thesis has phantoms A, B and C, not {letter!r}")
    return NetworkGrid(mask, size_mm / mask.shape[0], tuple((e - 1,) for e in _THESIS_ELECTRODES[letter]))


def network_for_layout(layout: Layout, refinement: int = 1) -> NetworkGrid:
    """The resistor network of ``layout``, ``refinement`` elements across each electrode.

    Rectangular sheets are cut into square elements of the electrode size over
    ``refinement``; the electrodes must sit on that grid (``grid-4x4`` gives
    phantom C, ``square-16`` phantom B). A disc is cut into elements of 1/17 of its
    diameter over ``refinement`` (the thesis's phantom A resolution), keeping the
    elements whose centres lie on the disc; an electrode is the elements whose
    centres lie on its face (at least the one nearest its centroid).
    """
    if refinement < 1:
        raise LayoutInvalid(f"network refinement must be at least 1, got {refinement}")
    if isinstance(layout.sheet, DiscSheet):
        return _disc_network(layout, refinement)
    sizes = {(e.width_mm, e.height_mm) for e in layout.electrodes if isinstance(e, RectElectrode)}
    cell = min(min(s) for s in sizes) / refinement
    width, height = layout.sheet.size_mm
    cols, rows = round(width / cell), round(height / cell)
    on_grid = np.isclose(cols * cell, width) and np.isclose(rows * cell, height)
    electrodes = []
    for e in layout.rectangles:
        x0, y0, x1, y1 = (v / cell for v in e.bounds_mm)
        on_grid &= all(np.isclose(v, round(v)) for v in (x0, y0, x1, y1))
        electrodes.append(tuple(r * cols + c for r in range(round(y0), round(y1)) for c in range(round(x0), round(x1))))
    if not on_grid:
        raise LayoutInvalid(f"layout {layout.name!r}: the resistor network needs electrode edges on a grid of "
                            f"square elements; these do not fit one")
    return NetworkGrid(np.ones((rows, cols), dtype=bool), cell, tuple(electrodes))


def _disc_network(layout: Layout, refinement: int) -> NetworkGrid:
    diameter = 2 * disc_of(layout.sheet).radius_mm
    n = 17 * refinement
    cell = diameter / n
    centres = (np.argwhere(np.ones((n, n), dtype=bool))[:, ::-1] + 0.5) * cell
    mask = layout.contains(centres).reshape(n, n)
    kept = centres[mask.ravel()]
    electrodes = []
    for e in layout.electrodes:
        inside = np.flatnonzero(e.contains(layout.sheet, kept))
        if inside.size == 0:
            inside = np.array([np.argmin(np.linalg.norm(kept - e.centroid_mm(layout.sheet), axis=1))])
        electrodes.append(tuple(int(i) for i in inside))
    return NetworkGrid(mask, cell, tuple(electrodes))
