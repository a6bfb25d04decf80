"""Real in-bed recordings as scenes: PmatData experiment I and PoPu's Tactilus maps.

Both put the head at row 0 and are placed centred on the target mat with an
area-conserving resampling (each sensel's force is shared among the cells it
overlaps), so the field keeps the force that lands on the mat and its orientation.

PmatData (FSA SoftFlex 2048, 64 x 32, 1 Hz) holds uncalibrated raw counts. We
drop frames whose total is not within half to twice the file's median (the
empty first frame and the garbage second one most files have), replace
saturated (4095) and isolated cells (more than four times their highest
neighbour) by their neighbours' median, and scale each frame so its force on
the mat is the subject's weight times g. Counts above the documented 0-1000
range are kept: they form contiguous clusters under the heels and sacrum.

Sensel pitch: no datasheet value was found. ``PMAT_SENSEL_MM`` = 28.5 mm +/- 2.5 mm
(square sensels assumed) comes from two estimates that agree. Anatomy: occiput
to heel spans 59.2, 56.5 and 56.5 rows in the supine maps of subjects of 175, 183
and 186 cm, i.e. 28.0, 30.8 and 31.3 mm per row taking that span as height minus
9 cm. Force: if a count is 0.1 mmHg (the documented 0-1000 range over the FSA's
usual 0-100 mmHg), the median total of each subject's 17 files equals the
weight at 27.3, 25.9 and 29.5 mm. One inch (25.4 mm) would make S8 (186 cm) 1.44 m
from occiput to heel. Pressure goes as 1/pitch^2: +/-2.5 mm is about +/-18 % in
kPa. At 28.5 mm the recording is 912 x 1824 mm; on a 900 mm mat 6 mm of each edge
column (well under 1 % of the counts) falls off before the force is scaled.

Left and right: a recording lies as the scenes do, columns towards the patient's left
(:mod:`appliance.sim.body`). PmatData's columns run the other way: in both curled postures
of S1, S4 and S6 the knees, which point to the side a patient lies on, lie towards the
columns the dataset's side names (right fetal: legs centred 2 to 9 columns further towards
the last column than the trunk), so its maps are mirrored on reading. PoPu's run our way
(``left2``: legs 4.6 columns towards the last one).

PoPu (Tactilus, 64 x 27) values are taken as mmHg, which the repository does not
state. ``POPU_SENSEL_MM`` = 31.75 mm (1.25 in) +/- 2 mm, inferred the same way
(occiput row 3 to heel row ~59.5 for the 190 cm volunteer: 32 mm per row). Read
as mmHg at that pitch the maps carry about 2.4 times the volunteer's 96 kg
(1.5 times even at 25.4 mm), so either the unit or the sensor's calibration is
off; :func:`popu_scene` reports the implied force and can scale to the weight.
Snapshot times are read from the ids as hhmmsscc clock times (an inference:
consecutive ids step about 0.52 s).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from scipy.ndimage import maximum_filter, median_filter

from appliance.errors import DataFileInvalid
from appliance.sim.body import BED_GRID, G_M_S2, MatGrid
from appliance.sim.field import KPA_PER_MMHG, PressureField
from appliance.sim.scene_base import ElectrodeFault, Scene

PMAT_SHAPE, PMAT_SENSEL_MM, PMAT_SATURATED = (64, 32), 28.5, 4095
POPU_SHAPE, POPU_SENSEL_MM, POPU_SNAPSHOT_S = (64, 27), 31.75, 0.5
_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], dtype=bool)


class RecordedScene(Scene):
    """Frames (kPa, on ``grid``) held from each of ``times_s`` to the next; ``info`` says where they came from.

    The last frame is held for one median frame step, or until ``duration_s`` when given.
    """

    def __init__(self, frames_kpa: np.ndarray, times_s: np.ndarray, grid: MatGrid, info: dict, *,
                 duration_s: float | None = None, faults: tuple[ElectrodeFault, ...] = ()):
        self.frames, self.times_s, self.grid, self.info = frames_kpa, np.asarray(times_s, float), grid, info
        step = float(np.median(np.diff(self.times_s))) if len(self.times_s) > 1 else 1.0
        self.duration_s = float(self.times_s[-1] + step if duration_s is None else duration_s)
        self.faults = tuple(sorted(faults, key=lambda f: f.at_s))

    def _index(self, t_s: float) -> int:
        return max(0, int(np.searchsorted(self.times_s, t_s, side="right")) - 1)

    def pressure_at(self, t_s: float) -> PressureField:
        self._check_times(t_s)
        return PressureField(self.frames[self._index(t_s)].copy(), self.grid.pitch_mm)

    def change_box_mm(self, t0_s: float, t1_s: float):
        self._check_times(t0_s, t1_s)
        i0, i1 = self._index(t0_s), self._index(t1_s)
        if i0 == i1:
            return None
        return self._box(np.abs(np.diff(self.frames[i0:i1 + 1], axis=0)).max(axis=0))


def force_n(pressure_kpa: np.ndarray, pitch_mm: float) -> np.ndarray:
    """Force (N) of each map in a stack (..., rows, cols) of square cells."""
    return np.asarray(pressure_kpa).sum(axis=(-2, -1)) * pitch_mm**2 * 1e-3


def resample_onto(pressure: np.ndarray, pitch_mm: float, grid: MatGrid,
                  shift_mm: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Maps (..., rows, cols) of ``pitch_mm`` cells placed centred on ``grid`` (moved by ``shift_mm``, across
    and along), force kept cell by cell.

    Force that falls outside the mat is lost; inside, the total is kept to rounding.

    >>> out = resample_onto(np.ones((2, 2)), 30.0, MatGrid(100.0, 100.0, 20.0))
    >>> out.shape, round(float(out.sum()) * 400, 9)
    ((5, 5), 3600.0)
    """
    p = np.asarray(pressure, dtype=float)
    rows, cols = p.shape[-2:]
    out_rows, out_cols = grid.shape
    dx, dy = shift_mm
    wy = area_shares((grid.height_mm - rows * pitch_mm) / 2 + dy + np.arange(rows + 1) * pitch_mm,
                     np.arange(out_rows + 1) * grid.pitch_mm)
    wx = area_shares((grid.width_mm - cols * pitch_mm) / 2 + dx + np.arange(cols + 1) * pitch_mm,
                     np.arange(out_cols + 1) * grid.pitch_mm)
    return wy @ p @ wx.T / grid.pitch_mm**2


