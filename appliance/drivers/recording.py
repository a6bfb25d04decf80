"""Writing acquired frames: the frame file of DESIGN.md and a quality file beside it.

``F.csv`` is exactly the frame contract (``drive_pos,drive_neg,meas_pos,meas_neg,volts``,
NaN where a reading is unusable), so every reader of frames reads it.
``F.quality.csv`` carries per reading what the contract has no room for: the
flags, the range, the share of full scale and when it was taken. Both are
written to a temporary file and renamed, so a crash or power loss leaves either
the old file or the new one, never half of one.
"""

from __future__ import annotations

import io
from pathlib import Path

from appliance.core.frames import frame_to_csv
from appliance.drivers.scan import AcquiredFrame, flag_names
from appliance.files import write_atomic

QUALITY_HEADER = ("drive_pos", "drive_neg", "meas_pos", "meas_neg", "measured_volts", "flags", "range",
                  "full_scale_fraction", "time_s")


def quality_path(frame_path: Path) -> Path:
    """``F.quality.csv`` beside ``F.csv``."""
    frame_path = Path(frame_path)
    return frame_path.with_name(frame_path.stem + ".quality.csv")


def quality_to_csv(frame: AcquiredFrame) -> str:
    out = io.StringIO()
    temperature = "unknown" if frame.temperature_c is None else f"{frame.temperature_c:.2f}"
    out.write(f"# sets={frame.sets} drive_current_a={frame.drive_current_a:.6e} duration_s={frame.duration_s:.4f} "
              f"temperature_c={temperature}\n")
    for condition in frame.conditions:
        out.write(f"# condition: {condition}\n")
    out.write(",".join(QUALITY_HEADER) + "\n")
    for k, row in enumerate(frame.protocol.readings.tolist()):
        out.write(f"{row[0]},{row[1]},{row[2]},{row[3]},{frame.measured_volts[k]:.9e},"
                  f"{flag_names(int(frame.flags[k]))},{frame.range_index[k]},{frame.fraction[k]:.4f},"
                  f"{frame.time_s[k]:.6f}\n")
    return out.getvalue()


def write_frame(path: Path, frame: AcquiredFrame) -> None:
    """Write the frame file and its quality file, each atomically."""
    write_atomic(Path(path), frame_to_csv(frame.protocol, frame.volts))
    write_atomic(quality_path(path), quality_to_csv(frame))


def series_paths(path: Path, count: int) -> list[Path]:
    """One path per set of a timed series: ``run.csv`` gives ``run-001.csv``, ``run-002.csv``, ..."""
    path = Path(path)
    if count == 1:
        return [path]
    return [path.with_name(f"{path.stem}-{k:03d}{path.suffix}") for k in range(1, count + 1)]
