"""``appliance run``: the monitor, on the virtual bed when there is no hardware.

It builds (or loads) the reconstruction model, calibrates the virtual mat the
first time, takes the empty-mat reference, puts the scenario's patient on and
prints one line per pressure map. Each map goes through
the alert pipeline (regions, dose, turn clock, alarms); alarm and turn events are
printed and, with the alert state, committed to the SQLite store
(``appliance.db``); ``live.json`` is the web screen's view of the newest map. Nothing
else is written per frame: a Pi's SD card and CPU are spent only on what is read.

``--config`` reads the monitor's TOML file (:mod:`appliance.service.config`);
the options override it. Started again on the same data directory, it resumes
where the store left off. SIGTERM (systemd's stop) ends it after the frame.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path


def add_parsers(sub) -> None:
    from appliance.cli_args import LONGEST_RUN_H, seed, whole_within, within
    from appliance.service.config_sections import FRAME_INTERVAL_RANGE_S, SPEED_RANGE

    p = sub.add_parser("run", help="run the monitor (the virtual bed when there is no hardware)")
    p.add_argument("--config", type=Path, default=None,
                   help="the monitor's TOML configuration (default: none, the virtual bed); the options below "
                        "override it")
    p.add_argument("--check-config", action="store_true", help="check the configuration, print it and exit")
    p.add_argument("--layout", default=None, help="mat layout (default grid-16x32, a 900 x 1900 mm bed)")
    p.add_argument("--scenario", default=None,
                   help="the virtual patient: a built-in scenario or a scenario .toml file (default turn-schedule)")
    most_frames = round(LONGEST_RUN_H * 3600 / FRAME_INTERVAL_RANGE_S[0])     # a year at the shortest interval
    p.add_argument("--frames", type=whole_within(1, most_frames), default=None,
                   help="stop after this many frames (default: run until stopped or the scenario ends)")
    p.add_argument("--interval", type=within(*FRAME_INTERVAL_RANGE_S, "s"), default=None,
                   help="seconds between frames (default 1)")
    p.add_argument("--speed", type=within(*SPEED_RANGE), default=None,
                   help="virtual bed: scene seconds per wall-clock second (default 1, real time; 0 for as fast as "
                        "it goes)")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where the store, calibrations and the live view are kept (default $APPLIANCE_DATA_DIR "
                        "or ~/.local/share/appliance)")
    p.add_argument("--calibration", type=Path, default=None,
                   help="pressure calibration to use (refused unless made for this layout and reconstruction)")
    p.add_argument("--seed", type=seed, default=None, help="seed of the simulated noise")
    p.add_argument("--cache-dir", type=Path, default=None, help="where built models are kept")
    p.add_argument("--screen", metavar="[HOST:]PORT", default=None,
                   help="also serve the nurse's screen (python -m webui) on this port, stopped with the monitor "
                        "(under systemd the screen has its own unit instead)")
    p.set_defaults(run=_run)


SCREEN_NICE = 10
OVERRIDES = {"layout": "layout", "scenario": "scenario", "interval": "frame_interval_s", "speed": "speed",
             "data_dir": "data_dir", "calibration": "calibration", "seed": "seed", "cache_dir": "cache_dir"}


def monitor_config(args, **fixed):
    """The configuration file's settings (or the defaults), with the command line's options over them."""
    import dataclasses

    from appliance.errors import ConfigError
    from appliance.service.config import config_from_mapping, load_config

    config = load_config(args.config) if args.config else config_from_mapping({})
    changes = {field: getattr(args, option) for option, field in OVERRIDES.items()
               if getattr(args, option, None) is not None}
    changes.update(fixed)
    if changes.get("scenario") is not None and config.source != "virtual":
        raise ConfigError("--scenario is for the virtual bed, but the configuration's source is a board")
    config = dataclasses.replace(config, **changes)
    _check_named(config)
    return config


def _check_named(config) -> None:
    """The layout, scenario, calibration and data folder the configuration names, refused before the model is
    built (minutes on a bed mat) and by --check-config, which would otherwise pass a typo."""
    from appliance.cli_args import check_input
    from appliance.core.named_layouts import get_layout
    from appliance.errors import ConfigError

    get_layout(config.layout)
    if config.source == "virtual":
        from appliance.sim.scenes import load_scene

        load_scene(config.scenario)
    if config.calibration is not None:
        check_input(Path(config.calibration), "calibration")
    for what, folder in (("data folder", config.data_dir), ("cache folder", config.cache_dir)):
        if folder is not None and Path(folder).exists() and not Path(folder).is_dir():
            raise ConfigError(f"{what} {folder} is a file, not a folder")


def _run(args) -> int:
    import signal

    from appliance.service.assemble import assemble
    from appliance.service.daemon import MonitorDaemon

    if args.screen:
        listen_address(args.screen, "--screen")
    config = monitor_config(args)
    if args.check_config:
        print(config)
        return 0
    say = _printer()
    screen = _start_screen(args.screen, config, say) if args.screen else None
    where = (f"a virtual bed ({config.layout}, scenario {config.scenario}); no hardware"
             if config.source == "virtual" else f"the front end board ({config.layout})")
    say(f"appliance: monitoring {where}; bed {config.bed_id}")
    daemon: MonitorDaemon
    try:
        daemon = assemble(config, say=say, on_event=lambda e: print(f"  {_event_line(e)}", flush=True),
                          on_map=lambda m: _show(m, len(daemon.model.setup.protocol)))
        signal.signal(signal.SIGTERM, daemon.request_stop)
        started = time.perf_counter()
        try:
            done = daemon.run(args.frames)
        except KeyboardInterrupt:
            done = None
        finally:
            daemon.close()
    finally:
        if screen is not None:
            screen.terminate()
            screen.wait(timeout=10)
    elapsed = time.perf_counter() - started
    say(f"stopped{'' if done is None else f' after {done} frames'} in {elapsed:.1f} s; data in "
        f"{daemon.config.data_dir}")
    return 0


def _start_screen(where: str, config, say):
    """``python -m webui`` on the monitor's data directory, as a child process below the monitor's priority, so
    many open screens never take the monitor's CPU."""
    import os
    import subprocess
    import sys

    from appliance.service.config_sections import default_data_dir

    host, port = listen_address(where, "--screen")
    data_dir = config.data_dir or default_data_dir()
    screen = subprocess.Popen([sys.executable, "-m", "webui", "--data-dir", str(data_dir), "--host", host,
                               "--port", str(port)], preexec_fn=lambda: os.nice(SCREEN_NICE))
    say(f"the nurse's screen: http://{host}:{port}/ (the first visit sets up the admin account)")
    return screen


