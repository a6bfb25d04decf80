"""Frame files: one set of readings as CSV, one row per reading in protocol order.

Header ``drive_pos,drive_neg,meas_pos,meas_neg,volts``; electrode numbers 1-based.
A reading the front end could not take is written ``nan`` (or left empty) and read
back as NaN: the reconstruction drops it as it would a broken electrode's.

>>> import numpy as np
>>> from appliance.core.protocols import adjacent_protocol
>>> print(frame_to_csv(adjacent_protocol(4), np.array([0.5, -0.25, 0.125, 1.0])).splitlines()[1])
1,2,3,4,5.000000000e-01
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.core.csv_files import read_rows
from appliance.core.protocols import CSV_HEADER, Protocol, validate_readings
from appliance.errors import DataFileInvalid, ModelInputInvalid, ProtocolInvalid

FRAME_HEADER = CSV_HEADER + ("volts",)


@dataclass(frozen=True)
class Frame:
    """The readings of a frame file with the protocol its rows spell out; NaN marks a missing reading."""

    protocol: Protocol
    volts: np.ndarray


def frame_to_csv(protocol: Protocol, volts: np.ndarray) -> str:
    """CSV text of a frame: the protocol's rows with their readings (volts, 10 significant digits)."""
    volts = np.asarray(volts, dtype=float)
    if volts.shape != (len(protocol),):
        raise ModelInputInvalid(f"a frame of protocol {protocol.name!r} needs {len(protocol)} readings, "
                                f"got shape {volts.shape}")
    out = io.StringIO()
    out.write(",".join(FRAME_HEADER) + "\n")
    for row, v in zip(protocol.readings.tolist(), volts.tolist()):
        out.write(f"{row[0]},{row[1]},{row[2]},{row[3]},{'nan' if math.isnan(v) else f'{v:.9e}'}\n")
    return out.getvalue()


def load_frame(path: Path, n_electrodes: int) -> Frame:
    """Read a frame file for a layout of ``n_electrodes`` electrodes.

    Raises
    ------
    DataFileInvalid
        Missing or unreadable file, wrong header, a row without five values, text
        where a number belongs, or no readings at all; the message names the file
        and the line.
    ProtocolInvalid
        A row names an electrode the layout does not have.
    """
    path = Path(path)
    rows: list[list[int]] = []
    volts: list[float] = []
    lines: list[int] = []
    for line, row in read_rows(path, FRAME_HEADER, "frame file"):
        if len(row) != 5:
            raise DataFileInvalid(f"frame file {path}, line {line}: expected 5 values, got {len(row)}")
        try:
            rows.append([int(cell) for cell in row[:4]])
        except ValueError:
            raise DataFileInvalid(f"frame file {path}, line {line}: electrode numbers must be integers, got "
                                  f"{','.join(row[:4])}") from None
        value = row[4].strip()
        try:
            volts.append(float(value) if value and value.lower() != "nan" else math.nan)
        except ValueError:
            raise DataFileInvalid(f"frame file {path}, line {line}: reading {value!r} is not a number") from None
        if math.isinf(volts[-1]):
            raise DataFileInvalid(f"frame file {path}, line {line}: reading {value!r} is not finite")
        lines.append(line)
    if not volts:
        raise DataFileInvalid(f"frame file {path}: no readings")
    electrodes = np.array(rows)
    validate_readings(electrodes, n_electrodes, lambda i: f"frame file {path}, line {lines[i]}")
    return Frame(Protocol(electrodes, n_electrodes, path.stem), np.array(volts))


def check_same_protocol(frame: Frame, other: Frame, other_name: str, expected: Protocol | None = None) -> None:
    """Refuse two frames whose rows differ, or a frame whose rows are not ``expected``'s,
    naming the first row that differs."""
    for reference, label in ((other.protocol, other_name), (expected, "the model's protocol")):
        if reference is None:
            continue
        a, b = frame.protocol.readings, reference.readings
        if len(a) != len(b):
            raise ProtocolInvalid(f"{frame.protocol.name}: {len(a)} readings, {label} has {len(b)}")
        differ = np.flatnonzero((a != b).any(axis=1))
        if differ.size:
            i = int(differ[0])
            raise ProtocolInvalid(f"{frame.protocol.name}: reading {i + 1} is {tuple(a[i].tolist())}, {label} "
                                  f"has {tuple(b[i].tolist())}; is the frame from another layout or protocol?")


def load_calibration(path: Path, protocol: Protocol, grid, reference: np.ndarray) -> np.ndarray:
    """The thesis's experimental sensitivity (eq. 3.4.1) from a calibration file.

    The file holds one frame per pixel, an object placed in that pixel: header
    ``pixel_row,pixel_col,drive_pos,drive_neg,meas_pos,meas_neg,volts`` (rows and
    columns from 0 at the top-left), the readings of each pixel in protocol order.

    Returns
    -------
    ndarray, shape (n_imaged_pixels, n_readings)
        S = V_p - V_H, rows in the grid's imaged-pixel order.

    Raises
    ------
    DataFileInvalid
        A malformed line, a pixel outside the grid, readings out of protocol order,
        or an imaged pixel left uncalibrated.
    """
    path = Path(path)
    readings: dict[int, list] = {}
    for line, row in read_rows(path, ("pixel_row", "pixel_col") + FRAME_HEADER, "calibration file"):
        try:
            r, c, a, b, m, n = (int(cell) for cell in row[:6])
            volts = float(row[6])
        except (ValueError, IndexError):
            raise DataFileInvalid(f"calibration file {path}, line {line}: expected 6 integers and a reading, got "
                                  f"{','.join(row)}") from None
        if not (0 <= r < grid.rows and 0 <= c < grid.cols):
            raise DataFileInvalid(f"calibration file {path}, line {line}: pixel ({r}, {c}) is outside the "
                                  f"{grid.rows} x {grid.cols} grid")
        pixel = readings.setdefault(r * grid.cols + c, [])
        expected = protocol.readings[len(pixel)] if len(pixel) < len(protocol) else None
        if expected is None or tuple(expected) != (a, b, m, n):
            raise DataFileInvalid(f"calibration file {path}, line {line}: pixel ({r}, {c}) reading "
                                  f"{len(pixel) + 1} is {(a, b, m, n)}, the protocol has "
                                  f"{None if expected is None else tuple(expected)}")
        pixel.append(volts)
    out = np.empty((grid.n_inside, len(protocol)))
    for k, flat in enumerate(grid.inside_index):
        values = readings.get(int(flat))
        if values is None or len(values) != len(protocol):
            r, c = divmod(int(flat), grid.cols)
            raise DataFileInvalid(f"calibration file {path}: pixel ({r}, {c}) is not calibrated "
                                  f"({0 if values is None else len(values)} of {len(protocol)} readings)")
        out[k] = np.array(values) - reference
    return out
