"""The ``sim`` commands: the virtual bed's models run from the command line.

``appliance sim load-test`` repeats the thesis's load test (chapter 6.3) on the
simulated mat and prints one CSV row per pressure on stdout.

``appliance sim run`` replays a scenario through the whole monitor (the same
daemon ``appliance run`` starts) on a simulated clock, as fast as the machine
goes, and writes every event as one JSON object per line::

    {"time_s": 29400.0, "type": "alarm", "kind": "raised", "priority": "medium",
     "category": "clinical", "key": "pressure:sacrum", "site": "sacrum", "posture": "supine",
     "x_mm": 861.3, "y_mm": 452.5, "alarm_id": 1, "message": "...", "user": null, "channel": null,
     "patient": null}

``--acknowledge-after-min`` plays a nurse who acknowledges each alarm that long
after it is raised, so the record shows acknowledgements and what they end.

``appliance sim replay`` feeds a scenario's true maps (its own pressure field
averaged over the monitor's pixels, :mod:`appliance.sim.true_maps`) straight into
the alert layer, with no mat and no reconstruction, and writes the same records:
the alert logic checked on true maps, e.g. recorded PmatData nights.

``appliance sim map`` puts pressure maps (CSV in mmHg) on the virtual bed and
writes the maps the appliance reconstructs from them (:mod:`appliance.cli_map`).
"""

from __future__ import annotations

import sys
from pathlib import Path


def add_parsers(sub) -> None:
    from appliance.cli_args import LONGEST_RUN_H, density, numbers, seed, within
    from appliance.service.config_sections import FRAME_INTERVAL_RANGE_S
    from appliance.sim.load_test import AREA_RANGE_CM2
    from appliance.sim.mechanics import DEFAULT_PARAMETERS, TEMPERATURE_RANGE_C

    hours = within(0.0, LONGEST_RUN_H, "h", above=True)
    interval = within(*FRAME_INTERVAL_RANGE_S, "s")         # the configuration's frame_interval_s, which it overrides

    p = sub.add_parser("sim", help="simulate the sensor mat (the virtual bed)")
    sim = p.add_subparsers(dest="sim_command", required=True, metavar="SIM_COMMAND")
    p = sim.add_parser("load-test", help="a centred square load stepped through pressures, as thesis chapter 6")
    p.add_argument("--layout", default="grid-4x4", help="layout name or .toml file (default grid-4x4)")
    p.add_argument("--area-cm2", required=True, type=within(*AREA_RANGE_CM2, "cm2"), help="load area, 1 to 36 cm2")
    p.add_argument("--pressures", required=True, metavar="P1,P2,...",
                   type=numbers(within(0.0, DEFAULT_PARAMETERS.max_pressure_kpa, "kPa")),
                   help="pressures in kPa up to the mat model's validity limit, applied in this order (the mat "
                        "remembers the previous one)")
    p.add_argument("--density", type=density, default=1.0, help="FEM mesh density")
    low_c, high_c = TEMPERATURE_RANGE_C
    p.add_argument("--temperature-c", type=within(low_c, high_c, "C"), default=20.0,
                   help="liquid temperature at the start")
    p.add_argument("--drift-c-per-step", type=within(low_c - high_c, high_c - low_c, "C"), default=None,
                   help="warming of the liquid between steps, C (default: the thesis's, fitted; 0 for none); a step "
                        "cannot cross more than the mat model's whole temperature range")
    p.set_defaults(run=_load_test)

    p = sim.add_parser("run", help="replay a scenario through the whole monitor on a simulated clock, events to "
                                   "JSON lines")
    p.add_argument("--scenario", required=True, help="a built-in scenario's name or a scenario .toml file")
    p.add_argument("--hours", required=True, type=hours, help="simulated hours to run (within the scenario)")
    p.add_argument("--out", required=True, type=Path, help="the event record (JSON lines)")
    p.add_argument("--interval", type=interval, default=60.0,
                   help="simulated seconds between frames (default 60: one map a minute)")
    p.add_argument("--config", type=Path, default=None,
                   help="the monitor's TOML configuration (alert settings, layout); its source must be virtual")
    p.add_argument("--layout", default=None, help="mat layout (default grid-16x32)")
    p.add_argument("--seed", type=seed, default=None, help="seed of the simulated noise")
    p.add_argument("--acknowledge-after-min", type=within(0.0, 24 * 60, "min"), default=None, metavar="M",
                   help="a simulated nurse acknowledges each alarm M minutes after it is raised (a day at most: "
                        "an alarm left longer was missed, not answered)")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where the run's store is kept (default: a fresh temporary folder, removed afterwards)")
    p.add_argument("--cache-dir", type=Path, default=None, help="where built models are kept")
    p.set_defaults(run=_run)

    p = sim.add_parser("replay", help="a scenario's true maps straight into the alert layer (no mat, no "
                                      "reconstruction), events to JSON lines")
    p.add_argument("--scenario", required=True, help="a built-in scenario's name or a scenario .toml file")
    p.add_argument("--hours", type=hours, default=None, help="simulated hours to replay (default: all of it)")
    p.add_argument("--out", required=True, type=Path, help="the event record (JSON lines)")
    p.add_argument("--interval", type=interval, default=60.0, help="simulated seconds between maps (default 60)")
    p.add_argument("--config", type=Path, default=None, help="the monitor's TOML configuration (alert settings)")
    p.add_argument("--layout", default=None, help="mat layout whose pixels the maps are averaged over "
                                                  "(default grid-16x32)")
    p.set_defaults(run=_replay)

    from appliance.cli_map import add_parser as add_map_parser

    add_map_parser(sim)


