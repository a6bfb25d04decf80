"""The clinical engineer's functions on the running monitor: the thesis's operator functions, as daemon commands.

The web screen is another process and the daemon owns the front end, so each
function is a command queued in the store and run by the daemon between frames
(monitoring pauses meanwhile; long ones report progress, which also feeds the
systemd watchdog). They reuse the bench tools: frames are written in the frame
file format every reader of frames takes, the contact check and self-test are
the drivers' own, the pressure calibration is the procedure of ``appliance
calibrate pressure``, and a model is built as the model cache builds it.

What they write goes to ``<data_dir>/engineering/`` under a UTC time stamp, and
every file name a command carries must be a plain name in that folder. Nothing
written is taken into use by itself: a new calibration replaces the running one
only through ``load``, after it is checked against the running mat and
reconstruction.

Arguments are checked once for both sides, by
:mod:`appliance.service.engineering_tasks`: the screen refuses bad input before
queueing, and the daemon refuses it again, since the store accepts whatever any
process queues.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from appliance.calibration import calibration_loads, pressure_calibration
from appliance.core.frames import frame_to_csv
from appliance.core.model_cache import build_model, default_cache_dir, model_path, save_model
from appliance.core.pressure import (KPA_PER_MMHG, check_plausible, load_pressure_calibration,
                                     save_pressure_calibration)
from appliance.core.render import write_png
from appliance.drivers.recording import series_paths
from appliance.drivers.scan import UNUSABLE
from appliance.errors import ConfigError
from appliance.files import write_atomic
from appliance.service.board_source import BoardFrame, BoardSource
from appliance.service.engineering_tasks import ENGINEERING_DIR, checked_args, engineering_file
from appliance.service.monitor import Monitor, reference_state
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.frontend import VirtualFrame
from appliance.sim.loads import empty_mat

IMAGE_FULL_SCALE_MMHG = 100.0       # the darkest colour, as on the live view
IMAGE_SIDE_PX = 320                 # a saved map is enlarged to about this many pixels on its longer side
EMPTY_MAT_MMHG = 10.0
"""A new empty-mat reference is refused when the frame, imaged against the present reference, peaks at or above
this: the empty 4x4 virtual mat imaged to at most 2 mmHg against a fresh reference of its own (two noise seeds),
and a 40 mm square of 1 kPa (7.5 mmHg) on it to 12 mmHg. Fixed, not the alert threshold: a light patient whose
load stays below the threshold would otherwise become the zero every later map is measured from, and the monitor
would read that patient as an empty mat. It is half the lowest threshold a ward may set (20 mmHg)."""
MAX_PAUSE_S = 30 * 60.0
"""The longest a series may hold monitoring up, on the monitor's clock: nobody watches the patient meanwhile
(the next map's dose counts the pause as its pressure held)."""


# Frames and electrodes.

def mean_of_sets(frames: list) -> tuple[np.ndarray, np.ndarray]:
    """Per reading the mean over the sets where it was usable (NaN where it never was), and the flags of
    all sets; a reading usable in some sets keeps only the warning flags (as ``scan.average_frames``)."""
    stack = np.array([f.volts for f in frames], dtype=float)
    finite = np.isfinite(stack)
    count = finite.sum(axis=0)
    volts = np.where(count > 0, np.where(finite, stack, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)
    flags = np.bitwise_or.reduce(np.array([f.flags for f in frames], dtype=np.int64), axis=0)
    return volts, np.where(count > 0, flags & ~int(UNUSABLE), flags)


def electrode_states(protocol, flags: np.ndarray) -> list[dict]:
    """Each electrode judged from the readings it takes part in: ``open`` when none is usable; ``degraded``
    when some are not, for a reason other than an open electrode they share; else ``ok``."""
    readings = protocol.readings
    unusable = (np.asarray(flags) & int(UNUSABLE)) != 0
    involved = [(readings == e).any(axis=1) for e in range(1, protocol.n_electrodes + 1)]
    opened = [k + 1 for k, rows in enumerate(involved) if unusable[rows].all()]
    explained = np.isin(readings, opened).any(axis=1)
    states = []
    for electrode, rows in enumerate(involved, start=1):
        status = "open" if electrode in opened else "degraded" if (unusable & rows & ~explained).any() else "ok"
        states.append({"electrode": electrode, "readings": int(rows.sum()), "usable": int((rows & ~unusable).sum()),
                       "status": status, "ok": status == "ok"})
    return states


def readings_summary(volts: np.ndarray, flags: np.ndarray, protocol, frames: list) -> dict:
    """What a screen shows of readings (one set, or one row per set): how many are usable (in every set),
    their range, the electrodes not ``ok`` by ``flags`` and the technical conditions the frames carried."""
    volts = np.atleast_2d(volts)
    finite = volts[np.isfinite(volts)]
    return {"readings": len(protocol), "usable": int(np.isfinite(volts).all(axis=0).sum()),
            "min_volts": float(finite.min()) if finite.size else None,
            "max_volts": float(finite.max()) if finite.size else None,
            "flagged_electrodes": [s["electrode"] for s in electrode_states(protocol, flags) if not s["ok"]],
            "conditions": list(dict.fromkeys(str(c) for f in frames for c in getattr(f, "conditions", ())))}


def _contact_result(report) -> dict:
    return {"limit_ohm": report.limit_ohm, "open_electrodes": sorted(report.open_electrodes),
            "pairs": [{"pair": list(pair), "impedance_ohm": None if math.isinf(z) else float(z),
                       "high": bool(z > report.limit_ohm)} for pair, z in zip(report.pairs, report.impedance_ohm)]}


# The commands.

Report = Callable[[float, str], None]


class EngineeringTasks:
    """The engineering commands of ``daemon``, writing to ``data_dir``/engineering and building models into
    ``cache_dir`` (defaults: the daemon's configured folders)."""

    def __init__(self, daemon, data_dir: Path | None = None, cache_dir: Path | None = None):
        data_dir = data_dir or daemon.config.data_dir
        if data_dir is None:
            raise ConfigError("the engineering commands need the monitor's data directory ([monitor] data_dir)")
        self.daemon = daemon
        self.folder = Path(data_dir) / ENGINEERING_DIR
        self.cache_dir = Path(cache_dir or daemon.config.cache_dir or default_cache_dir())

    def handlers(self) -> dict[str, Callable]:
        runs = {"acquire": self.acquire, "series": self.series, "contact-check": self.contact_check,
                "self-test": self.self_test, "capture-reference": self.capture_reference,
                "calibrate": self.calibrate, "rebuild-model": self.rebuild_model, "save": self.save_image,
                "load": self.load_calibration}
        return {task: self._command(task, run) for task, run in runs.items()}

    def _command(self, task: str, run: Callable) -> Callable:
        """A daemon command handler: arguments checked, then ``run(now, args, report)``; its result as JSON."""
        def handle(now: float, args: dict, _user: str, command_id: int):
            result = run(now, checked_args(task, args), self.daemon.progress(command_id))
            return [], json.dumps(result)
        return handle

    @property
    def protocol(self):
        return self.daemon.model.setup.protocol

    def _new_path(self, prefix: str, suffix: str, count: int = 1) -> Path:
        """``<prefix>-<UTC stamp><suffix>`` in the engineering folder, numbered on if that is taken."""
        self.folder.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        path, k = self.folder / f"{prefix}-{stamp}{suffix}", 1
        while series_paths(path, count)[0].exists():
            k += 1
            path = self.folder / f"{prefix}-{stamp}-{k}{suffix}"
        return path

    def _check_pause(self, task: str, sets: int, interval_s: float = 0.0) -> None:
        """Refuse ``sets`` sets ``interval_s`` apart when they would hold monitoring up beyond ``MAX_PAUSE_S``:
        on the virtual bed each set is a frame interval of scene time, on a board the interval of wall time."""
        source = self.daemon.source
        step = source.front_end.frame_interval_s if isinstance(source, VirtualBedSource) else interval_s
        if sets * step > MAX_PAUSE_S:
            raise ConfigError(f"{task}: {sets} sets {step:g} s apart hold monitoring up for {sets * step / 60:.0f} "
                              f"min of the monitor's clock; at most {MAX_PAUSE_S / 60:.0f} min: take at most "
                              f"{int(MAX_PAUSE_S // step)} sets")

    def acquire(self, _now: float, args: dict, report: Report) -> dict:
        """One set of readings, or the average of ``averages`` sets, written as a frame file."""
        n = args["averages"]
        self._check_pause("acquire", n)
        frames = []
        for k in range(1, n + 1):
            frames.append(self.daemon.source.acquire())
            report(k / n, f"set {k} of {n}")
        volts, flags = mean_of_sets(frames)
        path = self._new_path("readings", ".csv")
        write_atomic(path, frame_to_csv(self.protocol, volts))
        return {"file": path.name, "sets": n, **readings_summary(volts, flags, self.protocol, frames)}

    def series(self, _now: float, args: dict, report: Report) -> dict:
        """``count`` sets, one every ``interval_s`` of wall time, each its own numbered frame file; a stop
        request ends the series early with the sets taken so far."""
        count, interval = args["count"], args["interval_s"]
        self._check_pause("series", count, interval)
        paths = series_paths(self._new_path("series", ".csv", count), count)
        stop = self.daemon.stop_requested
        written, frames = [], []
        next_start = time.monotonic()
        for k, path in enumerate(paths, start=1):
            while (wait := next_start - time.monotonic()) > 0 and not stop.is_set():
                stop.wait(min(wait, 1.0))
                report((k - 1) / count, f"waiting for set {k} of {count}")
            if stop.is_set():
                break
            next_start = time.monotonic() + interval
            frame = self.daemon.source.acquire()
            write_atomic(path, frame_to_csv(self.protocol, frame.volts))
            written.append(path.name)
            frames.append(frame)
            report(k / count, f"set {k} of {count}")
        if not frames:
            raise ConfigError("the monitor is stopping: no set of the series was taken")
        flags = np.bitwise_or.reduce(np.array([f.flags for f in frames], dtype=np.int64), axis=0)
        return {"files": written, "sets": len(written), "of": count, "interval_s": interval,
                "stopped_early": len(written) < count,
                **readings_summary(np.array([f.volts for f in frames]), flags, self.protocol, frames)}

    def _frame_check(self, report: Report) -> tuple[BoardFrame | VirtualFrame, list[dict]]:
        frame = self.daemon.source.acquire()
        report(1.0, "one frame taken")
        return frame, electrode_states(self.protocol, frame.flags)

    def contact_check(self, _now: float, _args: dict, report: Report) -> dict:
        """On a board, the contact check of every neighbouring pair; on the virtual bed, which has no
        contact-test current, each electrode judged from one frame's readings."""
        source, n = self.daemon.source, self.protocol.n_electrodes
        if isinstance(source, BoardSource):
            from appliance.drivers.contact import check_contacts

            contact = check_contacts(source.front_end, n)
            report(1.0, "contact check done")
            return {"source": "board", "checked": "two-electrode impedance of each neighbouring pair at the "
                                                  "contact-test current", **_contact_result(contact),
                    "electrodes": [{"electrode": e, "ok": e not in contact.open_electrodes} for e in range(1, n + 1)]}
        _frame, electrodes = self._frame_check(report)
        return {"source": "virtual", "checked": "the virtual front end has no contact-test current: each electrode "
                                                "judged from the readings it takes part in, in one frame",
                "open_electrodes": [s["electrode"] for s in electrodes if s["status"] == "open"],
                "electrodes": electrodes}

    def self_test(self, _now: float, _args: dict, report: Report) -> dict:
        """On a board, the drivers' self-test (chip read-backs, signal path, contact); on the virtual bed, which
        has no chips, that a frame comes with readings and a temperature, and each electrode's readings."""
        source, n = self.daemon.source, self.protocol.n_electrodes
        if isinstance(source, BoardSource):
            from appliance.drivers.selftest import run_self_test

            result = run_self_test(source.front_end, n)
            report(1.0, "self-test done")
            return {"source": "board", "passed": result.passed,
                    "checks": [{"part": c.part, "where": c.where, "ok": c.ok, "detail": c.detail}
                               for c in result.checks],
                    "contact": None if result.contact is None else _contact_result(result.contact)}
        frame, electrodes = self._frame_check(report)
        usable = int(np.isfinite(frame.volts).sum())
        temperature = frame.temperature_c
        checks = [{"part": "virtual front end", "where": "simulation", "ok": usable > 0,
                   "detail": f"a frame with {usable} of {len(frame.volts)} readings usable"},
                  {"part": "thermometer", "where": "simulation",
                   "ok": temperature is not None and math.isfinite(temperature),
                   "detail": "no temperature" if temperature is None else f"{temperature:.2f} degC"}]
        return {"source": "virtual", "checked": "the virtual front end simulates whole frames and has no chips to "
                                                "read back: a frame, its temperature and each electrode's readings",
                "passed": all(c["ok"] for c in checks) and all(s["status"] != "open" for s in electrodes),
                "checks": checks, "electrodes": electrodes}

    def capture_reference(self, now: float, _args: dict, report: Report) -> dict:
        """A new empty-mat reference, refused while the mat is loaded: when the frame, imaged against the
        present reference, peaks at or above ``EMPTY_MAT_MMHG``. With no reference yet there is nothing to
        compare with, and the frame is taken as it is."""
        daemon = self.daemon
        monitor = daemon.monitor
        frame = daemon.source.acquire()
        report(0.5, "frame taken; checking the mat is empty")
        peak = None
        if monitor.reference is not None:
            probe = Monitor(lambda: frame, daemon.model, monitor.calibration)
            probe.reference, probe.reference_temperature_c = monitor.reference, monitor.reference_temperature_c
            peak = probe.next_map().peak_kpa
            if not peak < EMPTY_MAT_MMHG * KPA_PER_MMHG:       # NaN (nothing readable) is not an empty mat either
                raise ConfigError(f"the mat is loaded: it reads {peak / KPA_PER_MMHG:.0f} mmHg at its peak against "
                                  f"the present reference, at or above the {EMPTY_MAT_MMHG:g} mmHg an empty mat may "
                                  "show; clear the mat and capture again (the reference is unchanged)")
        report(0.6, "the mat is empty; fitting the contacts and the sheet to it")
        fit = monitor.take_reference(frame, lambda step, share: report(0.6 + 0.4 * share, f"relinearising: {step}"))
        daemon.writes.save_state("reference", reference_state(daemon.model, frame, fit), now)
        daemon.pipeline.hold_open_alarms()                   # a new zero may read less: no alarm ends by that alone
        report(1.0, "reference replaced")
        return {"usable": int(np.isfinite(frame.volts).sum()), "readings": len(frame.volts),
                "temperature_c": frame.temperature_c,
                "peak_mmhg_before": None if peak is None else peak / KPA_PER_MMHG,
                "contact_fit": None if fit is None else fit.summary()}

    def calibrate(self, _now: float, args: dict, report: Report) -> dict:
        """The pressure calibration procedure on the simulated mat on the bench (a copy of the virtual bed's
        mat, so the patient's scene goes on untouched), saved but not taken into use."""
        source, model = self.daemon.source, self.daemon.model
        if not isinstance(source, VirtualBedSource):
            raise ConfigError("a pressure calibration of a real mat needs the operator at the bench placing each "
                              "weight: run `appliance calibrate pressure --source hardware` there, then upload the "
                              "file here and load it")
        layout = model.setup.layout
        bench = VirtualBedSource(layout, empty_mat(layout), model.setup.protocol, seed=source.front_end.seed)
        loads = calibration_loads(layout, positions=args["positions"])
        calibration = pressure_calibration(
            bench.acquire, bench.place, model, loads,
            progress=lambda k, n, load: report(k / n, f"load {k} of {n}: {load.side_mm:g} mm square, "
                                                      f"{load.pressure_kpa:g} kPa"))
        path = self._new_path("pressure", ".json")
        save_pressure_calibration(path, calibration)
        report(1.0, f"saved to {path.name}")
        return {"file": path.name, "loads": len(loads), "layout": calibration.layout_name,
                "algorithm": calibration.algorithm, "pixels": list(calibration.pixels),
                "max_change": float(calibration.curve.change[-1]), "max_kpa": float(calibration.curve.pressure[-1]),
                "in_use": False, "note": "load it to use it"}

    def rebuild_model(self, _now: float, _args: dict, report: Report) -> dict:
        """The reconstruction model built afresh and saved where the model cache looks for it; it replaces the
        running one only when built, saved and accepted by the running calibration."""
        setup = self.daemon.model.setup
        started = time.perf_counter()
        model = build_model(setup, lambda step, share: report(share, f"building the model: {step}"))
        save_model(model, model_path(setup, self.cache_dir))
        model.cache_dir = self.cache_dir                      # where the models fitted to references go
        self._replace_monitor(model, self.daemon.monitor.calibration)
        return {"layout": setup.layout.name, "pixels": list(model.reconstructor.grid.shape),
                "readings": len(setup.protocol), "seconds": round(time.perf_counter() - started, 2)}

    def save_image(self, _now: float, _args: dict, report: Report) -> dict:
        """The pressure map of a frame taken now, as a PNG (0 to 100 mmHg, as the live view colours it); the
        frame is the engineer's, not the alarm pipeline's."""
        pressure_map = self.daemon.monitor.next_map()
        mmhg = pressure_map.pressure_kpa / KPA_PER_MMHG
        path = self._new_path("map", ".png")
        write_png(path, mmhg, vmin=0.0, vmax=IMAGE_FULL_SCALE_MMHG, palette="sequential",
                  scale=max(1, IMAGE_SIDE_PX // max(mmhg.shape)))
        report(1.0, f"saved to {path.name}")
        return {"file": path.name, "peak_mmhg": pressure_map.peak_kpa / KPA_PER_MMHG, "pixels": list(mmhg.shape),
                "colour_scale_mmhg": [0.0, IMAGE_FULL_SCALE_MMHG]}

    def load_calibration(self, _now: float, args: dict, report: Report) -> dict:
        """A pressure calibration from the engineering folder in place of the running one, if it fits the
        running mat and reconstruction; otherwise refused, the running one kept."""
        path = engineering_file(self.folder.parent, args["file"])
        calibration = load_pressure_calibration(path)
        check_plausible(calibration, path.name)                        # a flat or scaled-away curve blinds
        self._replace_monitor(self.daemon.model, calibration)        # refuses one for another mat
        report(1.0, f"{path.name} in use")
        return {"file": path.name, "in_use": True, "layout": calibration.layout_name,
                "note": f"in use until the monitor restarts; to keep it, set [monitor] calibration = \"{path}\""}

    def _replace_monitor(self, model, calibration) -> None:
        """A monitor for ``model`` and ``calibration`` (checked to fit) with the running one's reference."""
        old = self.daemon.monitor
        fresh = Monitor(old.acquire, model, calibration)
        if old.reference is not None:
            fresh.set_reference(old.reference, old.reference_temperature_c)     # a new model is fitted to it now
        fresh.conditions = old.conditions
        self.daemon.model, self.daemon.monitor = model, fresh
        self.daemon.pipeline.hold_open_alarms()          # a new scale may read less: no alarm ends by that alone


def engineering_commands(daemon, *, data_dir: Path | None = None, cache_dir: Path | None = None) -> dict:
    """The engineering command handlers of ``daemon``, by kind, for ``daemon.add_commands``."""
    return EngineeringTasks(daemon, data_dir, cache_dir).handlers()
