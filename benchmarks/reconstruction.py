"""Reconstruction benchmark: speed against error for every layout, algorithm and resolution, beside pyEIT.

    python benchmarks/reconstruction.py      # writes benchmarks/reconstruction.md and reconstruction.png

Test loads are 20 mm squares thinning the liquid by 40 % (relative conductivity -0.4), at random
places, simulated on a mesh four times finer than, and built apart from, the reconstruction mesh;
Gaussian noise of 0.1 % and 1 % of the rms reference reading is added to every reading. pyEIT 1.2.4
reconstructs the same frames on its own mesh of matched size, with point electrodes at our
electrodes' centres. Timings are medians in this one run.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import sys
import time
from pathlib import Path

import numpy as np

from appliance.core.fem import build_fem_model
from appliance.core.forward import simulate
from appliance.core.layouts import DiscSheet
from appliance.core.merit import image_figures
from appliance.core.mesh import mesh_layout
from appliance.core.model_cache import ModelSetup, build_model
from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.pixels import pixel_grid
from appliance.core.protocols import default_protocol
from appliance.core.reconstruct import ReconstructionOptions, readings_using, without_readings
from appliance.core.regularisation import NoiseModel

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, median_seconds, pyplot, save_figure, table  # noqa: E402

HERE = Path(__file__).parent
COMMAND = "python benchmarks/reconstruction.py"
LAYOUTS = ("circular-16", "square-16", "grid-4x4")
ALGORITHMS = ("greit", "gn-laplace", "gn-noser", "gn-tikhonov", "backprojection")
RESOLUTIONS = (16, 32)
NOISES = (1e-3, 1e-2)
N_LOADS = 40
LOAD_MM, LOAD_CHANGE = 20.0, -0.4


def test_loads(layout):
    """Positions, clean frames and the reference, simulated on the fine truth mesh."""
    rng = np.random.default_rng(2026)
    truth = build_fem_model(layout, density=4)
    protocol = default_protocol(layout)
    reference = simulate(truth, np.ones(truth.n_elements), protocol)
    positions = []
    while len(positions) < N_LOADS:
        x, y = rng.uniform(12, 88, 2)
        if not isinstance(layout.sheet, DiscSheet) or np.hypot(x - 50, y - 50) < 36:
            positions.append((x, y))
    frames = np.array([simulate(truth, conductivity(truth, [Inclusion("rect", x, y, LOAD_MM, LOAD_MM,
                                                                      1 + LOAD_CHANGE)]), protocol)
                       for x, y in positions])
    return np.array(positions), frames, reference


def noisy(frames, reference, level, seed):
    rng = np.random.default_rng(seed)
    return frames + rng.normal(0, level * np.sqrt(np.mean(reference**2)), frames.shape)


def figures(images, grid, positions, areas=None):
    """Per-load figures of merit of images (n_loads, n_pixels on the grid's imaged pixels)."""
    areas = np.full(grid.n_inside, np.prod(grid.pixel_mm)) if areas is None else areas
    centres = grid.centres_mm[grid.inside_index]
    centre = (grid.width_mm / 2, grid.height_mm / 2)
    return [image_figures(img, centres, areas, pos, LOAD_MM**2, LOAD_CHANGE, centre)
            for img, pos in zip(images, positions)]


def summary(figs):
    ce = np.array([f.centroid_error_mm for f in figs])
    ar = np.array([f.amplitude_response for f in figs])
    pe = np.array([f.position_error_mm for f in figs])
    return {"centroid_median": float(np.nanmedian(ce)), "centroid_p95": float(np.nanpercentile(ce, 95)),
            "ar_mean": float(np.nanmean(ar)), "ar_cv": float(np.nanstd(ar) / abs(np.nanmean(ar))),
            "pe_mean": float(np.nanmean(pe)), "pe_sd": float(np.nanstd(pe)),
            "res": float(np.nanmean([f.resolution for f in figs])),
            "sd": float(np.nanmean([f.shape_deformation for f in figs])),
            "rng": float(np.nanmean([f.ringing for f in figs]))}


def ours(layout, protocol, positions, frames_by_noise, reference):
    rows = []
    for pixels in RESOLUTIONS:
        for algorithm in ALGORITHMS:
            for noise in NOISES:
                options = ReconstructionOptions(algorithm, noise=NoiseModel(relative=0.0, absolute=noise))
                start = time.perf_counter()
                model = build_model(ModelSetup(layout, protocol, options, pixels=(pixels, pixels)))
                setup = time.perf_counter() - start
                r = model.reconstructor
                frames = frames_by_noise[noise]
                frame_s = median_seconds(lambda: r.pixels(frames[0], reference), 1000, warmup=20)
                images = np.array([r.pixels(f, reference) for f in frames])
                s = summary(figures(images, r.grid, positions, r.linear.areas_mm2))
                rows.append({"layout": layout.name, "method": f"ours {algorithm}", "pixels": pixels, "noise": noise,
                             "setup_s": setup, "frame_s": frame_s, "elements": r.linear.mapping.shape[0], **s})
                print(rows[-1]["layout"], rows[-1]["method"], pixels, noise, f"{s['centroid_median']:.2f}",
                      flush=True)
                if algorithm == "greit" and pixels == RESOLUTIONS[0]:
                    rows.append(fitted_row(layout, model, frames, reference, positions, noise, setup))
    return rows


def fitted_row(layout, model, frames, reference, positions, noise, setup):
    """The regions of the GREIT image fitted to the readings (appliance/core/localise.py)."""
    errors, times = [], []
    for frame, position in zip(frames, positions):
        start = time.perf_counter()
        regions = model.regions(frame, reference)
        times.append(time.perf_counter() - start)
        errors.append(np.hypot(regions[0].x_mm - position[0], regions[0].y_mm - position[1]) if regions else np.nan)
    nan = float("nan")
    return {"layout": layout.name, "method": "ours greit + region fit", "pixels": RESOLUTIONS[0], "noise": noise,
            "setup_s": setup, "frame_s": float(np.median(times)), "elements": model.reconstructor.linear.mapping.shape[0],
            "centroid_median": float(np.nanmedian(errors)), "centroid_p95": float(np.nanpercentile(errors, 95)),
            "ar_mean": nan, "ar_cv": nan, "pe_mean": nan, "pe_sd": nan, "res": nan, "sd": nan, "rng": nan}


def cramer_rao(layout, protocol, positions, reference, noise=1e-2, count=20):
    """Median over load positions of the median radial error of an ideal unbiased estimator of a
    load's position (fitting x, y, change and size) at ``noise``, from the Fisher information."""
    truth = build_fem_model(layout, density=2)
    sd = noise * np.sqrt(np.mean(reference**2))
    rng = np.random.default_rng(0)

    def readings(x, y, change=LOAD_CHANGE, side=LOAD_MM):
        sigma = conductivity(truth, [Inclusion("rect", x, y, side, side, 1 + change)])
        return simulate(truth, sigma, protocol)

    medians = []
    for x, y in positions[:count]:
        h = 0.5
        s = np.column_stack([(readings(x + h, y) - readings(x - h, y)) / (2 * h),
                             (readings(x, y + h) - readings(x, y - h)) / (2 * h),
                             (readings(x, y, LOAD_CHANGE + 0.05) - readings(x, y, LOAD_CHANGE - 0.05)) / 0.1,
                             (readings(x, y, side=LOAD_MM + 1) - readings(x, y, side=LOAD_MM - 1)) / 2])
        covariance = np.linalg.pinv(s.T @ s / sd**2)[:2, :2]
        draws = rng.multivariate_normal([0, 0], covariance, 4000)
        medians.append(np.median(np.hypot(draws[:, 0], draws[:, 1])))
    return float(np.median(medians))


def peer(layout, protocol, positions, frames_by_noise, reference, elements):
    try:
        from pyeit_peer import run_pyeit
    except ImportError:
        return []
    grid = pixel_grid(layout, 32, 32)
    sheet = ("disc", layout.sheet.radius_mm) if isinstance(layout.sheet, DiscSheet) else \
        ("rect", *layout.sheet.size_mm)
    all_frames = np.vstack([frames_by_noise[n] for n in NOISES])
    result = run_pyeit(sheet, layout.centroids_mm(), protocol.readings, reference, all_frames,
                       grid.centres_mm[grid.inside_index], elements)
    rows = []
    for algorithm in ("jac", "bp", "greit"):
        images = result[algorithm]["images"]
        for k, noise in enumerate(NOISES):
            s = summary(figures(images[k * N_LOADS:(k + 1) * N_LOADS], grid, positions))
            rows.append({"layout": layout.name, "method": f"pyEIT {algorithm}", "pixels": "own", "noise": noise,
                         "setup_s": result[algorithm]["setup_s"], "frame_s": result[algorithm]["frame_s"],
                         "elements": result[algorithm]["n_elements"], **s})
    return rows


def setup_race():
    """Whole model setup at about 4,400 elements: ours (mesh to reconstruction matrix) and pyEIT's JAC."""
    from pyeit_peer import run_pyeit

    rows = []
    for name in ("circular-16", "grid-4x4"):
        layout = get_layout(name)
        protocol = default_protocol(layout)
        density = min(np.arange(0.8, 2.5, 0.05), key=lambda d: abs(mesh_layout(layout, d).n_triangles - 4400))
        start = time.perf_counter()
        model = build_model(ModelSetup(layout, protocol, ReconstructionOptions("gn-laplace")))
        default_s = time.perf_counter() - start
        start = time.perf_counter()
        big = build_model(ModelSetup(layout, protocol, ReconstructionOptions("gn-laplace"), density=float(density)))
        ours_s = time.perf_counter() - start
        reference = big.reconstructor.linear.reference
        sheet = ("disc", 50.0) if name == "circular-16" else ("rect", 100.0, 100.0)
        grid = big.reconstructor.grid
        start = time.perf_counter()
        result = run_pyeit(sheet, layout.centroids_mm(), protocol.readings, reference, reference[None] * 1.01,
                           grid.centres_mm, 4400, algorithms=("jac",), frame_repeats=10)
        pyeit_total = time.perf_counter() - start
        rows.append([name, big.reconstructor.linear.mapping.shape[0], f"{ours_s:.2f}",
                     result["jac"]["n_elements"], f"{result['jac']['setup_s']:.2f}", f"{pyeit_total:.2f}",
                     f"{result['jac']['setup_s'] / ours_s:.0f}x", model.reconstructor.linear.mapping.shape[0],
                     f"{default_s:.2f}"])
        print(rows[-1], flush=True)
    return rows


FRAME_RACE_LAYOUT = "circular-16"
FRAME_RACE_ROUNDS = 50


def frame_race(layout, protocol, frames, reference):
    """Per frame, side by side on the same frames: our whole one-step path (``ReconstructionModel.reconstruct``
    with its checks of the frame and the reference, GREIT on 16 x 16 pixels), a bare product with the
    same matrix, and pyEIT's GREIT ``solve``; each call timed alone, the three interleaved frame by frame
    for ``FRAME_RACE_ROUNDS`` rounds over every frame, medians."""
    from pyeit_peer import pyeit_solver

    model = build_model(ModelSetup(layout, protocol, ReconstructionOptions("greit", noise=NoiseModel(0.0, 1e-2)),
                                   pixels=(16, 16)))
    matrix = model.reconstructor.matrix
    sheet = ("disc", layout.sheet.radius_mm)
    theirs = pyeit_solver(sheet, layout.centroids_mm(), protocol.readings, reference,
                          build_fem_model(layout).n_elements)
    calls = {"ours": lambda f: model.reconstruct(f, reference, iterate="never"),
             "bare": lambda f: matrix @ (f - reference),
             "pyeit": theirs}
    times = {name: [] for name in calls}
    for name, call in calls.items():
        call(frames[0])                                     # warm: the reference's fit, pyEIT's first call
    for _ in range(FRAME_RACE_ROUNDS):
        for frame in frames:
            for name, call in calls.items():
                start = time.perf_counter()
                call(frame)
                times[name].append(time.perf_counter() - start)
    medians = {name: float(np.median(t)) for name, t in times.items()}
    row = [layout.name, len(times["ours"]), f"{medians['ours'] * 1e6:.1f}", f"{medians['bare'] * 1e6:.1f}",
           f"{medians['pyeit'] * 1e6:.1f}", f"{medians['ours'] / medians['bare']:.1f}",
           f"{medians['ours'] / medians['pyeit']:.2f}"]
    print(row, flush=True)
    return row


def broken_electrodes(layout, protocol, positions, frames, reference):
    model = build_model(ModelSetup(layout, protocol, ReconstructionOptions(noise=NoiseModel(0.0, 1e-3))))
    errors, updates = [], []
    for electrode in range(1, layout.n_electrodes + 1):
        drop = readings_using(protocol, [electrode])
        start = time.perf_counter()
        r = without_readings(model.reconstructor, drop)
        updates.append(time.perf_counter() - start)
        images = np.array([r.pixels(np.where(drop, np.nan, f), reference) for f in frames[::4]])
        errors += [f.centroid_error_mm for f in figures(images, r.grid, positions[::4], r.linear.areas_mm2)]
    return [layout.name, f"{np.median(errors):.2f}", f"{np.percentile(errors, 95):.2f}",
            f"{np.median(updates) * 1e3:.1f}", f"{np.max(updates) * 1e3:.1f}"]


def plot(rows, path):
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 5), sharey=True)
    markers = dict(zip(LAYOUTS, "o^s"))
    for ax, noise in zip(axes, NOISES):
        for row in rows:
            if row["noise"] != noise or row["pixels"] not in (16, "own"):
                continue
            peer_row = row["method"].startswith("pyEIT")
            ax.scatter(row["frame_s"] * 1e3, row["centroid_median"], marker=markers[row["layout"]],
                       color="grey" if peer_row else None, s=40)
            ax.annotate(f"{row['method'].split(' ')[1]}", (row["frame_s"] * 1e3, row["centroid_median"]),
                        fontsize=6, xytext=(3, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"noise {noise:.1%} of the rms reading (o disc, ^ square, s grid; grey: pyEIT)", fontsize=9)
        ax.set_xlabel("per-frame reconstruction, ms (median of 1000)")
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_ylabel("median centroid error, mm (20 mm loads)")
    save_figure(fig, path, "Speed against error: ours (16 x 16 pixels) and pyEIT 1.2.4 on the same frames")


def main():
    rows, broken, bounds, frame_row = [], [], {}, None
    for name in LAYOUTS:
        layout = get_layout(name)
        protocol = default_protocol(layout)
        positions, clean, reference = test_loads(layout)
        frames_by_noise = {n: noisy(clean, reference, n, seed=k) for k, n in enumerate(NOISES)}
        rows += ours(layout, protocol, positions, frames_by_noise, reference)
        elements = build_fem_model(layout).n_elements
        rows += peer(layout, protocol, positions, frames_by_noise, reference, elements)
        if name == FRAME_RACE_LAYOUT and rows[-1]["method"].startswith("pyEIT"):
            frame_row = frame_race(layout, protocol, np.vstack([frames_by_noise[n] for n in NOISES]), reference)
        broken.append(broken_electrodes(layout, protocol, positions, frames_by_noise[1e-3], reference))
        bounds[name] = cramer_rao(layout, protocol, positions, reference)
    race = setup_race()
    plot(rows, HERE / "reconstruction.png")
    (HERE / "reconstruction.md").write_text(render(rows, broken, race, bounds, frame_row))
    print((HERE / "reconstruction.md").read_text())


def render(rows, broken, race, bounds, frame_row) -> str:
    def fmt(row):
        return [row["layout"], row["method"], row["pixels"], f"{row['noise']:.1%}", row["elements"],
                f"{row['setup_s']:.2f}", f"{row['frame_s'] * 1e3:.3f}", f"{row['centroid_median']:.2f}",
                f"{row['centroid_p95']:.2f}", f"{row['ar_mean']:.2f}", f"{row['ar_cv']:.2f}",
                f"{row['pe_mean']:+.2f} ± {row['pe_sd']:.2f}", f"{row['res']:.2f}", f"{row['sd']:.2f}",
                f"{row['rng']:.2f}"]

    headers = ["layout", "method", "pixels", "noise", "elements", "setup s", "frame ms", "centroid median mm",
               "centroid p95 mm", "AR", "AR CV", "PE mm", "RES", "SD", "RNG"]
    best_peer = {}
    for row in rows:
        if row["method"].startswith("pyEIT") and row["noise"] == 1e-2:
            key = row["layout"]
            best_peer[key] = min(best_peer.get(key, (np.inf, "")), (row["centroid_median"], row["method"]))
    at_one = {(row["layout"], row["method"]): row["centroid_median"] for row in rows
              if row["noise"] == 1e-2 and row["pixels"] in (16, "own")}
    versus = []
    for name in LAYOUTS:
        image, fitted = at_one[name, "ours greit"], at_one[name, "ours greit + region fit"]
        if name in best_peer:
            best, method = best_peer[name]
            versus.append([name, f"{image:.2f}", f"{fitted:.2f}", f"{best:.2f} ({method})", f"{image / best:.2f}",
                           f"{fitted / best:.2f}", f"{bounds[name]:.2f}", f"{0.5 * best:.2f}"])
        else:
            versus.append([name, f"{image:.2f}", f"{fitted:.2f}", "not run", "", "", f"{bounds[name]:.2f}", ""])
    return f"""# Reconstruction: speed against error, beside pyEIT

Made by `{COMMAND}` on {machine()}.

Test loads: {N_LOADS} squares of {LOAD_MM:g} mm at random places (on the disc, within 36 mm of its centre),
relative conductivity change {LOAD_CHANGE:+g}, simulated on a mesh four times finer than the one that
reconstructs and built apart from it; Gaussian noise of 0.1 % and 1 % of the rms reference reading on every
reading. Ours declares that noise to its reconstructor (the appliance measures its own noise); pyEIT 1.2.4
runs with the settings of its own examples (JAC p 0.5, lambda 0.01, Kotre; GREIT n 32, lambda 0.01;
BP), on its own mesh of matched element count, with point electrodes at our electrodes' centres, on the
same frames and the same protocols. Every image is scored on the pixel grid (pyEIT's resampled onto 32 x 32):
centroid of the quarter-amplitude set, and GREIT's figures of merit (amplitude response AR and its
spread over positions, position error PE toward the centre, resolution RES, shape deformation SD, ringing
RNG). Ours is timed as the product of its matrix with a frame (median of 1000); pyEIT as its `solve`.

![speed against error](reconstruction.png)

## Under noise, against pyEIT's best (1 % noise, median centroid error, mm)

"Image" is the centroid of our GREIT image's quarter-amplitude set, scored exactly as pyEIT's images are.
"Fitted" is where the appliance places a region: the regions the image finds, each fitted to the readings
for position, size and depth (`appliance/core/localise.py`). The Cramer-Rao column is the median error an
ideal unbiased estimator of the load's position (knowing its shape, fitting position, change and size)
would make at this noise, from the Fisher information of the truth model: no method can do better on
average without bias.

{table(["layout", "ours, image", "ours, fitted", "pyEIT, best", "image / pyEIT", "fitted / pyEIT",
        "Cramer-Rao bound", "half of pyEIT's best"], versus)}

Where half of pyEIT's best lies below the Cramer-Rao bound, halving pyEIT's error is not possible for any
unbiased method on these loads: pyEIT's GREIT is then already within a factor of two of what the readings
allow. pyEIT's JAC and BP do break down at 1 % noise (see the full table); its GREIT, which weights each
reading by the regularised normal matrix rather than dividing it by the reference, does not on loads of
this size.

## Per frame: our whole path against pyEIT's GREIT, side by side

{frame_section(frame_row)}

## Setup: mesh to reconstruction matrix

At about 4,400 elements, ours builds everything (mesh, forward model, Jacobian, lambda and matrix); pyEIT's
JAC setup builds its Jacobian and matrix on a mesh it has already made (its mesh time is extra).

{table(["layout", "our elements", "ours s", "pyEIT elements", "pyEIT JAC setup s", "pyEIT mesh + setup s",
        "pyEIT JAC / ours", "default elements", "ours at default s"], race)}

## Any one electrode removed (GREIT, 0.1 % noise)

The reconstructor drops every reading that uses the electrode and rebuilds its matrix from the stored
Jacobian, keeping lambda.

{table(["layout", "median centroid error mm", "95th percentile mm", "update median ms", "update max ms"], broken)}

## Every layout, algorithm and resolution

{table(headers, [fmt(row) for row in rows])}
"""


def frame_section(row) -> str:
    if row is None:
        return "Not run: pyEIT is not installed (`pip install -e '.[bench]'`)."
    return f"""On {FRAME_RACE_LAYOUT}'s 1 % and 0.1 % noise frames, {FRAME_RACE_ROUNDS} rounds: "ours" is what the
monitor calls for a one-step image, `ReconstructionModel.reconstruct(frame, reference, iterate="never")`, with every
check it makes (missing readings, the reference's fit to the model and its correlation, non-finite readings);
"bare" is the product of the same matrix with the frame's change alone; pyEIT's is its GREIT `solve` (n 32).
Each call is timed alone, the three interleaved frame by frame; medians.

{table(["layout", "calls each", "ours us", "bare product us", "pyEIT GREIT us", "ours / bare", "ours / pyEIT"],
       [row])}"""


if __name__ == "__main__":
    main()
