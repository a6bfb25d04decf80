"""Training the posture classifier (:mod:`appliance.alerts.posture`) from real recordings.

The shipped model is made by ``python -m appliance.alerts.posture_training --train`` from PmatData and PoPu,
whose fields the simulator reads (:mod:`appliance.sim.recordings`); apart from the classifier so that the monitor
and the screen, which only load the model, import no simulator.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import affine_transform, gaussian_filter
from scipy.optimize import minimize

from appliance.alerts.anatomy import LYING, BodyView
from appliance.alerts.posture import MODEL_FILE, PostureModel, posture_features
from appliance.errors import ModelInputInvalid
from appliance.sim.body import MatGrid
from appliance.sim.recordings import pmat_scene, popu_scene, resample_onto

TRAINING_SEED = 20240611
PMAT_POSTURE_NAMES = {1: "supine", 2: "right-90", 3: "left-90", 4: "right-30", 5: "right-60", 6: "left-30",
                      7: "left-60", 8: "supine", 9: "supine", 10: "supine", 11: "supine", 12: "supine",
                      13: "fetal-right", 14: "fetal-left", 15: "inclined", 16: "inclined", 17: "inclined"}
"""PmatData experiment I's posture files by the names the monitor uses."""

POPU_POSE_NAMES = {"supine": "supine", "prone": "prone", "left": "left-90", "right": "right-90"}
"""PoPu's pose families: its left and right poses lie fully on that side (their tilt is not recorded)."""

SHIPPED_PMAT_SUBJECTS = (1, 2, 3, 5, 7, 8, 9, 10)
"""PmatData subjects the shipped model learns from: S4, S6 and S11 validate the whole product."""

SHIPPED_POPU_VARIATIONS = (0, 1)
"""PoPu variations the shipped model learns from: variation 2 is held out."""

BED_PITCH_MM = 1900.0 / 64
"""The default bed's (grid-16x32) pixel along the body; its pixels across are 30 mm, taken here as square
(the view is 1 % narrower than the bed's, which no feature notices)."""

NOISE_KPA = 0.1
"""Noise added to every pixel of an augmented map: a reconstruction's floor away from the body."""

FLOOR_KPA = 0.3
"""An augmented map reads cells under a floor drawn up to this as no load: the bed's reconstructed map reads most
cells under 0.3 kPa as zero (74 % of those between 0.05 and 0.3 kPa in the training subjects' maps read through the
virtual bed) and those above nearly as they are."""

L2 = 1e-4
"""The logistic regression's L2 penalty. With FLOOR_KPA, chosen by leave one training subject out
(``benchmarks/posture_choices.py``: S1-S3, S5, S7-S10 only, their maps clean, blurred and read through the
virtual bed; the held-out S4, S6 and S11 play no part): floor 0.3 kPa and L2 1e-4 took no group wrong on any of
them and gave the true group the most probability, where no floor got 1 to 6 wrong and read 77-80 % of the
chain's tilts against 94 %, and a floor of 0.5 kPa 11 wrong on the clean maps."""

AUGMENTED_COPIES = 3
"""Augmented copies of each training map (besides the map itself and the mirror images of all)."""

N_COMPONENTS = 80
"""Principal components the classifier reads, chosen by leave-one-subject-out over the eight training subjects
alone (S1-S3, S5, S7-S10; the held-out S4, S6 and S11 play no part in any choice): 20, 40 and 80 components
got 99.1, 98.7 and 99.9 % on the 4 groups, 95.3, 93.8 and 96.6 % on the tilt (benchmarks/posture.md, section 0)."""

FRAMES_PER_RECORDING = 6
"""Frames taken from the middle half of each recording (the person settled); more add little, being alike."""


def bed_views(field_kpa: np.ndarray, pitch_mm: float) -> list[BodyView]:
    """Scene fields (n, rows head to foot, cols right to left) as the default bed's pixel grid sees them
    perfectly: block-averaged, force kept, onto its 30 mm pixels."""
    fields = np.asarray(field_kpa, float)
    grid = MatGrid(fields.shape[-1] * pitch_mm // BED_PITCH_MM * BED_PITCH_MM, fields.shape[-2] * pitch_mm,
                   BED_PITCH_MM)
    return [BodyView(m, (BED_PITCH_MM, BED_PITCH_MM), True) for m in resample_onto(fields, pitch_mm, grid)]


