"""Figures of merit of the thesis's chapter 5: fractional change, visibility, sensitivity.

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