def area_shares(src_edges: np.ndarray, dst_edges: np.ndarray) -> np.ndarray:
    """Length (mm) each destination interval shares with each source interval: (n_dst, n_src)."""
    low = np.maximum(dst_edges[:-1, None], src_edges[None, :-1])
    high = np.minimum(dst_edges[1:, None], src_edges[None, 1:])
    return np.clip(high - low, 0.0, None)


def read_pmat_frames(path) -> np.ndarray:
    """Raw counts of one PmatData experiment-I file, shape (frames, 64, 32), head at row 0."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (FileNotFoundError, UnicodeDecodeError) as exc:
        raise DataFileInvalid(f"PmatData file {path} cannot be read: {exc}") from None
    frames = []
    for n, line in enumerate(lines, start=1):
        values = line.split()
        if len(values) != PMAT_SHAPE[0] * PMAT_SHAPE[1]:
            raise DataFileInvalid(f"PmatData file {path}, line {n}: {len(values)} values, expected 2048")
        try:
            frames.append(np.array(values, dtype=float).reshape(PMAT_SHAPE))
        except ValueError:
            raise DataFileInvalid(f"PmatData file {path}, line {n}: a value is not a number") from None
    if not frames:
        raise DataFileInvalid(f"PmatData file {path} holds no frame")
    return np.stack(frames)


def clean_pmat_frames(raw: np.ndarray, source: str = "the recording") -> tuple[np.ndarray, dict]:
    """Counts with bad frames replaced by the last good one and bad cells by their neighbours' median."""
    frames = np.array(raw, dtype=float)
    totals = frames.sum(axis=(1, 2))
    good = (totals > 0.5 * np.median(totals)) & (totals < 2 * np.median(totals))
    if not good.any():
        raise DataFileInvalid(f"no frame of {source} has a plausible total")
    bad_cells = 0
    for frame in (frames[k] for k in np.flatnonzero(good)):
        ring_max = maximum_filter(frame, footprint=_RING, mode="constant")
        bad = (frame >= PMAT_SATURATED) | ((frame > 100) & (frame > 4 * ring_max))
        if bad.any():
            frame[bad] = median_filter(frame, footprint=_RING, mode="constant")[bad]
            bad_cells += int(bad.sum())
    first = int(np.argmax(good))
    for k in range(len(frames)):
        if not good[k]:
            frames[k] = frames[k - 1] if k > first else frames[first]
    return frames, {"bad_frames": int((~good).sum()), "bad_cells": bad_cells}


