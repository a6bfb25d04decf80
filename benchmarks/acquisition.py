"""Acquisition benchmark: frame time on each board profile's timing model, where it goes, and accuracy.

    python benchmarks/acquisition.py        # writes benchmarks/acquisition.md and acquisition.png

The emulated board charges every bus transfer (bytes on the wire at the
profile's clock plus one Python call's overhead) and every wait to a simulated
clock, so a frame's duration is the profile's timing model, not this machine's
speed. Host CPU time per frame (drivers, scan engine and emulators together) is
reported beside it as a median of repeated runs.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from appliance.core.layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.drivers.emulated.board import EmulatedBoard
from appliance.drivers.emulated.sensor import ForwardSensor
from appliance.drivers.frontend import open_front_end
from appliance.drivers.profile import board_profile
from appliance.drivers.scan import ScanEngine

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, pyplot, save_figure, table  # noqa: E402

HERE = Path(__file__).parent
COMMAND = "python benchmarks/acquisition.py"
CASES = (("reference", "grid-4x4", 3.0), ("ad5933", "grid-4x4", 1.5), ("reference", "circular-16", None),
         ("ad5933", "circular-16", None), ("reference-32", "grid-4x4", None))
STEADY_FRAMES = 3
WHERE = {"EmulatedSPIDevice.transfer": "bus transfers", "EmulatedI2CBus._transact": "bus transfers",
         "EmulatedGPIOLines.set_values": "bus transfers", "EmulatedGPIOLines.get_values": "bus transfers",
         "EmulatedGPIOLines.wait_edge": "conversion", "AD5933.measure": "conversion",
         "AD5933._wait_for": "conversion", "AD5933.start": "excitation start", "FrontEnd.measure": "settling",
         "AD5933FrontEnd._measure_system_phase": "excitation start"}


class TimeLedger:
    """Splits the simulated clock's waits by what waited: bus transfers, settling, conversions."""

    def __init__(self, clock):
        self.spent: dict[str, float] = defaultdict(float)
        self._sleep = clock.sleep
        clock.sleep = self._charged

    def _charged(self, seconds: float) -> None:
        frame = sys._getframe(1)
        label = "other"
        for _ in range(6):
            if frame is None:
                break
            found = WHERE.get(frame.f_code.co_qualname)
            if found:
                label = found
                break
            frame = frame.f_back
        self.spent[label] += seconds
        self._sleep(seconds)


def sensor_readings(sensor, protocol, current_a):
    z = sensor.transfer
    a, b, c, d = (protocol.readings - 1).T
    return current_a * (z[c, a] - z[c, b] - z[d, a] + z[d, b])


def run_case(profile_name: str, layout_name: str, order: str):
    layout = get_layout(layout_name)
    protocol = default_protocol(layout)
    sensor = ForwardSensor.of_layout(layout)
    board = EmulatedBoard(board_profile({"profile": profile_name}), sensor)
    front_end = open_front_end(board, board.profile)
    engine = ScanEngine(front_end, protocol, order=order)
    cold = engine.scan()
    ledger = TimeLedger(board.clock)
    frames, cpu = [], []
    for _ in range(STEADY_FRAMES):
        start = time.process_time()
        frames.append(engine.scan())
        cpu.append(time.process_time() - start)
    steady = frames[-1]
    expected = sensor_readings(sensor, protocol, steady.drive_current_a)
    accuracy = front_end.profile.accuracy
    worst = np.max(np.abs(steady.volts - expected) / (accuracy.relative * np.abs(expected) + accuracy.absolute_v))
    spent = {k: v / STEADY_FRAMES for k, v in ledger.spent.items()}
    bus_calls = sum(1 for t in board.log if t.kind in ("spi", "gpio") or t.kind.startswith("i2c")) / STEADY_FRAMES
    return dict(profile=profile_name, layout=layout_name, order=order, readings=len(protocol), cold_s=cold.duration_s,
                steady_s=float(np.median([f.duration_s for f in frames])), cpu_s=float(np.median(cpu)),
                usable=int(steady.usable.sum()), worst=float(worst), min_fraction=float(np.nanmin(steady.fraction)),
                spent=spent, bus_calls=bus_calls, times=steady.time_s, order_index=engine.reading_order())


