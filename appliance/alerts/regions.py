"""Loaded regions with a stable identity across frames, for the screen and the history.

A pressure-sore alert counts how long the same tissue has been loaded, so a
region must keep its name while the patient breathes, sinks in or shifts a few
centimetres. :class:`RegionTracker` segments each frame at the threshold
(:func:`~appliance.core.pressure_map.loaded_regions`) and matches the regions to
the last frame's: by mask overlap first (the same pixels are the same tissue),
then, for regions that overlap nothing, by centroid distance within
``max_jump_mm`` (a one-pixel heel that steps to the next pixel overlaps nothing).
A split gives the id to the child with the largest overlap and new ids to the
others (``split_from``); a merge keeps the oldest id and lists the absorbed ones
(``merged``); both are reported on the frame where they happen. A region that
vanishes is dropped and its id is never reused, so an alert raised on an id
cannot be inherited by unrelated tissue. Alarms do not rest on regions (they are
per tissue site, :mod:`appliance.alerts.pipeline`); a region is what the screen
draws and the history charts, named by the site it holds.

>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.pixels import pixel_grid
>>> from appliance.core.pressure_map import PressureMap
>>> grid = pixel_grid(get_layout("grid-16x32"))
>>> kpa = np.zeros(grid.shape); kpa[15, 60] = 6.0                   # a heel
>>> tracker = RegionTracker(grid)
>>> [(r.id, r.area_cm2) for r in tracker.update(PressureMap(0.0, kpa, [], None, 0))]
[(1, 8.90625)]
>>> kpa = np.roll(kpa, 2, axis=0)                                     # 60 mm across the bed
>>> [(r.id, r.first_seen_s) for r in tracker.update(PressureMap(1.0, kpa, [], None, 0))]
[(1, 0.0)]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from appliance.core.pixels import PixelGrid
from appliance.core.pressure_map import HIGH_PRESSURE_KPA, PressureMap, loaded_regions

MAX_JUMP_MM = 60.0
"""A little more than one bed pixel (56 mm), far less than the 190 mm between the heels."""


@dataclass(frozen=True)
class TrackedRegion:
    """A loaded region with its identity: ``first_seen_s`` is when its tissue was first loaded
    (a split child inherits its parent's, so a split on a blurred map does not restart the clock);
    ``split_from`` and ``merged`` report this frame's split and merge; ``zone`` is the tissue site the alert
    pipeline finds in it (None until named)."""

    id: int
    x_mm: float
    y_mm: float
    peak_kpa: float
    mean_kpa: float
    area_cm2: float
    mask: np.ndarray
    first_seen_s: float
    zone: str | None = None
    split_from: int | None = None
    merged: tuple[int, ...] = ()


class RegionTracker:
    """Regions of each frame at or above ``threshold_kpa`` and at least ``min_area_cm2``, with ids
    stable across frames.

    ``min_area_cm2`` defaults to one pixel, which keeps every region: a heel's contact
    (about 35 mm across) fills one 56 mm bed pixel, so any larger minimum would drop the
    heels, the site most at risk; set it on fine grids to drop single-pixel specks.
    """

    def __init__(self, grid: PixelGrid, *, threshold_kpa: float = HIGH_PRESSURE_KPA,
                 min_area_cm2: float | None = None, max_jump_mm: float = MAX_JUMP_MM):
        w, h = grid.pixel_mm
        self.grid = grid
        self.threshold_kpa = threshold_kpa
        self.min_area_cm2 = w * h / 100.0 if min_area_cm2 is None else min_area_cm2
        self.max_jump_mm = max_jump_mm
        self.next_id = 1
        self.regions: list[TrackedRegion] = []

    def update(self, pressure_map: PressureMap) -> list[TrackedRegion]:
        """This frame's regions, highest peak first, with ids carried over from the last frame."""
        tolerance = 1e-9 * self.min_area_cm2          # area is a count of pixels times their area
        current = [r for r in loaded_regions(pressure_map.pressure_kpa, self.grid, self.threshold_kpa)
                   if r.area_cm2 >= self.min_area_cm2 - tolerance]
        prev = self.regions
        overlap = np.array([[np.count_nonzero(p.mask & c.mask) for c in current] for p in prev], dtype=int)
        overlap = overlap.reshape(len(prev), len(current))
        heir: dict[int, int] = {}                     # current index -> index of the previous region it continues
        merged: dict[int, list[int]] = {}
        for i in sorted(range(len(prev)), key=lambda i: (prev[i].first_seen_s, prev[i].id)):   # oldest first
            if overlap[i].any():
                j = int(np.argmax(overlap[i]))
                if j in heir:
                    merged.setdefault(j, []).append(prev[i].id)
                else:
                    heir[j] = i
        split_from = {j: int(np.argmax(overlap[:, j])) for j in range(len(current))
                      if j not in heir and overlap[:, j].any()}
        loose_prev = [i for i in range(len(prev)) if not overlap[i].any()]
        loose_cur = [j for j in range(len(current)) if not overlap[:, j].any()]
        if loose_prev and loose_cur:
            distance = np.array([[np.hypot(prev[i].x_mm - current[j].x_mm, prev[i].y_mm - current[j].y_mm)
                                  for j in loose_cur] for i in loose_prev])
            rows, cols = linear_sum_assignment(np.where(distance <= self.max_jump_mm, distance, 1e12))
            for a, b in zip(rows, cols):
                if distance[a, b] <= self.max_jump_mm:
                    heir[loose_cur[b]] = loose_prev[a]
        out = []
        for j, r in enumerate(current):
            if j in heir:
                ident, first = prev[heir[j]].id, prev[heir[j]].first_seen_s
            else:
                ident, self.next_id = self.next_id, self.next_id + 1
                first = prev[split_from[j]].first_seen_s if j in split_from else pressure_map.time_s
            out.append(TrackedRegion(ident, r.x_mm, r.y_mm, r.peak_kpa, r.mean_kpa, r.area_cm2, r.mask, first,
                                     None, prev[split_from[j]].id if j in split_from else None,
                                     tuple(sorted(merged.get(j, ())))))
        self.regions = out
        return out

    def state(self) -> dict:
        """What a restart needs, in plain JSON types: the next id and the last frame's regions
        (masks as flat row-major pixel indices)."""
        return {"shape": list(self.grid.shape), "next_id": self.next_id,
                "regions": [{"id": r.id, "x_mm": r.x_mm, "y_mm": r.y_mm, "peak_kpa": r.peak_kpa,
                             "mean_kpa": r.mean_kpa, "area_cm2": r.area_cm2, "first_seen_s": r.first_seen_s,
                             "mask": np.flatnonzero(r.mask).tolist()} for r in self.regions]}

    @classmethod
    def from_state(cls, grid: PixelGrid, state: dict, **options) -> RegionTracker:
        """A tracker on ``grid`` that carries on from ``state`` (of :meth:`state`) after a restart."""
        if tuple(state["shape"]) != grid.shape:
            raise ValueError(f"tracker state of a {tuple(state['shape'])} grid for a {grid.shape} pixel grid")
        tracker = cls(grid, **options)
        tracker.next_id = int(state["next_id"])
        for r in state["regions"]:
            mask = np.zeros(grid.rows * grid.cols, bool)
            mask[np.asarray(r["mask"], dtype=int)] = True
            tracker.regions.append(TrackedRegion(int(r["id"]), r["x_mm"], r["y_mm"], r["peak_kpa"], r["mean_kpa"],
                                                 r["area_cm2"], mask.reshape(grid.shape), r["first_seen_s"]))
        return tracker
