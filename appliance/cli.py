"""The ``appliance`` command line.

Each subcommand parses its arguments, calls the core, and prints: tables and
files on stdout, progress and summaries on stderr. Bad input exits with status 2
and one line naming what is wrong; hardware that did not answer exits 3.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from appliance.cli_args import check_input, density, numbers, parse_inclusion, parse_pixels, whole_within, within
from appliance.errors import ApplianceError, BusError, ChipError
from appliance.files import check_writable

HARDWARE_EXIT = 3
"""Exit status when the front end's buses or chips did not answer: unlike a refusal (2: bad input, a damaged
file, a data folder in use), which a person must act on, this may pass (a device not ready at boot), so the
service manager starts the monitor again."""


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (BusError, ChipError) as exc:
        print(f"appliance: error: {exc}", file=sys.stderr)
        return HARDWARE_EXIT
    except ApplianceError as exc:
        print(f"appliance: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        return 0


def _parser() -> argparse.ArgumentParser:
    from appliance.core.layouts import MAX_GRID_ELECTRODES
    from appliance.sim.mechanics import TEMPERATURE_RANGE_C

    parser = argparse.ArgumentParser(prog="appliance", description="Bedside EIT pressure-sore monitor.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("layouts", help="list the built-in sensor-mat layouts")
    p.set_defaults(run=_layouts)

    p = sub.add_parser("scenarios", help="list the built-in scenarios of the virtual bed, a line each")
    p.set_defaults(run=_scenarios)

    p = sub.add_parser("layout", help="print a layout as TOML (a starting point for a custom mat)")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.set_defaults(run=_layout)

    p = sub.add_parser("protocol", help="print a measurement protocol as CSV")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.add_argument("--kind", default="default",
                   choices=["default", "adjacent", "opposite", "skip", "distributed", "local", "rows"])
    # no mat has more electrodes than the largest grid, so a skip or reach beyond it is a typo (the layout's own
    # electrode count bounds the skip further once it is known)
    p.add_argument("--skip", type=whole_within(0, MAX_GRID_ELECTRODES - 2), default=0,
                   help="electrodes skipped between a drive pair (--kind skip)")
    p.add_argument("--reach", type=within(0.0, MAX_GRID_ELECTRODES, "electrode spacings", above=True), default=None,
                   help="electrode spacings a reading may lie from its drive pair (--kind local or rows)")
    p.set_defaults(run=_protocol)

    p = sub.add_parser("simulate", help="simulate one frame of readings and print it as CSV")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.add_argument("--model", default="fem", choices=["fem", "network"],
                   help="finite elements with contact impedance, or the thesis's resistor network")
    p.add_argument("--density", type=density, default=1.0, help="mesh density (2 halves every element edge)")
    p.add_argument("--protocol", type=Path, help="protocol CSV file (default: the layout's default protocol)")
    p.add_argument("--inclusion", action="append", default=[], metavar="SHAPE:X,Y,W,H,CONTRAST",
                   help="rect:X,Y,W,H,CONTRAST or disc:X,Y,D,CONTRAST in mm, conductivity ratio; repeatable")
    # EIT front ends drive 0.01 to 10 mA; 10 mA rms is IEC 60601-1's patient auxiliary current limit (at 100 kHz)
    p.add_argument("--current-ma", type=within(0.01, 10.0, "mA"), default=1.0, help="drive current, mA")
    p.add_argument("--out", type=Path, help="write the frame here instead of stdout")
    p.set_defaults(run=_simulate)

    p = sub.add_parser("reconstruct", help="reconstruct an image off-line from a reference and a frame")
    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.add_argument("--reference", required=True, type=Path, help="reference frame (CSV, or a KTC2023 .mat file)")
    p.add_argument("--frame", required=True, type=Path, help="frame to image (same format and protocol)")
    p.add_argument("--out", required=True, type=Path, help="image as CSV (pixel grid, row-major) or .png")
    p.add_argument("--algorithm", default=None,
                   help="greit, gn-laplace, gn-noser, gn-tikhonov or backprojection (default: greit; "
                        "gn-laplace for ktc-32)")
    p.add_argument("--iterate", default=None, choices=["auto", "always", "never"],
                   help="iterative Gauss-Newton for large changes (default auto: when the one-step image "
                        "needs it; always for ktc-32)")
    p.add_argument("--noise", type=numbers(within(0.0, 1.0), 2), default=None, metavar="RELATIVE,ABSOLUTE",
                   help="reading noise: a share of each reading and of the rms reading, at most the reading itself "
                        "(default 1e-3,1e-4)")
    p.add_argument("--pixels", default=None, metavar="ROWSxCOLS", help="pixel grid (default 16 on the short side)")
    p.add_argument("--density", type=density, default=None,
                   help="forward mesh density (default: the appliance's for the layout, 0.5 on a bed mat)")
    p.add_argument("--calibration", type=Path, help="experimental sensitivity for backprojection (eq. 3.4.1)")
    p.add_argument("--normalise", action="store_true", help="write the thesis's 0-100 display scale (eq. 3.4.3)")
    p.add_argument("--segment", type=Path, help="also write the KTC2023 256 x 256 label image (CSV) here")
    p.add_argument("--pressure", type=Path, metavar="CAL.json",
                   help="write the pressure map in kPa with this calibration (from appliance calibrate pressure)")
    p.add_argument("--temperature-c", type=within(*TEMPERATURE_RANGE_C, "C"), default=None,
                   help="--pressure: the frame's liquid temperature, corrected to the calibration's where the "
                        "correction holds (default: no correction)")
    p.add_argument("--cache-dir", type=Path, default=None, help="where built models are kept")
    p.set_defaults(run=_reconstruct)

    from appliance.cli_calibrate import add_parsers as add_calibrate_parsers
    from appliance.cli_charting import add_parsers as add_charting_parsers
    from appliance.cli_frontend import add_parsers as add_frontend_parsers
    from appliance.cli_hospital import add_parsers as add_hospital_parsers
    from appliance.cli_provision import add_parsers as add_provision_parsers
    from appliance.cli_run import add_parsers as add_run_parsers
    from appliance.cli_sim import add_parsers as add_sim_parsers
    from appliance.cli_ward import add_parsers as add_ward_parsers

    add_frontend_parsers(sub)
    add_sim_parsers(sub)
    add_run_parsers(sub)
    add_calibrate_parsers(sub)
    add_ward_parsers(sub)
    add_hospital_parsers(sub)
    add_provision_parsers(sub)
    add_charting_parsers(sub)
    return parser


def _layouts(args) -> int:
    from appliance.core.named_layouts import BUILTIN_NAMES, get_layout

    for name in BUILTIN_NAMES:
        layout = get_layout(name)
        w, h = layout.sheet.size_mm
        shape = layout.grid_shape
        kind = f"{shape[0]} x {shape[1]} grid" if shape is not None else "around the edge"
        print(f"{name:12s} {w:g} x {h:g} mm, {layout.n_electrodes} electrodes {kind}")
    print("grid-RxC     R x C grid over a 900 x 1900 mm bed mat (grid-RxC@HxW for another size)")
    return 0


def _scenarios(args) -> int:
    from appliance.sim.scenes import builtin_descriptions

    for name, description in builtin_descriptions().items():
        print(f"{name:16s} {description}")
    return 0


def _layout(args) -> int:
    from appliance.core.layout_files import layout_to_toml
    from appliance.core.named_layouts import get_layout

    sys.stdout.write(layout_to_toml(get_layout(args.layout)))
    return 0


def _protocol(args) -> int:
    from appliance.core.named_layouts import get_layout
    from appliance.core.protocols import protocol_for, protocol_to_csv
    from appliance.errors import ConfigError

    if args.reach is not None and args.kind not in ("local", "rows"):
        raise ConfigError(f"--reach is for --kind local or rows, not {args.kind}")
    if args.skip and args.kind != "skip":
        raise ConfigError(f"--skip is for --kind skip, not {args.kind}")
    protocol = protocol_for(get_layout(args.layout), args.kind, skip=args.skip, reach=args.reach)
    sys.stdout.write(protocol_to_csv(protocol))
    return 0


def _simulate(args) -> int:
    from appliance.core.fem import build_fem_model
    from appliance.core.forward import simulate
    from appliance.core.frames import frame_to_csv
    from appliance.core.named_layouts import get_layout
    from appliance.core.network import build_network_model, network_for_layout
    from appliance.core.phantoms import conductivity, covered_area_mm2
    from appliance.core.protocols import default_protocol, load_protocol
    from appliance.errors import ModelInputInvalid

    if args.out:
        check_writable(args.out, "--out")
    layout = get_layout(args.layout)
    protocol = load_protocol(args.protocol, layout.n_electrodes) if args.protocol else default_protocol(layout)
    inclusions = [parse_inclusion(text) for text in args.inclusion]
    start = time.perf_counter()
    if args.model == "fem":
        model = build_fem_model(layout, density=args.density)
    else:
        model = build_network_model(network_for_layout(layout, max(1, round(args.density))))
    built = time.perf_counter()
    for inclusion, text in zip(inclusions, args.inclusion):
        if covered_area_mm2(model, conductivity(model, [inclusion])) == 0:
            raise ModelInputInvalid(f"inclusion {text!r} covers no element of the {layout.name} model: it is off the "
                                    "sheet or smaller than an element")
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


def _reconstruct(args) -> int:
    from appliance.core.frames import Frame, check_same_protocol, load_calibration, load_frame
    from appliance.core import ktc
    from appliance.core.model_cache import ModelSetup, cached_model, default_cache_dir, default_setup
    from appliance.core.named_layouts import get_layout
    from appliance.core.reconstruct import build_reconstructor
    from appliance.core.regularisation import NoiseModel
    from appliance.core.render import write_image
    from appliance.errors import ConfigError

    if args.pressure and args.normalise:
        raise ConfigError("--pressure writes kPa; --normalise would rescale them: use one or the other")
    if args.temperature_c is not None and not args.pressure:
        raise ConfigError("--temperature-c corrects to the pressure calibration's temperature; add --pressure")
    check_writable(args.out, "--out", (".csv", ".png"))
    if args.segment:
        check_writable(args.segment, "--segment", (".csv",))
    for option in ("calibration", "pressure"):
        if getattr(args, option):
            check_input(getattr(args, option), f"--{option}")
    layout = get_layout(args.layout)
    frames = []
    for path in (args.reference, args.frame):
        if path.suffix.lower() == ".mat":
            if layout.name != "ktc-32":
                raise ConfigError(f"{path}: MAT files hold KTC2023 tank data; use --layout ktc-32")
            data = ktc.load_ktc(path)
            frames.append(Frame(data.protocol, data.transfer_ohm))
        else:
            frames.append(load_frame(path, layout.n_electrodes))
    reference, frame = frames
    check_same_protocol(frame, reference, f"reference {args.reference}")
    is_ktc = layout.name == "ktc-32"
    setup = ktc.ktc_setup(reference.protocol) if is_ktc else default_setup(layout, reference.protocol)
    iterate = args.iterate or (ktc.ITERATE if is_ktc else "auto")
    options = setup.options
    if args.algorithm:
        options = dataclasses.replace(options, algorithm=args.algorithm)
    if args.noise:
        options = dataclasses.replace(options, noise=NoiseModel(*args.noise))
    pixels = parse_pixels(args.pixels) or setup.pixels
    setup = ModelSetup(layout, reference.protocol, options, args.density or setup.density, pixels,
                       setup.contact_impedance_ohm_m2)
    pressure = None
    volts = frame.volts
    if args.pressure:
        from appliance.cli_calibrate import pressure_calibration_for
        from appliance.core.pressure import temperature_corrected

        pressure = pressure_calibration_for(args.pressure, layout, options.algorithm, pixels)
        iterate = args.iterate or pressure.notes.get("iterate", iterate)      # as the calibration's images were
        volts = temperature_corrected(volts, args.temperature_c, pressure.reference_temperature_c,
                                      pressure.temperature_coefficient_per_c)
    start = time.perf_counter()
    model, loaded = cached_model(setup, args.cache_dir or default_cache_dir(),
                                 lambda step, share: print(f"building the model: {step} ({share:.0%})",
                                                           file=sys.stderr))
    built = time.perf_counter()
    if args.calibration:
        r = model.reconstructor
        sensitivity = load_calibration(args.calibration, reference.protocol, r.grid, reference.volts)
        model.reconstructor = build_reconstructor(r.linear, r.options, r.usable, sensitivity=sensitivity)
    image, info = model.reconstruct(volts, reference.volts, iterate=iterate)
    done = time.perf_counter()
    if pressure is None:
        write_image(args.out, image, args.normalise)
    else:
        from appliance.cli_calibrate import write_pressure_map

        pressure_kpa = pressure.pressure_kpa(image)
        write_pressure_map(args.out, pressure_kpa)
    if args.segment:
        labels = ktc.segment(image)
        args.segment.write_text("\n".join(",".join(str(v) for v in row) for row in labels) + "\n")
    print(f"{layout.name}: {options.algorithm}, {image.shape[0]} x {image.shape[1]} pixels, model "
          f"{'loaded' if loaded else 'built'} in {(built - start) * 1e3:.0f} ms; {info['usable_readings']} of "
          f"{len(reference.protocol)} readings used, {info['iterations']} iterations, reconstructed in "
          f"{(done - built) * 1e3:.0f} ms", file=sys.stderr)
    if pressure is not None:
        from appliance.cli_calibrate import report_pressure

        report_pressure(pressure_kpa, model.reconstructor.grid)
    return 0
