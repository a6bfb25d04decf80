"""The ``calibrate`` commands, and the pressure map that ``reconstruct --pressure`` writes with their result.

``calibrate pressure`` puts known weights on known areas and fits the map from
image to kPa (:mod:`appliance.core.pressure`); ``calibrate sensitivity`` runs
the thesis's procedure, an object on each pixel in turn, for backprojection.
``--source`` says where the frames come from: the virtual bed (loads placed in
the simulation, frames from the whole-frame chain), the emulated board measuring
the virtual bed (the real scan path, slower), or the real board, with the
operator placing each weight when prompted. The procedures are the same for all
three (:mod:`appliance.calibration`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

SENSITIVITY_PRESSURE_KPA = 10.0
MAX_POSITIONS = 20          # 20 x 20 places per load size: beyond it a calibration would run for days
MAX_FRAMES_PER_POSTURE = 100    # PmatData records a posture for 1 to 3.5 min at 1 Hz: its middle half holds no more


def add_parsers(sub) -> None:
    from appliance.cli_args import MAT_MM, numbers, whole_within, within
    from appliance.cli_frontend import MAX_AVERAGE
    from appliance.sim.mechanics import DEFAULT_PARAMETERS

    # the mat model's validity limit, 375 mmHg: beyond the peaks a body lying on a mat exerts
    kpa = within(0.0, DEFAULT_PARAMETERS.max_pressure_kpa, "kPa", above=True)

    p = sub.add_parser("calibrate", help="calibrate the mat: pressure from known loads, or the thesis's sensitivity")
    calibrate = p.add_subparsers(dest="calibrate_command", required=True, metavar="CALIBRATE_COMMAND")

    p = calibrate.add_parser("pressure", help="known weights on known areas, fitted to kPa (for reconstruct "
                                              "--pressure)")
    _source_options(p)
    p.add_argument("--out", type=Path, required=True, help="pressure calibration file (JSON)")
    p.add_argument("--algorithm", default=None,
                   help="the reconstruction it is fitted to: greit, gn-laplace, gn-noser or gn-tikhonov "
                        "(default greit)")
    p.add_argument("--positions", type=whole_within(1, MAX_POSITIONS), default=2, metavar="N",
                   help=f"each load size at N x N places across the mat (default 2, at most {MAX_POSITIONS})")
    p.add_argument("--pressures", type=numbers(kpa), default=None, metavar="P1,P2,...",
                   help="pressures each load is pressed to, kPa (default: the standard set, 2 to 20 kPa)")
    p.add_argument("--averages", type=whole_within(1, MAX_AVERAGE), default=1, metavar="K",
                   help="frames averaged per load (default 1, at most as acquire --average)")
    p.add_argument("--maps", type=Path, default=None, metavar="PMATDATA",
                   help="calibrate from people's pressure maps instead of weights: a PmatData folder (virtual "
                        "source; a bed mat reads bodies through this far better than through weights)")
    p.add_argument("--subjects", default=None, metavar="N1,N2,...", help="with --maps: whose maps")
    p.add_argument("--frames-per-posture", type=whole_within(1, MAX_FRAMES_PER_POSTURE), default=1, metavar="K",
                   help="with --maps: frames taken from each posture's recording (default 1)")
    p.add_argument("--cache-dir", type=Path, default=None, help="where built models are kept")
    p.set_defaults(run=_pressure)

    p = calibrate.add_parser("sensitivity", help="an object on each pixel in turn: the experimental sensitivity "
                                                 "for reconstruct --calibration (thesis eq. 3.4.1)")
    _source_options(p)
    p.add_argument("--out", type=Path, required=True, help="calibration file (CSV)")
    p.add_argument("--side-mm", type=within(0.0, MAT_MM, "mm", above=True), default=None,
                   help="side of the square object (default: one pixel)")
    p.add_argument("--pressure-kpa", type=kpa, default=SENSITIVITY_PRESSURE_KPA,
                   help=f"pressure of the object (default {SENSITIVITY_PRESSURE_KPA:g} kPa)")
    p.set_defaults(run=_sensitivity)


def _source_options(p: argparse.ArgumentParser) -> None:
    from appliance.cli_args import density, seed

    p.add_argument("--layout", required=True, help="layout name or .toml file")
    p.add_argument("--source", default="virtual", choices=["virtual", "emulated", "hardware"],
                   help="virtual bed (default), the emulated board measuring it, or the real board with an "
                        "operator placing the weights")
    p.add_argument("--pixels", default=None, metavar="ROWSxCOLS", help="pixel grid (default 16 on the short side)")
    p.add_argument("--config", type=Path,
                   help="appliance TOML configuration; its [board] table is the board (for the virtual and "
                        "emulated sources, default: the reference board at a current suiting the virtual mat)")
    p.add_argument("--profile", help="board profile: reference, reference-32 or ad5933 (overrides --config)")
    p.add_argument("--density", type=density, default=1.0, help="virtual or emulated: the virtual mat's mesh density")
    p.add_argument("--seed", type=seed, default=0, help="virtual or emulated: the front end's errors and noise")


def _pressure(args) -> int:
    from appliance.calibration import CALIBRATION_PRESSURES_KPA, calibration_loads, pressure_calibration
    from appliance.files import check_writable
    from appliance.core.model_cache import cached_model, default_cache_dir, default_setup
    from appliance.core.named_layouts import get_layout
    from appliance.core.pressure import save_pressure_calibration
    from appliance.errors import ConfigError

    if args.maps and args.source == "hardware":
        raise ConfigError("--maps lays recorded people on the virtual mat; on hardware, calibrate with weights")
    if args.subjects and not args.maps:
        raise ConfigError("--subjects says whose --maps calibrate the mat; add --maps")
    check_writable(args.out, "--out")
    pressures = args.pressures or CALIBRATION_PRESSURES_KPA
    layout = get_layout(args.layout)
    setup = default_setup(layout)
    protocol = setup.protocol
    if args.algorithm:
        setup = dataclasses.replace(setup, options=dataclasses.replace(setup.options, algorithm=args.algorithm))
    if args.pixels:
        setup = dataclasses.replace(setup, pixels=_pixels(args.pixels))
    options = setup.options
    loads = _map_loads(args) if args.maps else \
        calibration_loads(layout, positions=args.positions, pressures_kpa=pressures)
    start = time.perf_counter()
    model, _ = cached_model(setup, args.cache_dir or default_cache_dir(),
                            lambda step, share: print(f"building the model: {step} ({share:.0%})", file=sys.stderr))

    def progress(k, n, load):
        what = f"map {load.name}" if args.maps else \
            f"{load.side_mm:g} mm square at ({load.x_mm:g}, {load.y_mm:g}) mm, {load.pressure_kpa:.1f} kPa"
        print(f"load {k}/{n}: {what}", file=sys.stderr, flush=True)

    with _opened_source(args, layout, protocol) as (acquire, place, stamp):
        calibration = pressure_calibration(acquire, place, model, loads, averages=args.averages, progress=progress,
                                           iterate="never" if options.algorithm == "backprojection" else None)
        calibration = stamp(calibration, model)
    save_pressure_calibration(args.out, calibration)
    curve, flat = calibration.curve, calibration.flat_field
    flat_text = "no flat field" if flat is None else f"flat field {flat.min():.2f} to {flat.max():.2f}"
    print(f"{layout.name}: pressure calibration of {calibration.algorithm} images of {calibration.pixels[0]} x "
          f"{calibration.pixels[1]} pixels from {len(loads)} loads ({args.source}) in "
          f"{time.perf_counter() - start:.0f} s: changes up to {curve.change[-1]:.3g} read 0 to "
          f"{curve.pressure[-1]:.1f} kPa, {flat_text}; written to {args.out}", file=sys.stderr)
    return 0


def _sensitivity(args) -> int:
    from appliance.calibration import sensitivity_calibration
    from appliance.files import check_writable
    from appliance.core.named_layouts import get_layout
    from appliance.core.pixels import pixel_grid
    from appliance.core.protocols import default_protocol

    check_writable(args.out, "--out")
    layout = get_layout(args.layout)
    protocol = default_protocol(layout)
    grid = pixel_grid(layout, *(_pixels(args.pixels) or (None, None)))
    side_mm = min(grid.pixel_mm) if args.side_mm is None else args.side_mm
    start = time.perf_counter()

    def progress(k, n, pixel):
        print(f"pixel {k}/{n}: row {pixel[0]}, column {pixel[1]}", file=sys.stderr, flush=True)

    with _opened_source(args, layout, protocol) as (acquire, place, _):
        rows = sensitivity_calibration(acquire, place, grid, protocol, side_mm, args.pressure_kpa,
                                       progress=progress)
    args.out.write_text(calibration_to_csv(rows), encoding="utf-8")
    print(f"{layout.name}: sensitivity of {grid.n_inside} pixels ({grid.rows} x {grid.cols} grid), a {side_mm:g} mm "
          f"square at {args.pressure_kpa:g} kPa ({args.source}), {len(protocol)} readings each, in "
          f"{time.perf_counter() - start:.0f} s; written to {args.out}", file=sys.stderr)
    return 0


def calibration_to_csv(rows) -> str:
    """The rows of :func:`appliance.calibration.sensitivity_calibration` as the file ``load_calibration`` reads."""
    from appliance.core.frames import FRAME_HEADER

    lines = [",".join(("pixel_row", "pixel_col") + FRAME_HEADER)]
    lines += [f"{r},{c},{a},{b},{m},{n},{v:.9e}" for r, c, a, b, m, n, v in rows]
    return "\n".join(lines) + "\n"


def _pixels(text: str | None) -> tuple[int, int] | None:
    from appliance.cli_args import parse_pixels

    return parse_pixels(text)


def _map_loads(args) -> list:
    """The people's maps ``--maps`` and ``--subjects`` name, as calibration loads."""
    from appliance.errors import ConfigError
    from appliance.sim.recordings import pmat_map_loads

    try:
        subjects = [int(v) for v in args.subjects.split(",")] if args.subjects else []
    except ValueError:
        raise ConfigError(f"--subjects takes subject numbers separated by commas, got {args.subjects!r}") from None
    if not subjects:
        raise ConfigError("--maps needs --subjects: the people whose maps calibrate the mat")
    return pmat_map_loads(args.maps, subjects, frames_per_posture=args.frames_per_posture)


