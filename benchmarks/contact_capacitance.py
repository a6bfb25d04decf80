"""How much error capacitive electrode contacts cause through an RMS detector and through a phase-sensitive one.

    python benchmarks/contact_capacitance.py      # writes benchmarks/contact_capacitance.md (a few seconds)

The thesis's grid-4x4 mat (saline, the emulated board's sheet) is read with the distributed protocol at each
built-in board's frequency, current, input capacitance and compliance, through contacts of R parallel C
(R 200 ohm, C swept; each electrode's R and C drawn within +/-30 % of nominal, the same draw for every row).
Each reading is what the profile's detector reports (``appliance/drivers/emulated/electrode_interface.py``):
the AD8436's magnitude on the reference board, the in-phase part on the AD5933 (its DFT) and on the parallel
board (synchronous demodulators, 0.5 degree reference phase error, the largest its model draws). The same
phasors are also put through the other kind of detector, so each row compares the two on one board. Truth
is the sheet's own resistive reading at the set current. No noise is added: the errors are the contacts'.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

from appliance.core.named_layouts import get_layout  # noqa: E402
from appliance.core.phantoms import Inclusion  # noqa: E402
from appliance.core.protocols import default_protocol  # noqa: E402
from appliance.drivers.emulated.electrode_interface import ElectrodeContact, detect, reading_phasors  # noqa: E402
from appliance.drivers.emulated.sensor import ForwardSensor  # noqa: E402
from appliance.drivers.profile import board_profile  # noqa: E402

HERE = Path(__file__).parent
RESISTANCE_OHM = 200.0
CAPACITANCES_F = (0.0, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5)
SPREAD = 0.3
PHASE_ERROR_RAD = {"rms": 0.0, "dft": 0.0, "synchronous": math.radians(0.5)}
BOARDS = {"reference": {}, "ad5933": {}, "parallel": {"grid": {"rows": 4, "cols": 4}}}


def current_of(profile) -> float:
    x = profile.excitation
    if profile.chain == "ad5933":
        from appliance.drivers.frontend_ad5933 import ACTUAL_VPP

        return ACTUAL_VPP[x.output_range_vpp] / (2 * math.sqrt(2)) * x.transconductance_a_per_v
    return x.current_a


def errors(profile, transfers, protocol, capacitance_f: float) -> dict:
    """Static and change errors (% of the frame's rms reading / of the change) for both kinds of detector."""
    n = transfers[0].shape[0]
    contact = ElectrodeContact.uniform(n, resistance_ohm=RESISTANCE_OHM, capacitance_f=capacitance_f,
                                       spread=SPREAD, rng=np.random.default_rng(7))
    x, m = profile.excitation, profile.measurement
    current = current_of(profile)
    own = m.detector
    kinds = {"magnitude (RMS)": ("rms", 0.0), "in-phase": (own if own != "rms" else "synchronous",
                                                        PHASE_ERROR_RAD[own if own != "rms" else "synchronous"])}
    readings = protocol.readings - 1
    truth = [current * (z[c, a] - z[c, b] - z[d, a] + z[d, b]) for z in transfers for a, b, c, d in [readings.T]]
    out = {}
    for label, (detector, phase) in kinds.items():
        got = []
        for z in transfers:
            phasors, drive_v, limited = reading_phasors(z, readings, current, contact, x.frequency_hz,
                                                        m.input_capacitance_f, x.compliance_v)
            got.append(detect(phasors, detector, phase))
        scale = np.sqrt(np.mean(truth[0] ** 2))
        static = np.abs(got[0] - truth[0]) / scale
        change_true = truth[1] - truth[0]
        change = np.linalg.norm((got[1] - got[0]) - change_true) / np.linalg.norm(change_true)
        out[label] = (100 * np.median(static), 100 * static.max(), 100 * change, int(limited.sum()))
    pair = np.array([[0, 1, 0, 1]])
    phasor, _, _ = reading_phasors(transfers[0], pair, current, contact, x.frequency_hz, m.input_capacitance_f,
                                   x.compliance_v)
    z_true = float(transfers[0][0, 0] - 2 * transfers[0][0, 1] + transfers[0][1, 1]) + \
        float(contact.resistance_ohm[0] + contact.resistance_ohm[1])
    out["contact check"] = (abs(phasor[0]) / current, phasor[0].real / current, z_true)
    return out


def run() -> str:
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    transfers = [ForwardSensor.of_layout(layout).transfer,
                 ForwardSensor.of_layout(layout, inclusions=[Inclusion("disc", 50, 50, 20, 20, 0.5)]).transfer]
    sections, worst = [], []
    for name, overrides in BOARDS.items():
        profile = board_profile({"profile": name, **overrides})
        rows, changes = [], []
        for c in CAPACITANCES_F:
            e = errors(profile, transfers, protocol, c)
            zc = abs(RESISTANCE_OHM / (1 + 2j * math.pi * profile.excitation.frequency_hz * RESISTANCE_OHM * c))
            rms, phase = e["magnitude (RMS)"], e["in-phase"]
            check = e["contact check"]
            changes.append((rms[2], phase[2], c))
            rows.append([f"{c * 1e9:g}" if c else "0", f"{zc:.0f}",
                         f"{rms[0]:.3f} / {rms[1]:.2f}", f"{rms[2]:.2f}",
                         f"{phase[0]:.3f} / {phase[1]:.2f}", f"{phase[2]:.2f}",
                         f"{check[0]:.0f} / {check[1]:.0f} / {check[2]:.0f}", f"{rms[3]}"])
        m = profile.measurement
        rms_worst, phase_worst = max(changes), max(changes, key=lambda row: row[1])
        worst.append([name, f"`{m.detector}`", f"{rms_worst[0]:.2f} % (at {rms_worst[2] * 1e9:g} nF)",
                      f"{phase_worst[1]:.2f} % (at {phase_worst[2] * 1e9:g} nF)"])
        sections.append(
            f"### {name}: {profile.excitation.frequency_hz / 1e3:g} kHz, {current_of(profile) * 1e3:.2f} mA, "
            f"inputs {m.input_capacitance_f * 1e12:g} pF to ground, detector `{m.detector}`\n\n"
            + table(["contact C (nF)", "contact impedance (ohm)", "RMS: static error median / max (%)", "RMS: change error (%)",
                     "in-phase: static median / max (%)", "in-phase: change error (%)",
                     "contact check 1-2 ohm: RMS / in-phase / resistive", "drives at compliance"], rows))
    summary = table(["board", "its detector", "worst change error, magnitude (RMS)", "worst change error, in-phase"],
                    worst)
    return summary + "\n\n" + "\n\n".join(sections)


def main() -> None:
    body = run()
    report = f"""# Contact capacitance: RMS detection against phase-sensitive detection

Command: `python benchmarks/contact_capacitance.py` ({machine()}).

grid-4x4, distributed protocol (448 readings), contacts R = {RESISTANCE_OHM:g} ohm parallel C, each electrode's R
and C within +/-{SPREAD:.0%} of nominal. Static error: |reading - the sheet's resistive reading|, in % of the
frame's rms reading (median / max over readings). Change error: ||change - true change|| / ||true change|| for a
20 mm disc at half the conductivity in the middle, the difference an image is made from. "RMS" puts the
phasors through a magnitude detector with the phase comparator's sign; "in-phase" through the board's own
phase-sensitive path (the AD5933's DFT, or a synchronous demodulator with 0.5 degree phase error; on the
reference board, the synchronous demodulator it does not have). The contact check drives and reads electrodes
1 and 2 and reports ohms; the resistive column is the sheet plus the two contacts' R.

Reading it: with no capacitance the quadrature comes from the unequal contacts against the inputs'
capacitance to ground, which turn the return electrode's common-mode voltage into a differential one; the
magnitude adds it to every reading, the in-phase path drops it. As C grows the common-mode voltage itself
takes a phase and part of that error is in-phase, so both detectors' static errors grow alike, but it is
nearly the same in the loaded frame as in the reference and cancels from the change the image is made of
(the in-phase change error stays small) while the magnitude's does not. Large C shorts the contacts and
both errors vanish. The contact check reads a capacitive contact below its resistance through either
detector. The scan engine's reciprocity check sees such errors: on the emulated boards, contacts of 30 to
100 ohm (+/-30 %) behind 100 pF to 1 nF inputs left 5 to 135 of grid-4x4's 224 reciprocal pairs flagged in the
cases tried.

{body}
"""
    (HERE / "contact_capacitance.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
