"""The operator functions that use the front end (thesis 3.3): ``acquire`` and ``selftest``; and ``wiring``,
the tables a front end is built and checked by.

``--emulated`` runs them on the emulated board measuring the layout's mat (with
``--inclusion`` objects on it); without it they open the real board named by
``--config`` (its ``[board]`` table) or the reference profile.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

MAX_AVERAGE = 1000          # sets averaged into one frame (the thesis averages 30)
MAX_SERIES = 60             # sets in one series: watching for longer is the monitor's (appliance run)


def add_parsers(sub) -> None:
    from appliance.cli_args import whole_within, within
    from appliance.drivers.boards import HOST_BOARDS
    from appliance.service.config_sections import FRAME_INTERVAL_RANGE_S

    p = sub.add_parser("acquire", help="acquire frames of readings from the front end")
    _board_options(p)
    p.add_argument("--protocol", type=Path, help="protocol CSV file (default: the layout's default protocol)")
    p.add_argument("--average", type=whole_within(1, MAX_AVERAGE), default=1, metavar="N",
                   help=f"average N complete sets (thesis: 30; 1 to {MAX_AVERAGE})")
    p.add_argument("--series", type=whole_within(1, MAX_SERIES), default=1, metavar="N",
                   help=f"acquire N sets (1 to {MAX_SERIES})")
    p.add_argument("--interval", type=within(0.0, FRAME_INTERVAL_RANGE_S[1], "s"), default=1.0, metavar="S",
                   help="seconds between sets of a series, at most the monitor's longest frame interval")
    p.add_argument("--order", default="optimised", choices=["optimised", "protocol"],
                   help="reading order: grouped by drive, rising level (default), or as the protocol lists them")
    p.add_argument("--out", type=Path, required=True,
                   help="frame file (CSV); a series writes NAME-001.csv, ...; each gets a .quality.csv beside it")
    p.set_defaults(run=_acquire)

    p = sub.add_parser("selftest", help="check every chip, the signal path and each electrode's contact")
    _board_options(p)
    p.add_argument("--check", action="store_true",
                   help="only hold the profile against a host board (names, pins, SPI modes, enabled buses); "
                        "no hardware is touched")
    p.add_argument("--board", choices=sorted(HOST_BOARDS),
                   help="with --check: the host board (default: every board the profile claims)")
    p.set_defaults(run=_selftest)

    p = sub.add_parser("wiring", help="print a profile's wiring (chip, bus, BCM GPIO, header pin, line name) and "
                                      "its analogue rails, as markdown")
    p.add_argument("--config", type=Path, help="appliance TOML configuration; its [board] table describes the board")
    p.add_argument("--profile", help="a built-in profile (overrides --config); default: every built-in profile")
    p.add_argument("--out", type=Path, help="write the tables to this .md file instead of printing them")
    p.set_defaults(run=_wiring)


def _board_options(p: argparse.ArgumentParser) -> None:
    from appliance.cli_args import seed

    p.add_argument("--layout", default="grid-4x4", help="layout name or .toml file (default grid-4x4)")
    p.add_argument("--emulated", action="store_true", help="use the emulated front end instead of the real board")
    p.add_argument("--config", type=Path, help="appliance TOML configuration; its [board] table describes the board")
    p.add_argument("--profile", help="board profile: reference, reference-32 or ad5933 (overrides --config)")
    p.add_argument("--inclusion", action="append", default=[], metavar="SHAPE:X,Y,W,H,CONTRAST",
                   help="emulated mat only: an object on it, as for simulate; repeatable")
    p.add_argument("--seed", type=seed, default=0, help="emulated board only: its component errors and noise")


def board_table(args) -> dict:
    """The ``[board]`` table of ``--config`` (empty without one), its profile overridden by ``--profile``."""
    from appliance.drivers.profile import board_table_from_file
    from appliance.service.config import load_config

    if args.config:
        load_config(args.config)        # the whole file checked: a typo elsewhere in it is refused, not ignored
    table = board_table_from_file(args.config) if args.config else {}
    if args.profile:
        table["profile"] = args.profile
    return table


def _open(args):
    """The layout, the board and its front end the options ask for."""
    from appliance.cli_args import parse_inclusion
    from appliance.core.named_layouts import get_layout
    from appliance.drivers.backend import open_board, open_front_end
    from appliance.errors import ConfigError

    layout = get_layout(args.layout)
    table = board_table(args)
    if args.emulated:
        table["backend"] = "emulated"
    elif args.inclusion:
        raise ConfigError("--inclusion places objects on the emulated mat; add --emulated")
    inclusions = [parse_inclusion(text) for text in args.inclusion]

    def sensor():
        from appliance.drivers.emulated.sensor import ForwardSensor

        return ForwardSensor.of_layout(layout, inclusions=inclusions)

    board, profile = open_board(table, sensor=sensor, seed=args.seed)
    try:
        front_end = open_front_end(board, profile)
    except BaseException:
        board.close()
        raise
    kind = "emulated" if args.emulated or type(board).__name__ == "EmulatedBoard" else "hardware"
    return layout, board, profile, front_end, kind


def _acquire(args) -> int:
    from appliance.files import check_writable
    from appliance.core.protocols import default_protocol, load_protocol
    from appliance.drivers.recording import series_paths, write_frame
    from appliance.drivers.scan import ScanEngine, average_frames

    check_writable(args.out, "--out", (".csv",))
    layout, board, profile, front_end, kind = _open(args)
    protocol = load_protocol(args.protocol, layout.n_electrodes) if args.protocol else default_protocol(layout)
    paths = series_paths(args.out, args.series)
    engine = ScanEngine(front_end, protocol, order=args.order, progress=_progress)
    troubled = False
    with board:
        try:
            next_start = board.clock.monotonic()
            for k, path in enumerate(paths, start=1):
                board.clock.sleep(max(0.0, next_start - board.clock.monotonic()))
                next_start = board.clock.monotonic() + args.interval
                frame = average_frames([engine.scan() for _ in range(args.average)])
                write_frame(path, frame)
                troubled |= bool(frame.conditions)
                _report(k, len(paths), path, frame, kind, profile.name)
        finally:
            front_end.close()
    return 1 if troubled else 0


def _progress(done: int, total: int) -> None:
    if sys.stderr.isatty() and (done == total or done % max(1, total // 20) == 0):
        print(f"\r  {done}/{total} readings", end="\n" if done == total else "", file=sys.stderr, flush=True)


def _report(k: int, n: int, path: Path, frame, kind: str, profile: str) -> None:
    usable = int(frame.usable.sum())
    clock = "emulated board time" if kind == "emulated" else "measured"
    print(f"set {k}/{n}: {path}: {usable} of {len(frame.protocol)} readings usable, {frame.sets} set(s) averaged, "
          f"{frame.duration_s:.2f} s ({clock}, {profile} profile), {frame.drive_current_a * 1e3:.2f} mA",
          file=sys.stderr)
    for condition in frame.conditions:
        print(f"  technical condition: {condition}", file=sys.stderr)


def _selftest(args) -> int:
    from appliance.drivers.selftest import run_self_test
    from appliance.errors import ConfigError

    if args.check:
        return _check_board(args)
    if args.board:
        raise ConfigError("--board names the host for --check; a self-test runs on the board it finds")
    layout, board, profile, front_end, kind = _open(args)
    with board:
        try:
            report = run_self_test(front_end, layout.n_electrodes)
        finally:
            front_end.close()
    print(f"self-test of the {profile.name} front end ({kind}), {layout.name} layout")
    print(report.text())
    return 0 if report.passed else 1


def _check_board(args) -> int:
    """Hold the profile against ``--board`` or each board it claims; a mismatch is a ConfigError (status 2)."""
    from appliance.drivers.board_check import check_profile
    from appliance.drivers.boards import HOST_BOARDS, SYSTEMS
    from appliance.drivers.profile import board_profile
    from appliance.errors import ConfigError

    profile = board_profile(board_table(args))
    hosts = [args.board] if args.board else list(profile.boards)
    if not hosts:
        raise ConfigError(f"profile {profile.name} claims no board; name one with --board")
    kernel = SYSTEMS[profile.system].kernel
    for name in hosts:
        host = HOST_BOARDS[name]
        check_profile(profile, host)
        unverified = "" if host.names(kernel) else " (its line names are not verified: only GPIOn names were placed)"
        print(f"profile {profile.name} fits {host.name} ({host.model}) running {profile.system}{unverified}")
    return 0


def _wiring(args) -> int:
    from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
    from appliance.drivers.wiring import wiring_markdown
    from appliance.files import check_writable, write_atomic

    if args.out:
        check_writable(args.out, "--out", (".md",))
    if args.config or args.profile:
        text = wiring_markdown(board_profile(board_table(args)))
    else:
        text = "\n".join(wiring_markdown(board_profile({"profile": name})) for name in BUILTIN_PROFILES)
    if args.out:
        write_atomic(args.out, text)
    else:
        print(text, end="")
    return 0
