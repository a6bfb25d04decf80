"""The reconstruction pixel grid, apart from the forward mesh, and the maps between them.

Images are rows x columns of equal pixels tiling the sheet's bounding box,
row-major from the top-left. A pixel is imaged when at least a quarter of it
lies on the sheet; the others (the corners around a disc) are NaN. Each forward
element takes the pixel values in proportion to the share of its area in each
pixel, found by sampling the element on a fine barycentric (or, for squares,
regular) lattice.

>>> from appliance.core.named_layouts import get_layout
>>> grid = pixel_grid(get_layout("grid-4x4"))
>>> grid.shape, grid.pixel_mm
((16, 16), (6.25, 6.25))
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from appliance.core.forward import ForwardModel
from appliance.core.layouts import Layout
from appliance.errors import ConfigError

MIN_COVER = 0.25
"""Share of a pixel that must lie on the sheet for it to be imaged."""

DEFAULT_PIXELS_ACROSS = 16
"""Pixels along the shorter side of the sheet by default (16 x 16 on the 100 mm sensors)."""

MAX_PIXEL_MM = 30.0
"""The largest default pixel: a heel or an occiput loads 5 to 7 cm, and commercial pressure mats
sample at 1.3 to 3.2 cm, so a bed's map is drawn no coarser than this."""


@dataclass(frozen=True)
class PixelGrid:
    """``rows`` x ``cols`` pixels over a ``width_mm`` x ``height_mm`` sheet; ``inside`` marks
    the imaged pixels, shape (rows, cols)."""

    rows: int
    cols: int
    width_mm: float
    height_mm: float
    inside: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.cols

    @property
    def pixel_mm(self) -> tuple[float, float]:
        """(width, height) of one pixel."""
        return self.width_mm / self.cols, self.height_mm / self.rows

    @property
    def n_inside(self) -> int:
        return int(self.inside.sum())

    @cached_property
    def centres_mm(self) -> np.ndarray:
        """Centres of all pixels, row-major, shape (rows * cols, 2)."""
        w, h = self.pixel_mm
        r, c = np.divmod(np.arange(self.rows * self.cols), self.cols)
        return np.column_stack([(c + 0.5) * w, (r + 0.5) * h])

    @cached_property
    def inside_index(self) -> np.ndarray:
        """Flat (row-major) indices of the imaged pixels, shape (n_inside,)."""
        return np.flatnonzero(self.inside.ravel())

    def image(self, values: np.ndarray) -> np.ndarray:
        """The (rows, cols) image of ``values`` on the imaged pixels (n_inside,); NaN elsewhere."""
        out = np.full(self.rows * self.cols, np.nan, dtype=np.result_type(values, np.float32))
        out[self.inside_index] = values
        return out.reshape(self.rows, self.cols)

    def pixel_of(self, points_mm: np.ndarray) -> np.ndarray:
        """Flat index of the pixel holding each point (clipped to the grid), shape (n,)."""
        w, h = self.pixel_mm
        c = np.clip((points_mm[:, 0] // w).astype(int), 0, self.cols - 1)
        r = np.clip((points_mm[:, 1] // h).astype(int), 0, self.rows - 1)
        return r * self.cols + c


def pixel_grid(layout: Layout, rows: int | None = None, cols: int | None = None) -> PixelGrid:
    """The pixel grid of ``layout``: by default 16 pixels along its shorter side and square-ish pixels,
    none larger than ``MAX_PIXEL_MM``."""
    width, height = layout.sheet.size_mm
    if rows is None and cols is None:
        pixel = min(min(width, height) / DEFAULT_PIXELS_ACROSS, MAX_PIXEL_MM)
        rows, cols = (math.ceil(height / pixel - 1e-9), math.ceil(width / pixel - 1e-9))
    elif rows is None or cols is None:
        if rows is None:
            assert cols is not None
            rows = max(1, round(cols * height / width))
        else:
            cols = max(1, round(rows * width / height))
    if rows < 1 or cols < 1:
        raise ConfigError(f"a pixel grid needs at least one row and column, got {rows} x {cols}")
    w, h = width / cols, height / rows
    k = 8
    offsets = (np.arange(k) + 0.5) / k
    sub = np.array([(x, y) for y in offsets for x in offsets])
    centres = PixelGrid(rows, cols, width, height, np.ones((rows, cols), bool)).centres_mm
    points = (centres[:, None, :] - 0.5 * np.array([w, h]) + sub[None] * np.array([w, h])).reshape(-1, 2)
    cover = layout.contains(points).reshape(rows * cols, k * k).mean(axis=1)
    return PixelGrid(rows, cols, width, height, (cover >= MIN_COVER).reshape(rows, cols))


def element_pixel_map(model: ForwardModel, grid: PixelGrid, samples: int = 6) -> sp.csr_matrix:
    """Share of each element's area in each imaged pixel, shape (n_elements, n_inside).

    Every row sums to 1: area on a pixel too little on the sheet to be imaged
    (the corners around a disc) counts for the nearest imaged pixel.
    """
    weights, points = _element_samples(model, samples)                 # (s,), (n_el, s, 2)
    n_el, s = points.shape[:2]
    flat = grid.pixel_of(points.reshape(-1, 2))
    inside = grid.centres_mm[grid.inside_index]
    nearest = np.argmin(((grid.centres_mm[:, None, :] - inside[None]) ** 2).sum(axis=2), axis=1)
    column = nearest.copy()
    column[grid.inside_index] = np.arange(grid.n_inside)
    m = sp.csr_matrix((np.tile(weights, n_el), (np.repeat(np.arange(n_el), s), column[flat])),
                      shape=(n_el, grid.n_inside))
    return m


def pixel_areas_mm2(model: ForwardModel, mapping: sp.csr_matrix) -> np.ndarray:
    """Sheet area each imaged pixel stands for, shape (n_inside,), mm^2."""
    return np.asarray(mapping.T @ model.areas_mm2).ravel()


def _element_samples(model: ForwardModel, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Equal-area sample points in every element: weights (s,) summing to 1, points (n_el, s, 2)."""
    corners = model.nodes_mm[model.element_nodes]                      # (n_el, m, 2)
    k = samples
    if corners.shape[1] == 3:
        # Centroids of the k^2 sub-triangles of a regular subdivision, all of equal area.
        bary = []
        for i in range(k):
            for j in range(k - i):
                bary.append(((i + 1 / 3) / k, (j + 1 / 3) / k))
                if i + j < k - 1:
                    bary.append(((i + 2 / 3) / k, (j + 2 / 3) / k))
        b = np.array(bary)
        lam = np.column_stack([b[:, 0], b[:, 1], 1 - b[:, 0] - b[:, 1]])
    else:
        t = (np.arange(k) + 0.5) / k
        u_grid, v_grid = np.meshgrid(t, t)
        u, v = u_grid.ravel(), v_grid.ravel()
        lam = np.column_stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v])   # TL, TR, BR, BL
    points = np.einsum("sm,emd->esd", lam, corners)
    return np.full(len(lam), 1.0 / len(lam)), points
