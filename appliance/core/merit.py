"""Figures of merit: the thesis's chapter 5 (fractional change, visibility, sensitivity) and GREIT's
for images (amplitude response, position error, resolution, shape deformation, ringing).

Readings enter as magnitudes, as the thesis's RMS-to-DC converter measured them
(Appendix B takes ``abs`` of every simulated reading of phantom C).

>>> import numpy as np
>>> reference = np.array([1.0, -2.0, 4.0])
>>> round(fractional_change(np.array([1.1, -2.2, 4.4]), reference), 6)
0.1
>>> visibility(np.array([1.0, -2.0, 4.0]), reference)
0.0
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.core.forward import ForwardModel, simulate
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import Protocol
from appliance.errors import ModelInputInvalid


def _magnitudes(volts, reference) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.abs(np.asarray(volts, dtype=float)), np.abs(np.asarray(reference, dtype=float))
    if v.shape != u.shape or v.ndim != 1 or v.size == 0:
        raise ModelInputInvalid(f"readings and reference must be matching non-empty vectors, got {v.shape} "
                                f"and {u.shape}")
    return v, u


def fractional_change(volts, reference) -> float:
    """dV/V of eq. 5.2.3: the mean over readings of (V - V_u) / V_u."""
    v, u = _magnitudes(volts, reference)
    if np.any(u == 0):
        raise ModelInputInvalid("a reference reading is zero: dV/V is undefined for it")
    return float(np.mean((v - u) / u))


def visibility(volts, reference) -> float:
    """Visibility Q of eq. 5.2.4: the mean over readings of (V - V_u) / (V + V_u).

    Positive for an object less conductive than the background, negative for a
    more conductive one, bounded by 1 in magnitude.
    """
    v, u = _magnitudes(volts, reference)
    total = v + u
    if np.any(total == 0):
        raise ModelInputInvalid("a reading and its reference are both zero: Q is undefined for it")
    return float(np.mean((v - u) / total))


def calibration_sensitivity(model: ForwardModel, protocol: Protocol, centres_mm: np.ndarray, object_mm: float,
                            contrast: float = 1e-3, background: float = 1.0) -> np.ndarray:
    """The thesis's experimental sensitivity (eq. 3.4.1), simulated.

    A square object ``object_mm`` wide of conductivity ``contrast`` x background is
    placed at each of ``centres_mm`` in turn; S = |V_p| - |V_H| for every reading.

    Returns
    -------
    ndarray, shape (n_positions, n_readings), volts per amp
    """
    homogeneous = np.abs(simulate(model, np.full(model.n_elements, background), protocol))
    rows = []
    for x, y in np.asarray(centres_mm, dtype=float):
        sigma = conductivity(model, [Inclusion("rect", x, y, object_mm, object_mm, contrast)], background)
        rows.append(np.abs(simulate(model, sigma, protocol)) - homogeneous)
    return np.array(rows)


def sensitivity_profile(sensitivity: np.ndarray) -> np.ndarray:
    """The thesis's sensitivity of each position: S summed over all readings.

    This is the normaliser of the backprojection of eq. 3.4.2, and what the
    thesis's sensitivity profiles (Figs. 3.4.17, 3.4.18, 5.3.3) and its peak values
    (4533 for B, 9735 for C) show. Changes of opposite sign cancel in it, which is
    why C's edge, where nearby readings rise and fall together, scores low.

    Parameters
    ----------
    sensitivity : ndarray, shape (n_positions, n_readings)
        From :func:`calibration_sensitivity`.
    """
    return np.asarray(sensitivity).sum(axis=1)


@dataclass(frozen=True)
class ImageFigures:
    """GREIT's figures of merit (Adler et al. 2009) of one image of one target, plus our centroid error.

    Attributes
    ----------
    amplitude_response : float
        The image's integral over the target's (area x change): 1 is a true-sized image.
    position_error_mm : float
        Target's distance from the sheet's centre minus the image's: positive toward the centre.
    resolution : float
        sqrt(area of the quarter-amplitude set / sheet area).
    shape_deformation : float
        Share of the quarter-amplitude set outside the disc of its own area at its centroid.
    ringing : float
        Opposite-sign amplitude outside the set over the amplitude inside it.
    centroid_error_mm : float
        Distance from the target's centre to the amplitude-weighted centroid of the set.
    """

    amplitude_response: float
    position_error_mm: float
    resolution: float
    shape_deformation: float
    ringing: float
    centroid_error_mm: float


def image_figures(pixels: np.ndarray, centres_mm: np.ndarray, areas_mm2: np.ndarray, target_mm,
                  target_area_mm2: float, target_change: float, sheet_centre_mm) -> ImageFigures:
    """The figures of merit of an image of a single target of relative change ``target_change``.

    Parameters
    ----------
    pixels, areas_mm2 : ndarray, shape (n,)
        Image values (NaN counts as 0) and the area each pixel stands for.
    centres_mm : ndarray, shape (n, 2)
    target_mm, sheet_centre_mm : (x, y)
    """
    x = np.nan_to_num(np.asarray(pixels, dtype=float)) * np.sign(target_change)   # the target's sign positive
    peak = x.max()
    if not peak > 0:
        nan = float("nan")
        return ImageFigures(0.0, nan, nan, nan, nan, nan)
    q = x >= 0.25 * peak
    area_q = areas_mm2[q].sum()
    weight = x[q] * areas_mm2[q]
    centroid = weight @ centres_mm[q] / weight.sum()
    target, centre = np.asarray(target_mm, float), np.asarray(sheet_centre_mm, float)
    radius = np.sqrt(area_q / np.pi)
    outside_disc = np.linalg.norm(centres_mm[q] - centroid, axis=1) > radius
    opposite = (~q) & (x < 0)
    return ImageFigures(
        amplitude_response=float(x @ areas_mm2 / (target_area_mm2 * abs(target_change))),
        position_error_mm=float(np.linalg.norm(target - centre) - np.linalg.norm(centroid - centre)),
        resolution=float(np.sqrt(area_q / areas_mm2.sum())),
        shape_deformation=float(areas_mm2[q][outside_disc].sum() / area_q),
        ringing=float(-(x[opposite] * areas_mm2[opposite]).sum() / weight.sum()),
        centroid_error_mm=float(np.linalg.norm(centroid - target)),
    )
