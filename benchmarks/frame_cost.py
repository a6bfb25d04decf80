"""What one steady frame of the monitor costs the Pi: fsyncs, bytes written and CPU, against an earlier tree.

    python benchmarks/frame_cost.py                  # writes benchmarks/frame_cost.md (about 5 min)
    python benchmarks/frame_cost.py --baseline REV   # against another commit

Both trees run the same command, ``appliance run`` on the default bed (grid-16x32 read through the parallel
board, the virtual patient lying still, one frame a second of bed time, as fast as it goes), in fresh data
folders, sharing the model cache. The baseline is checked out into a temporary worktree and imported from it
with this interpreter, so the two differ only in their code, and they run alternately in one run.

A steady frame's cost is the difference between a long run and a short one, divided by the frames between
them, so start-up (loading the model, the calibration, the store) cancels out:

- fsync and fdatasync calls: counted by ``strace -f -c`` over the whole process tree (every thread);
- bytes written, by file: ``write`` and ``pwrite64`` calls in the same trace, each call's file named by
  ``strace -y``;
- CPU seconds (user + system, every thread; ``resource.getrusage`` of the child), median of ``REPEATS``.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

HERE = Path(__file__).parent
ROOT = HERE.parent
BASELINE = "1315c8b"
"""The tree before the monitor stopped writing map files every frame and syncing every quiet frame."""
SHORT, LONG = 10, 70
REPEATS = 7
RUNNER = """
import atexit, runpy, sys, time
from appliance.service import virtual_bed
acquiring = [0.0]
acquire = virtual_bed.VirtualBedSource.acquire
def timed(self, *args, **kwargs):
    start = time.thread_time()
    try:
        return acquire(self, *args, **kwargs)
    finally:
        acquiring[0] += time.thread_time() - start
virtual_bed.VirtualBedSource.acquire = timed
def report():
    sys.stderr.write(f"{chr(10)}COST cpu {time.process_time()} acquiring {acquiring[0]}{chr(10)}")
