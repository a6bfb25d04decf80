"""Peak memory of each built-in layout's cold model build (and grid-12x24's), each in a fresh process with an
empty cache.

    python benchmarks/cold_build.py        # writes benchmarks/cold_build.md (about 2 min)

A Pi has 0.5 to 8 GB, so the model the monitor builds on its first start must fit: the limit is 0.6 GB for
the bed (grid-16x32). The figure is the build process's peak resident memory (``ru_maxrss``), the
interpreter and libraries included, with the default reconstruction of each layout (``default_setup``).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

HERE = Path(__file__).parent
LIMIT_GB = 0.6
BUILD = """
import json, resource, sys, tempfile, time
from appliance.core.model_cache import cached_model, default_setup
from appliance.core.named_layouts import get_layout
start = time.perf_counter()
with tempfile.TemporaryDirectory() as cache:
    model, loaded = cached_model(default_setup(get_layout(sys.argv[1])), cache)
print(json.dumps({"peak_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, "loaded": loaded,
                  "seconds": time.perf_counter() - start, "pixels": int(model.reconstructor.grid.n_inside),
                  "readings": len(model.setup.protocol)}))
"""


def cold_build(layout: str) -> dict:
    done = subprocess.run([sys.executable, "-c", BUILD, layout], capture_output=True, text=True, check=True,
                          cwd=HERE.parent)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    from appliance.core.named_layouts import BUILTIN_NAMES

    rows = []
    for name in (*BUILTIN_NAMES, "grid-12x24"):
        r = cold_build(name)
        assert not r["loaded"], "a cold build must not find a cached model"
        rows.append([name, r["readings"], r["pixels"], f"{r['peak_bytes'] / 2**20:.0f}",
                     f"{r['peak_bytes'] / 1e9:.3f}", f"{r['seconds']:.0f}"])
        print(rows[-1], flush=True)
    bed = next(row for row in rows if row[0] == "grid-16x32")
    text = f"""# Cold model builds: peak memory

Made by `python benchmarks/cold_build.py` on {machine()}.
Each built-in layout's reconstruction model built from nothing (an empty cache) in a fresh process; peak
resident memory of that process (`ru_maxrss`, interpreter and libraries included).

{table(["layout", "readings", "pixels", "peak MiB", "peak GB", "seconds"], rows)}

The bed (grid-16x32): {bed[4]} GB at its peak, against the {LIMIT_GB} GB limit
({"within" if float(bed[4]) <= LIMIT_GB else "OVER"}).
"""
    (HERE / "cold_build.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
