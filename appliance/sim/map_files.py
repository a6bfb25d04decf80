"""Pressure maps as files: a grid of pressures in mmHg, one CSV line per row of sensels.

The format, read and written here::

    # any number of comment lines first, each starting with '#'
    0,0,12.5,30,0
    0,4,41,55.2,3
    ...

Row 0 is the head end, as in PmatData's files; column 0 lies at the mat's left
edge seen from above with the head at the top (x = 0 of the scene's grid: the
patient's right when supine, as the body model and PmatData have it). Values are
separated by commas, every row has as many as the first, and each is a finite,
non-negative pressure in mmHg. The sensel pitch is not in the file: the command
line or the scenario gives it.

A map the appliance reconstructs is written the same way (CSV, ``nan`` for a
pixel off the sheet, no comment) or as a PNG, chosen by the file's extension.

>>> import tempfile
>>> path = Path(tempfile.mkdtemp()) / "m.csv"
>>> _ = path.write_text("# two rows\\n1, 2, 3\\n4, 5, 6\\n")
>>> read_map_mmhg(path).tolist()
[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from appliance.errors import ConfigError, DataFileInvalid
from appliance.files import check_writable, write_atomic

MIN_PITCH_MM, MAX_PITCH_MM = 1.0, 100.0
"""Sensel pitches accepted. Pressure-mapping mats have sensels from a few mm (seat and foot mats) to about
32 mm (bed mats: PmatData's 28.5, PoPu's 31.75); a pitch below 1 mm or above 100 mm (wider than a heel, so
no map of a body) is far more likely a unit slip (cm, m, inches) than a mat."""

OUTPUT_SUFFIXES = (".csv", ".png")
PNG_FULL_SCALE_MMHG = 100.0     # white at 0, darkest at 100 mmHg and over: the live view's scale
PNG_SCALE = 16


def check_pitch_mm(value, where: str) -> float:
    """``value`` as a sensel pitch in mm, or a ConfigError naming ``where`` and the range accepted."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not MIN_PITCH_MM <= value <= MAX_PITCH_MM:
        raise ConfigError(f"{where} must be a sensel pitch from {MIN_PITCH_MM:g} to {MAX_PITCH_MM:g} mm (pressure "
                          f"mats' sensels are a few mm to about 32 mm; outside that range it is a unit slip), "
                          f"got {value!r}")
    return float(value)


def read_map_mmhg(path) -> np.ndarray:
    """The map in ``path`` (rows, cols) in mmHg; a bad shape, value or file is named with its line and column."""
    path = Path(path)
    what = f"pressure map {path}"
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataFileInvalid(f"{what} does not exist") from None
    except IsADirectoryError:
        raise DataFileInvalid(f"{what} is a folder, not a CSV file") from None
    except OSError as exc:
        raise DataFileInvalid(f"{what} cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise DataFileInvalid(f"{what} is not a text file") from None
    lines = [(n, line) for n, line in enumerate(text.splitlines(), start=1) if line.strip()]
    while lines and lines[0][1].lstrip().startswith("#"):
        lines.pop(0)
    if not lines:
        raise DataFileInvalid(f"{what} holds no values")
    rows: list[list[float]] = []
    for n, line in lines:
        cells = line.split(",")
        if rows and len(cells) != len(rows[0]):
            raise DataFileInvalid(f"{what}, line {n}: {len(cells)} values, but the first row has {len(rows[0])} "
                                  "(every row needs as many)")
        values = []
        for j, cell in enumerate(cells):
            where = f"{what}, line {n} (row {len(rows)}, column {j})"
            try:
                value = float(cell)
            except ValueError:
                raise DataFileInvalid(f"{where}: {cell.strip()!r} is not a number") from None
            if not math.isfinite(value):
                raise DataFileInvalid(f"{where}: {cell.strip()} is not a finite pressure")
            if value < 0:
                raise DataFileInvalid(f"{where}: {value:g} mmHg is negative; a mat can only be pressed")
            values.append(value)
        rows.append(values)
    grid = np.array(rows)
    if min(grid.shape) < 2:
        raise DataFileInvalid(f"{what} has {grid.shape[0]} row(s) of {grid.shape[1]} value(s); a map needs at "
                              "least 2 rows and 2 columns, values separated by commas")
    return grid


def check_output_path(path: Path) -> Path:
    """``path`` if a map can be written there: a .csv or .png file in a folder that exists."""
    return check_writable(path, "output", OUTPUT_SUFFIXES, ".csv (mmHg on the pixel grid) or .png")


def write_map_mmhg(path: Path, mmhg: np.ndarray) -> None:
    """``mmhg`` (rows, cols, NaN off the sheet) as CSV, or as a PNG on the live view's 0 to 100 mmHg scale.

    The file is replaced whole (written beside it, then renamed): an existing file is never left half-written.
    """
    path = check_output_path(path)
    if path.suffix.lower() == ".png":
        from appliance.core.render import write_png

        write_png(path, mmhg, vmin=0.0, vmax=PNG_FULL_SCALE_MMHG, palette="sequential", scale=PNG_SCALE)
    else:
        write_atomic(path, "\n".join(",".join("nan" if np.isnan(v) else f"{v:.6g}" for v in row) for row in mmhg)
                     + "\n")
