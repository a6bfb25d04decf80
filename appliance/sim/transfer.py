"""Transfer impedances alone, from one factorisation with the electrodes' unknowns eliminated last.

The virtual bed needs only the transfer impedances Z = E^T K^-1 E, not the
potential everywhere. In the complete electrode model each electrode's
current enters through one unknown of its own (its potential), so E picks
unknowns. Numbered last, they form the trailing block of K = L U, and

    (K^-1)_22 = (L_22 U_22)^-1

so Z is one factorisation plus a dense inverse of the electrode block: none of
the per-electrode triangular solves of :func:`appliance.core.forward.solve_electrodes`,
which are most of its time on a bed-size mesh (benchmarks/simulator.md). The system is
scaled to a unit diagonal first, as :mod:`appliance.core.linsolve` does.

>>> import numpy as np
>>> from appliance.core.fem import build_fem_model
>>> from appliance.core.forward import solve_electrodes
>>> from appliance.core.named_layouts import get_layout
>>> model = build_fem_model(get_layout("grid-4x4"), density=0.5)
>>> sigma = np.random.default_rng(1).uniform(1e-3, 1e-2, model.n_elements)
>>> z = TransferSolver(model).transfer(sigma)
>>> bool(np.abs(z - solve_electrodes(model, sigma).transfer).max() < 1e-10 * np.abs(z).max())
True
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from appliance.core.forward import ForwardModel, check_conductivity
from appliance.errors import ModelInputInvalid, SolverError


class TransferSolver:
    """``model``'s transfer impedances at any conductivity, its electrode unknowns numbered last once."""

    def __init__(self, model: ForwardModel):
        columns = np.flatnonzero(np.diff(model.electrodes.indptr))
        fed = sp.csc_matrix(model.electrodes[:, columns])
        if fed.nnz != columns.size or not np.all(fed.data == 1.0):
            raise ModelInputInvalid("the transfer alone needs each electrode fed through one unknown of its own "
                                    "(the complete electrode model)")
        self.model = model
        self.columns = columns
        # The rest keep the model's own (fill-reducing) numbering; the electrodes' unknowns follow.
        rest = np.setdiff1d(np.arange(model.system.n), fed.indices)
        self.system = model.system.permuted(np.concatenate([rest, fed.indices]))

    def transfer(self, sigma) -> np.ndarray:
        """Transfer impedances (ohm), shape (n_electrodes, n_electrodes), at conductivity ``sigma``.

        Raises
        ------
        SolverError
            The system is not positive definite (a pivot off the diagonal, or a bad diagonal).
        """
        matrix = self.system.matrix(check_conductivity(self.model, sigma))
        diagonal = matrix.diagonal()
        if not np.all(np.isfinite(diagonal) & (diagonal > 0)):
            raise SolverError("system matrix has a non-positive or non-finite diagonal")
        scale = 1.0 / np.sqrt(diagonal)
        scaled = sp.csc_matrix(matrix.multiply(scale[:, None]).multiply(scale[None, :]))
        try:
            lu = spla.splu(scaled, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True, "Equil": False})
        except RuntimeError as exc:
            raise SolverError(f"system matrix is singular: {exc}") from None
        n, m = scaled.shape[0], self.columns.size
        if not np.array_equal(lu.perm_r, np.arange(n)):
            raise SolverError("system matrix is not positive definite: the factorisation pivoted off the diagonal")
        lower = lu.L[n - m:, n - m:].toarray()
        upper = lu.U[n - m:, n - m:].toarray()
        block = la.solve_triangular(upper, la.solve_triangular(lower, np.eye(m), lower=True, unit_diagonal=True))
        ends = scale[n - m:]
        z = np.zeros((self.model.n_electrodes, self.model.n_electrodes))
        z[np.ix_(self.columns, self.columns)] = ends[:, None] * block * ends[None, :]
        return z
