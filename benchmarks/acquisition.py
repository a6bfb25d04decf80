"""Acquisition benchmark: frame time on each board profile's timing model, where it goes, and accuracy.

    python benchmarks/acquisition.py        # writes benchmarks/acquisition.md, acquisition.png and
                                            # acquisition_parallel.png

The emulated board charges every bus transfer (bytes on the wire at the
profile's clock plus one Python call's overhead) and every wait to a simulated
clock, so a frame's duration is the profile's timing model, not this machine's
speed. Host CPU time per frame (drivers, scan engine and emulators together) is
reported beside it as a median of repeated runs.

Every built-in profile's frame is also tabled on the buses of the appliance's image (the
system it names: the I2C clock its device tree sets, the SPI clocks the profile opens its
devices at), beside the AD5933 at Linux's default I2C clock of 100 kHz.

The parallel profile (the bed's 16 x 32 mat, rows protocol) gets its own
section: full-pass and adaptive frame times, the time of one step by operation
against the timing budget and the designs it was chosen over, its accuracy
against the forward model, and the dynamic range of the bed's readings, empty
and under simulated patients.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import dataclasses
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from appliance.core.fem import build_fem_model
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol, protocol_for
from appliance.drivers.ad7606 import CONVERSION_S
from appliance.drivers.adg1414 import DriveMatrix
from appliance.drivers.boards import I2C_DEFAULT_CLOCK_HZ, SYSTEMS
from appliance.drivers.channel_map import ChannelMap
from appliance.drivers.contact import check_contacts
from appliance.drivers.backend import emulated_board, open_front_end
from appliance.drivers.emulated.parallel import SWITCH_OHM, ParallelErrors
from appliance.drivers.emulated.sensor import ForwardSensor
from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
from appliance.drivers.scan import Flag, ScanEngine
from appliance.sim.bed import VirtualBed
from appliance.sim.chain import FrameChain
from appliance.sim.mechanics import DEFAULT_PARAMETERS
from appliance.sim.scenes import load_scene
from appliance.sim.transfer import TransferSolver

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, pyplot, save_figure, table  # noqa: E402

HERE = Path(__file__).parent
COMMAND = "python benchmarks/acquisition.py"
CASES = (("reference", "grid-4x4", 3.0), ("ad5933", "grid-4x4", 1.5), ("reference", "circular-16", None),
         ("ad5933", "circular-16", None), ("reference-32", "grid-4x4", None))
STEADY_FRAMES = 3
PARALLEL_TARGET_S = 1.0
WHERE = {"EmulatedSPIDevice.transfer": "bus transfers", "EmulatedI2CBus._transact": "bus transfers",
         "EmulatedGPIOLines.set_values": "bus transfers", "EmulatedGPIOLines.get_values": "bus transfers",
         "EmulatedGPIOLines.wait_edge": "conversion", "AD5933.measure": "conversion",
         "AD5933._wait_for": "conversion", "AD5933.start": "excitation start", "FrontEnd.measure": "settling",
         "AD5933FrontEnd._measure_system_phase": "excitation start"}


PARALLEL_OPERATIONS = {"ADG1414Chain.write": "drive switch transfer", "ChipSelectDecoder.select": "decoder address",
                       "ChipSelectDecoder.transfer": "ADC read-out", "AD7606Array.convert": "CONVST and BUSY",
                       "ParallelFrontEnd.step": "settling wait", "ParallelFrontEnd.measure_zero": "settling wait"}
PARALLEL_PHASES = {"check_contacts_parallel": "contact check", "ParallelFrontEnd.measure_zero": "zero",
                   "ScanEngine._steps": "steps"}
LOADED_KPA = 4.3          # 32 mmHg: an electrode under at least this is marked loaded for the adaptive frame
BED_LAYOUT = "grid-16x32"
SCENE_HOURS = np.arange(0.0, 6.01, 0.5)


class TimeLedger:
    """Splits the simulated clock's waits by what waited (the innermost caller ``where`` names), and, with
    ``phases``, also by the phase of the frame (the outermost caller ``phases`` names)."""

    def __init__(self, clock, where=WHERE, phases=None):
        self.spent: dict = defaultdict(float)
        self.where, self.phases = where, phases
        self._sleep = clock.sleep
        clock.sleep = self._charged

    def _charged(self, seconds: float) -> None:
        frame = sys._getframe(1)
        label, phase, depth = None, "other", 0
        while frame is not None and (self.phases is not None or (label is None and depth < 6)):
            name = frame.f_code.co_qualname
            if label is None and name in self.where:
                label = self.where[name]
            if self.phases is not None and name in self.phases:
                phase = self.phases[name]
            frame, depth = frame.f_back, depth + 1
        label = label or "other"
        self.spent[label if self.phases is None else (phase, label)] += seconds
        self._sleep(seconds)


def sensor_readings(sensor, protocol, current_a):
    z = sensor.transfer
    a, b, c, d = (protocol.readings - 1).T
    return current_a * (z[c, a] - z[c, b] - z[d, a] + z[d, b])


def run_case(profile_name: str, layout_name: str, order: str, system=None):
    """Frames of a profile on a layout; on the profile's own system unless ``system`` is given."""
    layout = get_layout(layout_name)
    protocol = default_protocol(layout)
    sensor = ForwardSensor.of_layout(layout)
    board = emulated_board(board_profile({"profile": profile_name}), sensor, system=system)
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


