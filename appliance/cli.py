"""The ``appliance`` command line.

Each subcommand parses its arguments, calls the core, and prints: tables and
files on stdout, progress and summaries on stderr. Bad input exits with status 2
and one line naming what is wrong.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from appliance.errors import ApplianceError


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except ApplianceError as exc:
        print(f"appliance: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="appliance", description="Bedside EIT pressure-sore monitor.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("layouts", help="list the built-in sensor-mat layouts")
    p.set_defaults(run=_layouts)

    p = sub.add_parser("layout", help="print a layout as TOML (a starting point for a custom mat)")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.set_defaults(run=_layout)

    p = sub.add_parser("protocol", help="print a measurement protocol as CSV")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.add_argument("--kind", default="default",
                   choices=["default", "adjacent", "opposite", "skip", "distributed", "local"])
    p.add_argument("--skip", type=int, default=0, help="electrodes skipped between a drive pair (--kind skip)")
    p.add_argument("--reach", type=float, default=None,
                   help="electrode spacings a reading may lie from its drive pair (--kind local)")
    p.set_defaults(run=_protocol)

    p = sub.add_parser("simulate", help="simulate one frame of readings and print it as CSV")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.add_argument("--model", default="fem", choices=["fem", "network"],
                   help="finite elements with contact impedance, or the thesis's resistor network")
    p.add_argument("--density", type=float, default=1.0, help="mesh density (2 halves every element edge)")
    p.add_argument("--protocol", type=Path, help="protocol CSV file (default: the layout's default protocol)")
    p.add_argument("--inclusion", action="append", default=[], metavar="SHAPE:X,Y,W,H,CONTRAST",
                   help="rect:X,Y,W,H,CONTRAST or disc:X,Y,D,CONTRAST in mm, conductivity ratio; repeatable")
    p.add_argument("--current-ma", type=float, default=1.0, help="drive current, mA")
    p.add_argument("--out", type=Path, help="write the frame here instead of stdout")
    p.set_defaults(run=_simulate)
    return parser


def _layouts(args) -> int:
    from appliance.core.layouts import BUILTIN_NAMES, get_layout

    for name in BUILTIN_NAMES:
        layout = get_layout(name)
        w, h = layout.sheet.size_mm
        kind = f"{layout.grid_shape[0]} x {layout.grid_shape[1]} grid" if layout.is_grid else "around the edge"
        print(f"{name:12s} {w:g} x {h:g} mm, {layout.n_electrodes} electrodes {kind}")
    print("grid-RxC     R x C grid over a 900 x 1900 mm bed mat (grid-RxC@HxW for another size)")
    return 0


def _layout(args) -> int:
    from appliance.core.layout_files import layout_to_toml
    from appliance.core.layouts import get_layout

    sys.stdout.write(layout_to_toml(get_layout(args.layout)))
    return 0


def _protocol(args) -> int:
    from appliance.core.layouts import get_layout
    from appliance.core.protocols import protocol_for, protocol_to_csv

    protocol = protocol_for(get_layout(args.layout), args.kind, skip=args.skip, reach=args.reach)
    sys.stdout.write(protocol_to_csv(protocol))
    return 0


def _simulate(args) -> int:
    from appliance.core.fem import build_fem_model
    from appliance.core.forward import simulate
    from appliance.core.frames import frame_to_csv
    from appliance.core.layouts import get_layout
    from appliance.core.network import build_network_model, network_for_layout
    from appliance.core.phantoms import conductivity, covered_area_mm2
    from appliance.core.protocols import default_protocol, load_protocol

    layout = get_layout(args.layout)
    protocol = load_protocol(args.protocol, layout.n_electrodes) if args.protocol else default_protocol(layout)
    inclusions = [_parse_inclusion(text) for text in args.inclusion]
    start = time.perf_counter()
    if args.model == "fem":
        model = build_fem_model(layout, density=args.density)
    else:
        model = build_network_model(network_for_layout(layout, max(1, round(args.density))))
    built = time.perf_counter()
    sigma = conductivity(model, inclusions)
    volts = simulate(model, sigma, protocol, current_a=args.current_ma * 1e-3)
    done = time.perf_counter()
    text = frame_to_csv(protocol, volts)
    if args.out:
        args.out.write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    print(f"{layout.name}: {args.model} model, {model.n_elements} elements, built in "
          f"{(built - start) * 1e3:.0f} ms; {len(protocol)} readings ({protocol.name}) over "
          f"{len(protocol.drives)} drives in {(done - built) * 1e3:.0f} ms; inclusions cover "
          f"{covered_area_mm2(model, sigma):.0f} mm^2", file=sys.stderr)
    return 0


def _parse_inclusion(text: str):
    from appliance.core.phantoms import Inclusion
    from appliance.errors import ModelInputInvalid

    shape, _, numbers = text.partition(":")
    try:
        values = [float(v) for v in numbers.split(",")]
    except ValueError:
        raise ModelInputInvalid(f"inclusion {text!r}: values must be numbers") from None
    if shape == "rect" and len(values) == 5:
        return Inclusion("rect", *values)
    if shape == "disc" and len(values) == 4:
        x, y, d, contrast = values
        return Inclusion("disc", x, y, d, d, contrast)
    raise ModelInputInvalid(f"inclusion {text!r}: use rect:X,Y,W,H,CONTRAST or disc:X,Y,D,CONTRAST")
