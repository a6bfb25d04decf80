"""How long the real-kernel tests take: the first run with the kernel's download, then later runs.

    python benchmarks/kernel_vm.py            # writes benchmarks/kernel_vm.md (about 3 min)
    python benchmarks/kernel_vm.py --runs 5

Each run is ``python -m pytest -q tests/test_kernel_buses.py`` in a process of its own, timed from start to
exit, as a developer would run it. The first uses an empty kernel cache (``XDG_CACHE_HOME`` in a temporary
folder), so it downloads and unpacks Debian's kernel; the later ones use the usual cache, filled first if
it is empty. The machine's one-minute load average is printed beside each run: under TCG emulation the
guest competes with everything else for the cores.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

HERE = Path(__file__).parent
ROOT = HERE.parent
TEST = "tests/test_kernel_buses.py"


def timed_run(env: dict) -> tuple[float, str, float]:
    """Wall seconds, pytest's last line and the load average at the start of one run of the kernel tests."""
    load = os.getloadavg()[0]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", TEST], cwd=ROOT,
                          env=env, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    last = (done.stdout.strip().splitlines() or ["(no output)"])[-1]
    if done.returncode != 0:
        raise SystemExit(f"the kernel tests failed (exit {done.returncode}): {last}\n{done.stdout[-2000:]}")
    return seconds, last, load


def folder_mb(folder: Path) -> float:
    """Megabytes of the files under ``folder``."""
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file() and not f.is_symlink()) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, choices=range(1, 21), metavar="1-20",
                        help="later runs to time (default 3)")
    args = parser.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as empty:
        seconds, last, load = timed_run({**os.environ, "XDG_CACHE_HOME": empty})
        rows.append(["first, with the kernel's download", f"{seconds:.1f}", f"{load:.1f}", last])
        print(rows[-1], flush=True)
        cache = Path(empty) / "appliance" / "kernel-vm"
        lists_mb = folder_mb(cache / "apt")
        kernel_mb = folder_mb(cache) - lists_mb
    timed_run(dict(os.environ))  # fills the usual cache if it was empty, so no later run downloads
    for run in range(1, args.runs + 1):
        seconds, last, load = timed_run(dict(os.environ))
        rows.append([f"later run {run}", f"{seconds:.1f}", f"{load:.1f}", last])
        print(rows[-1], flush=True)
    later = sorted(float(row[1]) for row in rows[1:])
    kvm = os.access("/dev/kvm", os.R_OK | os.W_OK)
    text = f"""# The real-kernel tests: how long they take

Made by `python benchmarks/kernel_vm.py --runs {args.runs}` on {machine()}, {os.cpu_count()} cores,
{platform.system()} {platform.release()}; /dev/kvm {"opens" if kvm else "absent or closed"} (the VM tries KVM first and falls
back on QEMU's TCG emulation when KVM cannot run the guest, as under a nested hypervisor).

Each run is `python -m pytest -q {TEST}` in a fresh process, timed from start to exit. The first run has
an empty kernel cache and downloads Debian's kernel; later runs boot the cached one.

{table(["run", "wall s", "load average at start", "pytest's summary"], rows)}

Later runs: median {later[len(later) // 2]:.1f} s (from {later[0]:.1f} to {later[-1]:.1f} s).

The cache the first run leaves: {kernel_mb:.0f} MB of unpacked kernel and modules, {lists_mb:.0f} MB of package
lists and downloads.
"""
    (HERE / "kernel_vm.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