def recording_fields(pmat_dir=None, popu_dir=None, subjects=(), popu_variations=(),
                     frames=FRAMES_PER_RECORDING) -> tuple[np.ndarray, list[str], float]:
    """True fields (n, rows, cols) of ``frames`` frames of each chosen recording, their posture names,
    and the fields' pitch (mm)."""
    fields: list[np.ndarray] = []
    names: list[str] = []
    pitch: float | None = None

    def take(scene, name):
        nonlocal pitch
        n = len(scene.frames)
        picks = np.unique(np.linspace(0.25 * n, 0.75 * n, frames).astype(int).clip(0, n - 1))
        fields.extend(scene.frames[picks])
        names.extend([name] * len(picks))
        pitch = scene.grid.pitch_mm

    for subject in subjects:
        for number, name in PMAT_POSTURE_NAMES.items():
            take(pmat_scene(pmat_dir, subject, number), name)
    for variation in popu_variations:
        for family, name in POPU_POSE_NAMES.items():
            for k in range(1, 8):
                take(popu_scene(popu_dir, f"{family}{k}", variation, scale_to_weight=True), name)
    if pitch is None:
        raise ModelInputInvalid("no recordings chosen: name PmatData subjects or PoPu variations")
    return np.stack(fields), names, pitch


def mirrored(name: str) -> str:
    """The posture seen in a mirror: left and right swap."""
    return name.replace("left", "@").replace("right", "left").replace("@", "right")


def augmented(fields: np.ndarray, pitch_mm: float, rng: np.random.Generator,
              floor_kpa: float = FLOOR_KPA) -> list[BodyView]:
    """Fields as a reconstruction might see them: shifted up to 60 mm, turned up to 5 degrees, placed on
    the bed's pixels, blurred (0-1.2 pixel sigma), under a smooth gain of +-20 %, with noise, and the cells
    under a floor (0 to ``floor_kpa``) read as no load."""
    moved = []
    for field in fields:
        angle = np.deg2rad(rng.uniform(-5, 5))
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        centre = (np.array(field.shape) - 1) / 2
        shift = rng.uniform(-60, 60, 2) / pitch_mm
        moved.append(affine_transform(field, turn, offset=centre - turn @ centre - shift, order=1))
    views = []
    for view in bed_views(np.array(moved), pitch_mm):
        kpa = gaussian_filter(view.kpa, rng.uniform(0.0, 1.2))
        gain = 1 + 0.2 * np.clip(gaussian_filter(rng.normal(size=kpa.shape), 3) * 4, -1, 1)
        kpa = kpa * gain * rng.uniform(0.8, 1.2) + rng.normal(0, NOISE_KPA, kpa.shape)
        kpa = np.where(kpa < rng.uniform(0.0, floor_kpa), 0.0, kpa)
        views.append(BodyView(kpa, view.pitch_mm, view.transposed))
    return views


def training_set(fields: np.ndarray, names: list[str], pitch_mm: float, copies: int, seed,
                 floor_kpa: float = FLOOR_KPA):
    """Feature rows and names: each field as the bed sees it, ``copies`` augmented copies, and the mirror
    image of each (left and right swapped), so both sides learn from every side posture."""
    rng = np.random.default_rng(seed)
    rows, labels = [], []
    for flip, label_of in ((False, str), (True, mirrored)):
        source = fields[:, :, ::-1] if flip else fields
        views = bed_views(source, pitch_mm)
        for _ in range(copies):
            views += augmented(source, pitch_mm, rng, floor_kpa)
        rows += [posture_features(v) for v in views]
        labels += [label_of(n) for n in names] * (copies + 1)
    return np.array(rows), labels


