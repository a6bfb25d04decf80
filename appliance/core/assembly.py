"""Assembly of K(sigma) = sum_e sigma_e k_e + K_fixed on a sparsity pattern fixed in advance.

Both forward models (finite elements and the resistor network) are sums of
per-element matrices scaled by the element's conductivity, plus a part that does
not depend on it (contact impedance, metal electrodes). The pattern and the
place of every element entry in the CSR data are worked out once, so each new
conductivity costs one ``bincount`` over the entries, with no sorting.

>>> import numpy as np
>>> k = np.array([[1.0, -1.0], [-1.0, 1.0]])        # one unit resistor
>>> a = build_assembler(3, np.array([[0, 1], [1, 2]]), np.stack([k, k]))
>>> a.matrix(np.array([1.0, 2.0])).toarray()
array([[ 1., -1.,  0.],
       [-1.,  3., -2.],
       [ 0., -2.,  2.]])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Assembler:
    """Assembles an ``n x n`` CSR matrix from element conductivities on a fixed pattern.

    Attributes
    ----------
    n : int
        Matrix size.
    indptr, indices : ndarray
        The CSR pattern (sorted, no duplicates).
    slot : ndarray, shape (n_entries,)
        Position in the CSR data of each element entry.
    element : ndarray, shape (n_entries,)
        Element whose conductivity scales the entry.
    value : ndarray, shape (n_entries,)
        The entry at unit conductivity.
    fixed : ndarray, shape (nnz,)
        The conductivity-independent part, on the same pattern.
    """

    n: int
    indptr: np.ndarray
    indices: np.ndarray
    slot: np.ndarray
    element: np.ndarray
    value: np.ndarray
    fixed: np.ndarray

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def matrix(self, sigma: np.ndarray) -> sp.csr_matrix:
        """K(sigma) as CSR; ``sigma`` has one entry per element."""
        data = np.bincount(self.slot, weights=sigma[self.element] * self.value, minlength=self.nnz)
        return sp.csr_matrix((data + self.fixed, self.indices, self.indptr), shape=(self.n, self.n))

    def permuted(self, order: np.ndarray) -> Assembler:
        """The assembler of P K P^T: unknown ``order[i]`` becomes unknown i."""
        position = np.empty_like(order)
        position[order] = np.arange(len(order))
        rows = position[np.repeat(np.arange(self.n), np.diff(self.indptr))]
        cols = position[self.indices]
        sort = np.lexsort((cols, rows))
        where = np.empty_like(sort)
        where[sort] = np.arange(len(sort))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=self.n))]).astype(np.int32)
        return Assembler(self.n, indptr, cols[sort].astype(np.int32), where[self.slot], self.element, self.value,
                         self.fixed[sort])


def build_assembler(n: int, element_dofs: np.ndarray, element_matrices: np.ndarray,
                    fixed: sp.spmatrix | None = None, keep: np.ndarray | None = None) -> Assembler:
    """Precompute the pattern of ``sum_e sigma_e P_e k_e P_e^T + fixed``.

    Parameters
    ----------
    n : int
        Number of degrees of freedom before ``keep`` is applied.
    element_dofs : ndarray, shape (n_elements, m)
        Degrees of freedom of each element, or -1 for an unused slot.
    element_matrices : ndarray, shape (n_elements, m, m)
        Each element's matrix at unit conductivity.
    fixed : sparse matrix, shape (n, n), optional
        Conductivity-independent part.
    keep : ndarray of int, optional
        The degrees of freedom to keep, in order (others are grounded and dropped);
        by default all.
    """
    n_el, m = element_dofs.shape
    rows = np.repeat(element_dofs, m, axis=1).ravel()
    cols = np.tile(element_dofs, (1, m)).ravel()
    element = np.repeat(np.arange(n_el), m * m)
    value = element_matrices.reshape(-1)
    used = (rows >= 0) & (cols >= 0) & (value != 0)
    rows, cols, element, value = rows[used], cols[used], element[used], value[used]
    fixed = sp.coo_matrix((n, n)) if fixed is None else sp.coo_matrix(fixed)
    renumber = np.arange(n) if keep is None else np.full(n, -1)
    if keep is not None:
        renumber[keep] = np.arange(len(keep))
    size = n if keep is None else len(keep)
    rows, cols = renumber[rows], renumber[cols]
    frows, fcols = renumber[fixed.row], renumber[fixed.col]
    kept = (rows >= 0) & (cols >= 0)
    fkept = (frows >= 0) & (fcols >= 0)
    rows, cols, element, value = rows[kept], cols[kept], element[kept], value[kept]
    frows, fcols, fvals = frows[fkept], fcols[fkept], fixed.data[fkept]
    keys = np.concatenate([rows, frows]).astype(np.int64) * size + np.concatenate([cols, fcols])
    unique, inverse = np.unique(keys, return_inverse=True)
    pattern_rows, indices = np.divmod(unique, size)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(pattern_rows, minlength=size))])
    slot = inverse[: len(rows)]
    fixed_data = np.bincount(inverse[len(rows):], weights=fvals, minlength=len(unique))
    return Assembler(size, indptr.astype(np.int32), indices.astype(np.int32), slot, element, value, fixed_data)


def offset_variables(element_dofs: np.ndarray, element_matrices: np.ndarray, base_dofs: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Rewrite element matrices for potentials expressed as an offset plus a base potential.

    Where ``base_dofs`` names a base unknown (>= 0) for a local node, that node's
    potential is its own unknown plus the base's: u = v + U. The expanded system
    keeps stiff couplings (metal, near-ideal contacts) acting on the small offsets
    v only, so its residual stays at rounding level.

    Parameters
    ----------
    element_dofs : ndarray, shape (n_elements, m)
    element_matrices : ndarray, shape (n_elements, m, m)
    base_dofs : ndarray, shape (n_elements, m)
        Base unknown of each local node, or -1.

    Returns
    -------
    dofs : ndarray, shape (n_elements, 2 m)
    matrices : ndarray, shape (n_elements, 2 m, 2 m)
    """
    m = element_dofs.shape[1]
    expand = np.hstack([np.eye(m), np.eye(m)])
    matrices = np.einsum("ai,tab,bj->tij", expand, element_matrices, expand)
    return np.concatenate([element_dofs, base_dofs], axis=1), matrices


def offset_potentials(base: np.ndarray, n_unknowns: int, keep: np.ndarray) -> sp.csr_matrix:
    """The map from kept unknowns to node potentials when node i's potential is its own
    unknown plus, where ``base[i] >= 0``, that base unknown (see :func:`offset_variables`).

    Returns shape (len(base), len(keep)); an unknown left out of ``keep`` is grounded (zero).
    """
    n_nodes = len(base)
    offsets = np.flatnonzero(base >= 0)
    rows = np.concatenate([np.arange(n_nodes), offsets])
    cols = np.concatenate([np.arange(n_nodes), base[offsets]])
    full = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_nodes, n_unknowns))
    return sp.csr_matrix(full[:, keep])
