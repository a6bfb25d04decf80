"""Time from ``appliance run`` to its first pressure map, with an empty model cache (cold) and a filled one (warm).

    python benchmarks/first_start.py        # writes benchmarks/first_start.md (about 2 min)

A nurse who switches a new monitor on waits for the first map; the requirement is 60 s at most. Each run is a
fresh process of ``appliance run --frames 1`` on the virtual bed (the default layout, grid-16x32) with its own
empty data folder; a cold run also has its own empty cache folder, a warm run the cache a cold run filled.
The phases are read off the monitor's progress lines, timed as they arrive on its output.
"""

from __future__ import annotations

import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

HERE = Path(__file__).parent
LIMIT_S = 60.0
RUNS = 3
COMMAND = [sys.executable, "-m", "appliance", "run", "--frames", "1"]
MAP_LINE = re.compile(r"^\d+:\d\d:\d\d  peak ")
MILESTONES = {"model": "building the reconstruction model", "calibration": "taking the pressure calibration",
              "reference": "resuming or taking the empty-mat reference"}
"""Each phase by the start of the first progress line it prints (appliance.service.starting)."""


def first_start(cache: Path, data: Path) -> dict:
    """One run's times (s from the start of the process): each phase's first line and the first map."""
    started = time.perf_counter()
    process = subprocess.Popen([*COMMAND, "--cache-dir", str(cache), "--data-dir", str(data)], cwd=HERE.parent,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert process.stdout is not None
    seen: dict[str, float] = {}
    lines = []
    for line in process.stdout:
        now = time.perf_counter() - started
        lines.append(line.rstrip())
        for phase, words in MILESTONES.items():
            if line.startswith(words):
                seen.setdefault(phase, now)
        if MAP_LINE.match(line):
            seen.setdefault("map", now)
    if process.wait() != 0 or "map" not in seen:
        raise RuntimeError(f"appliance run failed (exit {process.returncode}):\n" + "\n".join(lines[-20:]))
    seen["built"] = "building the reconstruction model: done" in "\n".join(lines)
    return seen


def phases(run: dict) -> list[float]:
    """Start-up before the first phase, model build (0 when loaded), calibration, reference and first frame,
    and the whole time to the first map."""
    model_at = run.get("model", run["calibration"])
    return [model_at, run["calibration"] - model_at, run["reference"] - run["calibration"],
            run["map"] - run["reference"], run["map"]]


def main() -> None:
    load_before = os.getloadavg()
    rows, totals = [], {"cold": [], "warm": []}
    with tempfile.TemporaryDirectory() as work:
        for k in range(RUNS):
            cache = Path(work, f"cache-{k}")
            for kind in ("cold", "warm"):       # the warm run on the cache its cold run filled
                run = first_start(cache, Path(work, f"data-{kind}-{k}"))
                assert run["built"] == (kind == "cold"), f"a {kind} run must {'' if kind == 'cold' else 'not '}build"
                times = phases(run)
                totals[kind].append(times[-1])
                rows.append([kind, k + 1, *(f"{t:.1f}" for t in times)])
                print(rows[-1], flush=True)
    load_after = os.getloadavg()
    cold, warm = max(totals["cold"]), max(totals["warm"])
    verdict = "holds" if cold <= LIMIT_S else "does NOT hold"
    text = f"""# First start: time to the first map

Made by `python benchmarks/first_start.py` on {machine()}, {os.cpu_count()} CPUs shared with other work:
load average (1, 5, 15 min) {", ".join(f"{x:.2f}" for x in load_before)} before the runs and
{", ".join(f"{x:.2f}" for x in load_after)} after, so the figures are those of a busy machine.

Each run is a fresh process of

    {" ".join(["python", *COMMAND[1:]])} --cache-dir CACHE --data-dir DATA

on the virtual bed (grid-16x32, scenario turn-schedule) with its own empty data folder. A cold run has an
empty cache folder, so it builds the reconstruction model; the warm run after it loads the model that cold run
saved. Both take the calibration the package ships for the bed. Times are seconds from the start of the process,
each phase from its first progress line to the next phase's (the first map from its printed line); a warm
run prints no model lines, so loading its model counts in the first column:

{table(["run", "#", "start-up to the first phase", "model build", "calibration",
        "reference and first frame", "to the first map"], rows)}

Median time to the first map: cold {statistics.median(totals["cold"]):.1f} s, warm
{statistics.median(totals["warm"]):.1f} s; the slowest: cold {cold:.1f} s, warm {warm:.1f} s. The requirement of
at most {LIMIT_S:.0f} s to the first map {verdict} on this machine, also for the slowest cold start.
"""
    (HERE / "first_start.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
