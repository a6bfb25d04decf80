"""Scenes: what lies on the mat over time, so a simulator can replay a night on the bed.

A scene answers ``pressure_at(t_s)`` and, between two times, whether the field
changed and the box (mm) that holds the change, so a simulator re-solves the
mat's mechanics only there. A :class:`BodyScene` is a timeline of events on the
parametric body (:mod:`appliance.sim.body`): lie down, shift a few cm, turn to
another posture, leave the bed and return, keep still. Each change blends the
fields linearly over its transition time, so the total force stays m g during
a turn and falls to zero as the patient leaves. Scenarios are TOML files::

    [scene]
    width_mm = 900
    duration_s = 7200
    weight_kg = 75

    [[event]]
    at_s = 0
    kind = "lie-down"
    posture = "supine"

``[scene] sites = ["heel-left", "heel-right"]`` keeps only those sites' patches,
at their whole-body pressures (the rest of the body lies on another surface).
Electrode faults play on any scene, sorted by time::

    [[fault]]
    at_s = 3600
    electrode = 5            # 1-based
    kind = "disconnect"      # or "reconnect"

Instead of events, a file may hold recorded segments played one after another,
each from the start of its recording, its last frame held ``hold_s`` after it
ends; the scene lasts the segments' total (``[scene] duration_s`` may lengthen
it). Paths are taken relative to the scenario file's folder::

    [[recording]]
    source = "pmatdata"
    dir = "../shared/data/pmatdata"
    subject = 1
    posture = 1              # experiment I posture file, 1 to 17
    hold_s = 600
    pitch_mm = 28.5          # optional: the sensel pitch (default PMAT_SENSEL_MM, recordings.py)

    [[recording]]
    source = "maps"          # pressure maps in mmHg (sim/map_files.py), in this order
    files = ["supine.csv", "left-30.csv"]
    pitch_mm = 28.5          # their sensel pitch, 1 to 100 mm
    each_s = 1800            # each map held this long; or rate_hz = 1 (each held 1 / rate_hz)
    hold_s = 0               # optional: the last one held this much longer

Maps are placed centred on the [scene] grid with their force kept
(:mod:`appliance.sim.map_scenes`); a map that lays no force on it, or a pressure
beyond the mat model's limit, is refused naming the file and cell.

Unknown keys and kinds, negative or overlapping times and positions off the mat
are refused with the event's (fault's, segment's) number and field. A change box
is conservative: it holds every cell that moved by more than
``CHANGE_TOLERANCE_KPA`` at any time between the two instants, even when the
field came back.

>>> scene = load_scene("supine-still")
>>> scene.changes(600.0, 1200.0), scene.pressure_at(600.0).pressure_kpa.shape
(False, (190, 90))
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np

from appliance.core.toml_files import check_keys, read_toml
from appliance.errors import ConfigError, DataFileInvalid, ModelInputInvalid
from appliance.sim.body import (BED_GRID, POSTURES, SURFACES, MatGrid, Placement, Subject, is_number, body_field,
                                check_sites)
from appliance.sim.field import PressureField
from appliance.sim.map_files import check_pitch_mm
from appliance.sim.map_scenes import map_recording
from appliance.sim.recordings import PMAT_SENSEL_MM, RecordedScene, pmat_scene
from appliance.sim.scene_base import ElectrodeFault, Scene

DEFAULT_TRANSITION_S = {"lie-down": 10.0, "shift": 2.0, "turn": 20.0, "leave": 5.0, "return": 10.0}
_PLACE = {"posture", "x_mm", "y_mm", "rotation_deg", "transition_s"}
EVENT_FIELDS = {"lie-down": _PLACE, "return": _PLACE, "turn": {"posture", "transition_s"},
                "shift": {"dx_mm", "dy_mm", "rotation_deg", "transition_s"}, "leave": {"transition_s"},
                "still": {"duration_s"}}
SCENE_FIELDS = {"description", "width_mm", "height_mm", "pitch_mm", "weight_kg", "height_cm", "surface",
                "duration_s", "sites"}
RECORDED_SCENE_FIELDS = {"description", "width_mm", "height_mm", "pitch_mm", "duration_s"}
FAULT_FIELDS = {"at_s", "electrode", "kind"}
FAULT_KINDS = {"disconnect": False, "reconnect": True}
RECORDING_FIELDS = {"pmatdata": {"source", "dir", "subject", "posture", "hold_s", "pitch_mm", "shift_mm"},
                    "maps": {"source", "files", "pitch_mm", "each_s", "rate_hz", "hold_s"}}
PMAT_POSTURES = range(1, 18)
PMAT_POSTURE_FILES = {"supine": 1, "right-90": 2, "left-90": 3, "right-30": 4, "right-60": 5, "left-30": 6,
                      "left-60": 7, "fetal-right": 13, "fetal-left": 14, "inclined": 15}
"""PmatData experiment I's posture file for each posture the monitor names (file 15 is the head of the bed at
30 degrees; 16 and 17 raise it to 45 and 60, and 8 to 12 are supine variants: star, arms crossed, knees up)."""


@dataclass(frozen=True)
class Step:
    """One change from ``before`` to ``after`` (a placement, or None for an empty bed) over [start, end]."""

    start_s: float
    end_s: float
    before: Placement | None
    after: Placement | None

    def weight(self, t_s: float) -> float:
        """How far the change has gone at ``t_s``: 0 before it starts, 1 once it ends."""
        if self.end_s <= self.start_s:
            return 1.0 if t_s >= self.start_s else 0.0
        return min(1.0, max(0.0, (t_s - self.start_s) / (self.end_s - self.start_s)))


class BodyScene(Scene):
    """A subject on the mat through a list of non-overlapping steps; the bed is empty before the first.
    With ``sites``, only those sites load the mat."""

    def __init__(self, subject: Subject, steps: list[Step], grid: MatGrid = BED_GRID,
                 surface: str = "standard-foam", duration_s: float | None = None,
                 sites: frozenset[str] | None = None, faults: tuple[ElectrodeFault, ...] = ()):
        self.subject, self.steps, self.grid, self.surface = subject, list(steps), grid, surface
        self.sites, self.faults = check_sites(sites), tuple(sorted(faults, key=lambda f: f.at_s))
        end = max((s.end_s for s in self.steps), default=0.0)
        self.duration_s = float(end if duration_s is None else duration_s)
        if self.duration_s <= 0 or self.duration_s < end:
            raise ModelInputInvalid(f"scene duration {self.duration_s:g} s must be positive and cover the "
                                    f"last change, which ends at {end:g} s")

    def _field(self, placement: Placement | None) -> np.ndarray:
        if placement is None:
            return np.zeros(self.grid.shape)
        return body_field(self.subject, placement, self.grid, self.surface, self.sites).pressure_kpa

    def pressure_at(self, t_s: float) -> PressureField:
        self._check_times(t_s)
        started = [s for s in self.steps if s.start_s <= t_s]
        if not started:
            return self.grid.zeros()
        step = started[-1]
        w = step.weight(t_s)
        p = self._field(step.after) if w == 1.0 else (1 - w) * self._field(step.before) + w * self._field(step.after)
        return PressureField(p, self.grid.pitch_mm)

    def change_box_mm(self, t0_s: float, t1_s: float) -> tuple[float, float, float, float] | None:
        self._check_times(t0_s, t1_s)
        change = np.zeros(self.grid.shape)
        for step in self.steps:
            dw = step.weight(t1_s) - step.weight(t0_s)
            if dw > 0:
                change = np.maximum(change, dw * np.abs(self._field(step.after) - self._field(step.before)))
        return self._box(change)


def builtin_scenes() -> tuple[str, ...]:
    """Names of the scenarios shipped in ``appliance/sim/scenarios``."""
    folder = resources.files("appliance.sim").joinpath("scenarios")
    return tuple(sorted(f.name[:-5] for f in folder.iterdir() if f.name.endswith(".toml")))


def builtin_descriptions() -> dict[str, str]:
    """Each built-in scenario's ``[scene] description``, by name ("" where a file gives none)."""
    folder = resources.files("appliance.sim").joinpath("scenarios")
    return {name: str(tomllib.loads(folder.joinpath(f"{name}.toml").read_text(encoding="utf-8"))
                      .get("scene", {}).get("description", "")) for name in builtin_scenes()}


