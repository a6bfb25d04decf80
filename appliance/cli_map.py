"""``appliance sim map``: pressure maps put on the virtual bed, and the maps the appliance reconstructs from them.

Each input map (CSV in mmHg, :mod:`appliance.sim.map_files`) is placed centred on
the mat with its force kept (:mod:`appliance.sim.map_scenes`), pressed into the
mat's mechanics, read by the emulated front end against the empty mat's reference,
reconstructed and calibrated to pressure by the monitor's own chain
(:class:`~appliance.service.monitor.Monitor`), and written in mmHg on the
reconstruction's pixel grid, which covers the whole mat, turned to the input's
orientation (head end at row 0, column 0 at the mat's left edge). The model and the
calibration are made once for all the maps of a call: the virtual mat's own
calibration, made by the monitor's procedure and kept where the monitor keeps it,
unless ``--calibration`` names one. The mat is emptied between two maps, so each is
laid on a mat at rest and its result does not hang on the maps before it.

Everything given is checked before anything is built or written; each output is
written whole when its map is done (an existing file is replaced, never left
half-written), so a failure later loses none of the maps already written.
"""

from __future__ import annotations

import sys
from pathlib import Path

from appliance.errors import ConfigError


def add_parser(sim) -> None:
    from appliance.cli_args import seed

    p = sim.add_parser("map", help="put pressure maps (CSV, mmHg) on the virtual bed and write the maps the appliance "
                                   "reconstructs from them")
    p.add_argument("--map", dest="maps", action="append", default=[], type=Path, metavar="IN.csv",
                   help="a pressure map: CSV of mmHg, head end at row 0, no header ('#' comment lines allowed); "
                        "repeatable")
    p.add_argument("--pitch-mm", dest="pitches", action="append", default=[], metavar="MM",
                   help="the maps' sensel pitch in mm, 1 to 100: once for all, or once per --map in their order")
    p.add_argument("--out", dest="outs", action="append", default=[], type=Path, metavar="OUT",
                   help="where each --map's reconstruction goes, in their order: .csv (mmHg on the pixel grid) "
                        "or .png")
    p.add_argument("--layout", default=None, help="mat layout (default: the monitor's, grid-16x32)")
    p.add_argument("--calibration", type=Path, default=None,
                   help="pressure calibration to use (default: the virtual mat's own, made once and kept with the "
                        "models)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the simulated noise")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="where built models and the virtual mat's calibration are kept")
    p.set_defaults(run=_map)


def _map(args) -> int:
    from appliance.cli_calibrate import pressure_calibration_for
    from appliance.core.model_cache import cached_model, default_cache_dir, default_setup
    from appliance.core.named_layouts import get_layout
    from appliance.service.config_sections import MonitorConfig
    from appliance.sim.map_files import write_map_mmhg
    from appliance.sim.map_scenes import load_map, place_map, scene_grid

    pitches, outs = _checked_arguments(args)
    layout = get_layout(args.layout or MonitorConfig().layout)
    grid = scene_grid(layout)
    placed = [place_map(load_map(path), pitch, grid, f"pressure map {path}") for path, pitch in zip(args.maps, pitches)]
    setup = default_setup(layout)                                       # the monitor's model of the mat
    calibration = None if args.calibration is None else \
        pressure_calibration_for(args.calibration, layout, setup.options.algorithm, setup.pixels)
    cache = args.cache_dir or default_cache_dir()
    model, _ = cached_model(setup, cache,
                            lambda step, share: _say(f"building the reconstruction model: {step} ({share:.0%})"))
    bed = _MapBed(layout, model, calibration, cache, args.seed)
    for item, out in zip(placed, outs):
        mmhg, conditions = bed.measure(item)
        write_map_mmhg(out, mmhg)
        print(_summary(item, mmhg, grid, conditions, layout.name, out), flush=True)
    return 0