def image_report(results: dict, bed: dict, slow: dict) -> str:
    """Every built-in profile's steady frame on the buses of the image's system, and the AD5933 at 100 kHz."""
    rows = []

    def row(name, layout, system, seconds, target):
        profile = board_profile({"profile": name})
        spi = sorted({address.max_speed_hz / 1e6 for address in profile.spi.values()})
        verdict = "-" if target is None else f"{target:.1f} ({'met' if seconds <= target else 'MISSED'})"
        rows.append([name, layout, system.name, f"{system.i2c_clock_hz.get(profile.i2c_bus, I2C_DEFAULT_CLOCK_HZ) / 1e3:g}",
                     ", ".join(f"{mhz:g}" for mhz in spi), f"{seconds:.2f}", verdict])

    targets = {(p, lay): target for p, lay, target in CASES}
    for name in BUILTIN_PROFILES:
        system = SYSTEMS[board_profile({"profile": name}).system]
        if name == "parallel":
            row(name, f"{BED_LAYOUT} (full pass)", system, bed["steady_s"], PARALLEL_TARGET_S)
            continue
        layout = "grid-4x4"
        row(name, layout, system, results[name, layout, "optimised"]["steady_s"], targets[name, layout])
        if name == "ad5933":
            row(name, layout, slow["system"], slow["steady_s"], targets[name, layout])
    return table(["profile", "layout", "system", "I2C1 kHz", "SPI MHz", "frame s (optimised order)", "target s"], rows)


def bed_sensor(layout):
    """The empty bed mat: the liquid sheet of the mat's defaults (depth x conductivity), contact impedance as in
    core/fem.py, solved for its transfer impedances."""
    sheet = DEFAULT_PARAMETERS.rest_depth_mm * 1e-3 * DEFAULT_PARAMETERS.conductivity_s_per_m
    model = build_fem_model(layout)
    return ForwardSensor(TransferSolver(model).transfer(np.full(model.n_elements, sheet))), sheet


