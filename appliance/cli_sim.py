"""The ``sim`` commands: the virtual bed's models run from the command line.

``appliance sim load-test`` repeats the thesis's load test (chapter 6.3) on the
simulated mat and prints one CSV row per pressure on stdout.
"""

from __future__ import annotations

import sys


def add_parsers(sub) -> None:
    p = sub.add_parser("sim", help="simulate the sensor mat (the virtual bed)")
    sim = p.add_subparsers(dest="sim_command", required=True, metavar="SIM_COMMAND")
    p = sim.add_parser("load-test", help="a centred square load stepped through pressures, as thesis chapter 6")
    p.add_argument("--layout", default="grid-4x4", help="layout name or .toml file (default grid-4x4)")
    p.add_argument("--area-cm2", required=True, type=float, help="load area, 1 to 36 cm2")
    p.add_argument("--pressures", required=True, metavar="P1,P2,...",
                   help="pressures in kPa, applied in this order (the mat remembers the previous one)")
    p.add_argument("--density", type=float, default=1.0, help="FEM mesh density")
    p.add_argument("--temperature-c", type=float, default=20.0, help="liquid temperature at the start")
    p.add_argument("--drift-c-per-step", type=float, default=None,
                   help="warming of the liquid between steps, C (default: the thesis's, fitted; 0 for none)")
    p.set_defaults(run=_load_test)


def _load_test(args) -> int:
    from appliance.errors import ModelInputInvalid
    from appliance.sim.load_test import THESIS_DRIFT_C_PER_STEP, load_test

    try:
        pressures = [float(text) for text in args.pressures.split(",")]
    except ValueError:
        raise ModelInputInvalid(f"--pressures takes numbers (kPa) separated by commas, got "
                                f"{args.pressures!r}") from None
    drift = THESIS_DRIFT_C_PER_STEP if args.drift_c_per_step is None else args.drift_c_per_step
    rows = load_test(args.area_cm2, pressures, layout=args.layout, density=args.density,
                     temperature_c=args.temperature_c, drift_c_per_step=drift)
    lines = ["pressure_kpa,visibility,dv_over_v,deformation_mm"]
    lines += [f"{r.pressure_kpa:g},{r.visibility:.6g},{r.dv_over_v:.6g},{r.deformation_mm:.6g}" for r in rows]
    sys.stdout.write("\n".join(lines) + "\n")
    return 0