class _MapBed:
    """The virtual bed read through the monitor's chain: a placed map in, the monitor's map of it out (mmHg)."""

    def __init__(self, layout, model, calibration, cache: Path, seed: int):
        from appliance.service.assemble import virtual_calibration_path
        from appliance.service.monitor import Monitor
        from appliance.service.virtual_bed import VirtualBedSource
        from appliance.sim.loads import empty_mat

        self.source = VirtualBedSource(layout, empty_mat(layout), model.setup.protocol, seed=seed)
        if calibration is None:
            path = virtual_calibration_path(cache, model)
            calibration, made = self.source.calibration(
                model, path, progress=lambda k, n, load: _say(f"calibrating the virtual mat: load {k}/{n}")
                if k % 10 == 1 else None)
            _say(f"pressure calibration {'made and saved to' if made else 'loaded from'} {path}")
        self.monitor = Monitor(self.source.acquire, model, calibration)
        self.monitor.take_reference(self.source.empty_reference())
        self.maps = 0

    def measure(self, placed) -> tuple:
        """The monitor's map of ``placed`` (mmHg, in the map's orientation) and the frame's technical conditions."""
        from appliance.core.pressure import KPA_PER_MMHG
        from appliance.sim.field import PressureField
        from appliance.sim.loads import StaticScene

        bed = self.source.bed
        if self.maps:
            self.source.place(None)
            self.source.acquire()               # the last map lifted off: the mat back at rest
        field = PressureField(placed.kpa, placed.grid.pitch_mm)
        bed.set_scene(StaticScene(field))
        pressure_map = self.monitor.next_map()
        self.maps += 1
        mmhg = pressure_map.pressure_kpa / KPA_PER_MMHG
        turned = bed.field_at(0.0).pressure_kpa.shape != field.pressure_kpa.shape     # the bed turned the map
        return (mmhg.T if turned else mmhg), self.monitor.conditions


def _checked_arguments(args) -> tuple[list[float], list[Path]]:
    """The pitch of each map and the checked outputs; any missing, mismatched or unusable argument refused."""
    from appliance.sim.map_files import check_output_path, check_pitch_mm

    if not args.maps:
        raise ConfigError("give at least one --map (a CSV of pressures in mmHg)")
    if not args.pitches:
        raise ConfigError("--pitch-mm is missing: give the maps' sensel pitch in mm (1 to 100)")
    if len(args.pitches) not in (1, len(args.maps)):
        raise ConfigError(f"give one --pitch-mm for all the maps or one per --map: {len(args.maps)} maps, "
                          f"{len(args.pitches)} pitches")
    if len(args.outs) != len(args.maps):
        raise ConfigError(f"give one --out per --map, in their order: {len(args.maps)} maps, {len(args.outs)} outputs")
    pitches = []
    for text in args.pitches:
        try:
            value = float(text)
        except ValueError:
            raise ConfigError(f"--pitch-mm must be a number of mm, got {text!r}") from None
        pitches.append(check_pitch_mm(value, "--pitch-mm"))
    pitches = pitches * len(args.maps) if len(pitches) == 1 else pitches
    inputs = {path.resolve() for path in args.maps}
    seen = set()
    for out in args.outs:
        check_output_path(out)
        if out.resolve() in inputs:
            raise ConfigError(f"--out {out} is one of the input maps: it would be overwritten")
        if out.resolve() in seen:
            raise ConfigError(f"--out {out} is given twice: each map needs its own output")
        seen.add(out.resolve())
    return pitches, args.outs


def _summary(item, mmhg, grid, conditions, layout_name: str, out: Path) -> str:
    """One line: the map, what fell off the mat, the peak in and out and where each load is centred."""
    import numpy as np

    rows, cols = item.mmhg.shape
    x0, y0 = item.offset_mm()
    given = _peak_and_centre(item.mmhg, x0 + (np.arange(cols) + 0.5) * item.pitch_mm,
                             y0 + (np.arange(rows) + 0.5) * item.pitch_mm)
    made = _peak_and_centre(mmhg, (np.arange(mmhg.shape[1]) + 0.5) * grid.width_mm / mmhg.shape[1],
                            (np.arange(mmhg.shape[0]) + 0.5) * grid.height_mm / mmhg.shape[0])
    share = item.share_off_mat
    lost = "all on the mat" if share == 0 else \
        f"{'less than 0.1%' if share < 0.0005 else f'{share:.1%}'} of its force off the mat"
    notes = "".join(f"; {c}" for c in conditions)
    return (f"{item.source} ({rows} x {cols} sensels of {item.pitch_mm:g} mm, {lost}): peak {given} in, {made} out "
            f"on {layout_name}{notes}; written to {out}")


def _peak_and_centre(mmhg, xs, ys) -> str:
    """The map's peak, and the pressure-weighted centre (mm on the mat) of the region around it down to
    FOOTPRINT_SHARE of it, as the monitor finds a load on a blurred map."""
    import numpy as np
    from scipy import ndimage

    from appliance.core.pressure_map import FOOTPRINT_SHARE

    values = np.nan_to_num(np.asarray(mmhg, dtype=float), nan=0.0)
    peak = float(values.max())
    if peak <= 0:
        return "0 mmHg"
    labels, _ = ndimage.label(values >= FOOTPRINT_SHARE * peak)
    weights = np.where(labels == labels[np.unravel_index(values.argmax(), values.shape)], values, 0.0)
    x, y = weights.sum(axis=0) @ xs / weights.sum(), weights.sum(axis=1) @ ys / weights.sum()
    return f"{peak:.0f} mmHg centred at ({x:.0f}, {y:.0f}) mm"


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
