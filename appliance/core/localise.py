"""Where each pressed region is: its position, size and depth fitted to the readings.

A regularised image blurs, and the blur pulls a region's centroid toward where the
sensor is more sensitive, by a good part of a millimetre on the 100 mm sensors even
without noise; yet the readings pin a 20 mm load's position to about 0.1 to 0.2 mm at
1 % noise (the Cramer-Rao bound). So the image only finds the regions (the connected
parts of its quarter-amplitude set); each region is then modelled as a soft-edged disc
of relative change ``change`` and radius ``radius_mm`` at (``x_mm``, ``y_mm``), and all
regions' parameters are fitted at once to the readings by weighted least squares,
with the forward model's Jacobian on the elements. The fit's covariance gives each
position's uncertainty.

>>> Region(10.0, 20.0, 5.0, -0.4, 0.1, 0.1).position_mm
(10.0, 20.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize

from appliance.core.forward import ForwardModel
from appliance.core.jacobian import jacobian
from appliance.core.reconstruct import Reconstructor

EDGE_MM_PER_PIXEL = 0.25
"""Width of a spot's soft edge, as a share of the pixel size: smooth enough to fit, sharp
enough to stand for a load's edge."""


@dataclass(frozen=True)
class Region:
    """A fitted region: the centre of its change on the sheet and the radius of a disc of its area (mm),
    its relative change, and the centre's standard deviations (mm).

    The change is fitted through the linearised model, which overstates large changes
    (about -0.6 for a true -0.4); the iterated image gives the depth, this its place.
    """

    x_mm: float
    y_mm: float
    radius_mm: float
    change: float
    sd_x_mm: float
    sd_y_mm: float

    @property
    def position_mm(self) -> tuple[float, float]:
        return self.x_mm, self.y_mm


def find_regions(image: np.ndarray, sign: float = -1.0, fraction: float = 0.25) -> list[np.ndarray]:
    """The connected parts (4-neighbour) of the image's ``fraction``-amplitude set of the given
    sign, largest amplitude first, each as a boolean mask over the image."""
    value = np.nan_to_num(np.asarray(image, dtype=float)) * np.sign(sign)
    peak = value.max()
    if not peak > 0:
        return []
    labels, count = ndimage.label(value >= fraction * peak)
    masks = [labels == k for k in range(1, count + 1)]
    return sorted(masks, key=lambda m: -value[m].max())


class _Spots:
    """Soft-edged discs evaluated on the forward elements, and their readings through J."""

    def __init__(self, centroids_mm, edge_mm):
        self.centroids = centroids_mm
        self.edge = edge_mm

    def conductivity_change(self, theta: np.ndarray) -> np.ndarray:
        change = np.zeros(len(self.centroids))
        for x, y, radius, amplitude in theta.reshape(-1, 4):
            d = np.hypot(self.centroids[:, 0] - x, self.centroids[:, 1] - y)
            change += amplitude * 0.5 * (1 - np.tanh((d - abs(radius)) / self.edge))
        return change


def localise(model: ForwardModel, r: Reconstructor, frame: np.ndarray, reference: np.ndarray,
             image: np.ndarray | None = None, sign: float = -1.0, max_regions: int = 8) -> list[Region]:
    """Fit the regions the image shows to the readings.

    Parameters
    ----------
    model : ForwardModel
        The forward model ``r`` was linearised from (its Jacobian on the elements is used).
    r : Reconstructor
    image : ndarray, optional
        The image of ``frame`` (by default ``r``'s one-step image).
    sign : float
        -1 to fit the pressed (less conductive) regions, +1 for more conductive ones.
    """
    image = r.reconstruct(frame, reference) if image is None else image
    masks = find_regions(image, sign)[:max_regions]
    if not masks:
        return []
    grid = r.grid
    centres = grid.centres_mm
    area = float(np.prod(grid.pixel_mm))
    start = []
    for mask in masks:
        flat = mask.ravel()
        weight = np.abs(np.nan_to_num(image.ravel()[flat]))
        cx, cy = weight @ centres[flat] / weight.sum()
        radius = np.sqrt(flat.sum() * area / np.pi)
        start += [cx, cy, radius, float(np.nan_to_num(image.ravel()[flat]).min() if sign < 0 else
                                        np.nan_to_num(image.ravel()[flat]).max())]
    theta0 = np.array(start)
    u = r.usable
    data = (frame - reference)[u] / r.scale(reference)
    std = r.options.noise.std(r.linear.reference)[u]
    j = jacobian(model, np.ones(model.n_elements), r.linear.protocol, relative=True)[u]
    spots = _Spots(model.centroids_mm, EDGE_MM_PER_PIXEL * min(grid.pixel_mm))

    def residual(theta):
        return (data - j @ spots.conductivity_change(theta)) / std

    width, height = grid.width_mm, grid.height_mm
    lower = np.tile([0.0, 0.0, 0.25 * min(grid.pixel_mm), -0.95], len(masks))
    upper = np.tile([width, height, 0.5 * max(width, height), 50.0], len(masks))
    fit = optimize.least_squares(residual, np.clip(theta0, lower + 1e-9, upper - 1e-9), bounds=(lower, upper),
                                 x_scale="jac")
    try:
        covariance = np.linalg.inv(fit.jac.T @ fit.jac)
    except np.linalg.LinAlgError:
        covariance = np.full((len(fit.x), len(fit.x)), np.nan)
    out = []
    for k, theta in enumerate(fit.x.reshape(-1, 4)):
        # Near an edge a larger disc centred further out covers nearly the same sheet, so the
        # disc's centre is loosely pinned; the centre of the change on the sheet is not.
        centre, area = _on_sheet(spots, model.areas_mm2, theta)
        step = np.array([0.05, 0.05, 0.05, 1e-3])
        gradient = np.column_stack([(_on_sheet(spots, model.areas_mm2, theta + np.eye(4)[i] * step[i])[0] - centre)
                                    / step[i] for i in range(4)])
        sd = np.sqrt(np.abs(np.diag(gradient @ covariance[4 * k: 4 * k + 4, 4 * k: 4 * k + 4] @ gradient.T)))
        out.append(Region(float(centre[0]), float(centre[1]), float(np.sqrt(area / np.pi)), float(theta[3]),
                          float(sd[0]), float(sd[1])))
    return out


def _on_sheet(spots: _Spots, areas: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid (mm) and area (mm^2, by the change's share of its peak) of one spot on the sheet."""
    weight = np.abs(spots.conductivity_change(theta)) * areas
    return weight @ spots.centroids / weight.sum(), float(weight.sum() / max(abs(theta[3]), 1e-12))