def loaded_electrodes(layout, field) -> list[int]:
    """Electrodes whose centre lies under at least LOADED_KPA of the scene's pressure."""
    x, y = layout.centroids_mm().T
    rows, cols = field.pressure_kpa.shape
    pressure = field.pressure_kpa[np.clip((y // field.pitch_mm).astype(int), 0, rows - 1),
                                  np.clip((x // field.pitch_mm).astype(int), 0, cols - 1)]
    return [int(e) + 1 for e in np.flatnonzero(pressure >= LOADED_KPA)]


def adcs_per_step(protocol, adc_of_channel) -> float:
    """Mean number of converters a step must read, for a channel -> ADC wiring."""
    cmap = ChannelMap(*protocol_grid(protocol))
    channels, _ = cmap.channels_of_protocol(protocol.readings)
    adc = adc_of_channel(channels)
    return float(np.mean([len(set(adc[protocol.drive_index == d].tolist())) for d in range(len(protocol.drives))]))


def protocol_grid(protocol) -> tuple[int, int]:
    layout = get_layout(BED_LAYOUT)
    assert protocol.n_electrodes == layout.n_electrodes
    return layout.grid_shape


def step_budget(profile, adcs: float, *, read_s=None, pipelined=True) -> float:
    """One drive's time on the timing model: switch transfer, CONVST, BUSY, read-out, and any settling the
    read-out does not hide (``read_s`` overrides the read-out: another way of reading the converters)."""
    o = profile.timing.call_overhead_s
    chips = DriveMatrix.chips_for(profile.channels)
    switch = o + 8 * chips / min(profile.spi["drive_switches"].max_speed_hz, 11e6)
    convert = o + max(o, CONVERSION_S[profile.measurement.adc_oversampling])
    read = adcs * (2 * o + 8 * 16 / profile.spi["adc"].max_speed_hz) if read_s is None else read_s
    settle = profile.timing.drive_settle_s
    return switch + convert + read + (max(0.0, settle - read) if pipelined else settle)


def run_parallel() -> dict:
    layout = get_layout(BED_LAYOUT)
    protocol = protocol_for(layout, "rows", reach=2)
    sensor, sheet = bed_sensor(layout)
    profile = board_profile({"profile": "parallel"})
    board = emulated_board(profile, sensor)
    fe = open_front_end(board, profile)
    engine = ScanEngine(fe, protocol)
    cold = engine.scan()
    ledger = TimeLedger(board.clock, PARALLEL_OPERATIONS, PARALLEL_PHASES)
    out = dict(readings=len(protocol), drives=len(protocol.drives), cold_s=cold.duration_s, sheet=sheet,
               coarse=len(engine.adaptive.coarse))

    def frame(kind, **scan_args):
        before, calls = dict(ledger.spent), len(board.log)
        start = time.process_time()
        taken = engine.scan(**scan_args)
        cpu = time.process_time() - start
        spent = {k: v - before.get(k, 0.0) for k, v in ledger.spent.items()}
        log = board.log[calls:]
        reads = sum(1 for t in log if t.kind == "spi" and t.target == fe.adc_device)
        steps = len(set(protocol.drive_index[(taken.flags & int(Flag.HELD)) == 0].tolist()))
        return dict(kind=kind, frame=taken, seconds=taken.duration_s, cpu_s=cpu, spent=spent, steps=steps,
                    adc_reads=reads - fe.cmap.n_adcs, calls=sum(1 for t in log if t.kind in ("spi", "gpio")))

    steady = [frame("full pass") for _ in range(STEADY_FRAMES)]
    out["steady"] = steady
    out["steady_s"] = float(np.median([f["seconds"] for f in steady]))
    out["cpu_s"] = float(np.median([f["cpu_s"] for f in steady]))
    start = board.clock.monotonic()
    check_contacts(fe, layout.n_electrodes)
    out["contact_s"] = board.clock.monotonic() - start
    last = steady[-1]["frame"]
    expected = sensor_readings(sensor, protocol, last.drive_current_a)
    accuracy = profile.accuracy
    out["worst"] = float(np.max(np.abs(last.volts - expected) / (accuracy.relative * np.abs(expected)
                                                                 + accuracy.absolute_v)))
    out["usable"] = int(last.usable.sum())
    out["min_fraction"] = float(np.nanmin(last.fraction))
    adaptive = []
    for name, hours in (("supine-still", 1.5), ("turn-schedule", 3.0)):
        bed = VirtualBed(layout, load_scene(name))
        loaded = loaded_electrodes(layout, bed.field_at(hours * 3600))
        f = frame(f"adaptive: {name} at {hours:g} h, {len(loaded)} loaded electrodes", loaded=loaded)
        f["loaded"] = len(loaded)
        adaptive.append(f)
    adaptive.append(frame("adaptive: coarse pass only (nothing loaded)", loaded=[]))
    out["adaptive"] = adaptive
    out["dynamic"] = dynamic_range(layout, protocol, profile, sensor)
    out["adcs_built"] = adcs_per_step(protocol, lambda ch: fe.cmap.adc_index[ch, 0])
    out["adcs_rowwise"] = adcs_per_step(protocol, lambda ch: ch // 8)
    out["profile"] = profile
    return out


def dynamic_range(layout, protocol, profile, sensor) -> list[dict]:
    """The readings of the protocol on the empty mat and under simulated patients, against the chain's ranges."""
    chain = FrameChain(profile)
    ranges = chain.ranges
    headroom = profile.measurement.range_headroom
    a, b = (protocol.drives - 1).T
    rows = []

    def row(label, z):
        volts = chain.ideal(z, protocol)
        peak = np.zeros(len(protocol.drives))
        np.maximum.at(peak, protocol.drive_index, np.abs(volts))
        drive_v = chain.current_a * (z[a, a] - z[a, b] - z[b, a] + z[b, b] + 2 * SWITCH_OHM)
        rows.append(dict(label=label, volts=np.abs(volts), wide=int((peak > headroom * ranges[1].full_scale_input_v)
                                                                     .sum()),
                         saturated=int((np.abs(volts) > 0.97 * ranges[0].full_scale_input_v).sum()),
                         drive_v=float(drive_v.max()),
                         compliance=int((drive_v > profile.excitation.compliance_v).sum())))

    row("empty mat", sensor.transfer)
    for name in ("supine-still", "turn-schedule"):
        bed = VirtualBed(layout, load_scene(name))
        worst = max(((h, bed.transfer_ohm(h * 3600)) for h in SCENE_HOURS if h * 3600 <= bed.scene.duration_s),
                    key=lambda hz: np.abs(chain.ideal(hz[1], protocol)).max())
        row(f"{name}, worst of every half hour ({worst[0]:g} h)", worst[1])
    return rows


def noise_floor_v(profile) -> tuple[float, float]:
    """(rms noise, one LSB) of a reading at the +/-5 V range, input-referred: converter and in-amp noise,
    quantisation, and the zero measurement's residual."""
    errors = ParallelErrors()
    gain = FrameChain(profile).gain
    lsb = 5.0 / 32768
    one = np.sqrt((errors.adc_noise_lsb * lsb) ** 2 + lsb ** 2 / 12 + (errors.input_noise_v * gain) ** 2)
    return float(np.hypot(one, one / np.sqrt(8)) / gain), lsb / gain


def parallel_report(r: dict) -> str:
    profile = r["profile"]
    o = profile.timing.call_overhead_s
    steady = r["steady"][-1]
    per_step = {label: v / steady["steps"] for (phase, label), v in steady["spent"].items() if phase == "steps"}
    other = steady["seconds"] - sum(v for (phase, _), v in steady["spent"].items() if phase == "steps")
    frame_rows = [["first frame (contact check, every drive probed)", "-", f"{r['cold_s']:.3f}", "-", "-"]]
    for f in r["steady"][-1:] + r["adaptive"]:
        frame_rows.append([f["kind"], f"{f['steps']} of {r['drives']}", f"{f['seconds']:.3f}",
                           f"{f['adc_reads'] / max(f['steps'], 1):.2f}", f"{f['cpu_s']:.1f}"])
    frame_rows.append(["contact check alone (256 steps; every tenth frame)", "256 pairs", f"{r['contact_s']:.3f}",
                       "-", "-"])
    frame_table = table(["frame", "drives taken", "seconds (timing model)", "ADCs read per step",
                         "host CPU s (emulators included)"], frame_rows)
    step_rows = [[label, f"{v * 1e6:.0f}"] for label, v in sorted(per_step.items(), key=lambda kv: -kv[1])]
    step_rows.append(["per step, all", f"{sum(per_step.values()) * 1e6:.0f}"])
    step_rows.append(["per frame outside the steps (zero, temperature, excitation on/off)", f"{other * 1e6:.0f}"])
    step_table = table(["operation", "us per step (full pass, measured)"], step_rows)
    drives = r["drives"]
    built = step_budget(profile, r["adcs_built"])
    designs = [
        ("as built: 4 x 2 tiles, read only the step's ADCs, next drive routed during read-out",
         r["adcs_built"], built),
        ("channels packed row by row (62 ADCs)", r["adcs_rowwise"], step_budget(profile, r["adcs_rowwise"])),
        ("every ADC read every step", 64, step_budget(profile, 64)),
        ("one daisy-chained transfer of 64 converters (needs a part with a chain input; the AD7606 has none)",
         64, step_budget(profile, 0, read_s=o + 64 * 16 * 8 / profile.spi["adc"].max_speed_hz)),
        ("as built, but settling after each switch (no pipelining)", r["adcs_built"],
         step_budget(profile, r["adcs_built"], pipelined=False)),
    ]
    design_rows = [[name, f"{adcs:.2f}", f"{t * 1e6:.0f}", f"{t * drives:.2f}"] for name, adcs, t in designs]
    design_rows.append(["the reference board's serial chain at its grid-4x4 pace (5.12 ms a reading)", "-", "-",
                        f"{5.12e-3 * r['readings']:.0f}"])
    design_table = table(["design", "ADCs read per step", "us per step (budget)", "full pass s (budget)"],
                         design_rows)
    noise, lsb = noise_floor_v(profile)
    ranges = FrameChain(profile).ranges
    dyn_rows = []
    for d in r["dynamic"]:
        v = d["volts"]
        small = np.percentile(v, 1)
        dyn_rows.append([d["label"], f"{v.min() * 1e3:.3f} / {small * 1e3:.3f} / {np.median(v) * 1e3:.2f} / "
                         f"{v.max() * 1e3:.1f}", f"{v.max() / ranges[1].full_scale_input_v:.0%}",
                         f"{d['wide']}", f"{d['saturated']}", f"{d['drive_v']:.2f}", f"{d['compliance']}"])
    dyn_table = table(["mat", "readings mV: min / 1st percentile / median / max", "max share of +/-5 V",
                       "drives on +/-10 V", "saturated", "max drive voltage V rms", "drives beyond compliance"],
                      dyn_rows)
    beyond = max(r["dynamic"][1:], key=lambda d: d["compliance"])
    empty = r["dynamic"][0]["volts"]
    m = profile.measurement
    return f"""## The parallel board on the bed mat (`parallel` profile, {BED_LAYOUT}, rows protocol)

The bed mat: {BED_LAYOUT} (512 electrodes at 60 mm), the liquid sheet of the mat's defaults
({r['sheet']:.4f} S), contact impedance as in `core/fem.py`; the rows protocol with reach 2
({r['readings']} readings, {r['drives']} drives). One excitation (AD9833, MCP4017, Howland source at
{profile.excitation.current_a * 1e3:g} mA, {profile.excitation.frequency_hz / 1e3:g} kHz) is switched to each drive pair
by 128 daisy-chained ADG1414 (one transfer a drive); every pair along the rows has its own in-amp
(x{m.inamp_gain:g}), synchronous demodulator and two-pole low-pass (x{m.lowpass_gain:g}, {m.lowpass_hz / 1e3:g} kHz),
and 64 AD7606 sample all 496 channels at once. Frames on the timing model ({o * 1e6:.0f} us a bus call, SPI
wire time at the profile's clocks); steady figures are the last of {STEADY_FRAMES} frames, host CPU their median.

{frame_table}

A full pass takes **{r['steady_s']:.2f} s** (target {PARALLEL_TARGET_S:g} s); an adaptive frame takes the {r['coarse']} drives along
the rows and only the column drives within two spacings of an electrode under {LOADED_KPA} kPa (32 mmHg),
holding the rest from the last frame (flagged HELD). The contact check is a pass of its own (disjoint
pairs along the rows at the test current) and runs every tenth frame; between checks an open electrode
still shows in every frame, as saturated channels or a drive with no signal.

### One step, measured, and the designs it was chosen over

{step_table}

The budget below is the timing model worked out by hand: a switch transfer is one call plus
{DriveMatrix.chips_for(profile.channels) * 8} bits at {profile.spi['drive_switches'].max_speed_hz / 1e6:g} MHz (the ADG1414 chain's
11 MHz limit), a conversion one call for CONVST and one for BUSY's edge, each converter read one decoder
address call and one {profile.spi['adc'].max_speed_hz / 1e6:.3g} MHz transfer of 128 bits; the low-pass settling
({profile.timing.drive_settle_s * 1e3:g} ms, to 1e-5 of a step) is hidden under the read-out of the previous drive
when the next drive is routed straight after CONVST (the AD7606 holds its sample). The measured step is
below the budget because a step's first converter is often the one the last step read (no address call).
The Pi cannot give 64 converters chip selects of their own (64 lines; its header has 28 GPIOs, and the
kernel's `cs-gpios` would need as many), hence the decoder.

{design_table}

Bill of materials of the measuring side: 496 channels, each an in-amp, a demodulator (an analogue switch
pair driven by the excitation's square wave) and a two-pole low-pass op-amp; 64 AD7606 (8 channels each,
4 x 2 pairs per tile; 16 inputs spare); 4 x 74HC154 and 1 x 74HC139 decoding 6 GPIO address lines; BUSY
ORed by 9 eight-input gates; and on the drive side 128 ADG1414 (1024 switches: I+ and I- for each electrode).

### Accuracy against the forward model

Every reading of a steady full pass against the forward model at the drive current, in units of the
profile's stated accuracy ({profile.accuracy.relative:.1%} + {profile.accuracy.absolute_v * 1e6:g} uV): worst
**{r['worst']:.2f}**; {r['usable']}/{r['readings']} usable; smallest share of full scale {r['min_fraction']:.4f}
(the +/-5 V range is the most sensitive there is: the small readings sit low in it, well above its noise).

### Dynamic range

Input-referred full scale: {ranges[1].full_scale_input_v * 1e3:.1f} mV rms at +/-5 V, {ranges[0].full_scale_input_v * 1e3:.1f} mV
at +/-10 V (gain {ranges[0].gain:.1f}: in-amp, demodulator 2 sqrt(2)/pi, low-pass); a drive's readings use the most
sensitive range that keeps them under {m.range_headroom:.0%} of it. Noise of one reading
{noise * 1e6:.1f} uV rms (converter 0.5 LSB, in-amp 0.4 uV, quantisation, and the zero's residual); one LSB at
+/-5 V is {lsb * 1e6:.2f} uV. The current source's compliance is {profile.excitation.compliance_v:g} V rms.

{dyn_table}

On the empty mat the smallest reading within reach is {empty.min() * 1e3:.3f} mV: {empty.min() / lsb:.0f} LSB and
{empty.min() / noise:.0f} times the noise ({20 * np.log10(empty.min() / noise):.0f} dB), and the largest uses
{empty.max() / ranges[1].full_scale_input_v:.0%} of the +/-5 V range, so no reading saturates and the drive voltage
stays a {profile.excitation.compliance_v / r['dynamic'][0]['drive_v']:.0f}th of the compliance. Under patients the
largest readings grow (thinner liquid near a load) and a few drives move to +/-10 V; none saturates. The smallest
loaded readings are small because they cancel (a measuring pair across a load's symmetry line), not for want
of gain. Where a load presses the membrane onto the base between a drive pair, the pair's impedance
rises by orders of magnitude and the source reaches its compliance: {beyond['compliance']} of {r['drives']} drives in
the worst case above ({beyond['label']}). Their readings come out scaled down by the current the source could
not deliver; the chain has no compliance detector to flag them (a drive with no current at all is flagged
as an open drive by the scan engine), which is as on the serial boards.

![parallel board: where a frame's time goes](acquisition_parallel.png)
"""


def plot_parallel(r: dict) -> None:
    plt = pyplot()
    frames = r["steady"][-1:] + r["adaptive"]
    labels = sorted({label for f in frames for (_, label) in f["spent"]})
    fig, ax = plt.subplots(figsize=(10, 4))
    names = [f["kind"].replace(", ", "\n").replace(": ", ":\n") for f in frames]
    bottom = np.zeros(len(frames))
    for label in labels:
        values = np.array([sum(v for (_, op), v in f["spent"].items() if op == label) for f in frames])
        ax.bar(names, values, bottom=bottom, label=label)
        bottom += values
    ax.axhline(PARALLEL_TARGET_S, color="k", linestyle="--", linewidth=1, label=f"{PARALLEL_TARGET_S:g} s target")
    ax.set_ylabel("seconds per frame (timing model)")
    ax.set_title(f"parallel board, {BED_LAYOUT}: where a frame's time goes")
    ax.legend(fontsize=7)
    ax.tick_params(axis="x", labelsize=7)
    save_figure(fig, HERE / "acquisition_parallel.png")


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
    bed = run_parallel()
    plot_parallel(bed)
    default_clock = dataclasses.replace(SYSTEMS["appliance-image"], i2c_clock_hz={1: I2C_DEFAULT_CLOCK_HZ},
                                        name="appliance-image, I2C1 at Linux's default")
    slow = run_case("ad5933", "grid-4x4", "optimised", system=default_clock) | {"system": default_clock}
    text = f"""# Acquisition: frame time on the boards' timing models

Command: `{COMMAND}` ({machine()}).

Each profile's chips run as register-level emulators on a simulated clock that
charges every bus transfer (bytes at the system's I2C clock and the profile's SPI clocks, plus
{board_profile({}).timing.call_overhead_s * 1e6:.0f} us per call from Python) and every wait, so the
durations below are the profile's timing model; the drivers and scan engine are
the ones that run on the hardware. "First frame" ranges each reading by a probe
at the least sensitive range and waits the worst-case settling (nothing is known
yet); later frames start from the previous frame's ranges and wait only the
settling their predicted step needs. Steady figures are medians of
{STEADY_FRAMES} frames. Host CPU is this machine's time for a whole steady frame,
emulators included.

{frame_table}

## Every profile on the image's buses

Each built-in profile on the system it names: an `appliance-image` variant (`image-build/`,
`build-image.sh --profile NAME`), whose device tree runs I2C1 at 400 kHz; SPI at the clocks the profile
opens its devices at. The last AD5933 row is the same frame with I2C1 at the 100 kHz that the mainline
device trees and Linux's driver give it when nothing sets it faster: the
AD5933's frame is mostly I2C transfers, so it misses its target there. `appliance selftest --check`
refuses a profile whose system runs I2C slower than the profile's `[board.timing] i2c_clock_hz`.

{image_report(results, bed, slow)}

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
    text += "\n" + parallel_report(bed)
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