def load_scene(path) -> Scene:
    """The scene in TOML file ``path``, or the built-in scenario of that name."""
    if str(path) in builtin_scenes():
        file = resources.files("appliance.sim").joinpath(f"scenarios/{path}.toml")
        data, where = tomllib.loads(file.read_text(encoding="utf-8")), f"built-in scenario {path}"
        folder = Path(str(file)).parent
    else:
        data, where = read_toml(Path(path), "scenario file", ConfigError), f"scenario file {path}"
        folder = Path(path).parent
    try:
        return scene_from_mapping(data, folder)
    except (ConfigError, DataFileInvalid) as exc:
        raise type(exc)(f"{where}: {exc}") from None


def scene_from_mapping(data: dict, folder: Path = Path(".")) -> Scene:
    """Build a scene from parsed TOML, recording paths taken from ``folder``; every bad key, kind,
    time or position is named."""
    _only(data, {"scene", "event", "recording", "fault"}, "the scenario")
    head = data.get("scene", {})
    if not isinstance(head, dict):
        raise ConfigError("[scene] must be a table")
    faults = _faults(data.get("fault", []))
    if "recording" in data:
        if "event" in data:
            raise ConfigError("a scenario holds either [[event]]s or [[recording]]s, not both")
        return _recorded_scene(head, data["recording"], faults, folder)
    _only(head, SCENE_FIELDS, "[scene]")
    surface = head.get("surface", "standard-foam")
    if not isinstance(head.get("description", ""), str):
        raise ConfigError(f"[scene] description must be text, got {head['description']!r}")
    if not isinstance(surface, str) or surface not in SURFACES:
        raise ConfigError(f"[scene] surface must be one of {', '.join(SURFACES)}, got {surface!r}")
    try:
        grid = _grid(head)
        subject = Subject(_number(head, "weight_kg", "[scene]", 75.0), _number(head, "height_cm", "[scene]", 175.0))
        sites = _sites(head)
    except ModelInputInvalid as exc:
        raise ConfigError(f"[scene]: {exc}") from None
    events = data.get("event", [])
    if not isinstance(events, list) or not all(isinstance(e, dict) for e in events):
        raise ConfigError("[[event]] entries must be tables")
    steps = _steps(events, subject, grid, surface)
    end = max([s.end_s for s in steps] + [_still_end(e) for e in events] + [0.0])
    duration = _positive(head, "duration_s", "[scene]") if "duration_s" in head else end
    if duration < end:
        raise ConfigError(f"[scene] duration_s = {duration:g} ends before the last event, at {end:g} s")
    if duration <= 0:
        raise ConfigError("the scene has no length: give [scene] duration_s or a still event")
    _check_fault_times(faults, duration)
    return BodyScene(subject, steps, grid, surface, duration, sites, faults)


