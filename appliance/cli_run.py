"""``appliance run``: the monitor, on the virtual bed when there is no hardware.

It builds (or loads) the reconstruction model, calibrates the virtual mat the
first time, takes the empty-mat reference, puts the scenario's patient on and
prints one line per pressure map, keeping the newest map in the data directory
(``live.png``, ``live.csv`` in kPa) for anyone to look at. Each map goes through
the alert pipeline (regions, dose, turn clock, alarms); alarm and turn events are
printed and, with the alert state, committed to the SQLite store
(``appliance.db``) frame by frame.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

LIVE_FULL_SCALE_MMHG = 100.0      # the live map's colour scale: white at 0, darkest at 100 mmHg and over


def add_parsers(sub) -> None:
    p = sub.add_parser("run", help="run the monitor (the virtual bed when there is no hardware)")
    p.add_argument("--layout", default="grid-8x16", help="mat layout (default grid-8x16, a 900 x 1900 mm bed)")
    p.add_argument("--scenario", default="turn-schedule",
                   help="the virtual patient: a built-in scenario or a scenario .toml file (default turn-schedule)")
    p.add_argument("--frames", type=int, default=None, help="stop after this many maps (default: run until Ctrl-C)")
    p.add_argument("--interval", type=float, default=1.0, help="scene seconds between frames (default 1)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="scene seconds per wall-clock second (default 1, real time; 0 for as fast as it goes)")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where calibrations and the live map are kept (default $APPLIANCE_DATA_DIR or "
                        "~/.local/share/appliance)")
    p.add_argument("--calibration", type=Path, default=None,
                   help="pressure calibration to use (refused unless made for this layout and reconstruction)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated noise")
    p.add_argument("--cache-dir", type=Path, default=None, help="where built models are kept")
    p.set_defaults(run=_run)


def _run(args) -> int:
    from appliance.alerts.pipeline import AlertPipeline, technical_alarms
    from appliance.core.layouts import get_layout
    from appliance.core.model_cache import ModelSetup, cached_model, default_cache_dir
    from appliance.core.pressure import load_pressure_calibration
    from appliance.core.protocols import default_protocol
    from appliance.errors import ConfigError
    from appliance.service.monitor import Monitor
    from appliance.service.virtual_bed import VirtualBedSource, default_data_dir
    from appliance.sim.scenes import load_scene
    from appliance.store import Store

    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    if not args.interval > 0 or args.speed < 0:
        raise ConfigError("--interval must be positive and --speed not negative")
    layout = get_layout(args.layout)
    scene = load_scene(args.scenario)
    protocol = default_protocol(layout)
    data_dir = args.data_dir or default_data_dir()
    data_dir.mkdir(parents=True, exist_ok=True)
    say = _printer()
    say(f"appliance: monitoring a virtual bed ({layout.name}, scenario {args.scenario}); no hardware, no server; "
        f"data in {data_dir}")
    model, _ = cached_model(ModelSetup(layout, protocol), args.cache_dir or default_cache_dir(),
                            lambda step, share: say(f"building the reconstruction model: {step} ({share:.0%})"))
    source = VirtualBedSource(layout, scene, protocol, seed=args.seed, frame_interval_s=args.interval)
    if args.calibration:
        calibration = load_pressure_calibration(args.calibration)
    else:
        path = data_dir / f"pressure-{layout.name}-{model.setup.options.algorithm}.json"
        calibration, made = source.calibration(
            model, path, progress=lambda k, n, load: say(f"calibrating the virtual mat: load {k}/{n}", every=10, k=k))
        say(f"pressure calibration {'made and saved to' if made else 'loaded from'} {path}")
    monitor = Monitor(source.acquire, model, calibration)      # refuses a calibration for another mat
    monitor.take_reference(source.empty_reference())
    pace = _pacer(args.interval / args.speed if args.speed > 0 else 0.0)
    pipeline = AlertPipeline(model.reconstructor.grid)
    store = Store.open(data_dir / "appliance.db")

    def on_map(pressure_map) -> None:
        _show(pressure_map, model.reconstructor.grid, data_dir, len(protocol))
        alerts = pipeline.update(pressure_map, technical_alarms(monitor.conditions))
        events = alerts.turn_events + alerts.alarm_events
        for event in events:
            print(f"  {_event_line(event)}", flush=True)
        store.record_map(pressure_map.time_s, pressure_map.pressure_kpa)
        store.commit_frame(pressure_map.time_s, events, {"alerts": pipeline.state()})

    started = time.perf_counter()
    try:
        made = monitor.run(on_map, frames=args.frames, pace=pace,
                           on_fault=lambda f: say(f"FAULT ({f.consecutive} in a row): {f.message}"))
    except KeyboardInterrupt:
        made = None
    finally:
        store.close()
    elapsed = time.perf_counter() - started
    say(f"stopped{'' if made is None else f' after {made} maps'} in {elapsed:.1f} s; the last map is in "
        f"{data_dir / 'live.png'}")
    return 0


def _show(pressure_map, grid, data_dir: Path, n_readings: int) -> None:
    """One line for the map, and the map itself kept as the newest in ``data_dir``."""
    import numpy as np

    from appliance.core.pressure import KPA_PER_MMHG
    from appliance.core.render import write_png
    from appliance.files import write_atomic

    m = pressure_map
    t = int(round(m.time_s))
    regions = "; ".join(f"{r.peak_mmhg:.0f} mmHg over {r.area_cm2:.0f} cm2 at ({r.x_mm:.0f}, {r.y_mm:.0f}) mm"
                        for r in m.regions[:3])
    print(f"{t // 3600}:{t % 3600 // 60:02d}:{t % 60:02d}  peak {m.peak_kpa:.1f} kPa ({m.peak_kpa / KPA_PER_MMHG:.0f} "
          f"mmHg)  {len(m.regions)} region(s) >= 32 mmHg{': ' + regions if regions else ''}  "
          f"[{m.usable_readings}/{n_readings} readings]", flush=True)
    rows = "\n".join(",".join("nan" if np.isnan(v) else f"{v:.3f}" for v in row) for row in m.pressure_kpa)
    write_atomic(data_dir / "live.csv", rows + "\n")
    write_png(data_dir / "live.png", m.pressure_kpa, vmin=0.0, vmax=LIVE_FULL_SCALE_MMHG * KPA_PER_MMHG,
              palette="sequential", scale=16)


def _event_line(event) -> str:
    """``ALARM raised (medium) pressure:sacrum:3: sustained pressure ...`` or ``TURN repositioned``."""
    if hasattr(event, "alarm_id"):
        who = f" by {event.user}" if event.user else ""
        where = f" to {event.channel}" if event.channel else ""
        return f"ALARM {event.kind}{who}{where} at {event.time_s:.0f} s ({event.priority}) {event.key}: {event.message}"
    return f"TURN {event.kind} at {event.time_s:.0f} s"


def _pacer(period_s: float):
    """A function that sleeps until ``period_s`` after its previous return (no sleep for 0)."""
    state = {"next": None}

    def pace() -> None:
        now = time.monotonic()
        if state["next"] is not None and state["next"] > now:
            time.sleep(state["next"] - now)
        state["next"] = max(now, state["next"] or now) + period_s

    return pace


def _printer():
    def say(text: str, every: int = 1, k: int = 0) -> None:
        if k % every == 0 or k == 1:
            print(text, file=sys.stderr, flush=True)

    return say
