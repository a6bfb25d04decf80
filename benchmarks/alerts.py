"""Alerts benchmark: false alarms on well-cared-for patients, detection delay against the true dose, and what
the monitor costs at 1 frame per second.

    python benchmarks/alerts.py        # writes benchmarks/alerts.md and alerts.png (about 10 min)

Everything runs through the monitor daemon that ``appliance run`` starts
(:func:`appliance.service.assemble.assemble`) on the default virtual bed (grid-16x32), with
the default alert settings unless a table says otherwise.

* Alarms per simulated patient-day: scenarios where the patient is cared for as
  the guidelines ask (turned every 2 h), with three noise seeds, and a night
  replayed from real PmatData recordings (S1, turned every 2 h between supine,
  right 30 degrees and left 30 degrees). Any pressure alarm here is a false alarm.
* Detection delay: the monitor sees a blurred, calibrated reconstruction; the
  truth is the scene's own 10 mm pressure field. For each tolerance curve, the
  time the monitor's region dose reaches a threshold is compared with the time
  the true dose reaches it anywhere within 100 mm of that region's centre.
  Positive: the monitor is late.
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
from pathlib import Path

import numpy as np

from appliance.alerts.dose import DoseMap, tolerance_curve
from appliance.core.pressure import KPA_PER_MMHG
from appliance.service.assemble import assemble
from appliance.service.config import config_from_mapping

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, pyplot, table  # noqa: E402

HERE = Path(__file__).parent
PMAT = HERE.parent.parent / "shared" / "data" / "pmatdata"
MINUTE = 60.0
DAY_S = 86400.0
THRESHOLDS = (0.25, 0.5, 0.75, 1.0)
NEIGHBOURHOOD_MM = 100.0


def replay(scenario, *, hours, seed=0, alerts=None, watch=None):
    """Events of ``scenario`` through the daemon, one map a minute; ``watch(daemon, map)`` sees each frame."""
    with tempfile.TemporaryDirectory() as data:
        config = config_from_mapping({"monitor": {"frame_interval_s": MINUTE, "data_dir": data},
                                      "virtual": {"scenario": str(scenario), "speed": 0, "seed": seed},
                                      "alerts": alerts or {}})
        events = []
        holder = {}
        daemon = assemble(config, say=lambda text: None, on_event=events.append, live=False,
                          on_map=(lambda m: watch(holder["daemon"], m)) if watch else None)
        holder["daemon"] = daemon
        start = time.perf_counter()
        try:
            frames = daemon.run(int(hours * 3600 / MINUTE) + 1)
        finally:
            daemon.close()
        return events, frames, time.perf_counter() - start


def recorded_night(folder: Path) -> Path:
    """PmatData S1 turned every 2 h for 12 h: supine, right 30, supine, left 30, supine, right 30."""
    path = folder / "pmat-night.toml"
    segments = "".join(f'[[recording]]\nsource = "pmatdata"\ndir = "{PMAT}"\nsubject = 1\nposture = {p}\n'
                       f'hold_s = {7200 - 120}\n\n' for p in (1, 4, 1, 6, 1, 4))
    path.write_text('[scene]\ndescription = "PmatData S1, q2h turns"\nduration_s = 43200\n\n' + segments)
    return path


def false_alarms(folder: Path) -> tuple[str, list]:
    runs = [("turned-every-2h", 24.0, seed) for seed in (0, 1, 2)]
    if PMAT.is_dir():
        runs.append((recorded_night(folder), 12.0, 0))
    rows, timings = [], []
    for scenario, hours, seed in runs:
        events, frames, seconds = replay(scenario, hours=hours, seed=seed)
        raised = Counter(e.key.split(":")[0] if e.key.startswith("pressure:") else e.key
                         for e in events if e.kind == "raised")
        turns = sum(e.kind == "repositioned" for e in events)
        per_day = DAY_S / (hours * 3600)
        name = "PmatData S1 night (recorded)" if isinstance(scenario, Path) else scenario
        rows.append([name, seed, f"{hours:g}", f"{raised['pressure'] * per_day:.1f}",
                     f"{raised['turn'] * per_day:.1f}",
                     f"{sum(n for k, n in raised.items() if k.startswith('technical')) * per_day:.1f}",
                     f"{turns} ({int(hours / 2)} turns + lying down)", f"{frames / seconds:.0f}"])
        timings.append(seconds)
    headers = ["scenario", "seed", "hours", "pressure alarms / day", "turn-due alarms / day",
               "technical alarms / day", "repositionings detected", "frames/s"]
    return table(headers, rows), rows


def dose_series(scenario, curve, hours):
    """Per frame: time, the monitor's region doses with centres, and the true dose field (layout orientation)."""
    frames = []
    state = {}

    def watch(daemon, pressure_map):
        bed = daemon.source.bed
        field = bed.field_at(pressure_map.time_s)
        if "true" not in state:
            state["true"] = DoseMap(field.pressure_kpa.shape, tolerance_curve(curve))
            state["pitch"] = field.pitch_mm
        else:
            state["true"].update(field.pressure_kpa, pressure_map.time_s - state["t"])
        state["t"] = pressure_map.time_s
        state["bed"] = bed
        regions = [(daemon.pipeline.dose.fraction(r.mask), r.x_mm, r.y_mm, r.zone, r.peak_kpa)
                   for r in daemon.pipeline.tracked]
        frames.append((pressure_map.time_s, regions, state["true"].dose.copy()))

    events, _, _ = replay(scenario, hours=hours, alerts={"curve": curve}, watch=watch)
    return frames, state["pitch"], state["bed"]


