"""Render the PmatData / PoPu maps used for hand-labelling and number their loaded spots.

The spot finder only NUMBERS candidate loaded spots so a labeller can refer to them;
it names nothing. Site names come from looking at the rendered panels.

    PYTHONPATH=. python tests/data/site_labels/render_maps.py pmat 4 out.png   # one subject, 17 maps
    PYTHONPATH=. python tests/data/site_labels/render_maps.py pmat 4 out.png 1,2,3,4,5,6  # some of them
    PYTHONPATH=. python tests/data/site_labels/render_maps.py popu 4 out.png   # PoPu prone1..7
    PYTHONPATH=. python tests/data/site_labels/render_maps.py one 4 13 out.png # one PmatData map, enlarged
    PYTHONPATH=. python tests/data/site_labels/render_maps.py spots 4 > S4.json  # the label file to fill in
"""

import json
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter, maximum_filter

from appliance.sim.body import MatGrid
from appliance.sim.recordings import pmat_scene, popu_scene

GRID = MatGrid(900.0, 1900.0, 10.0)
KPA_PER_MMHG = 0.133322
LOADED_MMHG = 32.0
MERGE_MM = 40.0
MAX_SPOTS = 12
SHARED = Path(__file__).resolve().parents[4] / "shared" / "data"      # beside the repository
PMAT_DIR, POPU_DIR = str(SHARED / "pmatdata"), str(SHARED / "popu")
POSTURES = {1: "supine", 2: "right-90", 3: "left-90", 4: "right-30", 5: "right-60", 6: "left-30", 7: "left-60",
            8: "supine", 9: "supine", 10: "supine", 11: "supine", 12: "supine", 13: "fetal-right",
            14: "fetal-left", 15: "inclined", 16: "inclined", 17: "inclined"}
"""Each PmatData experiment-i posture file as the monitor names the posture."""
NAMES = {1: "supine", 2: "right side 90", 3: "left side 90", 4: "right 30", 5: "right 60", 6: "left 30",
         7: "left 60", 8: "supine var 8", 9: "supine var 9", 10: "supine var 10", 11: "supine var 11",
         12: "supine var 12", 13: "right fetal", 14: "left fetal", 15: "head up 30", 16: "head up 45",
         17: "head up 60"}


def pmat_map(subject, posture):
    scene = pmat_scene(PMAT_DIR, subject, posture, GRID)
    return scene.frames[len(scene.frames) // 2]


def popu_map(pose, volunteer=4):
    scene = popu_scene(POPU_DIR, pose, 0, volunteer=volunteer, grid=GRID, scale_to_weight=True)
    return scene.frames[len(scene.frames) // 2]


def find_spots(kpa):
    """Candidate loaded spots: local maxima of the lightly smoothed map (sigma 1 cell) whose raw peak in
    the 3 x 3 cells around is >= 32 mmHg, highest first, merged when closer than 40 mm, at most 12.
    Returns [(row, col, peak_mmhg)]; cell centre in mm is (row*10+5, col*10+5)."""
    mmhg = kpa / KPA_PER_MMHG
    smooth = gaussian_filter(mmhg, 1.0)
    raw_peak = maximum_filter(mmhg, size=3)
    is_max = (smooth == maximum_filter(smooth, size=3)) & (raw_peak >= LOADED_MMHG) & (smooth > 0)
    cands = sorted(((raw_peak[r, c], r, c) for r, c in zip(*np.nonzero(is_max))), reverse=True)
    spots = []
    for peak, r, c in cands:
        if all(np.hypot(r - r2, c - c2) * 10.0 >= MERGE_MM for r2, c2, _ in spots):
            spots.append((int(r), int(c), float(round(peak, 1))))
    return spots[:MAX_SPOTS]


def draw(ax, kpa, title, vmax=120):
    mmhg = kpa / KPA_PER_MMHG
    from matplotlib.colors import PowerNorm
    # gamma 0.5: the faint body outline (head, arms, legs) stays visible next to the loaded spots
    im = ax.imshow(mmhg, cmap="jet", norm=PowerNorm(0.5, vmin=0, vmax=vmax), interpolation="nearest",
                   aspect="equal")
    ax.contour(mmhg, levels=[LOADED_MMHG], colors="white", linewidths=0.5)
    for i, (r, c, _) in enumerate(find_spots(kpa), 1):
        ax.plot(c, r, "o", mfc="none", mec="white", ms=7, mew=1.2)
        ax.text(c + 3, r, str(i), color="white", fontsize=10, fontweight="bold",
                bbox=dict(facecolor="black", alpha=0.6, pad=0.5, lw=0))
    ax.set_title(f"{title}\nHEAD\npatient's R | L", fontsize=9)
    ax.axvline(45, color="grey", lw=0.4, ls=":")
    for frac in (0.25, 0.5, 0.75):
        ax.axhline(190 * frac, color="grey", lw=0.4, ls=":")
    ax.set_xticks([0, 45, 89])
    ax.set_yticks(range(0, 190, 20))
    ax.tick_params(labelsize=6)
    return im


def render(maps, out, ncols=6, size=(20, 15.5)):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    nrows = -(-len(maps) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=size, dpi=90, constrained_layout=True)
    axes = np.atleast_1d(axes).ravel()
    for ax, (title, kpa) in zip(axes, maps):
        im = draw(ax, kpa, title)
    for ax in axes[len(maps):]:
        ax.axis("off")
    fig.colorbar(im, ax=axes.tolist(), shrink=0.4, label="mmHg (gamma 0.5 scale)", ticks=[0, 10, 32, 60, 90, 120])
    fig.savefig(out)
    plt.close(fig)


if __name__ == "__main__":
    kind = sys.argv[1]
    if kind == "pmat":
        s = int(sys.argv[2])
        postures = [int(x) for x in sys.argv[4].split(",")] if len(sys.argv) > 4 else range(1, 18)
        render([(f"S{s} #{p} {NAMES[p]}", pmat_map(s, p)) for p in postures], sys.argv[3],
               ncols=min(6, len(postures)) if len(sys.argv) <= 5 else int(sys.argv[5]),
               size=(20, 15.5) if len(sys.argv) <= 5 else (14, 15.5))
    elif kind == "popu":
        v = int(sys.argv[2])
        render([(f"PoPu v{v} prone{k}", popu_map(f"prone{k}", v)) for k in range(1, 8)], sys.argv[3],
               ncols=4, size=(14, 16))
    elif kind == "spots":
        s = int(sys.argv[2])
        maps = [{"posture_file": p, "posture": POSTURES[p],
                 "spots": [{"spot": i, "along_mm": r * 10 + 5, "across_mm": c * 10 + 5, "peak_mmhg": peak,
                            "site": None, "note": ""}
                           for i, (r, c, peak) in enumerate(find_spots(pmat_map(s, p)), 1)]}
                for p in range(1, 18)]
        print(json.dumps({"source": "PmatData experiment-i", "subject": s, "labeller": "hand, from the rendered maps",
                          "frame": "middle frame (len//2) of pmat_scene on a 900 x 1900 mm MatGrid at 10 mm",
                          "convention": "tests/data/site_labels/CONVENTION.md; along_mm from the mat's head end, "
                                        "across_mm from the mat's edge on the patient's right",
                          "spot_finder": "tests/data/site_labels/render_maps.py find_spots (numbers spots only; "
                                         "'spot' is its number)",
                          "maps": maps}, indent=1))
    elif kind == "one":
        s, p = int(sys.argv[2]), int(sys.argv[3])
        render([(f"S{s} #{p} {NAMES[p]}", pmat_map(s, p))], sys.argv[4], ncols=1, size=(8, 14))
