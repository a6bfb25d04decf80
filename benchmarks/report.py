"""Helpers shared by the benchmark scripts: timing by medians, markdown tables, provenance."""

from __future__ import annotations

import os
import platform
import shutil
import socket
import subprocess
import time
from datetime import date
from pathlib import Path

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


# For the benchmarks that run the appliance's processes: ports, waiting, CPU time, percentiles.

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mosquitto_binary() -> str:
    """Where Mosquitto is installed (Debian puts it in /usr/sbin, off a user's PATH)."""
    binary = shutil.which("mosquitto", path=os.environ.get("PATH", "") + ":/usr/sbin:/sbin")
    if binary is None:
        raise RuntimeError("mosquitto is not installed (apt-get install mosquitto); .ci/run installs it")
    return binary


def listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def wait_for(condition, timeout_s: float, what: str, poll_s: float = 0.05) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout_s:.0f} s")
        time.sleep(poll_s)


def cpu_seconds(pid: int) -> float:
    """User and system CPU time of process ``pid`` so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def percentile(values, q: float) -> float:
    """The ``q`` quantile of ``values`` as the nearest rank."""
    values = sorted(values)
    return values[min(len(values) - 1, round(q * (len(values) - 1)))]
