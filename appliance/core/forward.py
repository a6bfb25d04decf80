"""Forward models: electrode voltages for given element conductivities and drive patterns.

A :class:`ForwardModel` is what :mod:`appliance.core.fem` (finite elements with
the complete electrode model) and :mod:`appliance.core.network` (the thesis's
resistor network) build. Conductivity is always an argument, never stored: a
call factorises the system once and solves every drive pattern of the protocol
as one multi-column right-hand side.

>>> import numpy as np
>>> from appliance.core.layouts import get_layout
>>> from appliance.core.protocols import default_protocol
>>> from appliance.core.fem import build_fem_model
>>> layout = get_layout("grid-4x4")
>>> model = build_fem_model(layout)
>>> volts = simulate(model, np.ones(model.n_elements), default_protocol(layout))
>>> volts.shape
(448,)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from appliance.core.assembly import Assembler
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
    sheet : Assembler
        The conductivity-dependent part alone, over nodes and ungrounded: the
        currents it carries out of each electrode's contact nodes are checked
        against the currents driven.
    contact_nodes : tuple of ndarray
        For each electrode, the nodes through which it feeds the sheet.
    """

    kind: str
    system: Assembler
    electrodes: sp.csc_matrix
    centroids_mm: np.ndarray
    areas_mm2: np.ndarray
    fixed_elements: np.ndarray
    node_map: sp.csr_matrix
    sheet: Assembler
    contact_nodes: tuple

    @property
    def n_elements(self) -> int:
        return len(self.areas_mm2)

    @property
    def n_electrodes(self) -> int:
        return self.electrodes.shape[1]

    @cached_property
    def electrode_voltage_operator(self) -> sp.csr_matrix:
        """``electrodes.T`` as CSR, to read electrode voltages off a solution."""
        return sp.csr_matrix(self.electrodes.T)


@dataclass(frozen=True)
class DriveSolution:
    """Potentials for a set of drive patterns at one conductivity.

    Attributes
    ----------
    drives : ndarray, shape (n_drives, 2)
        Electrode numbers (1-based) of current in and current out.
    current_a : float
    solution : ndarray, shape (n_unknowns, n_drives)
    electrode_volts : ndarray, shape (n_electrodes, n_drives)
    relative_residual : float
        max over drives of ||b - K x|| / ||b|| of the solved system.
    """

    drives: np.ndarray
    current_a: float
    solution: np.ndarray
    electrode_volts: np.ndarray
    relative_residual: float


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


def factorise(model: ForwardModel, sigma) -> FactorisedSystem:
    """Assemble and factorise K(sigma) once, for any number of drive patterns."""
    return FactorisedSystem(model.system.matrix(check_conductivity(model, sigma)))


def solve_drives(model: ForwardModel, sigma, drives, current_a: float = 1.0,
                 factorised: FactorisedSystem | None = None) -> DriveSolution:
    """Solve every drive pattern at conductivity ``sigma`` with one factorisation.

    Parameters
    ----------
    drives : array_like, shape (n_drives, 2)
        Electrode numbers (1-based): current enters at the first, leaves at the second.
    current_a : float
        Drive current, A.
    factorised : FactorisedSystem, optional
        A factorisation of this model at ``sigma`` to reuse.
    """
    drives = np.asarray(drives, dtype=np.int64).reshape(-1, 2)
    if drives.size and (drives.min() < 1 or drives.max() > model.n_electrodes):
        raise ProtocolInvalid(f"drive names an electrode outside 1..{model.n_electrodes}")
    system = factorised or factorise(model, sigma)
    rhs = current_a * (model.electrodes[:, drives[:, 0] - 1] - model.electrodes[:, drives[:, 1] - 1])
    x, residual = system.solve(rhs.toarray())
    volts = model.electrode_voltage_operator @ x
    return DriveSolution(drives, current_a, x, volts, residual)


def readings_from(solution: DriveSolution, protocol: Protocol) -> np.ndarray:
    """The protocol's readings, V(meas+) - V(meas-), from solved drives; shape (n_readings,)."""
    lookup = {tuple(p): i for i, p in enumerate(solution.drives.tolist())}
    try:
        column = np.array([lookup[tuple(p)] for p in protocol.drives.tolist()])[protocol.drive_index]
    except KeyError as exc:
        raise ProtocolInvalid(f"drive {exc.args[0]} was not solved") from None
    r = protocol.readings
    v = solution.electrode_volts
    return v[r[:, 2] - 1, column] - v[r[:, 3] - 1, column]


def simulate(model: ForwardModel, sigma, protocol: Protocol, current_a: float = 1.0) -> np.ndarray:
    """Readings of ``protocol`` at conductivity ``sigma``, volts for ``current_a`` amps."""
    if protocol.n_electrodes != model.n_electrodes:
        raise ProtocolInvalid(f"protocol {protocol.name!r} is for {protocol.n_electrodes} electrodes, the "
                              f"model has {model.n_electrodes}")
    return readings_from(solve_drives(model, sigma, protocol.drives, current_a), protocol)


def electrode_currents(model: ForwardModel, sigma, solution: DriveSolution) -> np.ndarray:
    """Current each electrode feeds into the sheet, recovered from the potentials.

    Summing the sheet's own currents at each electrode's contact nodes checks a
    solution independently of how it was computed: it must equal the drive
    current at the drive electrodes and zero elsewhere.

    Returns
    -------
    ndarray, shape (n_electrodes, n_drives), A
    """
    nodal = model.sheet.matrix(check_conductivity(model, sigma)) @ (model.node_map @ solution.solution)
    return np.array([nodal[nodes].sum(axis=0) for nodes in model.contact_nodes])