def _load_test(args) -> int:
    from appliance.sim.load_test import THESIS_DRIFT_C_PER_STEP, load_test

    drift = THESIS_DRIFT_C_PER_STEP if args.drift_c_per_step is None else args.drift_c_per_step
    rows = load_test(args.area_cm2, args.pressures, layout=args.layout, density=args.density,
                     temperature_c=args.temperature_c, drift_c_per_step=drift)
    lines = ["pressure_kpa,visibility,dv_over_v,deformation_mm"]
    lines += [f"{r.pressure_kpa:g},{r.visibility:.6g},{r.dv_over_v:.6g},{r.deformation_mm:.6g}" for r in rows]
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def _run(args) -> int:
    import json
    import tempfile
    import time
    from collections import Counter

    from appliance.cli_run import monitor_config
    from appliance.errors import ConfigError
    from appliance.service.assemble import assemble
    from appliance.sim.scenes import load_scene

    _check_events_out(args.out)
    scene = load_scene(args.scenario)
    if args.hours * 3600 > scene.duration_s:
        raise ConfigError(f"scenario {args.scenario} lasts {scene.duration_s / 3600:g} h; --hours {args.hours:g} "
                          "is longer")
    args.speed = 0.0
    with tempfile.TemporaryDirectory(prefix="appliance-sim-") as scratch:
        config = monitor_config(args, data_dir=args.data_dir or Path(scratch))
        if config.source != "virtual":
            raise ConfigError("sim run needs the virtual bed: the configuration's source is a board")
        frames = int(args.hours * 3600 / args.interval) + 1
        counts: Counter[tuple[str, str]] = Counter()
        pending: list[tuple[float, int]] = []
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with args.out.open("w", encoding="utf-8") as out:
            def record(event) -> None:
                out.write(json.dumps(event.to_dict()) + "\n")
                counts[(event.type, event.kind)] += 1
                if event.kind == "raised" and args.acknowledge_after_min is not None:
                    pending.append((event.time_s + 60 * args.acknowledge_after_min, event.alarm_id))

            def nurse(pressure_map) -> None:
                """Acknowledge, at the next frame, each alarm whose response time has come by then."""
                due = pressure_map.time_s + config.frame_interval_s
                for item in [p for p in pending if p[0] <= due]:
                    pending.remove(item)
                    daemon.acknowledge(item[1], "simulated-nurse")

            def say(text):
                print(text, file=sys.stderr, flush=True)

            daemon = assemble(config, say=say, on_event=record, on_map=nurse, live=False)
            started = time.perf_counter()
            try:
                done = daemon.run(frames)
            finally:
                daemon.close()
    elapsed = time.perf_counter() - started
    summary = ", ".join(f"{n} {kind} {type_}" for (type_, kind), n in sorted(counts.items())) or "no events"
    simulated_h = max(done - 1, 0) * args.interval / 3600
    print(f"{args.scenario}: {done} frames ({simulated_h:g} simulated h) in {elapsed:.1f} s "
          f"({done / max(elapsed, 1e-9):.0f} frames/s); {summary}; written to {args.out}", file=sys.stderr)
    return 0


def _replay(args) -> int:
    import json

    import numpy as np

    from appliance.alerts.pipeline import AlertPipeline
    from appliance.cli_run import monitor_config
    from appliance.core.named_layouts import get_layout
    from appliance.core.pixels import pixel_grid
    from appliance.errors import ConfigError
    from appliance.sim.scenes import load_scene
    from appliance.sim.true_maps import true_map

    _check_events_out(args.out)
    scene = load_scene(args.scenario)
    end_s = scene.duration_s if args.hours is None else args.hours * 3600
    if end_s > scene.duration_s:
        raise ConfigError(f"scenario {args.scenario} lasts {scene.duration_s / 3600:g} h; --hours {args.hours:g} "
                          "is longer")
    config = monitor_config(args, data_dir=Path("."))
    grid = pixel_grid(get_layout(config.layout))
    pipeline = AlertPipeline(grid, config.alerts)
    times = np.arange(0.0, end_s + 1e-9, args.interval)
    written = 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", encoding="utf-8") as out:
        for t in times:
            frame = pipeline.update(true_map(scene, min(float(t), scene.duration_s - 1e-6), grid))
            for event in frame.turn_events + frame.alarm_events:
                out.write(json.dumps(pipeline.record(event).to_dict()) + "\n")
                written += 1
    print(f"{args.scenario}: {len(times)} true maps ({(len(times) - 1) * args.interval / 3600:g} h) on "
          f"{config.layout}; {written} events written to {args.out}", file=sys.stderr)
    return 0


def _check_events_out(path: Path) -> None:
    """The event record's path refused before the run if it is a folder or its folder cannot be made."""
    from appliance.errors import ConfigError

    if path.is_dir():
        raise ConfigError(f"--out {path} is a folder, not a file")
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"--out {path}: {parent} is a file, not a folder")