def listen_address(where: str, option: str) -> tuple[str, int]:
    """(host, port) from ``[HOST:]PORT`` (host 127.0.0.1 by default); a ConfigError naming ``option`` if bad."""
    from appliance.errors import ConfigError

    host, _, port = where.rpartition(":")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"{option} takes [HOST:]PORT with a port from 1 to 65535, got {where!r}")
    return host or "127.0.0.1", int(port)


def _show(pressure_map, n_readings: int) -> None:
    """One line for the map."""
    from appliance.core.pressure import KPA_PER_MMHG

    m = pressure_map
    t = round(m.time_s)
    regions = "; ".join(f"{r.peak_mmhg:.0f} mmHg over {r.area_cm2:.0f} cm2 at ({r.x_mm:.0f}, {r.y_mm:.0f}) mm"
                        for r in m.regions[:3])
    print(f"{t // 3600}:{t % 3600 // 60:02d}:{t % 60:02d}  peak {m.peak_kpa:.1f} kPa ({m.peak_kpa / KPA_PER_MMHG:.0f} "
          f"mmHg)  {len(m.regions)} region(s) >= 32 mmHg{': ' + regions if regions else ''}  "
          f"[{m.usable_readings}/{n_readings} readings]", flush=True)


def _event_line(event) -> str:
    """``ALARM raised (medium) pressure:sacrum:3: sustained pressure ...`` or ``TURN repositioned at 60 s``."""
    if event.type == "alarm":
        who = f" by {event.user}" if event.user else ""
        where = f" to {event.channel}" if event.channel else ""
        return (f"ALARM {event.kind}{who}{where} at {event.time_s:.0f} s ({event.priority}) {event.key}: "
                f"{event.message}")
    return f"TURN {event.kind} at {event.time_s:.0f} s"


def _printer():
    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    return say