def _grid(head: dict) -> MatGrid:
    return MatGrid(*(_number(head, k, "[scene]", d) for k, d in
                     (("width_mm", 900.0), ("height_mm", 1900.0), ("pitch_mm", 10.0))))


def _sites(head: dict) -> frozenset[str] | None:
    if "sites" not in head:
        return None
    sites = head["sites"]
    if not isinstance(sites, list) or not all(isinstance(site, str) for site in sites):
        raise ConfigError(f"[scene] sites must be a list of site names, got {sites!r}")
    return check_sites(sites)


def _faults(entries) -> tuple[ElectrodeFault, ...]:
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ConfigError("[[fault]] entries must be tables")
    faults = []
    for n, entry in enumerate(entries, start=1):
        where = f"fault {n}"
        _only(entry, FAULT_FIELDS, where)
        at = _number(entry, "at_s", where, None)
        if at < 0:
            raise ConfigError(f"{where}: at_s must not be negative, got {at:g}")
        electrode = entry.get("electrode")
        if isinstance(electrode, bool) or not isinstance(electrode, int) or electrode < 1:
            raise ConfigError(f"{where}: electrode must be an electrode number (an integer from 1), "
                              f"got {electrode!r}")
        kind = entry.get("kind")
        if kind not in FAULT_KINDS:
            raise ConfigError(f"{where}: kind must be one of {', '.join(FAULT_KINDS)}, got {kind!r}")
        faults.append(ElectrodeFault(at, electrode, FAULT_KINDS[kind]))
    return tuple(sorted(faults, key=lambda f: f.at_s))


def _check_fault_times(faults: tuple[ElectrodeFault, ...], duration_s: float) -> None:
    late = [f for f in faults if f.at_s > duration_s]
    if late:
        raise ConfigError(f"a fault at {late[0].at_s:g} s comes after the scene's end, at {duration_s:g} s")