def fit_logistic(features: np.ndarray, labels: list[str], l2: float = L2,
                 n_components: int = N_COMPONENTS) -> PostureModel:
    """Multinomial logistic regression on the leading principal components of the standardised features,
    classes weighted equally (supine has six recordings a subject, a side posture one), with an L2
    penalty; folded into one linear map over the features."""
    classes = tuple(p for p in LYING + ("inclined",) if p in set(labels))
    y = np.array([classes.index(n) for n in labels])
    mean, scale = features.mean(axis=0), features.std(axis=0) + 1e-6
    axes = np.linalg.svd((features - mean) / scale, full_matrices=False)[2][:n_components]
    x = (features - mean) / scale @ axes.T
    counts = np.bincount(y, minlength=len(classes))
    sample_weight = (len(y) / (len(classes) * counts))[y] / len(y)
    onehot = np.eye(len(classes))[y]
    n_axes = x.shape[1]

    def loss(theta):
        w = theta[:len(classes) * n_axes].reshape(len(classes), n_axes)
        b = theta[len(classes) * n_axes:]
        logits = x @ w.T + b
        logits -= logits.max(axis=1, keepdims=True)
        log_p = logits - np.log(np.exp(logits).sum(axis=1, keepdims=True))
        residual = (np.exp(log_p) - onehot) * sample_weight[:, None]
        value = -(sample_weight * (log_p * onehot).sum(axis=1)).sum() + 0.5 * l2 * (w**2).sum()
        return value, np.concatenate([(residual.T @ x + l2 * w).ravel(), residual.sum(axis=0)])

    theta0 = np.zeros(len(classes) * (n_axes + 1))
    fit = minimize(loss, theta0, jac=True, method="L-BFGS-B", options={"maxiter": 2000})
    w = fit.x[:len(classes) * n_axes].reshape(len(classes), n_axes) @ axes / scale
    b = fit.x[len(classes) * n_axes:] - w @ mean
    return PostureModel(classes, w, b, {"l2": l2, "components": n_components, "iterations": int(fit.nit),
                                        "samples": len(y)})


def training_features(pmat_dir, popu_dir, subjects=SHIPPED_PMAT_SUBJECTS,
                      popu_variations=SHIPPED_POPU_VARIATIONS, copies: int = AUGMENTED_COPIES,
                      seed: int = TRAINING_SEED, floor_kpa: float = FLOOR_KPA) -> dict:
    """Feature rows and posture names of each source (``S<k>``, ``popu/v<variation>``), augmented with a
    seed of the source's own, so a source's rows are the same whichever others are trained with."""
    sources = [(f"S{k}", [k], [], k) for k in subjects] + \
              [(f"popu/v{v}", [], [v], 1000 + v) for v in popu_variations]
    out = {}
    for name, pmat_subjects, variations, stream in sources:
        fields, names, pitch = recording_fields(pmat_dir, popu_dir, pmat_subjects, variations)
        out[name] = training_set(fields, names, pitch, copies, [seed, stream], floor_kpa)
    return out


def fit_sources(features_by_source: dict, sources) -> PostureModel:
    """The model learnt from the named sources of :func:`training_features`."""
    model = fit_logistic(np.vstack([features_by_source[s][0] for s in sources]),
                         [n for s in sources for n in features_by_source[s][1]])
    model.info["sources"] = list(sources)
    return model


def train_posture_model(pmat_dir, popu_dir, subjects=SHIPPED_PMAT_SUBJECTS,
                        popu_variations=SHIPPED_POPU_VARIATIONS, copies: int = AUGMENTED_COPIES,
                        seed: int = TRAINING_SEED) -> PostureModel:
    """A posture model learnt from PmatData ``subjects`` and PoPu ``popu_variations``; deterministic."""
    features = training_features(pmat_dir, popu_dir, subjects, popu_variations, copies, seed)
    model = fit_sources(features, list(features))
    model.info.update({"copies": copies, "seed": seed})
    return model


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m appliance.alerts.posture_training",
                                     description="Rebuild the shipped posture model from the recordings.")
    parser.add_argument("--train", action="store_true", required=True)
    parser.add_argument("--pmat", required=True, help="PmatData directory (holds experiment-i)")
    parser.add_argument("--popu", required=True, help="PoPu directory (holds preview_data)")
    parser.add_argument("--out", default=str(Path(__file__).with_name(MODEL_FILE)))
    args = parser.parse_args(argv)
    model = train_posture_model(args.pmat, args.popu)
    model.save(args.out)
    print(f"wrote {args.out}: classes {', '.join(model.classes)}; {model.info}")


if __name__ == "__main__":
    main()
