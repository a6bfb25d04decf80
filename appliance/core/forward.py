"""Forward models: electrode voltages for given element conductivities and drive patterns.

A :class:`ForwardModel` is what :mod:`appliance.core.fem` (finite elements with
the complete electrode model) and :mod:`appliance.core.network` (the thesis's
resistor network) build. Conductivity is always an argument, never stored: a
call factorises the system once and solves a unit current into each electrode
as one multi-column right-hand side; every drive pattern is a difference of
those columns, and every reading of any protocol follows from the electrodes'
transfer impedances.

>>> import numpy as np
>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.protocols import default_protocol
>>> from appliance.core.fem import build_fem_model
>>> layout = get_layout("grid-4x4")
>>> model = build_fem_model(layout)
>>> volts = simulate(model, np.ones(model.n_elements), default_protocol(layout))
>>> volts.shape
(448,)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from appliance.core.assembly import Assembler, build_assembler
from appliance.core.linsolve import FactorisedSystem
from appliance.core.protocols import Protocol
from appliance.errors import ModelInputInvalid, ProtocolInvalid


@dataclass(frozen=True)
class ForwardModel:
    """A linear conductance model ``K(sigma) x = E i`` over its unknowns x.

    Attributes
    ----------
    kind : str
        ``"fem"`` or ``"network"``.
    system : Assembler
        K(sigma), grounded (one unknown removed), symmetric positive definite.
    electrodes : sparse matrix, shape (n_unknowns, n_electrodes)
        Column l spreads a unit current into electrode l; its transpose reads the
        electrode voltages off a solution.
    centroids_mm, areas_mm2 : ndarray
        Element centroids (n_elements, 2) and areas (n_elements,), to map scenes and images.
    fixed_elements : ndarray of bool, shape (n_elements,)
        Elements whose conductance the model itself fixes (the network's metal
        electrodes); conductivities given for them are not used.
    node_map : sparse matrix, shape (n_nodes, n_unknowns)
        Node potentials from a solution.
    nodes_mm : ndarray, shape (n_nodes, 2)
        Node coordinates.
    element_nodes : ndarray, shape (n_elements, m)
        Nodes of each element (3 for triangles, 4 for the network's squares).
    element_matrices : ndarray, shape (n_elements, m, m)
        Each element's matrix over its nodes at unit conductivity.
    contact_nodes : tuple of ndarray
        For each electrode, the nodes through which it feeds the sheet.
    ordered : bool
        The unknowns are numbered in a fill-reducing order, so factorisations
        skip the ordering step (see :func:`with_fill_reducing_order`).
    """

    kind: str
    system: Assembler
    electrodes: sp.csc_matrix
    centroids_mm: np.ndarray
    areas_mm2: np.ndarray
    fixed_elements: np.ndarray
    node_map: sp.csr_matrix
    nodes_mm: np.ndarray
    element_nodes: np.ndarray
    element_matrices: np.ndarray
    contact_nodes: tuple
    ordered: bool = False

    @property
    def n_elements(self) -> int:
        return len(self.areas_mm2)

    @property
    def n_electrodes(self) -> int:
        return self.electrodes.shape[1]

    @cached_property
    def sheet(self) -> Assembler:
        """The conductivity-dependent part alone, over nodes and ungrounded: the currents it
        carries out of each electrode's contact nodes are checked against those driven."""
        dofs = np.where(self.fixed_elements[:, None], -1, self.element_nodes)
        return build_assembler(len(self.nodes_mm), dofs, self.element_matrices)


@dataclass(frozen=True)
class ElectrodeFields:
    """The model solved once per electrode at one conductivity.

    Column l of ``solution`` is the potential for a unit current into electrode l
    and out through the ground; by linearity the field of any drive (a, b) is
    column a minus column b, and every reading of every protocol follows from the
    transfer impedances ``transfer[m, l]``: the voltage of electrode m for a unit
    current into electrode l.

    Attributes
    ----------
    solution : ndarray, shape (n_unknowns, n_electrodes)
    transfer : ndarray, shape (n_electrodes, n_electrodes), ohm
    relative_residual : float
        max over columns of ||b - K x|| / ||b|| of the solved system.
    """

    solution: np.ndarray
    transfer: np.ndarray
    relative_residual: float

    def drive_potentials(self, drives) -> np.ndarray:
        """Solutions for unit current into the first electrode of each pair and out of the
        second; ``drives`` (n_drives, 2) holds 1-based numbers. Shape (n_unknowns, n_drives)."""
        drives = _pairs(drives, self.transfer.shape[0])
        return self.solution[:, drives[:, 0] - 1] - self.solution[:, drives[:, 1] - 1]

    def readings(self, protocol: Protocol, current_a: float = 1.0) -> np.ndarray:
        """The protocol's readings V(meas+) - V(meas-) in volts for ``current_a``; shape (n_readings,)."""
        return transfer_readings(self.transfer, protocol, current_a)


def transfer_readings(transfer: np.ndarray, protocol: Protocol, current_a: float = 1.0) -> np.ndarray:
    """The protocol's readings from the transfer impedances (n_electrodes, n_electrodes), volts."""
    if protocol.n_electrodes != transfer.shape[0]:
        raise ProtocolInvalid(f"protocol {protocol.name!r} is for {protocol.n_electrodes} electrodes, the "
                              f"model has {transfer.shape[0]}")
    a, b, c, d = (protocol.readings - 1).T
    return current_a * (transfer[c, a] - transfer[c, b] - transfer[d, a] + transfer[d, b])


def _pairs(drives, n_electrodes: int) -> np.ndarray:
    drives = np.asarray(drives, dtype=np.int64).reshape(-1, 2)
    if drives.size and (drives.min() < 1 or drives.max() > n_electrodes):
        raise ProtocolInvalid(f"drive names an electrode outside 1..{n_electrodes}")
    return drives


def check_conductivity(model: ForwardModel, sigma) -> np.ndarray:
    """``sigma`` as a float array, refused unless it is one positive finite value per element.

    Raises
    ------
    ModelInputInvalid
        Wrong length, or an element with a non-positive or non-finite conductivity.
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    if sigma.shape != (model.n_elements,):
        raise ModelInputInvalid(f"conductivity needs one value per element ({model.n_elements}), got shape "
                                f"{sigma.shape}")
    bad = np.flatnonzero(~np.isfinite(sigma) | (sigma <= 0))
    bad = bad[~model.fixed_elements[bad]]
    if bad.size:
        raise ModelInputInvalid(f"conductivity must be positive and finite: element {bad[0]} has "
                                f"{float(sigma[bad[0]])} ({bad.size} bad elements in all)")
    return np.where(model.fixed_elements, 1.0, sigma)


def with_fill_reducing_order(model: ForwardModel) -> ForwardModel:
    """``model`` with its unknowns renumbered in a fill-reducing order.

    The sparsity pattern never changes with conductivity, so the ordering is
    found once, from one factorisation, and every later factorisation skips it.
    """
    order = FactorisedSystem(model.system.matrix(np.ones(model.n_elements))).fill_order
    return dataclasses.replace(model, system=model.system.permuted(order),
                               electrodes=sp.csc_matrix(model.electrodes[order]),
                               node_map=sp.csr_matrix(model.node_map[:, order]), ordered=True)


def factorise(model: ForwardModel, sigma) -> FactorisedSystem:
    """Assemble and factorise K(sigma) once."""
    matrix = model.system.matrix(check_conductivity(model, sigma))
    return FactorisedSystem(matrix, ordering="NATURAL" if model.ordered else "MMD_AT_PLUS_A")


def solve_electrodes(model: ForwardModel, sigma, factorised: FactorisedSystem | None = None) -> ElectrodeFields:
    """Solve a unit current into each electrode with one factorisation of K(sigma).

    Electrodes the ground absorbs (the grounded electrode of the CEM model) need no
    solve: their column is zero. The others are solved ELECTRODE_BLOCK at a time, so the
    solve's work space (right-hand sides, residuals) stays a fraction of the solution's size.
    """
    system = factorised or factorise(model, sigma)
    columns = np.flatnonzero(np.diff(model.electrodes.indptr))
    x = np.zeros((model.system.n, model.n_electrodes))
    residual = 0.0
    for start in range(0, len(columns), ELECTRODE_BLOCK):
        block = columns[start:start + ELECTRODE_BLOCK]
        x[:, block], worst = system.solve(model.electrodes[:, block].toarray())
        residual = max(residual, worst)
    transfer = model.electrodes.T @ x
    return ElectrodeFields(x, transfer, residual)


ELECTRODE_BLOCK = 64
"""Electrodes solved at once: a bed mat's 512 at once would need three more copies of its 100 MB solution."""


def simulate(model: ForwardModel, sigma, protocol: Protocol, current_a: float = 1.0) -> np.ndarray:
    """Readings of ``protocol`` at conductivity ``sigma``, volts for ``current_a`` amps."""
    return solve_electrodes(model, sigma).readings(protocol, current_a)


def electrode_currents(model: ForwardModel, sigma, potentials: np.ndarray) -> np.ndarray:
    """Current each electrode feeds into the sheet, recovered from solved ``potentials``.

    Summing the sheet's own currents at each electrode's contact nodes checks a
    solution independently of how it was computed: it must equal the drive
    current at the drive electrodes and zero elsewhere.

    Parameters
    ----------
    potentials : ndarray, shape (n_unknowns, k)
        Solutions, such as :meth:`ElectrodeFields.drive_potentials`.

    Returns
    -------
    ndarray, shape (n_electrodes, k), A
    """
    nodal = model.sheet.matrix(check_conductivity(model, sigma)) @ (model.node_map @ potentials)
    return np.array([nodal[nodes].sum(axis=0) for nodes in model.contact_nodes])