@contextlib.contextmanager
def _opened_source(args, layout, protocol):
    """``(acquire, place, stamp)`` for ``args.source``, ``stamp(calibration, model)`` marking a calibration
    with the virtual mat it was made on; a board is closed when the procedure ends."""
    from appliance.cli_frontend import board_table
    from appliance.sim.loads import empty_mat

    table = board_table(args)
    unstamped = lambda calibration, model: calibration      # noqa: E731 (a real mat's readings are its own)
    if args.source == "hardware":
        sensor, place = _still_mat(layout), _operator_placer()
    else:
        from appliance.drivers.profile import board_profile
        from appliance.service.virtual_bed import VirtualBedSource
        from appliance.sim.frontend import virtual_board

        table = table or virtual_board(layout)      # unless told otherwise, the board that reads such a mat
        source = VirtualBedSource(layout, empty_mat(layout), protocol, seed=args.seed, profile=board_profile(table),
                                  density=args.density)
        place = source.place
        if args.source == "virtual":
            yield source.acquire, place, source.stamped
            return
        table, sensor = {**table, "backend": "emulated"}, (lambda: source.bed)
    with _scan_engine(table, sensor, protocol, args.seed) as engine:
        yield engine.scan, place, unstamped


def _still_mat(layout):
    """The sensor an emulated board measures when the operator, not the simulation, places the weights."""
    def sensor():
        from appliance.drivers.emulated.sensor import ForwardSensor

        return ForwardSensor.of_layout(layout)

    return sensor


