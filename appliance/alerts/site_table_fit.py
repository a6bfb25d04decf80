"""Fitting the site table (:mod:`appliance.alerts.site_table`) from the hand-labelled maps.

The labels name spots of PmatData maps, which the simulator reads (:mod:`appliance.sim.recordings`); apart from
the table so that the monitor and the screen, which only look sites up, import no simulator. Rebuild the shipped
table (``site_table.json``) with
``python -m appliance.alerts.site_table_fit --fit tests/data/site_labels --pmat PMATDATA_DIR``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from appliance.alerts.anatomy import BodyView, body_view
from appliance.alerts.body_frame import body_coordinates
from appliance.alerts.site_table import TABLE_PATH, LabelledPoint, SiteTable, relative_load
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.errors import DataFileInvalid
from appliance.sim.body import MatGrid
from appliance.sim.recordings import pmat_scene
from appliance.sim.true_maps import on_pixels

TRAINING_SUBJECTS = (1, 2, 3, 5, 7, 8, 9, 10)
"""PmatData subjects whose labels are fitted; S4, S6 and S11 are held out for validation."""

LABEL_MAT_MM = (900.0, 1900.0, 10.0)
"""The 10 mm mat the labels' positions are on (width, length, pitch)."""
MONITOR_LAYOUT = "grid-16x32"
"""The default bed's pixels: the frame is fitted on the map as the monitor sees it."""


def label_maps(label_dir: Path, pmat_dir: Path, subjects=TRAINING_SUBJECTS):
    """(subject, posture, view, spots) of every labelled map of ``subjects``: the middle frame the labels were
    given on, as the monitor's pixels see it; spots as in the label files."""
    grid, mat = pixel_grid(get_layout(MONITOR_LAYOUT)), MatGrid(*LABEL_MAT_MM)
    for subject in subjects:
        path = Path(label_dir) / f"pmatdata-S{subject}.json"
        try:
            maps = json.loads(path.read_text(encoding="utf-8"))["maps"]
        except (OSError, json.JSONDecodeError, KeyError) as exc:
            raise DataFileInvalid(f"site labels {path}: {exc}") from None
        for entry in maps:
            scene = pmat_scene(pmat_dir, subject, entry["posture_file"], mat)
            frame = scene.frames[len(scene.frames) // 2]
            yield subject, entry["posture"], body_view(on_pixels(frame, mat.pitch_mm, grid), grid), entry["spots"]


def labelled_points(subject: int, posture: str, view: BodyView, spots: list[dict]) -> list[LabelledPoint]:
    """The spots of one labelled map as points: the pixel each lies in, as the locator sees that pixel (where its
    centre lies in the body frame, its relative load)."""
    rows = np.array([int(p["along_mm"] // view.pitch_mm[0]) for p in spots], dtype=int)
    cols = np.array([int(p["across_mm"] // view.pitch_mm[1]) for p in spots], dtype=int)
    s, u = body_coordinates(view, posture, (rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1])
    load = relative_load(view, rows, cols)
    return [LabelledPoint(subject, posture, float(a), float(b), float(w), p["site"])
            for a, b, w, p in zip(s, u, load, spots)]


def fit_table(label_dir: Path, pmat_dir: Path, subjects=TRAINING_SUBJECTS) -> SiteTable:
    """The table learned from the labels of ``subjects`` (by default the training subjects only)."""
    points = [p for args in label_maps(label_dir, pmat_dir, subjects) for p in labelled_points(*args)]
    return SiteTable.from_points(points)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Rebuild the site table from the hand labels.")
    parser.add_argument("--fit", type=Path, required=True, metavar="LABEL_DIR", help="tests/data/site_labels")
    parser.add_argument("--pmat", type=Path, required=True, help="the PmatData folder the labels were given on")
    parser.add_argument("--out", type=Path, default=TABLE_PATH)
    args = parser.parse_args(argv)
    table = fit_table(args.fit, args.pmat)
    data = {"about": "hand-labelled spots of PmatData training subjects, their pixels in their body frames: "
                     "[s, u, relative load, site]; rebuilt by "
                     "python -m appliance.alerts.site_table_fit --fit LABEL_DIR",
            "subjects": list(TRAINING_SUBJECTS), "postures": table.to_json()}
    args.out.write_text(json.dumps(data, separators=(",", ":")) + "\n", encoding="utf-8")
    print(f"{args.out}: {sum(len(v[1]) for v in table.points.values())} points")


if __name__ == "__main__":
    main()