def pmat_subject(info_path, subject: int) -> tuple[float, float]:
    """(weight_kg, height_cm) of ``subject`` from the UTF-16 ``subject-info-i.csv``."""
    try:
        rows = list(csv.reader(Path(info_path).read_text(encoding="utf-16").splitlines()))
    except (FileNotFoundError, UnicodeError) as exc:
        raise DataFileInvalid(f"PmatData subject file {info_path} cannot be read: {exc}") from None
    for n, row in enumerate(rows[1:], start=2):
        try:
            if int(row[0]) == subject:
                return float(row[3]), float(row[2])
        except (ValueError, IndexError):
            raise DataFileInvalid(f"PmatData subject file {info_path}, row {n}: expected number, age, "
                                  f"height, weight; got {row}") from None
    raise DataFileInvalid(f"PmatData subject file {info_path} has no subject {subject}")


def pmat_scene(pmat_dir, subject: int, posture: int, grid: MatGrid = BED_GRID,
               sensel_mm: float = PMAT_SENSEL_MM, shift_mm: tuple[float, float] = (0.0, 0.0)) -> RecordedScene:
    """PmatData experiment I, subject ``S<subject>``, posture file ``<posture>.txt``, at 1 Hz, in kPa, centred on
    the mat and moved by ``shift_mm`` (across, along)."""
    root = _existing_dir(pmat_dir, "PmatData") / "experiment-i"
    weight_kg, height_cm = pmat_subject(root / "subject-info-i.csv", subject)
    path = root / f"S{subject}" / f"{posture}.txt"
    counts, report = clean_pmat_frames(read_pmat_frames(path), str(path))
    counts = counts[:, :, ::-1]                       # its columns run to the patient's right
    placed = _on_mat(resample_onto(counts, sensel_mm, grid, shift_mm), grid, path)
    kept = placed.sum(axis=(1, 2)) * grid.pitch_mm**2 / (counts.sum(axis=(1, 2)) * sensel_mm**2)
    frames = placed * (weight_kg * G_M_S2 / force_n(placed, grid.pitch_mm))[:, None, None]
    info = {"source": f"PmatData experiment-i S{subject}/{posture}.txt", "weight_kg": weight_kg,
            "height_cm": height_cm, "sensel_mm": sensel_mm, "rate_hz": 1.0, "posture_file": posture,
            "shift_mm": list(shift_mm),
            "kpa_per_count": float(np.median(weight_kg * G_M_S2 / force_n(counts, sensel_mm))),
            "share_off_mat": float(1 - np.median(kept)), **report}
    return RecordedScene(frames, np.arange(len(frames), dtype=float), grid, info)


