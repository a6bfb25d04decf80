"""Segmentation score of the Kuopio Tomography Challenge 2023 (KTC2023).

A 256x256 segmentation with labels 0 (water), 1 (resistive) and 2 (conductive)
is compared with the truth class by class. For the resistive and the conductive
class an SSIM-style index of the two binary masks is computed with a Gaussian
window (standard deviation 80 px, truncated at 160 px, zero padding, border
statistics renormalised); the score is the mean of the two indices, 1.0 being
perfect. A reconstruction that is not 256x256 scores 0.

Written from the description in ``shared/data/ktc2023/SOURCE.md``; it is a
re-implementation, not the organisers' code.

>>> import numpy as np
>>> rows, cols = np.mgrid[:256, :256]
>>> truth = np.zeros((256, 256), dtype=np.uint8)
>>> truth[(rows - 128) ** 2 + (cols - 100) ** 2 < 30 ** 2] = 2
>>> challenge_score(truth, truth)
1.0
>>> water = np.zeros_like(truth)
>>> class_index(truth == 1, water == 1)   # the class absent from both
1.0
>>> 0.5 <= challenge_score(truth, water) < 1.0
True
>>> challenge_score(truth, np.zeros((128, 128)))
0.0
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter

from appliance.errors import ModelInputInvalid

SHAPE = (256, 256)
"""Shape of a KTC2023 segmentation (pixels)."""

LABELS = (0, 1, 2)
"""Valid labels: 0 water, 1 resistive, 2 conductive."""

RESISTIVE = 1
CONDUCTIVE = 2

SIGMA_PX = 80.0
"""Standard deviation of the Gaussian window, in pixels."""

TRUNCATE = 2.0
"""Window half-width in standard deviations: 2 x 80 = 160 px, a 321x321 kernel."""

C1 = 1e-4
C2 = 9e-4


def _window(image: np.ndarray) -> np.ndarray:
    """Gaussian-weighted sum of ``image`` with zero padding, same shape as ``image``."""
    return gaussian_filter(image, sigma=SIGMA_PX, mode="constant", cval=0.0, truncate=TRUNCATE)


@lru_cache(maxsize=8)
def _normaliser(shape: tuple[int, ...]) -> np.ndarray:
    """The window applied to an all-ones image: the weight that falls inside the image at each pixel."""
    weight = _window(np.ones(shape, dtype=float))
    weight.setflags(write=False)
    return weight


def _local_mean(image: np.ndarray) -> np.ndarray:
    """Gaussian-weighted local mean, renormalised near the border."""
    return _window(image) / _normaliser(image.shape)


def _as_mask(mask, name: str) -> np.ndarray:
    array = np.asarray(mask)
    if array.ndim != 2 or array.size == 0:
        raise ModelInputInvalid(f"{name} must be a non-empty 2-D array, got shape {array.shape}")
    if array.dtype.kind not in "biuf" or not np.all((array == 0) | (array == 1)):
        raise ModelInputInvalid(f"{name} must be a boolean or 0/1 mask")
    return array.astype(float)


def class_index(truth_mask, reconstruction_mask) -> float:
    """SSIM-style index of two binary masks with the KTC2023 Gaussian window.

    Parameters
    ----------
    truth_mask : array_like of bool or {0, 1}, shape (M, N)
        Pixels of the true image that belong to the class.
    reconstruction_mask : array_like of bool or {0, 1}, shape (M, N)
        Pixels of the reconstruction that belong to the class; same shape as ``truth_mask``.

    Returns
    -------
    float
        Mean over all M x N pixels of
        ``(2 mu_t mu_r + c1)(2 s_tr + c2) / ((mu_t^2 + mu_r^2 + c1)(s_t^2 + s_r^2 + c2))``,
        where the local means, variances and covariance are Gaussian-weighted
        (sigma 80 px, truncated at 160 px, zero padding, renormalised by the
        window applied to an all-ones image), c1 = 1e-4 and c2 = 9e-4.
        1.0 when the masks are equal (in particular when both are empty);
        symmetric in its two arguments.

    Raises
    ------
    ModelInputInvalid
        If either mask is not a non-empty 2-D boolean/0-1 array, or the shapes differ.
    """
    t = _as_mask(truth_mask, "truth_mask")
    r = _as_mask(reconstruction_mask, "reconstruction_mask")
    if t.shape != r.shape:
        raise ModelInputInvalid(f"truth_mask and reconstruction_mask differ in shape: {t.shape} and {r.shape}")
    mu_t = _local_mean(t)
    mu_r = _local_mean(r)
    var_t = _local_mean(t * t) - mu_t * mu_t
    var_r = _local_mean(r * r) - mu_r * mu_r
    cov = _local_mean(t * r) - mu_t * mu_r
    numerator = (2.0 * mu_t * mu_r + C1) * (2.0 * cov + C2)
    denominator = (mu_t * mu_t + mu_r * mu_r + C1) * (var_t + var_r + C2)
    return float(np.mean(numerator / denominator))


def _check_labels(image: np.ndarray, name: str) -> None:
    if image.dtype.kind not in "biuf":
        raise ModelInputInvalid(f"{name} must hold numeric labels 0, 1, 2, got dtype {image.dtype}")
    bad = ~np.isin(image, LABELS)
    if np.any(bad):
        found = np.unique(image[bad])
        shown = ", ".join(str(v) for v in found[:5]) + (", ..." if found.size > 5 else "")
        raise ModelInputInvalid(f"{name} has labels other than 0 (water), 1 (resistive), 2 (conductive) "
                                f"at {int(bad.sum())} pixel(s): {shown}")


def challenge_score(truth, reconstruction) -> float:
    """KTC2023 score of one target: the mean of the conductive and resistive class indices.

    Parameters
    ----------
    truth : array_like, shape (256, 256)
        True segmentation: 0 water, 1 resistive, 2 conductive.
    reconstruction : array_like, shape (256, 256)
        Segmentation to score, same labels. Any other shape scores 0.

    Returns
    -------
    float
        ``(class_index(truth == 2, reconstruction == 2) + class_index(truth == 1, reconstruction == 1)) / 2``;
        1.0 is perfect. 0.0 when ``reconstruction`` is not 256x256 (checked
        before its labels, as the challenge does).

    Raises
    ------
    ModelInputInvalid
        If ``truth`` is not 256x256, or ``truth`` or a 256x256 ``reconstruction``
        holds labels other than 0, 1, 2.
    """
    t = np.asarray(truth)
    if t.shape != SHAPE:
        raise ModelInputInvalid(f"truth must be 256x256, got shape {t.shape}")
    _check_labels(t, "truth")
    r = np.asarray(reconstruction)
    if r.shape != SHAPE:
        return 0.0
    _check_labels(r, "reconstruction")
    conductive = class_index(t == CONDUCTIVE, r == CONDUCTIVE)
    resistive = class_index(t == RESISTIVE, r == RESISTIVE)
    return 0.5 * (conductive + resistive)
