"""The hospital soak at full size (300 beds, 30 minutes, every fault) run beside the rest of the suite.

Its 30 minutes are the engine's and the faults' own clock, so they cannot be compressed; run first and waited
for last, the soak adds little to the suite's time instead of 30 minutes. The run is
``benchmarks/hospital.py`` itself, as a separate process group (its servers, stations and bed workers are its
children), so a failing or interrupted suite stops all of it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "hospital.py"
ARGS = ("--beds", "300", "--minutes", "30")
"""The soak the hospital's ward IT asks for: 300 beds, 50 alarm changes a second, 30 minutes."""

WAIT_S = 75 * 60.0
"""The longest the soak may take from its start: 30 minutes of load, the servers' and beds' start, the drain and
the measuring, on a machine busy with the rest of the suite."""


class BackgroundSoak:
    """One run of the hospital benchmark in the background, its records in a folder of its own."""

    def __init__(self):
        self.folder = Path(tempfile.mkdtemp(prefix="hospital-long-soak-"))
        self.log_path = self.folder / "soak.log"
        with open(self.log_path, "wb") as log:
            self.process = subprocess.Popen(
                [sys.executable, str(BENCHMARK), *ARGS, "--keep", str(self.folder / "records"),
                 "--out", str(self.folder / "report.md"), "--json", str(self.folder / "measured.json")],
                stdout=log, stderr=subprocess.STDOUT, cwd=BENCHMARK.parents[1], start_new_session=True)
        self.started = time.monotonic()

    def result(self) -> dict:
        """The run's counts (``hospital.measured_record``), once it has finished; AssertionError with the end of
        its log if it failed or overran WAIT_S."""
        try:
            code = self.process.wait(max(1.0, WAIT_S - (time.monotonic() - self.started)))
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"the soak ran over {WAIT_S / 60:.0f} min:\n{self.log_tail()}") from None
        assert code == 0, f"the soak exited {code}:\n{self.log_tail()}"
        return json.loads((self.folder / "measured.json").read_text())

    def report(self) -> str:
        return (self.folder / "report.md").read_text()

    def log_tail(self, lines: int = 40) -> str:
        return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])

    def stop(self) -> None:
        """Stop the run and every process it started, and remove its records."""
        if self.process.poll() is None:
            with_group(self.process.pid, signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(30)
        with_group(self.process.pid, signal.SIGKILL)      # stragglers: servers or workers left by a killed harness
        shutil.rmtree(self.folder, ignore_errors=True)


def with_group(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(pid, sig)
