"""Measurement protocols: the ordered list of readings (drive+, drive-, meas+, meas-).

Current enters at drive+ and leaves at drive-; a reading is V(meas+) - V(meas-).
Electrode numbers are 1-based, as in files and on screen.

>>> from appliance.core.named_layouts import get_layout
>>> len(default_protocol(get_layout("circular-16"))), len(default_protocol(get_layout("grid-4x4")))
(208, 448)
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from appliance.core.csv_files import read_rows
from appliance.core.layouts import Layout
from appliance.errors import DataFileInvalid, ProtocolInvalid

CSV_HEADER = ("drive_pos", "drive_neg", "meas_pos", "meas_neg")


@dataclass(frozen=True)
class Protocol:
    """An ordered set of four-electrode readings on ``n_electrodes`` electrodes.

    Attributes
    ----------
    readings : ndarray, shape (n_readings, 4)
        Electrode numbers (1-based): drive_pos, drive_neg, meas_pos, meas_neg.
    n_electrodes : int
    name : str
    """

    readings: np.ndarray
    n_electrodes: int
    name: str = "custom"

    def __post_init__(self):
        readings = np.asarray(self.readings)
        if readings.ndim != 2 or readings.shape[1] != 4 or len(readings) == 0:
            raise ProtocolInvalid(f"protocol {self.name!r} needs rows of 4 electrode numbers, got shape "
                                  f"{readings.shape}")
        readings = readings.astype(np.int64)
        object.__setattr__(self, "readings", readings)
        validate_readings(readings, self.n_electrodes, lambda i: f"protocol {self.name!r} reading {i + 1}")

    def __len__(self) -> int:
        return len(self.readings)

    @cached_property
    def drives(self) -> np.ndarray:
        """The distinct drive pairs in order of first use, shape (n_drives, 2), 1-based."""
        pairs = self.readings[:, :2]
        _, first = np.unique(pairs, axis=0, return_index=True)
        return pairs[np.sort(first)]

    @cached_property
    def drive_index(self) -> np.ndarray:
        """For each reading, the row of :attr:`drives` it uses, shape (n_readings,)."""
        lookup = {tuple(p): i for i, p in enumerate(self.drives.tolist())}
        return np.array([lookup[tuple(p)] for p in self.readings[:, :2].tolist()])

    def reciprocal_pairs(self) -> np.ndarray:
        """Index pairs (i, j), i < j, of readings that are each other's reciprocal.

        Reading j drives on reading i's measuring pair and measures on its drive
        pair; the two must agree (with the sign that the pair orders give).
        Returns shape (n_pairs, 2).
        """
        index = {tuple(r): i for i, r in enumerate(self.readings.tolist())}
        pairs = []
        for i, (a, b, c, d) in enumerate(self.readings.tolist()):
            j = index.get((c, d, a, b))
            if j is not None and i < j:
                pairs.append((i, j))
        return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def validate_readings(readings: np.ndarray, n_electrodes: int, where) -> None:
    """Refuse an unknown electrode or a pair using one electrode twice; ``where(i)`` names row i."""
    for i, row in enumerate(readings):
        bad = [int(v) for v in row if not 1 <= v <= n_electrodes]
        if bad:
            raise ProtocolInvalid(f"{where(i)}: electrode {bad[0]} does not exist (the layout has "
                                  f"electrodes 1 to {n_electrodes})")
        if row[0] == row[1]:
            raise ProtocolInvalid(f"{where(i)}: drive pair uses electrode {row[0]} twice")
        if row[2] == row[3]:
            raise ProtocolInvalid(f"{where(i)}: measuring pair uses electrode {row[2]} twice")


# ---------------------------------------------------------------------------
# Peripheral protocols

def skip_protocol(n_electrodes: int, drive_skip: int = 0, meas_skip: int = 0, name: str | None = None) -> Protocol:
    """Drive (k, k+1+drive_skip), measure (m, m+1+meas_skip) around a ring, leaving out
    every measuring pair that touches a drive electrode.

    ``drive_skip=0, meas_skip=0`` is the adjacent protocol (16 x 13 = 208 readings
    on 16 electrodes); a drive pair that repeats one already used, reversed, is
    left out (opposite drive on 16 electrodes gives 8 drives).
    """
    n = n_electrodes
    if not 0 <= drive_skip < n - 1 or not 0 <= meas_skip < n - 1:
        raise ProtocolInvalid(f"skips must be between 0 and {n - 2} on {n} electrodes, got "
                              f"{drive_skip} and {meas_skip}")
    rows, seen = [], set()
    for k in range(n):
        a, b = k, (k + 1 + drive_skip) % n
        if frozenset((a, b)) in seen:
            continue
        seen.add(frozenset((a, b)))
        for j in range(n):
            m = (k + 1 + j) % n
            c, d = m, (m + 1 + meas_skip) % n
            if {c, d} & {a, b}:
                continue
            rows.append((a + 1, b + 1, c + 1, d + 1))
    return Protocol(np.array(rows), n, name or _skip_name(n, drive_skip, meas_skip))


def _skip_name(n: int, drive_skip: int, meas_skip: int) -> str:
    if drive_skip == meas_skip == 0:
        return "adjacent"
    if drive_skip == n // 2 - 1 and meas_skip == 0:
        return "opposite"
    return f"skip-{drive_skip}-{meas_skip}"


def adjacent_protocol(n_electrodes: int) -> Protocol:
    """Adjacent drive, adjacent measure (the thesis's phantoms A and B)."""
    return skip_protocol(n_electrodes, 0, 0)


def opposite_protocol(n_electrodes: int) -> Protocol:
    """Polar drive between diametrically opposite electrodes, adjacent measure."""
    if n_electrodes % 2:
        raise ProtocolInvalid(f"opposite drive needs an even number of electrodes, got {n_electrodes}")
    return skip_protocol(n_electrodes, n_electrodes // 2 - 1, 0)


# ---------------------------------------------------------------------------
# Grid protocols

def grid_pairs(rows: int, cols: int) -> np.ndarray:
    """Horizontally then vertically adjacent electrode pairs of a grid, row-major, 1-based."""
    number = np.arange(1, rows * cols + 1).reshape(rows, cols)
    horizontal = np.column_stack([number[:, :-1].ravel(), number[:, 1:].ravel()])
    vertical = np.column_stack([number[:-1, :].ravel(), number[1:, :].ravel()])
    return np.vstack([horizontal, vertical])


def distributed_protocol(rows: int, cols: int, reach: float | None = None, *,
                         measuring: str = "all") -> Protocol:
    """The thesis's distributed protocol for a grid (sensor C), optionally limited in reach.

    Every horizontally or vertically adjacent pair drives in turn; for each, every
    adjacent pair sharing no electrode with it is read (448 readings on 4 x 4).
    With ``reach`` only pairs whose midpoint lies within ``reach`` electrode
    spacings of the drive pair's midpoint (in both directions) are read, so that a
    bed-size mat stays practical. ``measuring="rows"`` reads horizontally adjacent
    pairs only: a front end with a fixed measuring channel on each pair along the
    rows has no others. With every pair measured the rule is symmetric, so every
    reading keeps its reciprocal (with ``rows``, the readings driven along a row).
    """
    if measuring not in MEASURING:
        raise ProtocolInvalid(f"measuring pairs must be one of {', '.join(MEASURING)}, got {measuring!r}")
    pairs = grid_pairs(rows, cols)
    if len(pairs) < 2:
        raise ProtocolInvalid(f"a {rows} x {cols} grid has too few adjacent pairs for a protocol")
    if reach is not None and not reach > 0:
        raise ProtocolInvalid(f"reach must be positive, got {reach}")
    r, c = np.divmod(pairs - 1, cols)
    mid = np.column_stack([r.mean(axis=1), c.mean(axis=1)])
    measured = np.arange(len(pairs)) if measuring == "all" else np.flatnonzero(r[:, 0] == r[:, 1])
    out = []
    for i, (a, b) in enumerate(pairs):
        for j in measured:
            p, q = pairs[j]
            if {a, b} & {p, q}:
                continue
            if reach is not None and np.max(np.abs(mid[i] - mid[j])) > reach + 1e-9:
                continue
            out.append((a, b, p, q))
    if not out:
        raise ProtocolInvalid(f"a {rows} x {cols} grid has no measuring pair within reach {reach} of a drive")
    name = ("distributed" if reach is None else f"local-{reach:g}") + ("" if measuring == "all" else "-rows")
    return Protocol(np.array(out), rows * cols, name)


MEASURING = ("all", "rows")
"""Which adjacent pairs a grid protocol measures on: all of them, or those along the rows."""


LOCAL_REACH_DEFAULT = 2.0
"""Reach, in electrode spacings, of the default protocol on grids of more than 16 electrodes."""

SERIAL_ELECTRODES = 32
"""The most electrodes a serial front end's multiplexers address (the ``reference-32`` profile); a grid
with more is read by the parallel front end, whose fixed channels measure along the rows."""


def default_protocol(layout: Layout) -> Protocol:
    """Adjacent for peripheral layouts, distributed for grids up to 16 electrodes, locality-limited up
    to 32, and beyond that locality-limited and measured along the rows, as the parallel front end
    that reads such a mat does."""
    if layout.grid_shape is None:
        return adjacent_protocol(layout.n_electrodes)
    rows, cols = layout.grid_shape
    if rows * cols <= 16:
        return distributed_protocol(rows, cols)
    return distributed_protocol(rows, cols, LOCAL_REACH_DEFAULT,
                                measuring="rows" if rows * cols > SERIAL_ELECTRODES else "all")


def protocol_for(layout: Layout, kind: str | None = None, *, skip: int = 0, reach: float | None = None) -> Protocol:
    """A named protocol kind for ``layout``: default, adjacent, opposite, skip, distributed, local or rows
    (local, measured on the pairs along the rows only)."""
    n = layout.n_electrodes
    if kind in (None, "default"):
        return default_protocol(layout)
    if kind == "adjacent":
        return adjacent_protocol(n)
    if kind == "opposite":
        return opposite_protocol(n)
    if kind == "skip":
        return skip_protocol(n, skip, 0)
    if kind in ("distributed", "local", "rows"):
        if layout.grid_shape is None:
            raise ProtocolInvalid(f"the {kind} protocol needs a grid layout; {layout.name!r} has its "
                                  f"electrodes around the edge")
        reach = (reach if reach is not None else LOCAL_REACH_DEFAULT) if kind != "distributed" else None
        return distributed_protocol(*layout.grid_shape, reach=reach,
                                    measuring="rows" if kind == "rows" else "all")
    raise ProtocolInvalid(f"unknown protocol kind {kind!r}: use default, adjacent, opposite, skip, "
                          f"distributed, local or rows")


# ---------------------------------------------------------------------------
# CSV

def protocol_to_csv(protocol: Protocol) -> str:
    """CSV text: a header, then one row per reading."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    writer.writerows(protocol.readings.tolist())
    return out.getvalue()


def load_protocol(path: Path, n_electrodes: int) -> Protocol:
    """Read a protocol CSV (header ``drive_pos,drive_neg,meas_pos,meas_neg``).

    Raises
    ------
    DataFileInvalid
        Unreadable file, wrong header, or a row that is not four integers.
    ProtocolInvalid
        A row names an unknown electrode or uses one electrode twice in a pair;
        the message gives the file and the line.
    """
    path = Path(path)
    readings, lines = [], []
    for line, row in read_rows(path, CSV_HEADER, "protocol file"):
        if len(row) != 4:
            raise DataFileInvalid(f"protocol file {path}, line {line}: expected 4 values, got {len(row)}")
        try:
            readings.append([int(cell) for cell in row])
        except ValueError:
            raise DataFileInvalid(f"protocol file {path}, line {line}: electrode numbers must be integers, "
                                  f"got {','.join(row)}") from None
        lines.append(line)
    if not readings:
        raise DataFileInvalid(f"protocol file {path}: no readings")
    validate_readings(np.array(readings), n_electrodes, lambda i: f"protocol file {path}, line {lines[i]}")
    return Protocol(np.array(readings), n_electrodes, path.stem)
