"""Reading the appliance's CSV files: the header checked, each data line with its number.

>>> from pathlib import Path
>>> import tempfile
>>> path = Path(tempfile.mkdtemp()) / "p.csv"
>>> _ = path.write_text("a,b\\n1,2\\n\\n3,4\\n")
>>> list(read_rows(path, ("a", "b"), "example file"))
[(2, ['1', '2']), (4, ['3', '4'])]
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from appliance.errors import DataFileInvalid


def read_rows(path: Path, header: tuple[str, ...], what: str):
    """The non-empty data lines of the CSV file ``path`` as (line number, cells).

    Raises
    ------
    DataFileInvalid
        The file cannot be read or is not text, or its first line is not ``header``;
        the message names ``what`` file and the line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DataFileInvalid(f"{what} {path}: cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise DataFileInvalid(f"{what} {path}: not a text file") from None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(cell.strip() for cell in rows[0]) != header:
        raise DataFileInvalid(f"{what} {path}, line 1: header must be {','.join(header)}")
    for line, row in enumerate(rows[1:], start=2):
        if row and any(cell.strip() for cell in row):
            yield line, row