def main() -> None:
    results = {(p, lay, order): run_case(p, lay, order) for p, lay, _ in CASES for order in ("optimised", "protocol")}
    rows = []
    for p, lay, target in CASES:
        opt, proto = results[p, lay, "optimised"], results[p, lay, "protocol"]
        rows.append([p, lay, opt["readings"], f"{opt['cold_s']:.2f}", f"{opt['steady_s']:.2f}",
                     f"{proto['steady_s']:.2f}", f"{1 - opt['steady_s'] / proto['steady_s']:.0%}",
                     "-" if target is None else f"{target:.1f} ({'met' if opt['steady_s'] <= target else 'MISSED'})",
                     f"{opt['steady_s'] / opt['readings'] * 1e3:.2f}", f"{opt['cpu_s'] * 1e3:.0f}"])
    frame_table = table(["profile", "layout", "readings", "first frame s", "frame s (optimised order)",
                         "frame s (protocol order)", "ordering saves", "target s", "ms per reading",
                         "host CPU ms per frame"], rows)
    labels = ("settling", "conversion", "bus transfers", "excitation start", "other")
    split_rows = []
    for p, lay, _ in CASES:
        r = results[p, lay, "optimised"]
        total = sum(r["spent"].values())
        split_rows.append([p, lay] + [f"{r['spent'].get(k, 0.0):.3f} ({r['spent'].get(k, 0.0) / total:.0%})"
                                      for k in labels] + [f"{r['bus_calls']:.0f}"])
    split_table = table(["profile", "layout"] + [f"{k} s" for k in labels] + ["bus calls per frame"], split_rows)
    accuracy_rows = [[p, lay, f"{r['usable']}/{r['readings']}", f"{r['worst']:.2f}", f"{r['min_fraction']:.2f}"]
                     for (p, lay, order), r in results.items() if order == "optimised"]
    accuracy_table = table(["profile", "layout", "usable", "worst error / stated accuracy",
                            "smallest share of full scale"], accuracy_rows)
    plot(results)
    text = f"""# Acquisition: frame time on the boards' timing models

Command: `{COMMAND}` ({machine()}).

Each profile's chips run as register-level emulators on a simulated clock that
charges every bus transfer (bytes at the profile's I2C/SPI clock plus
{board_profile({}).timing.call_overhead_s * 1e6:.0f} us per call from Python) and every wait, so the
durations below are the profile's timing model; the drivers and scan engine are
the ones that run on the hardware. "First frame" ranges each reading by a probe
at the least sensitive range and waits the worst-case settling (nothing is known
yet); later frames start from the previous frame's ranges and wait only the
settling their predicted step needs. Steady figures are medians of
{STEADY_FRAMES} frames. Host CPU is this machine's time for a whole steady frame,
emulators included.

{frame_table}

The optimised order takes each drive pair once and, within it, the readings in
rising order of the level the plan predicts, so the RMS converter (its falling
time constant is twice its rising one) only settles upwards; protocol order is
the protocol's own, which for these protocols already groups drives. The AD5933
has no RMS lag to order for: its settling cycles are fixed per reading.

## Where a steady frame's time goes (optimised order)

{split_table}

## Accuracy of the same frames against the sensor model

Every reading against the forward model's value at the drive current, in units
of the profile's stated accuracy (0.5 % of the reading + 2 uV: gain errors of the
current source, in-amp and RMS converter, noise and quantisation); 1.00 is the
limit the tests enforce.

{accuracy_table}

![reading times](acquisition.png)
"""
    (HERE / "acquisition.md").write_text(text)
    print(text)


def plot(results) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for (p, lay, order), r in results.items():
        if lay != "grid-4x4" or p == "reference-32":
            continue
        times = np.sort(r["times"][np.isfinite(r["times"])])
        axes[0].plot(times, np.arange(1, len(times) + 1), label=f"{p}, {order} order",
                     linestyle="-" if order == "optimised" else "--")
    axes[0].set_xlabel("time into the frame, s (timing model)")
    axes[0].set_ylabel("readings taken")
    axes[0].set_title("grid-4x4: readings against time")
    axes[0].legend(fontsize=8)
    names = [f"{p}\n{lay}" for p, lay, _ in CASES]
    bottom = np.zeros(len(CASES))
    for label in ("settling", "conversion", "bus transfers", "excitation start", "other"):
        values = np.array([results[p, lay, "optimised"]["spent"].get(label, 0.0) for p, lay, _ in CASES])
        axes[1].bar(names, values, bottom=bottom, label=label)
        bottom += values
    axes[1].set_ylabel("seconds per steady frame")
    axes[1].set_title("where the time goes")
    axes[1].legend(fontsize=8)
    axes[1].tick_params(axis="x", labelsize=7)
    save_figure(fig, HERE / "acquisition.png")


if __name__ == "__main__":
    main()
