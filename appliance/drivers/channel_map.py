"""Where each measuring channel of the parallel front end is: its electrode pair, its ADC and its input.

The parallel front end has a fixed differential channel on every pair of
horizontally adjacent electrodes: channel ``k`` of row ``r`` reads
V(r, k) - V(r, k + 1), so a grid of R x C electrodes has R x (C - 1) channels.
Each AD7606 converts eight of them. They are wired in tiles of
``tile_rows`` rows by ``8 / tile_rows`` pairs, because a drive's readings lie
within a few rows and pairs of it: on the bed's 16 x 32 grid a step of the
rows protocol needs 4.5 ADCs on average with 4 x 2 tiles, against 6.0 with the
channels packed row by row (``benchmarks/acquisition.md``). Electrodes are
1-based as everywhere; channels, ADCs and inputs are 0-based.

>>> cmap = ChannelMap(4, 8, tile_rows=4)
>>> cmap.n_channels, cmap.n_adcs, cmap.channel_of(1, 2), cmap.channel_of(3, 2)
(28, 4, (0, 1), (1, -1))
>>> cmap.adc_of(cmap.channel_of(10, 11)[0])
(0, 3)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from appliance.errors import ProtocolInvalid

CHANNELS_PER_ADC = 8


@dataclass(frozen=True)
class ChannelMap:
    """Channels of a ``rows`` x ``cols`` grid and the ADC tiles they are wired to."""

    rows: int
    cols: int
    tile_rows: int = 4

    @classmethod
    def of_profile(cls, profile) -> ChannelMap:
        return cls(profile.grid.rows, profile.grid.cols, tile_rows=profile.measurement.adc_tile_rows)

    @property
    def pairs_per_row(self) -> int:
        return self.cols - 1

    @property
    def n_channels(self) -> int:
        return self.rows * self.pairs_per_row

    @property
    def tile_cols(self) -> int:
        return CHANNELS_PER_ADC // self.tile_rows

    @property
    def tiles_per_band(self) -> int:
        return -(-self.pairs_per_row // self.tile_cols)

    @property
    def n_adcs(self) -> int:
        return -(-self.rows // self.tile_rows) * self.tiles_per_band

    def pair_of(self, channel: int) -> tuple[int, int]:
        """The (1-based) electrodes channel ``channel`` reads: V(first) - V(second)."""
        r, k = divmod(channel, self.pairs_per_row)
        first = r * self.cols + k + 1
        return first, first + 1

    def channel_of(self, pos: int, neg: int) -> tuple[int, int]:
        """(channel, sign) of a measuring pair: V(pos) - V(neg) = sign x the channel's reading.

        Raises :class:`~appliance.errors.ProtocolInvalid` for a pair that is not two
        horizontally adjacent electrodes: this front end has no channel on it.
        """
        left, right = min(pos, neg), max(pos, neg)
        r, k = divmod(left - 1, self.cols)
        if not (1 <= left and right <= self.rows * self.cols and right == left + 1 and k < self.pairs_per_row):
            raise ProtocolInvalid(f"measuring pair {pos}-{neg}: the parallel front end measures only horizontally "
                                  f"adjacent electrodes of its {self.rows} x {self.cols} grid (use the rows "
                                  "protocol)")
        return r * self.pairs_per_row + k, 1 if pos == left else -1

    def adc_of(self, channel: int) -> tuple[int, int]:
        """(ADC, input) that converts ``channel``."""
        r, k = divmod(channel, self.pairs_per_row)
        band, row_in_tile = divmod(r, self.tile_rows)
        tile, col_in_tile = divmod(k, self.tile_cols)
        return band * self.tiles_per_band + tile, row_in_tile * self.tile_cols + col_in_tile

    @cached_property
    def adc_index(self) -> np.ndarray:
        """(ADC, input) of every channel, shape (n_channels, 2)."""
        return np.array([self.adc_of(c) for c in range(self.n_channels)], dtype=np.int64).reshape(-1, 2)

    def channels_of_protocol(self, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(channel, sign) of each reading's measuring pair; refuses a pair the front end cannot read."""
        out = [self.channel_of(int(p), int(q)) for p, q in np.asarray(readings)[:, 2:4]]
        return (np.array([c for c, _ in out], dtype=np.int64).reshape(-1),
                np.array([s for _, s in out], dtype=np.int64).reshape(-1))
