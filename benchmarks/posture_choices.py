"""Posture choices: the augmentation's low-pressure floor and the L2 penalty, by leave one training subject out.

    python benchmarks/posture_choices.py --pmat ../shared/data/pmatdata --popu ../shared/data/popu
    # writes benchmarks/posture_choices.md (about 25 min on a loaded 2-core machine)

Only the eight training subjects (S1-S3, S5, S7-S10) take part: each is left out in turn, a model is learnt
from the other seven (and PoPu variations 0 and 1) and judged on the left-out subject's 17 postures. Maps
judged: six frames of each recording as the bed's pixels see them ("clean"), the same blurred
(``benchmarks/posture.py``'s stand-in for reconstruction), and the middle frame of each recording read through
the whole chain as ``benchmarks/alerts.py`` reads it (virtual bed, parallel board, reconstruction,
calibration). The group is the one whose postures have the most probability together; "-log p" is the mean
negative log of the true group's probability (lower is surer and righter). S4, S6 and S11 play no part.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from appliance.alerts.anatomy import body_view, posture_group, tilt_deg
from appliance.alerts.posture import posture_features
from appliance.alerts.posture_training import (FLOOR_KPA, L2, SHIPPED_PMAT_SUBJECTS, SHIPPED_POPU_VARIATIONS, bed_views,
                                                fit_logistic, recording_fields, training_features)

sys.path.insert(0, str(Path(__file__).parent))
from held_out_chain import MINUTE, POSTURE_OF_FILE, Chain, still_scene, true_frame
from posture import blurred
from report import machine, table

HERE = Path(__file__).resolve().parent
CHOICES = ((0.0, 1e-3), (0.0, 1e-4), (0.3, 1e-3), (0.3, 1e-4), (0.5, 1e-4))
"""(augmentation floor kPa, L2 penalty): no floor with the former L2 (its augmentation draws differ from the former
model's, the floor's level being drawn even when it is 0), and the candidates."""


def chain_reads(chain: Chain, subject: int) -> tuple[list[str], list]:
    """The middle frame of each of the subject's 17 recordings read through the chain: names and views."""
    names, views = [], []
    for posture_file in range(1, 18):
        frame = true_frame(subject, posture_file)
        read = list(chain.maps(still_scene(frame, 5 * MINUTE), [0.0, MINUTE]))[-1].pressure_kpa
        names.append(POSTURE_OF_FILE[posture_file])
        views.append(body_view(read, chain.grid))
    return names, views


def group_scores(model, names: list[str], rows: np.ndarray) -> tuple[int, float, int, int, int]:
    """Wrong groups, summed -log p of the true group, right tilts, side maps, and maps."""
    p = model.probabilities(rows)
    groups = [posture_group(c) for c in model.classes]
    kinds = sorted(set(groups))
    by_group = np.stack([p[:, [k for k, g in enumerate(groups) if g == kind]].sum(axis=1) for kind in kinds], 1)
    wrong, nll, tilts, sides = 0, 0.0, 0, 0
    for name, pg, pp in zip(names, by_group, p):
        best = kinds[int(np.argmax(pg))]
        wrong += best != posture_group(name)
        nll -= float(np.log(pg[kinds.index(posture_group(name))] + 1e-12))
        if tilt_deg(name) is not None:
            within = [k for k, g in enumerate(groups) if g == best]
            sides += 1
            tilts += tilt_deg(model.classes[within[int(np.argmax(pp[within]))]]) == tilt_deg(name)
    return wrong, nll, tilts, sides, len(names)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pmat", required=True)
    parser.add_argument("--popu", required=True)
    args = parser.parse_args()
    command = f"python benchmarks/posture_choices.py --pmat {args.pmat} --popu {args.popu}"
    chain = Chain(Path(tempfile.gettempdir()) / "appliance-bench-cache")
    tests = {}
    for k in SHIPPED_PMAT_SUBJECTS:
        fields, names, pitch = recording_fields(args.pmat, None, [k])
        views = bed_views(fields, pitch)
        chain_names, chain_views = chain_reads(chain, k)
        tests[k] = {"clean": (names, np.array([posture_features(v) for v in views])),
                    "blurred": (names, np.array([posture_features(v) for v in blurred(views)])),
                    "chain": (chain_names, np.array([posture_features(v) for v in chain_views]))}
        print(f"S{k} read through the chain", flush=True)
    rows = []
    for floor_kpa, l2 in CHOICES:
        features = training_features(args.pmat, args.popu, SHIPPED_PMAT_SUBJECTS, SHIPPED_POPU_VARIATIONS,
                                     floor_kpa=floor_kpa)
        totals = {which: np.zeros(5) for which in ("clean", "blurred", "chain")}
        for k in SHIPPED_PMAT_SUBJECTS:
            sources = [s for s in features if s != f"S{k}"]
            model = fit_logistic(np.vstack([features[s][0] for s in sources]),
                                 [x for s in sources for x in features[s][1]], l2=l2)
            for which, (names, x) in tests[k].items():
                totals[which] += group_scores(model, names, x)
        row = [f"{floor_kpa:.1f}", f"{l2:g}"]
        for wrong, nll, tilts, sides, n in totals.values():
            row += [f"{100 * (1 - wrong / n):.1f} % ({int(wrong)})", f"{nll / n:.3f}", f"{100 * tilts / sides:.1f} %"]
        rows.append(row)
        print(row, flush=True)
    n = {which: int(sum(len(tests[k][which][0]) for k in tests)) for which in ("clean", "blurred", "chain")}
    header = ["floor kPa", "L2"] + [f"{w} {c}" for w in ("clean", "blurred", "chain") for c in
                                    ("4 groups (wrong)", "-log p", "tilt")]
    report = f"""# Posture choices: augmentation floor and L2 penalty

Made by `{command}` on {machine()}.
Leave one training subject out over S1-S3, S5, S7-S10 only (S4, S6 and S11 play no part); maps: {n["clean"]}
clean, {n["blurred"]} blurred, {n["chain"]} read through the chain. The shipped model uses floor {FLOOR_KPA} kPa
and L2 {L2:g}.

{table(header, rows)}
"""
    (HERE / "posture_choices.md").write_text(report, encoding="utf-8")
    print(report)


if __name__ == "__main__":
    main()
