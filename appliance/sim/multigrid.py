"""Multigrid-preconditioned conjugate gradients for the mat mechanics' Newton systems.

Each Newton system is the membrane's stiffness, fixed for a grid, plus the foundation's slope, a
diagonal that changes at every step and over the whole footprint from one load to the next. A
factorisation serves one such system only; a multigrid hierarchy holds across all of them. Its
prolongators are built once per grid by smoothed aggregation of the stiffness alone (pyamg): they
carry the smooth, long-range modes that tension spreads, which is where a stiff foundation is
absent; where the foundation is stiff the system is diagonally dominant and Gauss-Seidel alone
damps its error. Each step only re-forms the coarse operators (Galerkin products) and factorises
the coarsest, a few dozen unknowns.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pyamg
import scipy.linalg
import scipy.sparse as sp
from pyamg.relaxation.relaxation import gauss_seidel

from appliance.errors import SolverError

COARSEST_UNKNOWNS = 40
"""The hierarchy's coarsening stops at this many unknowns, whose system is factorised densely each step:
a 40 x 40 Cholesky costs microseconds, and a smaller coarsest level only adds levels."""

HIERARCHY_SEED = 2026
"""Seed of the start vectors pyamg draws while building a hierarchy (see :class:`MembraneHierarchy`)."""
MAX_ITERATIONS = 200
"""Conjugate-gradient iterations allowed for one system; preconditioned by the hierarchy a bed's systems take
three on average and about twenty at the tightest, so this many mean the preconditioner has failed, not that
the system is hard."""


class MembraneHierarchy:
    """The multigrid prolongators of a grid's membrane stiffness (symmetric positive definite), made once."""

    def __init__(self, stiffness: sp.csr_matrix):
        # pyamg estimates each level's spectral radius (for its Jacobi prolongation smoother) from a random start
        # vector drawn from numpy's global generator; seeded here, and the caller's state given back, the same
        # grid always gets the same hierarchy, so a solve near rounding level converges or not alike every run.
        state = np.random.get_state()
        np.random.seed(HIERARCHY_SEED)
        try:
            hierarchy = pyamg.smoothed_aggregation_solver(sp.csr_matrix(stiffness, copy=True),
                                                          max_coarse=COARSEST_UNKNOWNS)
        finally:
            np.random.set_state(state)
        self.prolongators = [sp.csr_matrix(level.P) for level in hierarchy.levels[:-1]]
        self.restrictors = [sp.csr_matrix(p.T) for p in self.prolongators]

    def preconditioner(self, matrix: sp.csr_matrix) -> Callable[[np.ndarray], np.ndarray]:
        """One symmetric V-cycle for ``matrix`` (the stiffness plus a non-negative diagonal): a fixed,
        symmetric positive definite operator, so conjugate gradients may use it."""
        levels = [sp.csr_matrix(matrix)]
        for p, r in zip(self.prolongators, self.restrictors):
            levels.append(sp.csr_matrix(r @ levels[-1] @ p))
        coarsest = scipy.linalg.cho_factor(levels[-1].toarray())

        def cycle(b: np.ndarray, level: int = 0) -> np.ndarray:
            if level == len(self.prolongators):
                return scipy.linalg.cho_solve(coarsest, b)
            a = levels[level]
            x = np.zeros_like(b)
            gauss_seidel(a, x, b, sweep="forward")
            x += self.prolongators[level] @ cycle(self.restrictors[level] @ (b - a @ x), level + 1)
            gauss_seidel(a, x, b, sweep="backward")
            return x

        return cycle


def conjugate_gradients(matrix: sp.csr_matrix, rhs: np.ndarray, precondition: Callable[[np.ndarray], np.ndarray],
                        tolerance: float, start: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """``matrix`` x = ``rhs`` to a residual of ``tolerance`` times ``rhs``'s (2-norms), and the iterations it
    took. Raises SolverError if ``MAX_ITERATIONS`` do not get there: the step would be garbage."""
    x = np.zeros_like(rhs) if start is None else start.copy()
    r = rhs - matrix @ x
    target = tolerance * math.sqrt(dot(rhs, rhs))
    z = precondition(r)
    p, rz = z, dot(r, z)
    for iteration in range(MAX_ITERATIONS + 1):
        if math.sqrt(dot(r, r)) <= target:
            return x, iteration
        if iteration == MAX_ITERATIONS:
            break
        q = matrix @ p
        a = rz / dot(p, q)
        x += a * p
        r -= a * q
        z = precondition(r)
        rz, previous = dot(r, z), rz
        p = z + (rz / previous) * p
    raise SolverError(f"conjugate gradients on the mat mechanics reached a relative residual of "
                      f"{math.sqrt(dot(r, r)) / target * tolerance:.3g} in {MAX_ITERATIONS} iterations, "
                      f"not {tolerance:.3g}")


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b without BLAS: a threaded BLAS dot between two sparse products wakes idle threads that then spin
    against the next one, which cost a loaded two-core machine 25 ms a Newton step (and 17 ms a dot)."""
    return float(np.add.reduce(a * b))


FORCING_MAX = 0.1
"""The loosest a Newton step's systems are solved (relative residual): the first steps of a load, far from
its deflection, need only a direction (Eisenstat and Walker's forcing terms tighten it as Newton converges)."""

FORCING_MIN = 1e-10
"""The tightest: an inexact step's error is at most about this share of the step, so once Newton's steps
are near its stopping rule (1e-11 of the depth) the last one is as exact as a factorisation's, and the
deflection the same to well within a nanometre."""


class InexactSteps:
    """A Newton solve's linear systems, by conjugate gradients preconditioned by ``hierarchy`` to forcing
    terms of Eisenstat and Walker's second kind (0.9 times the residual's fall squared; their safeguard
    never binds below ``FORCING_MAX``), so the systems are solved as tightly as Newton's convergence can
    use. One instance per Newton solve: the volume's system starts from its last solution."""

    def __init__(self, hierarchy: MembraneHierarchy):
        self.hierarchy = hierarchy
        self.forcing = FORCING_MAX
        self._last_norm: float | None = None
        self._last_lift: np.ndarray | None = None

    def solve(self, matrix: sp.csr_matrix, rhs: np.ndarray, volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``matrix`` \\ ``rhs`` (``rhs`` the Newton residual, negated) and ``matrix`` \\ ``volume``."""
        norm = math.sqrt(dot(rhs, rhs))
        if self._last_norm:
            self.forcing = min(FORCING_MAX, max(0.9 * (norm / self._last_norm) ** 2, FORCING_MIN))
        self._last_norm = norm
        precondition = self.hierarchy.preconditioner(matrix)
        step, _ = conjugate_gradients(matrix, rhs, precondition, self.forcing)
        self._last_lift, _ = conjugate_gradients(matrix, volume, precondition, self.forcing, self._last_lift)
        return step, self._last_lift
