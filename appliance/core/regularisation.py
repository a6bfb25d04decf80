"""How much to trust the readings against the prior: noise model, priors, and the rule for lambda.

Readings are weighted by the inverse variance of their noise, never divided by
their reference. A reading's noise has two parts: one in proportion to the reading
(the front end sets its gain to fill the converter, so quantisation scales with
the reading) and one of fixed size (amplifier and contact noise), stated as a
share of the rms reading. The fixed part is why a reading that is near zero by
symmetry carries no more weight than its noise allows.

Lambda is chosen by one of two stated rules:

* ``expected-error`` (the default): the lambda that minimises the expected squared
  error of the image, bias plus noise, over training targets (a spot of the
  expected size and contrast at every pixel) under the noise model. This is GREIT's
  training criterion; it regularises more as the declared noise grows.
* ``noise-figure``: the lambda that gives a requested noise figure (Adler and
  Guardo 1996; GREIT recommends 0.5), the readings' signal-to-noise ratio over the
  image's for a small central target. It is blind to the noise level itself.

>>> import numpy as np
>>> NoiseModel(relative=1e-2, absolute=0.0).std(np.array([2.0, -1.0, 0.0]))
array([0.02, 0.01, 0.  ])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from appliance.core.pixels import PixelGrid
from appliance.errors import ConfigError

PRIORS = ("tikhonov", "noser", "laplace")


@dataclass(frozen=True)
class NoiseModel:
    """Standard deviation of each reading: ``relative`` times the reading and ``absolute`` times
    the rms reading, added in quadrature."""

    relative: float = 1e-3
    absolute: float = 1e-4

    def __post_init__(self):
        if not (self.relative >= 0 and self.absolute >= 0 and self.relative + self.absolute > 0):
            raise ConfigError(f"noise model needs non-negative parts, not both zero, got {self}")

    def std(self, readings: np.ndarray) -> np.ndarray:
        """Noise standard deviation of each reading, same units, shape (n,)."""
        v = np.asarray(readings, dtype=float)
        rms = np.sqrt(np.mean(v**2))
        return np.hypot(self.relative * v, self.absolute * rms)


def laplacian(grid: PixelGrid) -> sp.csr_matrix:
    """The graph Laplacian of the imaged pixels, 4-neighbour, shape (n_inside, n_inside)."""
    flat = np.full(grid.rows * grid.cols, -1)
    flat[grid.inside_index] = np.arange(grid.n_inside)
    index = flat.reshape(grid.rows, grid.cols)
    pairs = []
    for a, b in ((index[:, :-1], index[:, 1:]), (index[:-1, :], index[1:, :])):
        ok = (a >= 0) & (b >= 0)
        pairs.append(np.column_stack([a[ok], b[ok]]))
    edges = np.vstack(pairs)
    n = grid.n_inside
    adjacency = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adjacency = adjacency + adjacency.T
    return sp.csr_matrix(sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency)


def prior_matrix(kind: str, normal: np.ndarray, grid: PixelGrid) -> np.ndarray:
    """The penalty matrix P of a prior, scaled to the trace of ``normal`` (J^T W J).

    ``tikhonov``: the identity; ``noser``: diag(J^T W J)^0.5 (EIDORS' default exponent),
    which evens out the sensitivity; ``laplace``: L^T L of the pixel Laplacian, which
    penalises roughness rather than size (plus a ridge of 1e-6 of its mean diagonal, as
    L^T L alone does not penalise a uniform change).
    """
    if kind == "tikhonov":
        p = np.eye(len(normal))
    elif kind == "noser":
        p = np.diag(np.sqrt(np.maximum(np.diag(normal), 0.0)))
    elif kind == "laplace":
        lap = laplacian(grid)
        p = (lap.T @ lap).toarray()
        p += 1e-6 * np.trace(p) / len(p) * np.eye(len(p))     # a faint ridge: L^T L is singular on constants
    else:
        raise ConfigError(f"unknown prior {kind!r}: use one of {', '.join(PRIORS)}")
    return p * (np.trace(normal) / np.trace(p))


def noise_figure(matrix: np.ndarray, jacobian: np.ndarray, noise_std: np.ndarray, target: np.ndarray,
                 areas: np.ndarray) -> float:
    """NF = SNR of the readings / SNR of the image, for the pixel change ``target``.

    Parameters
    ----------
    matrix : ndarray, shape (n_pixels, n_readings)
        The reconstruction matrix.
    jacobian : ndarray, shape (n_readings, n_pixels)
    noise_std : ndarray, shape (n_readings,)
    target : ndarray, shape (n_pixels,)
        A small change to image.
    areas : ndarray, shape (n_pixels,)
        Pixel areas, to weight the image.
    """
    signal = jacobian @ target
    snr_in = np.linalg.norm(signal) / np.sqrt(np.sum(noise_std**2))
    image = matrix @ signal
    image_noise = np.einsum("pr,r,pr->p", matrix, noise_std**2, matrix)     # diag(R S R^T)
    snr_out = np.sqrt(np.sum(areas * image**2)) / np.sqrt(np.sum(areas * image_noise))
    return float(snr_in / snr_out)


def expected_error(matrix: np.ndarray, jacobian: np.ndarray, noise_std: np.ndarray, targets: np.ndarray,
                   desired: np.ndarray, areas: np.ndarray) -> float:
    """Mean over training targets of the area-weighted squared image error, bias plus noise.

    Parameters
    ----------
    targets : ndarray, shape (n_pixels, n_targets)
        The changes, one per column.
    desired : ndarray, shape (n_pixels, n_targets)
        The image each should give.
    """
    bias = matrix @ (jacobian @ targets) - desired
    noise = np.einsum("pr,r,pr->p", matrix, noise_std**2, matrix)
    return float((areas @ bias**2).mean() + areas @ noise)


class ExpectedErrorSpectrum:
    """The expected error of R(lambda) = L (N + lambda P)^-1 J^T W for every lambda at once.

    With the generalised eigenvectors V of (N, P) (V^T P V = I, V^T N V = diag(mu)),
    (N + lambda P)^-1 = V diag(1 / (mu + lambda)) V^T, so after O(n^3) preparation each
    lambda costs O(n^2): the bias and noise terms of :func:`expected_error` become
    weighted sums over the eigenpairs. ``left`` (L) is GREIT's desired-image blur, or None.
    The readings are weighted by the inverse of their noise variance (W = S^-1), so the
    noise term R S R^T = L (N + lambda P)^-1 N (N + lambda P)^-1 L^T needs N alone: nothing
    the size of the readings is formed, which a bed-size mat could not afford.
    """

    def __init__(self, normal, prior, targets, desired, areas, left=None):
        # In an order that frees each pixel-square matrix once it is used: a bed mat's are 30 MB each.
        self.mu, v = sla.eigh(normal, prior)
        u = v if left is None else left @ v
        weighted_u = u * areas[:, None]
        y = v.T @ (normal @ targets)                                  # (n, targets)
        self._h = np.einsum("it,it->i", y, weighted_u.T @ desired)
        g = u.T @ weighted_u
        del u, weighted_u
        self._g_m = y @ y.T
        self._g_m *= g
        del y
        self._g_q = v.T @ normal @ v                                  # R S R^T = L A^-1 N A^-1 L^T
        self._g_q *= g
        self._constant = float(np.einsum("pt,p,pt->", desired, areas, desired))
        self._targets = targets.shape[1]

    def __call__(self, lam: float) -> float:
        s = 1.0 / (self.mu + lam)
        ss = np.outer(s, s)
        bias = (ss * self._g_m).sum() - 2 * (s * self._h).sum() + self._constant
        return float(bias / self._targets + (ss * self._g_q).sum())


def minimise_lambda(cost, low: float = 1e-12, high: float = 1e4, steps: int = 36) -> float:
    """The lambda in [low, high] minimising ``cost(lam)``, by golden-section search on log lambda
    after a coarse scan (the cost need not be unimodal over the whole range)."""
    grid = np.linspace(np.log10(low), np.log10(high), 17)
    costs = [cost(10**g) for g in grid]
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    ratio = (np.sqrt(5) - 1) / 2
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa, fb = cost(10**a), cost(10**b)
    for _ in range(steps):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - ratio * (hi - lo)
            fa = cost(10**a)
        else:
            lo, a, fa = a, b, fb
            b = lo + ratio * (hi - lo)
            fb = cost(10**b)
    return float(10 ** (0.5 * (lo + hi)))


def choose_lambda(build, evaluate, target_figure: float, low: float = 1e-12, high: float = 1e4,
                  steps: int = 40) -> tuple[float, float]:
    """The lambda in [low, high] whose noise figure is ``target_figure``, by bisection on log lambda.

    ``build(lam)`` returns a reconstruction matrix and ``evaluate(matrix)`` its noise
    figure, which falls as lambda grows. If the target lies outside what the range
    reaches, the nearer end is returned. Returns (lambda, noise figure).
    """
    lo, hi = np.log10(low), np.log10(high)
    nf_lo, nf_hi = evaluate(build(low)), evaluate(build(high))
    if nf_hi >= target_figure:
        return high, nf_hi
    if nf_lo <= target_figure:
        return low, nf_lo
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if evaluate(build(10**mid)) > target_figure:
            lo = mid
        else:
            hi = mid
    lam = 10 ** (0.5 * (lo + hi))
    return lam, evaluate(build(lam))