atexit.register(report)
sys.argv = ["appliance"] + sys.argv[1:]
runpy.run_module("appliance", run_name="__main__")
"""
"""``appliance run`` with two notes made as it ends: the process's CPU seconds (every thread), and the main
thread's CPU seconds inside the virtual bed's ``acquire`` (the simulated patient, mat and front end: on a bed
that is the hardware's time, not the Pi's computing)."""


def run(tree: Path, frames: int, work: Path, strace: bool = False) -> dict:
    """One ``appliance run`` of ``frames`` frames from ``tree``: its CPU seconds, bytes written and syncs."""
    data = Path(tempfile.mkdtemp(dir=work))
    command = [sys.executable, "-c", RUNNER, "run", "--frames", str(frames), "--speed", "0",
               "--scenario", "supine-still", "--data-dir", str(data)]
    trace = work / "strace.txt"
    if strace:
        command = ["strace", "-f", "-qq", "-y", "-e", "trace=fsync,fdatasync,write,pwrite64", "-o", str(trace)] \
            + command
    env = {"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin", "HOME": str(Path.home())}
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0 or f"stopped after {frames} frames" not in done.stderr:
        raise RuntimeError(f"appliance run from {tree} failed ({done.returncode}): {done.stderr[-2000:]}")
    cost = re.search(r"COST cpu ([\d.e-]+) acquiring ([\d.e-]+)", done.stderr)
    out = {"cpu_s": float(cost.group(1)), "acquire_s": float(cost.group(2))}
    if strace:
        calls = re.findall(r"^\d+ +(\w+)\(\d+<([^>]*)>.*= (\d+)$", trace.read_text(), re.M)
        out["syncs"] = sum(name in ("fsync", "fdatasync") for name, _, _ in calls)
        out["written"] = {}
        for name, path, size in calls:
            if name in ("write", "pwrite64"):
                where = written_to(path, data)
                out["written"][where] = out["written"].get(where, 0) + int(size)
    shutil.rmtree(data)
    return out


def written_to(path: str, data: Path) -> str:
    """What a written file is, by name: the store, its WAL, the screen's live view, the newest map's files (a
    temporary name renamed over them), the terminal or another file."""
    if not path.startswith(str(data)):
        return "output" if path.startswith(("/dev/", "pipe:")) else "other"
    name = Path(path).name.lstrip(".")
    for prefix in ("appliance.db-wal", "appliance.db", "live.json", "live.png", "live.csv"):
        if name.startswith(prefix):
            return prefix
    return "other"


def per_frame(trees: dict[str, Path], work: Path) -> dict[str, dict]:
    """Steady-frame figures of each tree: syncs and bytes from one traced pair, CPU from ``REPEATS`` pairs, the
    trees taking turns so that a busy spell of the machine falls on both."""
    out, cpu = {}, {name: [] for name in trees}
    for name, tree in trees.items():
        short, long = (run(tree, n, work, strace=True) for n in (SHORT, LONG))
        out[name] = {"syncs": (long["syncs"] - short["syncs"]) / (LONG - SHORT),
                     "kib": {where: (long["written"].get(where, 0) - short["written"].get(where, 0))
                             / (LONG - SHORT) / 1024 for where in long["written"].keys() | short["written"].keys()}}
    for _ in range(REPEATS):
        for name, tree in trees.items():
            short, long = run(tree, SHORT, work), run(tree, LONG, work)
            total, bed = long["cpu_s"] - short["cpu_s"], long["acquire_s"] - short["acquire_s"]
            cpu[name].append((1000 * total / (LONG - SHORT), 1000 * (total - bed) / (LONG - SHORT)))
    for name in trees:
        total, monitor = np.median(np.array(cpu[name]), axis=0)
        out[name].update(cpu_ms=float(total), monitor_ms=float(monitor), monitor_all_ms=[m for _, m in cpu[name]])
    return out


def written(result: dict) -> float:
    """KiB a steady frame writes to files."""
    return sum(v for k, v in result["kib"].items() if k != "output")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default=BASELINE, help=f"the commit to compare with (default {BASELINE})")
    args = parser.parse_args()
    if shutil.which("strace") is None:
        sys.exit("frame_cost needs strace (Debian's strace package) to count fsyncs")
    with tempfile.TemporaryDirectory() as tmp:
        work, old = Path(tmp), Path(tmp) / "baseline"
        subprocess.run(["git", "worktree", "add", "--detach", str(old), args.baseline], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            trees = {"baseline": old, "this tree": ROOT}
            for tree in trees.values():                 # each tree's model and calibration cached before measuring
                run(tree, 1, work)
            results = per_frame(trees, work)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=False)
    base, now = results["baseline"], results["this tree"]
    files = ("appliance.db-wal", "appliance.db", "live.json", "live.png", "live.csv", "other")
    rows = [[f"{name} ({args.baseline if name == 'baseline' else 'HEAD'})", f"{r['syncs']:.2f}", f"{written(r):.1f}",
             *(f"{r['kib'].get(f, 0.0):.1f}" for f in files), f"{r['cpu_ms']:.0f}", f"{r['monitor_ms']:.1f}",
             ", ".join(f"{c:.1f}" for c in r["monitor_all_ms"])] for name, r in results.items()]
    text = f"""# The cost of one steady frame

Made by `python benchmarks/frame_cost.py` on {machine()}.
`appliance run --scenario supine-still --speed 0` on the default bed (grid-16x32, one frame per second of bed
time), per steady frame: the difference between a {LONG}-frame and a {SHORT}-frame run over the {LONG - SHORT}
frames between them. Syncs (fsync + fdatasync, every thread) and KiB written to files (by file; the
terminal's lines left out) from one traced pair. CPU (user + system, every thread) the median of {REPEATS} untraced pairs, the trees taking turns in one
run: the whole process, and the monitor's own (the whole less the virtual bed's `acquire`, which simulates the
patient, the mat and the front end: on a real bed that is the hardware's time, not the Pi's computing).

{table(["tree", "syncs per frame", "KiB written per frame", *(f"of it {f}" for f in files),
        "CPU ms per frame, with the simulated bed", "the monitor's own CPU ms per frame (median)", "each pair"],
       rows)}

This tree against the baseline: {base['syncs'] / max(now['syncs'], 1e-9):.0f}x fewer syncs
({now['syncs'] * 10:.2f} per 10 frames), {written(base) / written(now):.1f}x fewer bytes written, the monitor's own CPU
per frame {base['monitor_ms'] / now['monitor_ms']:.2f}x less.
"""
    (HERE / "frame_cost.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