@contextlib.contextmanager
def _scan_engine(table: dict, sensor, protocol, seed: int):
    """A scan engine on the board ``table`` describes, as ``acquire`` opens it; closed afterwards."""
    from appliance.drivers.backend import open_board, open_front_end
    from appliance.drivers.scan import ScanEngine

    board, profile = open_board(table, sensor=sensor, seed=seed)
    with board:
        front_end = open_front_end(board, profile)
        try:
            yield ScanEngine(front_end, protocol)
        finally:
            front_end.close()


def _operator_placer():
    """``place(load)`` on the real mat: the operator is told what to put where and confirms with Enter.

    The input closing (EOF) aborts the procedure; the procedure's own clean-up
    then asks for nothing more, so the abort is reported as it happened.
    """
    from appliance.calibration import grams_for
    from appliance.errors import ConfigError

    aborted = False

    def place(load) -> None:
        nonlocal aborted
        if aborted:
            return
        if load is None:
            task = "Clear the mat"
        else:
            task = (f"Put {grams_for(load):.0f} g on the {load.side_mm:g} mm square centred at "
                    f"({load.x_mm:g}, {load.y_mm:g}) mm")
        print(f"{task}, then press Enter", file=sys.stderr, flush=True)
        if not sys.stdin.readline():
            aborted = True
            raise ConfigError(f"calibration aborted: the input ended at {task!r}; nothing was written")

    return place


