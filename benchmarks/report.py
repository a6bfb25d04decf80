"""Helpers shared by the benchmark scripts: timing by medians, markdown tables, provenance."""

from __future__ import annotations

import platform
import subprocess
import time
from datetime import date

import numpy as np
import scipy


def median_seconds(function, repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``function()`` over ``repeats`` calls, after ``warmup`` calls."""
    for _ in range(warmup):
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def table(headers: list[str], rows: list[list]) -> str:
    """A markdown table; floats are written as given (format them first)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def machine() -> str:
    """One line naming the machine and library versions a report was made on."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                check=False).stdout.strip() or "uncommitted"
    except OSError:
        commit = "unknown"
    return (f"{date.today().isoformat()}, commit {commit}, {platform.machine()} {platform.processor() or ''} "
            f"Python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}").replace("  ", " ")


def pyplot():
    """matplotlib's pyplot, drawing off-screen (benchmarks run without a display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, title: str | None = None, dpi: int = 100) -> None:
    """Title, lay out, write and close ``fig``."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
