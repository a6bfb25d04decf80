"""Adaptive acquisition on a grid: which drives a frame takes, given the electrodes the caller marks as loaded.

A *coarse* pass takes every drive along a row each frame; the *fine* drives
(the others: along the columns) are taken only near loaded electrodes, where
the pressure map needs them. A drive is near when either of its electrodes
lies within ``radius`` electrode spacings (in both directions) of a loaded
electrode. Readings of drives not taken keep the last frame's values, flagged
as held (:mod:`appliance.drivers.scan`).

>>> import numpy as np
>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.protocols import protocol_for
>>> plan = AdaptivePlan(protocol_for(get_layout("grid-4x8"), "rows"), 4, 8)
>>> len(plan.coarse), len(plan.fine), len(plan.drives_for([])), len(plan.drives_for([1]))
(28, 24, 28, 37)
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from appliance.core.protocols import Protocol
from appliance.errors import ConfigError


class AdaptivePlan:
    """The coarse and fine drives of ``protocol`` on a ``rows`` x ``cols`` grid (row-major, 1-based electrodes)."""

    def __init__(self, protocol: Protocol, rows: int, cols: int, *, radius: float = 2.0):
        if protocol.n_electrodes != rows * cols:
            raise ConfigError(f"a {rows} x {cols} grid has {rows * cols} electrodes, the protocol "
                              f"{protocol.n_electrodes}")
        if not radius >= 0:
            raise ConfigError(f"the fine drives' radius must be at least 0 spacings, got {radius}")
        self.protocol, self.rows, self.cols, self.radius = protocol, rows, cols, radius
        row, col = np.divmod(protocol.drives - 1, cols)
        self._row, self._col = row, col
        along_row = row[:, 0] == row[:, 1]
        self.coarse = np.flatnonzero(along_row)
        self.fine = np.flatnonzero(~along_row)

    def drives_for(self, loaded: Iterable[int]) -> np.ndarray:
        """Indices (into ``protocol.drives``) of the drives to take this frame, in protocol order."""
        loaded = np.array(sorted({int(e) for e in loaded}), dtype=np.int64)
        bad = loaded[(loaded < 1) | (loaded > self.rows * self.cols)]
        if bad.size:
            raise ConfigError(f"loaded electrode {bad[0]} is not on the {self.rows} x {self.cols} grid")
        if loaded.size == 0:
            return self.coarse.copy()
        lr, lc = np.divmod(loaded - 1, self.cols)
        fine_r, fine_c = self._row[self.fine], self._col[self.fine]
        near = np.zeros(len(self.fine), dtype=bool)
        for k in range(2):
            dr = np.abs(fine_r[:, k, None] - lr[None, :])
            dc = np.abs(fine_c[:, k, None] - lc[None, :])
            near |= ((dr <= self.radius + 1e-9) & (dc <= self.radius + 1e-9)).any(axis=1)
        return np.sort(np.concatenate([self.coarse, self.fine[near]]))
