"""Alerts benchmark: posture, tissue sites and site alarms on held-out real bodies, reminders, and cost.

    python benchmarks/alerts.py        # writes benchmarks/alerts.md and alerts.png (about 15 min)
    python benchmarks/alerts.py --posture   # prints the posture section's table only (a few minutes)

Everything is judged on PmatData subjects S4, S6 and S11, which neither the posture
model, nor the site locator's geometry, nor the bed's pressure calibration was fitted
on (they were fitted on S1-S3, S5, S7-S10).

* Posture: the shipped model on the held-out subjects' maps (benchmarks/posture.py
  has the leave-one-subject-out study and the full confusion matrices).
* Sites: the located sites against the hand labels (tests/data/site_labels), on the
  true maps averaged over the monitor's 30 mm pixels and on the maps read through
  the whole chain (virtual bed, parallel board, reconstruction, calibration).
* Nights: held-out recordings held for hours (turned every 2 h through supine and
  30 degree tilts; unturned supine; side-lying; a restless night of small shifts).
  The truth is the dose rule applied to the true maps at the sites of the consensus labels;
  the alert layer is fed the true maps (``appliance sim replay``'s path) and the
  maps read through the chain (``appliance sim run``'s path), one map a minute.
* CPU and memory: ``appliance run`` in real time (1 frame/s) as a separate
  process, CPU time from /proc over 90 s after start-up, peak resident memory.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.alerts.anatomy import body_view, posture_group, tilt_deg
from appliance.alerts.dose import SiteDose, tolerance_curve
from appliance.alerts.pipeline import AlertPipeline, AlertSettings
from appliance.alerts.posture import SURE_GROUP_PROBABILITY, default_posture_model
from appliance.alerts.sites import label_cells, locate_sites
from appliance.core.pressure_map import PressureMap, loaded_regions
from appliance.sim.body import BED_GRID
from appliance.sim.recordings import RecordedScene
from appliance.sim.scenes import PMAT_POSTURE_FILES
from appliance.sim.true_maps import on_pixels

sys.path.insert(0, str(Path(__file__).parent))
from held_out_chain import MINUTE, POSTURE_OF_FILE, Chain, still_scene, true_frame  # noqa: E402
from report import machine, pyplot, table  # noqa: E402
from site_labels import HELD_OUT, MATCH_MM, labelled_spots, labels_at_spots, site_positions  # noqa: E402

HERE = Path(__file__).parent
HOUR = 3600.0
DAY_S = 86400.0
LOADED_MMHG = 32.0


# ---------------------------------------------------------------------------
# Posture and sites on the held-out maps

def posture_and_sites(chain: Chain) -> dict:
    """Per held-out map, on the true map and on the map read: the posture estimated and, for each loaded
    labelled spot, (hand label, locator's label)."""
    model = default_posture_model()
    spots = labelled_spots()
    out = {"true": [], "read": []}
    for subject in HELD_OUT:
        for posture_file in range(1, 18):
            frame = true_frame(subject, posture_file)
            true_view, read = chain.true_view(frame), chain.read_still(frame)
            labelled = [s for s in spots if s.subject == subject and s.posture_file == posture_file]
            for which, view in (("true", true_view), ("read", body_view(read, chain.grid))):
                found = model.classify(view)
                estimate = found.posture
                pairs = labels_at_spots(true_view, label_cells(view, estimate), labelled)
                out[which].append((subject, posture_file, estimate, pairs, found.sure))
    return out


def posture_rows(results) -> list[list]:
    rows = []
    for which, label in (("true", "true maps (30 mm pixels)"), ("read", "maps read through the chain")):
        items = results[which]
        truth = [POSTURE_OF_FILE[p] for _, p, *_ in items]
        guess = [g for _, _, g, *_ in items]
        sure = [s for *_, s in items]
        right = [posture_group(t) == posture_group(g) for t, g in zip(truth, guess)]
        sides = [(t, g) for t, g in zip(truth, guess) if tilt_deg(t) is not None]
        tilts = np.mean([tilt_deg(t) == tilt_deg(g) for t, g in sides])
        exact = np.mean([t == g for t, g in zip(truth, guess)])
        wrong_sure = sum(1 for ok, s in zip(right, sure) if not ok and s)
        rows.append([label, len(items), f"{np.mean(right):.1%}", f"{tilts:.1%} of {len(sides)}", f"{exact:.1%}",
                     f"{len(sure) - sum(sure)} ({sum(1 for ok, s in zip(right, sure) if not ok and not s)} wrong)",
                     wrong_sure])
    return rows


def site_rows(results) -> tuple[list[list], dict]:
    rows, wrong = [], {}
    for which, label in (("true", "true maps (30 mm pixels)"), ("read", "maps read through the chain")):
        pairs = [pair for *_, found, _ in results[which] for pair in found]
        named = [(hand, got) for hand, got, _ in pairs if hand]
        rows.append([label, len(pairs), f"{np.mean([h == g for h, g, _ in pairs]):.1%}", len(named),
                     f"{np.mean([h == g for h, g in named]):.1%}"])
        wrong[which] = Counter((hand, got) for hand, got, _ in pairs if hand != got)
    return rows, wrong


# ---------------------------------------------------------------------------
# Nights

@dataclass(frozen=True)
class Night:
    name: str
    subject: int
    segments: tuple[tuple[int, float, tuple[float, float]], ...]     # (posture file, seconds, shift across/along)

    @property
    def duration_s(self) -> float:
        return sum(s for _, s, _ in self.segments)

    def segment_at(self, t_s: float) -> tuple[int, tuple[float, float]]:
        start = 0.0
        for posture_file, seconds, shift in self.segments:
            if t_s < start + seconds:
                return posture_file, shift
            start += seconds
        return self.segments[-1][0], self.segments[-1][2]

    def scene(self) -> RecordedScene:
        starts = np.cumsum([0.0] + [s for _, s, _ in self.segments[:-1]])
        frames = np.stack([true_frame(self.subject, p, shift) for p, _, shift in self.segments])
        return RecordedScene(frames, starts, BED_GRID, {"source": self.name}, duration_s=self.duration_s)


def nights(subjects=HELD_OUT, on_the_right=(6,)) -> list[Night]:
    """Four nights for each of ``subjects`` (the held-out ones by default), side-lying on the left but for
    those ``on_the_right``."""
    out = []
    for subject in subjects:
        side = PMAT_POSTURE_FILES["right-90" if subject in on_the_right else "left-90"]
        turned = tuple((PMAT_POSTURE_FILES[p], 2 * HOUR, (0.0, 0.0))
                       for p in ("supine", "left-30", "supine", "right-30", "supine", "left-30"))
        rng = np.random.default_rng(subject)
        restless, t = [], 0.0
        while t < 8 * HOUR:
            seconds = float(rng.choice([5, 6, 7, 8, 9, 10])) * MINUTE
            shift = (float(rng.uniform(-40, 40)), float(rng.uniform(-30, 30)))
            restless.append((int(rng.choice([1, 8, 9])), min(seconds, 8 * HOUR - t), shift))
            t += seconds
        out += [Night("turned every 2 h (12 h)", subject, turned),
                Night("unturned supine (8 h)", subject, ((1, 8 * HOUR, (0.0, 0.0)),)),
                Night("side-lying (4 h)", subject, ((side, 4 * HOUR, (0.0, 0.0)),)),
                Night("restless, small shifts (8 h)", subject, tuple(restless))]
    return out


def true_site_peaks(night: Night, t_s: float, kpa: np.ndarray, grid, spots) -> dict[str, float]:
    """The true map's peak within MATCH_MM of each hand-labelled site of the posture held at ``t_s``."""
    posture_file, (dx, dy) = night.segment_at(t_s)
    view = body_view(kpa, grid)
    rows, cols = view.shape
    along = (np.arange(rows) + 0.5) * view.pitch_mm[0]
    across = (np.arange(cols) + 0.5) * view.pitch_mm[1]
    peaks = {}
    for site, (a, c) in site_positions(spots, night.subject, posture_file).items():
        near = np.hypot(along[:, None] - (a + dy), across[None, :] - (c + dx)) <= MATCH_MM
        peaks[site] = float(view.kpa[near].max())
    return peaks


def truth_alarms(night: Night, times, true_maps, grid, spots, settings=AlertSettings()) -> dict[str, float]:
    """When each labelled site's dose, by the alert layer's own rule, first reaches the alarm dose."""
    curve = tolerance_curve(settings.curve, floor_kpa=settings.threshold_kpa)
    dose = SiteDose(sorted({s.site for s in spots if s.site}), curve, recovery=settings.recovery,
                    relief_s=settings.relief_s)
    crossed, last = {}, None
    for t, kpa in zip(times, true_maps):
        peaks = true_site_peaks(night, t, kpa, grid, spots)
        if last is not None:
            dose.update(peaks, t - last)
        last = t
        for site, d in dose.doses().items():
            if d >= settings.alarm_dose and site not in crossed:
                crossed[site] = t
    return crossed


def layer_alarms(pressure_maps, grid, **layer) -> tuple[dict[str, float], list, list]:
    """The alert layer on a sequence of maps: first raise time per site, reminder raises, turn events.
    ``layer``: the pipeline's own options (another posture model or site table, for a study of training subjects)."""
    pipeline = AlertPipeline(grid, **layer)
    raised, reminders, turns = {}, [], []
    for m in pressure_maps:
        frame = pipeline.update(m)
        for e in frame.alarm_events:
            if e.kind == "raised" and e.key.startswith("pressure:"):
                raised.setdefault(e.key.split(":", 1)[1], e.time_s)
            elif e.kind == "raised" and e.key.startswith("turn:"):
                reminders.append((e.time_s, e.key, e.priority))
        turns += [(e.time_s, e.kind, e.posture) for e in frame.turn_events]
    return raised, reminders, turns


def run_night(night: Night, chain: Chain, spots, **layer) -> dict:
    times = np.arange(0.0, night.duration_s, MINUTE)
    scene = night.scene()
    grid = chain.grid
    true_maps = []
    for t in times:
        field = scene.pressure_at(float(t))
        true_maps.append(on_pixels(field.pressure_kpa, field.pitch_mm, grid))
    truth = truth_alarms(night, times, true_maps, grid, spots)
    on_truth = layer_alarms((PressureMap(float(t), k, loaded_regions(k, grid), None, 0)
                             for t, k in zip(times, true_maps)), grid, **layer)
    read = list(chain.maps(scene, times, seed=night.subject))
    on_chain = layer_alarms(read, grid, **layer)
    return {"truth": truth, "true": on_truth, "chain": on_chain, "hours": night.duration_s / HOUR}


def compare(truth: dict[str, float], raised: dict[str, float]) -> dict:
    matched = {s: raised[s] - t for s, t in truth.items() if s in raised}
    return {"truth": len(truth), "missed": sorted(set(truth) - set(raised)), "late_s": list(matched.values()),
            "false": sorted(set(raised) - set(truth))}


def night_rows(results: list[tuple[Night, dict]]) -> tuple[list[list], dict]:
    rows = []
    totals = {which: {"truth": 0, "missed": 0, "late_s": [], "false": 0, "hours": 0.0} for which in ("true", "chain")}
    for night, r in results:
        cells = [night.name, f"S{night.subject}", ", ".join(f"{s} {t / HOUR:.2f} h" for s, t in
                                                            sorted(r["truth"].items(), key=lambda x: x[1])) or "none"]
        for which in ("true", "chain"):
            c = compare(r["truth"], r[which][0])
            total = totals[which]
            total["truth"] += c["truth"]
            total["missed"] += len(c["missed"])
            total["late_s"] += c["late_s"]
            total["false"] += len(c["false"])
            total["hours"] += r["hours"]
            late = ", ".join(f"{x / 60:+.0f}" for x in c["late_s"]) or "-"
            cells += [", ".join(c["missed"]) or "-", late, ", ".join(c["false"]) or "-"]
        rows.append(cells)
    return rows, totals


def summary_rows(totals: dict) -> list[list]:
    """One row for the true maps and one for the chain: alarms, missed, lateness and false alarms."""
    rows = []
    for which, label in (("true", "the true maps"), ("chain", "the whole chain")):
        t = totals[which]
        late = np.median(t["late_s"]) / 60 if t["late_s"] else float("nan")
        rows.append([label, t["truth"], t["missed"], f"{late:+.0f}",
                     f"{max((abs(x) for x in t['late_s']), default=0) / 60:.0f}",
                     t["false"], f"{t['false'] / (t['hours'] / 24):.2f}"])
    return rows


NIGHT_SUMMARY = ["feeding", "true site alarms", "missed", "median late (min)", "worst late (min)", "false alarms",
                 "false per patient-day"]
NIGHT_COLUMNS = ["night", "subject", "true site alarms (h)", "true maps: missed", "late (min)", "false",
                 "chain: missed", "late (min)", "false"]


def reminder_rows(results: list[tuple[Night, dict]]) -> list[list]:
    rows = []
    for night, r in results:
        raised, reminders, turns = r["chain"]
        due = [f"{t / HOUR:.2f}" for t, key, _ in reminders if key == "turn:due"]
        overdue = [f"{t / HOUR:.2f}" for t, key, _ in reminders if key.startswith("turn:overdue")]
        seen = sum(kind == "repositioned" for _, kind, _ in turns)
        scheduled = sum(1 for a, b in zip(night.segments, night.segments[1:])
                        if posture_group(POSTURE_OF_FILE[a[0]]) != posture_group(POSTURE_OF_FILE[b[0]]))
        sacral = sum(1 for s in raised if s == "sacrum")
        rows.append([night.name, f"S{night.subject}", f"{seen} of {scheduled}", ", ".join(due) or "-",
                     ", ".join(overdue[:6]) + (" ..." if len(overdue) > 6 else "") or "-", sacral])
    return rows


# ---------------------------------------------------------------------------
# Cost

def cpu_and_memory(scenario: str, seconds: float = 90.0, settle_s: float = 20.0) -> dict:
    """``appliance run`` in real time: CPU share of one core after start-up, and peak resident memory."""
    with tempfile.TemporaryDirectory() as data:
        process = subprocess.Popen([sys.executable, "-m", "appliance", "run", "--scenario", scenario,
                                    "--interval", "1", "--speed", "1", "--data-dir", data],
                                   stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            process.stdout.readline()                       # the first map: start-up is over
            time.sleep(settle_s)
            cpu0, wall0 = _cpu_s(process.pid), time.monotonic()
            time.sleep(seconds)
            cpu1, wall1 = _cpu_s(process.pid), time.monotonic()
            status = Path(f"/proc/{process.pid}/status").read_text()
        finally:
            process.terminate()
            process.communicate(timeout=30)
    memory = {line.split(":")[0]: int(line.split()[1]) / 1024 for line in status.splitlines()
              if line.startswith(("VmRSS", "VmHWM"))}
    return {"cpu_share": (cpu1 - cpu0) / (wall1 - wall0), "rss_mb": memory["VmRSS"], "peak_mb": memory["VmHWM"]}


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / 100.0      # utime + stime, clock ticks of 10 ms


def per_frame_ms(chain: Chain, repeats: int = 200) -> dict:
    """Median time of the posture estimate, the site locator and a whole alert-layer frame on a read map."""
    frame = true_frame(4, 1)
    kpa = list(chain.maps(still_scene(frame, 5 * MINUTE), [0.0, MINUTE]))[-1]
    view = body_view(kpa.pressure_kpa, chain.grid)
    model = default_posture_model()
    pipeline = AlertPipeline(chain.grid)

    def median_ms(fn) -> float:
        samples = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            samples.append(time.perf_counter() - start)
        return 1000 * float(np.median(samples))

    clock = iter(range(10**9))
    return {"posture": median_ms(lambda: model.classify(view)),
            "sites": median_ms(lambda: locate_sites(view, "supine")),
            "frame": median_ms(lambda: pipeline.update(PressureMap(60.0 * next(clock), kpa.pressure_kpa,
                                                                   kpa.regions, None, 0)))}


# ---------------------------------------------------------------------------

def posture_only(chain: Chain) -> None:
    """Print the posture section's table, writing nothing: a check of a retrained posture model."""
    print(table(["maps", "n", "group right", "tilt right", "posture right", "unsure (of them wrong)",
                 "wrong and sure"], posture_rows(posture_and_sites(chain))))


def main() -> None:
    cache = Path(tempfile.gettempdir()) / "appliance-bench-cache"
    chain = Chain(cache)
    if sys.argv[1:] == ["--posture"]:
        posture_only(chain)
        return
    if sys.argv[1:]:
        raise SystemExit(f"usage: python benchmarks/alerts.py [--posture], got {' '.join(sys.argv[1:])}")
    spots = labelled_spots()
    started = time.perf_counter()
    sites = posture_and_sites(chain)
    results = [(night, run_night(night, chain, spots)) for night in nights()]
    rows, totals = night_rows(results)
    frame_ms = per_frame_ms(chain)
    usage = {name: cpu_and_memory(name) for name in ("supine-still", "restless")}
    _plot(results)
    s_rows, wrong = site_rows(sites)
    wrong_text = "; ".join(f"{n} x {b or 'unnamed'} where the labels say {a or 'unnamed'}"
                           for (a, b), n in wrong["read"].most_common(8))
    report = f"""# Alerts: posture, tissue sites and site alarms on held-out bodies; reminders; cost

Made by `python benchmarks/alerts.py` on {machine()} ({(time.perf_counter() - started) / 60:.0f} min).
Default bed (grid-16x32, 900 x 1900 mm, read through the parallel board; one-step Gauss-Newton maps on
30 mm pixels through the virtual mat's calibration made from people's maps) and default alert settings
(32 mmHg, Reswick-Rogers, alarm at dose 1, relief after 15 min below 32 mmHg, turn every 2 h, overdue
after 30 min more, repeated every 30 min). Every figure below is on PmatData subjects **S4, S6 and S11**,
which the posture model, the site locator and the bed's calibration never saw (all three were fitted on
S1-S3, S5, S7-S10).

## Posture on the held-out subjects

The shipped posture model on the middle frame of each of the 17 posture files of S4, S6 and S11 (51 maps).
Groups: supine (with the head of the bed raised), left, right, prone or other; tilt: 30, 60 or 90 degrees
among the side postures (curled counts as 90). The leave-one-subject-out study over all eleven subjects,
the confusion matrices and the prone maps are in `benchmarks/posture.md` (`python benchmarks/posture.py`).

{table(["maps", "n", "group right", "tilt right", "posture right", "unsure (of them wrong)", "wrong and sure"],
        posture_rows(sites))}

"Unsure": the postures of the estimate's group have less than {SURE_GROUP_PROBABILITY} probability together (the
floor chosen on the training subjects' leave-one-out study, `alerts/posture.py`); the alert layer then keeps the
last sure lying posture, so such a map neither counts as a turn nor renames the sites.

## Sites against the hand labels

The hand labels of the same 51 maps (`tests/data/site_labels/consensus`, named by eye on the 10 mm maps by
two readers apart, their disagreements settled by a third, none of them seeing the locator) against the
locator, which works on the posture the model estimated (`benchmarks/site_labels.py` scores them). A
labelled spot counts when the true map is at or above 32 mmHg within one of the monitor's pixels of it; the
locator's label for it is the site the locator gives the monitor pixel the spot lies in (`label_cells`;
unnamed below its floor), right when it equals the hand's (a buttock left unnamed by both is right). "Named by hand" repeats it for the spots the hand named a site.

{table(["maps", "loaded spots", "labelled right", "named by hand", "of those, right"], s_rows)}

Disagreements on the maps read: {wrong_text or "none"}.

## Site alarms over nights of held-out recordings

Each night holds the middle frame of held-out recordings for hours, one map a minute: turned every 2 h
(supine, left 30, supine, right 30, supine, left 30: 12 h), unturned supine (8 h), side-lying at 90 degrees
(4 h; S6 on the right side, the others on the left) and a restless night (8 h of supine variants, arms moved,
shifted by up to 40 mm across and 30 mm along every 5 to 10 min, the sacrum never offloaded). **Truth**: the
dose rule (the alert layer's own `SiteDose`, Reswick-Rogers, dose 1) applied to each site of those labels at
its peak within {MATCH_MM:g} mm on the true map averaged over the monitor's pixels. **True maps**: the alert layer
(posture model, site locator, site doses) fed those true maps, as `appliance sim replay` does. **Chain**: the
alert layer fed the maps read through the virtual bed, as `appliance sim run` does. Late in minutes (+ =
after the truth); a false alarm is a site alarm where the truth has none.

{table(NIGHT_SUMMARY, summary_rows(totals))}

{table(NIGHT_COLUMNS, rows)}

![site doses of the unturned nights](alerts.png)

## Turns and reminders through the chain

Repositionings seen against the changes of posture group the night holds (a new position counts once it has
lasted the relief time, 15 min, dated from its start; no reminder is raised while one is being held);
reminders raised (hours from the start): due at the 2 h interval (medium), overdue 30 min later (high,
escalated) and repeated every 30 min until a turn; sacral alarms raised.

{table(["night", "subject", "turns seen", "turn due (h)", "overdue (h)", "sacral alarms"],
       reminder_rows(results))}

## Cost

Per frame on the bed's read map (median of 200): posture estimate {frame_ms['posture']:.2f} ms, site locator
{frame_ms['sites']:.2f} ms, a whole alert-layer frame (posture, sites, doses, turns, regions, alarms)
{frame_ms['frame']:.2f} ms.

`appliance run --scenario NAME --interval 1 --speed 1` as its own process: CPU time from /proc over 90 s
after 20 s of settling (share of one core), resident memory at the end and its peak.

{table(["scenario", "CPU (one core)", "RSS (MB)", "peak RSS (MB)"],
       [[n, f"{u['cpu_share']:.1%}", f"{u['rss_mb']:.0f}", f"{u['peak_mb']:.0f}"] for n, u in usage.items()])}

A still patient costs no re-solve of the virtual bed (its chain and the reconstruction only); a restless
one re-solves the bed's mechanics at each shift, which is simulation cost a real mat does not have.
"""
    (HERE / "alerts.md").write_text(report, encoding="utf-8")
    print(report)


def _plot(results) -> None:
    plt = pyplot()
    unturned = [(n, r) for n, r in results if n.name.startswith("unturned")]
    fig, axes = plt.subplots(1, len(unturned), figsize=(4 * len(unturned), 3.5), sharey=True)
    for ax, (night, r) in zip(np.atleast_1d(axes), unturned):
        for which, style in (("true", "--"), ("chain", "-")):
            raised = r[which][0]
            for site, t in raised.items():
                ax.axvline(t / HOUR, ls=style, color="tab:blue" if which == "chain" else "tab:green", lw=1)
        for site, t in r["truth"].items():
            ax.axvline(t / HOUR, color="tab:red", lw=2, alpha=0.5)
            ax.text(t / HOUR, 0.9, site, rotation=90, fontsize=7, va="top")
        ax.set_title(f"S{night.subject}, unturned supine")
        ax.set_xlim(0, night.duration_s / HOUR)
        ax.set_xlabel("hours")
        ax.set_yticks([])
    np.atleast_1d(axes)[0].set_ylabel("site alarms: truth (red), true maps (green), chain (blue)")
    fig.tight_layout()
    fig.savefig(HERE / "alerts.png", dpi=100)


if __name__ == "__main__":
    main()