def read_popu_maps(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Tactilus readings of one PoPu file: maps (n, 64, 27), snapshot times (s), and the file's header."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        shape = (int(data["tactilus_rows"]), int(data["tactilus_columns"]))
        snaps = list(data["snapshots"].values())
        maps = np.stack([np.asarray(s["tactilus_readings"], dtype=float).reshape(shape) for s in snaps])
    except FileNotFoundError:
        raise DataFileInvalid(f"PoPu file {path} does not exist") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise DataFileInvalid(f"PoPu file {path} is not a Tactilus snapshot file: {exc!r}") from None
    header = {k: v for k, v in data.items() if k != "snapshots"}
    return maps, _popu_times([str(s.get("id", "")) for s in snaps]), header


def _popu_times(ids: list[str]) -> np.ndarray:
    """Seconds from the first snapshot, from ids ending in hhmmsscc; evenly spaced if they do not."""
    try:
        clock = np.array([int(i[-8:-6]) * 3600 + int(i[-6:-4]) * 60 + int(i[-4:-2]) + int(i[-2:]) / 100
                          for i in ids])
    except ValueError:
        clock = None
    if clock is None or len(clock) < 2 or not np.all((np.diff(clock) > 0) & (np.diff(clock) < 10)):
        return np.arange(len(ids)) * POPU_SNAPSHOT_S
    return clock - clock[0]


def popu_scene(popu_dir, pose: str = "supine1", variation: int = 0, volunteer: int = 4,
               grid: MatGrid = BED_GRID, sensel_mm: float = POPU_SENSEL_MM,
               scale_to_weight: bool = False) -> RecordedScene:
    """PoPu Tactilus maps for ``<pose>_<variation>.json`` read as mmHg, empty bed subtracted, in kPa.

    ``info["force_ratio"]`` is the recorded force over the volunteer's weight times g;
    ``scale_to_weight`` rescales each frame so the force on the mat is the weight instead.
    """
    folder = _existing_dir(popu_dir, "PoPu") / "preview_data" / "tactilus_data" / str(volunteer)
    maps, times, header = read_popu_maps(folder / f"{pose}_{variation}.json")
    empty_path = folder / "empty1.json"
    if empty_path.exists():
        maps = np.clip(maps - read_popu_maps(empty_path)[0].mean(axis=0), 0.0, None)
    kpa = maps * KPA_PER_MMHG
    weight = header.get("weight")
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not weight > 0:
        raise DataFileInvalid(f"PoPu file {folder / f'{pose}_{variation}.json'}: weight must be a positive "
                              f"number of kg, got {weight!r}")
    weight_n = weight * G_M_S2
    recorded = force_n(kpa, sensel_mm)
    frames = _on_mat(resample_onto(kpa, sensel_mm, grid), grid, folder / f"{pose}_{variation}.json")
    on_mat = force_n(frames, grid.pitch_mm)
    if scale_to_weight:
        frames = frames * (weight_n / on_mat)[:, None, None]
    info = {"source": f"PoPu tactilus {volunteer}/{pose}_{variation}.json", "weight_kg": weight_n / G_M_S2,
            "height_cm": header.get("height"), "sensel_mm": sensel_mm,
            "recorded_force_n": float(np.median(recorded)), "force_ratio": float(np.median(recorded) / weight_n),
            "share_off_mat": float(1 - np.median(on_mat / recorded))}
    return RecordedScene(frames, times, grid, info)


def _on_mat(frames: np.ndarray, grid: MatGrid, source: Path) -> np.ndarray:
    """``frames`` unless one of them lays no force on the mat."""
    if not np.all(force_n(frames, grid.pitch_mm) > 0):
        raise DataFileInvalid(f"{source}: a frame lays no force on the {grid.width_mm:g} x {grid.height_mm:g} mm mat")
    return frames


def _existing_dir(path, what: str) -> Path:
    path = Path(path)
    if not path.is_dir():
        raise DataFileInvalid(f"{what} data directory {path} does not exist")
    return path


PMAT_POSTURES = tuple(range(1, 18))


def pmat_map_loads(pmat_dir, subjects, postures=PMAT_POSTURES, frames_per_posture: int = 1,
                   grid: MatGrid = BED_GRID) -> list:
    """PmatData maps of ``subjects`` as calibration loads (:class:`~appliance.calibration.MapLoad`):
    ``frames_per_posture`` frames spread over the middle half of each posture's recording (the person
    settled), each named ``S<subject>/<posture>#<frame>``."""
    from appliance.calibration import MapLoad

    if frames_per_posture < 1:
        raise DataFileInvalid(f"frames per posture must be 1 or more, got {frames_per_posture}")
    loads = []
    for subject in subjects:
        for posture in postures:
            scene = pmat_scene(pmat_dir, subject, posture, grid)
            n = len(scene.frames)
            picks = np.unique(np.linspace(0.25 * n, 0.75 * n, frames_per_posture).astype(int)) \
                if frames_per_posture > 1 else [n // 2]
            loads += [MapLoad(scene.frames[k], grid.pitch_mm, f"S{subject}/{posture}#{k}") for k in picks]
    return loads