def _recorded_scene(head: dict, segments, faults: tuple[ElectrodeFault, ...], folder: Path) -> Scene:
    """Recorded segments (PmatData, map files) played one after another on the [scene] grid."""
    _only(head, RECORDED_SCENE_FIELDS, "[scene]")
    try:
        grid = _grid(head)
    except ModelInputInvalid as exc:
        raise ConfigError(f"[scene]: {exc}") from None
    if not isinstance(segments, list) or not segments or not all(isinstance(e, dict) for e in segments):
        raise ConfigError("[[recording]] entries must be tables, at least one")
    frames, times, infos, start = [], [], [], 0.0
    for n, segment in enumerate(segments, start=1):
        where = f"recording {n}"
        source = segment.get("source")
        if not isinstance(source, str) or source not in RECORDING_FIELDS:
            raise ConfigError(f"{where}: source must be one of {', '.join(RECORDING_FIELDS)}, got {source!r}")
        _only(segment, RECORDING_FIELDS[source], where)
        try:
            if source == "pmatdata":
                recording, hold = _pmat_segment(segment, where, folder, grid)
            else:
                recording, hold = _map_segment(segment, where, folder, grid)
        except DataFileInvalid as exc:
            raise DataFileInvalid(f"{where}: {exc}") from None
        frames.append(recording.frames)
        times.append(recording.times_s + start)
        infos.append({"start_s": start, **recording.info})
        start += recording.duration_s + hold
    duration = _positive(head, "duration_s", "[scene]") if "duration_s" in head else start
    if duration < start:
        raise ConfigError(f"[scene] duration_s = {duration:g} ends before the recordings, at {start:g} s")
    _check_fault_times(faults, duration)
    return RecordedScene(np.concatenate(frames), np.concatenate(times), grid, {"segments": infos},
                         duration_s=duration, faults=faults)


def _pmat_segment(segment: dict, where: str, folder: Path, grid: MatGrid):
    """A PmatData recording on ``grid`` and how long its last frame is held."""
    if not isinstance(segment.get("dir"), str):
        raise ConfigError(f"{where}: dir must be the path of the PmatData folder, got {segment.get('dir')!r}")
    data_dir = folder / segment["dir"]
    if not data_dir.is_dir():
        raise ConfigError(f"{where}: dir {str(data_dir)!r} is not a folder (the PmatData data set)")
    subject = _integer(segment, "subject", where)
    posture = segment.get("posture")
    if isinstance(posture, str):
        if posture not in PMAT_POSTURE_FILES:
            raise ConfigError(f"{where}: unknown posture {posture!r}; PmatData has "
                              f"{', '.join(PMAT_POSTURE_FILES)} (or a file number, 1 to 17)")
        posture = PMAT_POSTURE_FILES[posture]
    else:
        posture = _integer(segment, "posture", where)
        if posture not in PMAT_POSTURES:
            raise ConfigError(f"{where}: posture must be a file number 1 to 17 or one of "
                              f"{', '.join(PMAT_POSTURE_FILES)}, got {posture}")
    shift = segment.get("shift_mm", [0.0, 0.0])
    if not (isinstance(shift, list) and len(shift) == 2 and all(is_number(v) and abs(v) <= 300 for v in shift)):
        raise ConfigError(f"{where}: shift_mm must be [across, along] in mm, each within 300, got {shift!r}")
    hold = _not_negative(segment, "hold_s", where, None)
    pitch = check_pitch_mm(segment.get("pitch_mm", PMAT_SENSEL_MM), f"{where}: pitch_mm")
    across, along = float(shift[0]), float(shift[1])
    return pmat_scene(data_dir, subject, posture, grid, sensel_mm=pitch, shift_mm=(across, along)), hold


def _map_segment(segment: dict, where: str, folder: Path, grid: MatGrid):
    """Pressure map files played in order on ``grid``, and how long the last is held."""
    files = segment.get("files")
    if not isinstance(files, list) or not files or not all(isinstance(f, str) for f in files):
        raise ConfigError(f"{where}: files must be a list of pressure map files (CSV in mmHg), got {files!r}")
    if "pitch_mm" not in segment:
        raise ConfigError(f"{where} is missing 'pitch_mm' (the maps' sensel pitch)")
    pitch = check_pitch_mm(segment["pitch_mm"], f"{where}: pitch_mm")
    if ("each_s" in segment) == ("rate_hz" in segment):
        raise ConfigError(f"{where}: give how long each map is held, each_s, or the rate they play at, rate_hz "
                          "(one of the two)")
    each = _positive(segment, "each_s", where) if "each_s" in segment else 1.0 / _positive(segment, "rate_hz", where)
    hold = _not_negative(segment, "hold_s", where, 0.0)
    return map_recording([folder / f for f in files], pitch, grid, each), hold