def detection_delays(scenario, curve, hours):
    """For each threshold: monitor time, true time, zone, monitor peak and true peak (kPa) at the crossing.

    Where the monitor never crosses, the truth is taken anywhere on the mat.
    """
    frames, pitch, bed = dose_series(scenario, curve, hours)
    shape = frames[0][2].shape
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    out = {}
    for threshold in THRESHOLDS:
        hit = next(((t, x, y, zone, peak) for t, regions, _ in frames for dose, x, y, zone, peak in regions
                    if dose >= threshold), None)
        if hit is None:
            t_monitor, zone, peak, near = None, None, None, np.ones(shape, dtype=bool)
        else:
            t_monitor, x, y, zone, peak = hit
            near = np.hypot((xx + 0.5) * pitch - x, (yy + 0.5) * pitch - y) <= NEIGHBOURHOOD_MM
        t_true = next((t for t, _, true in frames if true[near].max() >= threshold), None)
        at = t_monitor if t_monitor is not None else (t_true if t_true is not None else frames[-1][0])
        true_peak = float(bed.field_at(at).pressure_kpa[near].max())
        out[threshold] = (t_monitor, t_true, zone, peak, true_peak)
    return out, frames


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


def main() -> None:
    with tempfile.TemporaryDirectory() as scratch:
        alarms_table, _ = false_alarms(Path(scratch))
    delay_rows, plots = [], {}
    for scenario, hours in (("supine-unturned", 12.0), ("heel-only", 12.0)):
        for curve in ("reswick-rogers", "linder-ganz"):
            delays, frames = detection_delays(scenario, curve, hours)
            plots[scenario, curve] = frames
            for threshold, (t_monitor, t_true, zone, peak, true_peak) in delays.items():
                monitor_text = "never" if t_monitor is None else f"{t_monitor / 3600:.2f}"
                true_text = "never" if t_true is None else f"{t_true / 3600:.2f}"
                delay = "-" if t_true is None or t_monitor is None else f"{(t_monitor - t_true) / 60:+.0f}"
                peak_text = "-" if peak is None else f"{peak / KPA_PER_MMHG:.0f}"
                delay_rows.append([scenario, curve, f"{threshold:g}", zone or "-", monitor_text, true_text, delay,
                                   peak_text, f"{true_peak / KPA_PER_MMHG:.0f}"])
    usage = {name: cpu_and_memory(name) for name in ("supine-still", "restless")}
    _plot(plots)
    usage_rows = [[name, f"{u['cpu_share']:.1%}", f"{u['rss_mb']:.0f}", f"{u['peak_mb']:.0f}"]
                  for name, u in usage.items()]
    report = f"""# Alerts: false alarms, detection delay, cost

Made by `python benchmarks/alerts.py` on {machine()}.
grid-16x32 virtual bed (900 x 1900 mm, 512 electrodes, read through the parallel board), one-step
Gauss-Newton maps on 30 mm pixels through the virtual mat's calibration made from people's maps, default
alert settings (32 mmHg, Reswick-Rogers, alarm at dose 1, turn every 2 h,
escalation after 15 min), one map per simulated minute unless said otherwise.

## Alarms per simulated patient-day, patients cared for as the guidelines ask

{alarms_table}

A pressure alarm here would be a false alarm: the patient is turned every 2 h, well inside the tolerance.
Turn-due alarms are the low-priority reminder the turn clock raises when a detected turn is 2 h old;
on a schedule of exactly 2 h a reminder can fall due in the minute before the nurse turns the patient.
"frames/s" is how fast the replay ran (simulated minutes per wall second).

## Detection delay against the true dose

Monitor: the first frame a tracked region's dose reaches the threshold. Truth: the first frame the dose of
the scene's own 10 mm pressure field reaches it within {NEIGHBOURHOOD_MM:g} mm of that region's centre.
Hours from the start of the night; delay in minutes (+ = the monitor is later than the truth, - = earlier).
Peaks: the monitor's region and the true field within {NEIGHBOURHOOD_MM:g} mm of it, at the monitor's crossing
(where the monitor never crosses: the true field's peak anywhere, at the truth's crossing).

{table(["scenario", "curve", "threshold (dose)", "zone", "monitor (h)", "truth (h)", "delay (min)",
        "monitor peak (mmHg)", "true peak (mmHg)"], delay_rows)}

![monitor and true dose](alerts.png)

How to read it: the dose grows as the tolerance curve says for the pressure each map reads, so the
delay follows the difference between the two peak columns. The Reswick-Rogers curve is steep between
32 and 70 mmHg: a few mmHg too high or too low move the crossing by an hour or more. The Linder-Ganz
sigmoid tolerates these pressures indefinitely once past its first hours, so neither the monitor nor the
truth crosses it. The bed's pixels are 30 mm and its electrodes 60 mm apart, and its calibration was made
from people's maps (benchmarks/bed.md): a heel (about 50 mm) is read near its true peak, no longer blurred
over a 112 mm electrode spacing.

## CPU and memory at 1 frame per second

`appliance run --scenario NAME --interval 1 --speed 1` as its own process: CPU time from /proc over 90 s
after 20 s of settling (share of one core), resident memory at the end and its peak.

{table(["scenario", "CPU (one core)", "RSS (MB)", "peak RSS (MB)"], usage_rows)}

A still patient costs no re-solve of the virtual bed (its chain and the reconstruction only); a restless
one re-solves the bed's mechanics at each shift, which is simulation cost a real mat does not have.
"""
    (HERE / "alerts.md").write_text(report, encoding="utf-8")
    print(report)


def _plot(plots) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, scenario in zip(axes, ("supine-unturned", "heel-only")):
        for curve, style in (("reswick-rogers", "-"), ("linder-ganz", "--")):
            frames = plots[scenario, curve]
            hours = [t / 3600 for t, _, _ in frames]
            monitor = [max((r[0] for r in regions), default=0.0) for _, regions, _ in frames]
            truth = [true.max() for _, _, true in frames]
            ax.plot(hours, monitor, style, color="tab:blue", label=f"monitor, {curve}")
            ax.plot(hours, truth, style, color="tab:red", label=f"truth (peak), {curve}")
        ax.axhline(1.0, color="grey", lw=0.8)
        ax.set_title(scenario)
        ax.set_xlabel("hours")
        ax.set_ylim(0, 3)
    axes[0].set_ylabel("dose (share of tolerance used)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(HERE / "alerts.png", dpi=100)


if __name__ == "__main__":
    main()