def pressure_calibration_for(path: Path, layout, algorithm: str, pixels: tuple[int, int] | None):
    """The pressure calibration in ``path``, refused unless it was made for this layout and reconstruction."""
    from appliance.core.pixels import pixel_grid
    from appliance.core.pressure import load_pressure_calibration

    calibration = load_pressure_calibration(path)
    calibration.check_fits(layout, algorithm, pixels or pixel_grid(layout).shape)
    return calibration


def write_pressure_map(path: Path, pressure_kpa) -> None:
    """The map in kPa: CSV as ``reconstruct`` writes images, or a PNG from white (0 kPa) to dark blue (the peak)."""
    if path.suffix.lower() == ".png":
        from appliance.core.render import write_png

        write_png(path, pressure_kpa, vmin=0.0, palette="sequential", scale=16)
    else:
        from appliance.core.render import write_image

        write_image(path, pressure_kpa, False)


def report_pressure(pressure_kpa, grid) -> None:
    """Peak pressure and the regions at or above the capillary closing pressure, on stderr."""
    import numpy as np

    from appliance.core.pressure import KPA_PER_MMHG
    from appliance.core.pressure_map import HIGH_PRESSURE_KPA, HIGH_PRESSURE_MMHG, loaded_regions

    if not np.isfinite(pressure_kpa).any():
        print("no pixel of the map could be read", file=sys.stderr)
        return
    peak = float(np.nanmax(pressure_kpa))
    regions = loaded_regions(pressure_kpa, grid)
    print(f"peak {peak:.1f} kPa ({peak / KPA_PER_MMHG:.0f} mmHg); {len(regions)} region(s) at or above "
          f"{HIGH_PRESSURE_MMHG:g} mmHg ({HIGH_PRESSURE_KPA:.2f} kPa)", file=sys.stderr)
    for region in regions:
        print(f"  peak {region.peak_kpa:.1f} kPa ({region.peak_mmhg:.0f} mmHg), mean {region.mean_kpa:.1f} kPa, "
              f"{region.area_cm2:.1f} cm2 centred at ({region.x_mm:.0f}, {region.y_mm:.0f}) mm", file=sys.stderr)