def _still_end(event: dict) -> float:
    return event["at_s"] + event["duration_s"] if event.get("kind") == "still" else 0.0


def _steps(events: list[dict], subject: Subject, grid: MatGrid, surface: str) -> list[Step]:
    steps, state, last, free_from = [], None, None, 0.0
    for n, event in enumerate(events, start=1):
        kind = event.get("kind")
        if kind not in EVENT_FIELDS:
            raise ConfigError(f"event {n}: kind must be one of {', '.join(EVENT_FIELDS)}, got {kind!r}")
        where = f"event {n} ({kind})"
        _only(event, EVENT_FIELDS[kind] | {"at_s", "kind"}, where)
        at = _number(event, "at_s", where, None)
        if at < 0:
            raise ConfigError(f"{where}: at_s must not be negative, got {at:g}")
        if at < free_from:
            raise ConfigError(f"{where}: at_s = {at:g} comes before the previous event ends, at {free_from:g} s")
        if kind == "still":
            free_from = at + _positive(event, "duration_s", where)
            continue
        span = _number(event, "transition_s", where, DEFAULT_TRANSITION_S[kind])
        if span < 0:
            raise ConfigError(f"{where}: transition_s must not be negative, got {span:g}")
        after = _next_state(kind, event, state, last, where, grid, subject)
        if after is not None:
            _check_fits(after, where, grid, subject, surface)
            last = after
        steps.append(Step(at, at + span, state, after))
        state, free_from = after, at + span
    return steps


def _next_state(kind, event, state, last, where, grid, subject) -> Placement | None:
    occupied = state is not None
    if occupied == (kind in ("lie-down", "return")):
        raise ConfigError(f"{where}: the bed is {'occupied' if occupied else 'empty'} at this time")
    if kind == "leave":
        return None
    if kind == "shift":
        return replace(state, x_mm=state.x_mm + _number(event, "dx_mm", where, 0.0),
                       y_mm=state.y_mm + _number(event, "dy_mm", where, 0.0),
                       rotation_deg=state.rotation_deg + _number(event, "rotation_deg", where, 0.0))
    base = state if kind == "turn" else (last if kind == "return" and last is not None else Placement())
    posture = event.get("posture", base.posture)
    if not isinstance(posture, str) or posture not in POSTURES:
        raise ConfigError(f"{where}: posture must be one of {', '.join(POSTURES)}, got {posture!r}")
    new = replace(base, posture=posture, **{k: _number(event, k, where, getattr(base, k))
                                            for k in ("x_mm", "y_mm", "rotation_deg") if k in event})
    return new.on(grid, subject)


def _check_fits(placement: Placement, where: str, grid: MatGrid, subject: Subject, surface: str) -> None:
    for key, value, size in (("x_mm", placement.x_mm, grid.width_mm), ("y_mm", placement.y_mm, grid.height_mm)):
        if value is not None and not 0 <= value <= size:        # None: centred
            raise ConfigError(f"{where}: {key} = {value:g} puts the body off the "
                              f"{grid.width_mm:g} x {grid.height_mm:g} mm mat")
    try:
        body_field(subject, placement, grid, surface)
    except ModelInputInvalid as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _only(table: dict, allowed: set, where: str) -> None:
    check_keys(table, allowed, where, ConfigError, noun="field")


def _number(table: dict, key: str, where: str, default: float | None) -> float:
    if key not in table:
        if default is None:
            raise ConfigError(f"{where} is missing {key!r}")
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _integer(table: dict, key: str, where: str) -> int:
    value = table.get(key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where}: {key} must be an integer, got {value!r}")
    return value


def _not_negative(table: dict, key: str, where: str, default: float | None) -> float:
    value = _number(table, key, where, default)
    if value < 0:
        raise ConfigError(f"{where}: {key} must not be negative, got {value:g}")
    return value


def _positive(table: dict, key: str, where: str) -> float:
    value = _number(table, key, where, None)
    if value <= 0:
        raise ConfigError(f"{where}: {key} must be positive, got {value:g}")
    return value
