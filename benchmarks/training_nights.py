"""Nights of the training subjects, each judged by an alert layer that never saw that subject.

    python benchmarks/training_nights.py     # writes benchmarks/training_nights.md (about 15 min)

The alert layer's constants (the site locator's distances, the tilt's sacral box, the turn rules) may be chosen
only on the training subjects (S1-S3, S5, S7-S10); benchmarks/alerts.md judges them on the held-out ones. This
is the study they are chosen by at the level of whole nights: the same four nights as alerts.md for each
training subject, the truth from that subject's hand labels, and the alert layer run with a posture model and a
site table both fitted on the other seven training subjects (and PoPu's variations 0 and 1, as shipped), on the
true maps and on the maps read through the virtual bed. The bed's pressure calibration was fitted on all eight,
so the chain's rows are not held out from it.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import sys
import tempfile
import time
from functools import partial
from pathlib import Path

from appliance.alerts.posture_training import SHIPPED_POPU_VARIATIONS, fit_sources, training_features
from appliance.alerts.site_table_fit import TRAINING_SUBJECTS, label_maps
from appliance.alerts.sites import locate_sites

sys.path.insert(0, str(Path(__file__).parent))
from alerts import NIGHT_COLUMNS, NIGHT_SUMMARY, night_rows, nights, run_night, summary_rows  # noqa: E402
from held_out_chain import PMAT, POSTURE_OF_FILE, Chain, true_frame  # noqa: E402
from report import machine, table  # noqa: E402
from site_labels import LABELS, labelled_spots, leave_one_out_tables  # noqa: E402

HERE = Path(__file__).parent
POPU = PMAT.parent / "popu"
ON_THE_RIGHT = (2, 8, 10)
"""Three of the eight lie on their right side for the side-lying night, the others on their left."""


def postures_read(model, subject: int, chain: Chain, posture_files) -> list[str]:
    """The posture ``model`` reads on the true map (monitor pixels) of each of the subject's ``posture_files``,
    with its probability, where it is not the posture recorded."""
    out = []
    for posture_file in posture_files:
        estimate = model.classify(chain.true_view(true_frame(subject, posture_file)))
        if estimate.posture != POSTURE_OF_FILE[posture_file]:
            out.append(f"{POSTURE_OF_FILE[posture_file]} read as {estimate.posture} ({estimate.confidence:.2f})")
    return out


def main() -> None:
    if sys.argv[1:]:
        raise SystemExit(f"usage: python benchmarks/training_nights.py, got {' '.join(sys.argv[1:])}")
    started = time.perf_counter()
    chain = Chain(Path(tempfile.gettempdir()) / "appliance-bench-cache")
    spots = labelled_spots(TRAINING_SUBJECTS)
    tables = leave_one_out_tables(list(label_maps(LABELS, PMAT, TRAINING_SUBJECTS)))
    features = training_features(PMAT, POPU, TRAINING_SUBJECTS, SHIPPED_POPU_VARIATIONS)
    results, misread = [], []
    for subject in TRAINING_SUBJECTS:
        others = [name for name in features if name != f"S{subject}"]
        posture_model = fit_sources(features, others)
        layer = {"classify": posture_model.classify, "locate": partial(locate_sites, table=tables[subject])}
        subject_nights = nights([subject], ON_THE_RIGHT)
        for night in subject_nights:
            results.append((night, run_night(night, chain, spots, **layer)))
            print(f"S{subject} {night.name}", flush=True)
        held = sorted({posture_file for night in subject_nights for posture_file, _, _ in night.segments})
        misread.append([f"S{subject}", "; ".join(postures_read(posture_model, subject, chain, held)) or "none"])
    rows, totals = night_rows(results)
    report = f"""# Nights of the training subjects, each left out of the alert layer's fit

Made by `python benchmarks/training_nights.py` on {machine()} ({(time.perf_counter() - started) / 60:.0f} min).
The four nights of `benchmarks/alerts.md` (turned every 2 h through supine and 30 degree tilts, 12 h; unturned
supine, 8 h; side-lying at 90 degrees, 4 h, on the right for S{", S".join(map(str, ON_THE_RIGHT))}, on the left
for the others; a restless night of small shifts, 8 h) for each training subject, one map a minute. **Truth**: the
dose rule at the sites of the subject's own hand labels on the true maps, as in alerts.md. The alert layer that
judges a subject's nights has a posture model and a site table fitted without that subject (on the other seven
and PoPu's variations 0 and 1); the chain's pressure calibration was fitted on all eight. This is the study the
alert layer's constants are chosen by; `benchmarks/alerts.md` judges them on S4, S6 and S11.

{table(NIGHT_SUMMARY, summary_rows(totals))}

{table(NIGHT_COLUMNS, rows)}

Postures the model fitted without the subject reads wrong on the true maps the nights hold (the probability
it gives its reading); a 60 or 90 degree tilt has no sacrum or occiput in the convention, so a 30 degree tilt
read as one relieves both:

{table(["subject", "posture recorded, read as"], misread)}
"""
    (HERE / "training_nights.md").write_text(report, encoding="utf-8")
    print(report)


if __name__ == "__main__":
    main()
