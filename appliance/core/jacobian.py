"""Sensitivity of every reading to every element's conductivity, by the adjoint method.

For a reading V(c) - V(d) of drive (a, b), with u_ab the field of a unit current
from a to b and u_cd that of a unit current from c to d (the adjoint field, by
reciprocity), dV/dsigma_e = -u_ab^T k_e u_cd, where k_e is element e's matrix at
unit conductivity. Both fields are differences of the per-electrode fields that
one factorisation already gives (:func:`appliance.core.forward.solve_electrodes`),
so the whole Jacobian costs no solve beyond the forward problem's: per element,
the L x L products of electrode fields, then four entries per reading.

>>> import numpy as np
>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.protocols import default_protocol
>>> from appliance.core.network import build_network_model, network_for_layout
>>> layout = get_layout("grid-4x4")
>>> model = build_network_model(network_for_layout(layout))
>>> J = jacobian(model, np.ones(model.n_elements), default_protocol(layout))
>>> J.shape
(448, 256)
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from appliance.core.forward import ElectrodeFields, ForwardModel, check_conductivity, solve_electrodes
from appliance.core.protocols import Protocol

CHUNK_ELEMENTS = 4096
"""Elements per block: bounds the (block, L, L) products to a few tens of megabytes."""


def jacobian(model: ForwardModel, sigma, protocol: Protocol, fields: ElectrodeFields | None = None,
             relative: bool = False) -> np.ndarray:
    """d(reading)/d(conductivity) for every reading and element.

    Parameters
    ----------
    sigma : ndarray, shape (n_elements,)
        Conductivity at which to linearise.
    fields : ElectrodeFields, optional
        The model already solved at ``sigma``.
    relative : bool
        Differentiate with respect to the relative change x of sigma = sigma (1 + x)
        instead: each column is multiplied by sigma_e.

    Returns
    -------
    ndarray, shape (n_readings, n_elements)
        Volts per amp per (siemens or unit relative change); zero for elements
        whose conductance the model fixes.
    """
    sigma = check_conductivity(model, sigma)
    fields = fields or solve_electrodes(model, sigma)
    potentials = model.node_map @ fields.solution               # (n_nodes, L)
    select = _reading_selector(protocol, model.n_electrodes)
    out = np.empty((len(protocol), model.n_elements))
    for start in range(0, model.n_elements, CHUNK_ELEMENTS):
        block = slice(start, start + CHUNK_ELEMENTS)
        u = potentials[model.element_nodes[block]]            # (n, m, L)
        s = np.matmul(u.transpose(0, 2, 1), np.matmul(model.element_matrices[block], u))   # (n, L, L)
        out[:, block] = (s.reshape(len(s), -1) @ select).T
    out[:, model.fixed_elements] = 0.0
    if relative:
        out *= sigma[None, :]
    return out


def _reading_selector(protocol: Protocol, n_electrodes: int) -> sp.csc_matrix:
    """The sparse map from the flattened L x L products u_l^T k u_m to the readings:
    -(s[a, c] - s[a, d] - s[b, c] + s[b, d]) for each reading (a, b, c, d)."""
    a, b, c, d = (protocol.readings - 1).T
    n = n_electrodes
    rows = np.concatenate([a * n + c, a * n + d, b * n + c, b * n + d])
    cols = np.tile(np.arange(len(protocol)), 4)
    values = np.repeat([-1.0, 1.0, 1.0, -1.0], len(protocol))
    return sp.csc_matrix((values, (rows, cols)), shape=(n * n, len(protocol)))



def pixel_jacobian(model: ForwardModel, sigma, protocol: Protocol, mapping: sp.spmatrix,
                   fields: ElectrodeFields | None = None, relative: bool = False,
                   dtype: type = np.float64) -> np.ndarray:
    """The Jacobian summed onto pixels, ``jacobian(...) @ mapping``, without the per-element Jacobian.

    :func:`jacobian` forms every element's L x L electrode products, which on a
    bed-size mat (hundreds of electrodes, 10^5 elements) is tens of gigabytes. Here
    each element matrix is split as k_e = F_e^T F_e, and for each pixel the electrode
    products summed over its elements, S = sum_e w_e (F_e u_e)^T (F_e u_e), are one
    dense matrix product (BLAS), from which every reading takes its four entries:
    -(S[a, c] - S[a, d] - S[b, c] + S[b, d]). Memory is the result plus one pixel's
    node potentials and L x L products (no potentials of every node: 94 MiB on a bed mat);
    time is a few seconds on a bed mat.

    Parameters
    ----------
    mapping : sparse matrix, shape (n_elements, n_pixels)
        Share of each element in each pixel (:func:`appliance.core.pixels.element_pixel_map`);
        non-negative.

    Returns
    -------
    ndarray, shape (n_readings, n_pixels), of ``dtype`` (each column computed in double precision)
    """
    sigma = check_conductivity(model, sigma)
    fields = fields or solve_electrodes(model, sigma)
    mapping = sp.csc_matrix(mapping)
    if mapping.shape[0] != model.n_elements or (mapping.data < 0).any():
        raise ValueError(f"mapping must be non-negative with one row per element ({model.n_elements}), "
                         f"got shape {mapping.shape}")
    weight = np.where(model.fixed_elements, 0.0, sigma if relative else 1.0)
    factors = _square_roots(model.element_matrices)                    # (n_el, m, m): k_e = F^T F
    node_map = sp.csr_matrix(model.node_map)        # each pixel's node potentials taken as it comes, not all at once
    a, b, c, d = (protocol.readings - 1).T
    out = np.empty((len(protocol), mapping.shape[1]), dtype=dtype)
    for k in range(mapping.shape[1]):
        rows = slice(mapping.indptr[k], mapping.indptr[k + 1])
        elements, share = mapping.indices[rows], mapping.data[rows] * weight[mapping.indices[rows]]
        nodes = model.element_nodes[elements]
        u = (node_map[nodes.ravel()] @ fields.solution).reshape(*nodes.shape, -1)      # (n, m, L)
        f = np.matmul(factors[elements], u)                                            # (n, m, L)
        f = (np.sqrt(share)[:, None, None] * f).reshape(-1, f.shape[2])
        s = f.T @ f
        out[:, k] = -(s[a, c] - s[a, d] - s[b, c] + s[b, d])
    return out


def _square_roots(matrices: np.ndarray) -> np.ndarray:
    """F with F^T F = k for each symmetric positive semi-definite k in a stack, shape as the stack."""
    values, vectors = np.linalg.eigh(matrices)
    return np.sqrt(np.clip(values, 0.0, None))[:, :, None] * np.swapaxes(vectors, 1, 2)
