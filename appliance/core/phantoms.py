"""Inclusions of different conductivity placed on a model: test objects for simulations.

An element takes an inclusion's conductivity when its centroid lies inside it;
later inclusions cover earlier ones. Meshes aligned with an inclusion's edges
reproduce its area exactly; otherwise the area error shrinks with the elements
(:func:`covered_area_mm2` reports what was actually placed).

>>> import numpy as np
>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.network import build_network_model, network_for_layout
>>> model = build_network_model(network_for_layout(get_layout("grid-4x4")))
>>> sigma = conductivity(model, [Inclusion("rect", 50.0, 50.0, 25.0, 25.0, 0.1)])
>>> covered_area_mm2(model, sigma)
625.0
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.core.forward import ForwardModel
from appliance.errors import ModelInputInvalid


@dataclass(frozen=True)
class Inclusion:
    """A rectangle (``width_mm`` x ``height_mm``) or disc (diameter ``width_mm``) centred at
    (``x_mm``, ``y_mm``) whose conductivity is ``contrast`` times the background's."""

    shape: str
    x_mm: float
    y_mm: float
    width_mm: float
    height_mm: float
    contrast: float

    def __post_init__(self):
        if self.shape not in ("rect", "disc"):
            raise ModelInputInvalid(f"inclusion shape must be 'rect' or 'disc', got {self.shape!r}")
        values = (self.x_mm, self.y_mm, self.width_mm, self.height_mm, self.contrast)
        if not all(np.isfinite(values)):
            raise ModelInputInvalid(f"inclusion values must be finite numbers, got {values}")
        if self.width_mm <= 0 or self.height_mm <= 0:
            raise ModelInputInvalid(f"inclusion size must be positive, got {self.width_mm} x {self.height_mm} mm")
        if self.contrast <= 0:
            raise ModelInputInvalid(f"inclusion contrast must be positive (a conductivity ratio), got {self.contrast}")

    def contains(self, points: np.ndarray) -> np.ndarray:
        dx, dy = points[:, 0] - self.x_mm, points[:, 1] - self.y_mm
        if self.shape == "disc":
            return dx**2 + dy**2 <= (self.width_mm / 2) ** 2
        return (np.abs(dx) <= self.width_mm / 2) & (np.abs(dy) <= self.height_mm / 2)


def conductivity(model: ForwardModel, inclusions, background: float = 1.0) -> np.ndarray:
    """Per-element conductivity of ``model`` with ``inclusions`` on a ``background``; shape (n_elements,)."""
    if not (np.isfinite(background) and background > 0):
        raise ModelInputInvalid(f"background conductivity must be positive and finite, got {background!r}")
    sigma = np.full(model.n_elements, float(background))
    for inclusion in inclusions:
        sigma[inclusion.contains(model.centroids_mm)] = background * inclusion.contrast
    return sigma


def covered_area_mm2(model: ForwardModel, sigma: np.ndarray, background: float = 1.0) -> float:
    """Area of the elements (other than metal electrodes) whose conductivity differs from the background."""
    changed = (sigma != background) & ~model.fixed_elements
    return float(model.areas_mm2[changed].sum())
