"""Which posture a patient lies in, from one pressure map seen as the body.

Two postures come from rules, because no recording shows them: ``out-of-bed``
(too little force on the mat for a body) and ``sitting-edge`` (all the load in a
short stretch beside one long edge). The lying postures come from a linear
classifier (multinomial logistic regression) trained on real recordings: PmatData
experiment I for supine, the side postures at 30, 60 and 90 degrees, the curled
ones and the raised head of the bed; PoPu's single volunteer for prone.

The features do not depend on where the body lies on the mat or on its weight:
the map is normalised to unit force and resampled, by area, onto a canonical grid
centred on its centre of force, then square-rooted (so the broad, light load of
the back and legs counts beside the bony peaks, and a peak that is 12 % off moves
the feature little). Moments of the load across the body (spread, skew, and the
spread in bands along the body) are appended: they carry how far the pelvis and
shoulders have rolled, which is what separates 30, 60 and 90 degrees.

The model is trained on maps as the default bed's pixel grid would see them,
augmented with the errors of reconstruction (blur, gain, shift, rotation,
noise, light load read as none; :mod:`appliance.alerts.posture_training`); ``benchmarks/posture.py``
reports how well it holds on subjects it never saw. The shipped model
(``posture_model.npz``) never saw PmatData S4, S6 and S11.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from importlib import resources

import numpy as np

from appliance.alerts.anatomy import LYING, POSTURES, BodyView, posture_group
from appliance.errors import DataFileInvalid, ModelInputInvalid

MIN_BODY_FORCE_N = 100.0
"""Less than this on the mat is out of bed: about 10 kg, a third of the lightest adult's trunk, while a
pillow, a bag or a hand leaning on the mat weighs less (the weight of a body lying or sitting is on the mat)."""

LOADED_KPA = 0.5
"""A cell carries load above this (about 4 mmHg): under it lies the noise floor of a reconstructed map."""

MIN_LOADED_AREA_M2 = 0.04
"""Less loaded area than this is out of bed, whatever the force: a lying adult loads 0.25 m2 or more and
a sitting one about 0.1 m2, while a bag or a knee on the mat loads a few hundred cm2."""

SITTING_MAX_LENGTH_MM = 700.0
"""Sitting puts the load within the width of the hips and thighs along the mat (about 400-500 mm);
lying loads 1.4 m or more, curled up 1 m."""

SITTING_EDGE_MM = 450.0
"""A patient sitting on the edge loads only the strip of the mat this deep from that long edge: the
ischial tuberosities sit 100-200 mm in, the backs of the thighs run out to the edge."""

SITTING_SHARE = 0.95
"""Share of the force that must lie within the sitting region (a hand on the mat may carry the rest)."""

CANONICAL_PITCH_MM = 40.0
CANONICAL_SHAPE = (54, 24)
"""The body-centred grid: 2160 mm along (a tall patient from either end of their centre of force) by
960 mm across, in 40 mm cells, coarser than the bed's 30 mm pixels, so a blurred map's features change little."""

BODY_BANDS_MM = ((-900.0, -450.0), (-450.0, -150.0), (-150.0, 150.0), (150.0, 450.0), (450.0, 1200.0))
"""Bands along the body, mm from the centre of force (about the buttocks): shoulders, back, pelvis,
thighs, legs; the load's spread across in each says how far that part has rolled."""

MODEL_FILE = "posture_model.npz"

SURE_GROUP_PROBABILITY = 0.8
"""An estimate is sure when the postures of its group (back, left, right, front or other) together have at least
this probability. Chosen on the leave-one-subject-out study over the eight training subjects alone (816 maps,
clean and blurred, with the model before the augmentation's low-pressure floor): every wrong group there had at
most 0.64, and 99 % of the right ones 0.83 or more. An unsure estimate must not count as a turn or rename the
sites (a supine patient with the arms raised can read as lying on the side); the alert layer holds the last sure
posture instead."""


@dataclass(frozen=True)
class PostureEstimate:
    """A posture, the probability the model gives it (``confidence``) and every posture's probability."""

    posture: str
    confidence: float
    probabilities: dict

    @classmethod
    def certain(cls, posture: str) -> PostureEstimate:
        """A posture known for sure (a rule's, or a test's)."""
        return cls(posture, 1.0, {p: float(p == posture) for p in POSTURES})

    @property
    def group_probability(self) -> float:
        """The probability that the patient lies in this posture's group, whichever posture of it."""
        group = posture_group(self.posture)
        return float(sum(v for p, v in self.probabilities.items() if posture_group(p) == group))

    @property
    def sure(self) -> bool:
        return self.group_probability >= SURE_GROUP_PROBABILITY


def check_view(view: BodyView) -> np.ndarray:
    """The view's pressures with unknown (NaN) and negative cells read as no load; ModelInputInvalid if
    the view is not a 2-D map with at least one known cell."""
    kpa = np.asarray(view.kpa, dtype=float)
    if kpa.ndim != 2 or min(kpa.shape) < 2:
        raise ModelInputInvalid(f"a posture needs a 2-D pressure map, got shape {kpa.shape}")
    if not np.isfinite(kpa).any():
        raise ModelInputInvalid("the pressure map holds no finite value: no posture can be read from it")
    if np.isinf(kpa).any():
        raise ModelInputInvalid("the pressure map holds an infinite value")
    if not (len(view.pitch_mm) == 2 and all(p > 0 for p in view.pitch_mm)):
        raise ModelInputInvalid(f"cell pitch must be two positive lengths, got {view.pitch_mm!r}")
    return np.clip(np.nan_to_num(kpa, nan=0.0), 0.0, None)


def force_on_mat_n(view: BodyView) -> float:
    """Force (N) the view's map lays on the mat."""
    return float(check_view(view).sum() * view.pitch_mm[0] * view.pitch_mm[1] * 1e-3)


def is_out_of_bed(view: BodyView) -> bool:
    """Too little force or loaded area for a body (see MIN_BODY_FORCE_N and MIN_LOADED_AREA_M2)."""
    kpa = check_view(view)
    area_m2 = (kpa > LOADED_KPA).sum() * view.pitch_mm[0] * view.pitch_mm[1] * 1e-6
    return force_on_mat_n(view) < MIN_BODY_FORCE_N or area_m2 < MIN_LOADED_AREA_M2


def is_sitting_on_edge(view: BodyView) -> bool:
    """All the load in a stretch shorter than SITTING_MAX_LENGTH_MM along the mat and within
    SITTING_EDGE_MM of one long edge, so no head and no heels on the mat.

    A rule, not a learnt class: no recording of a patient sitting on the edge exists here, so it is
    tested on synthetic sitting maps only and is not validated on real ones.
    """
    kpa = check_view(view)
    total = kpa.sum()
    if total <= 0:
        return False
    along = np.cumsum(kpa.sum(axis=1)) / total
    window = max(1, int(SITTING_MAX_LENGTH_MM // view.pitch_mm[0]))
    in_window = np.max(along[window - 1:] - np.concatenate([[0.0], along[:-window]])) \
        if window < len(along) else 1.0
    across = kpa.sum(axis=0) / total
    strip = max(1, round(SITTING_EDGE_MM / view.pitch_mm[1]))
    at_an_edge = max(across[:strip].sum(), across[-strip:].sum())
    return in_window >= SITTING_SHARE and at_an_edge >= SITTING_SHARE


def _rebin_weights(src_edges: np.ndarray, dst_edges: np.ndarray) -> np.ndarray:
    """Share of each source cell (columns) that falls in each destination cell (rows): the difference of
    the cell's cumulative mass at the destination edges, mass spread evenly over the cell."""
    width = np.diff(src_edges)
    cumulative = np.clip((dst_edges[:, None] - src_edges[None, :-1]) / width[None, :], 0.0, 1.0)
    return np.diff(cumulative, axis=0)


def canonical_map(view: BodyView) -> np.ndarray:
    """The map's share of force in each cell of CANONICAL_SHAPE, centred on the centre of force; the
    share that falls outside the grid is dropped."""
    kpa = check_view(view)
    mass = kpa / kpa.sum() if kpa.sum() > 0 else kpa
    grids = []
    for axis, (n_dst, pitch) in enumerate(zip(CANONICAL_SHAPE, view.pitch_mm)):
        src_edges = np.arange(kpa.shape[axis] + 1) * pitch
        centre = (mass.sum(axis=1 - axis) * (src_edges[:-1] + pitch / 2)).sum()
        dst_edges = centre + (np.arange(n_dst + 1) - n_dst / 2) * CANONICAL_PITCH_MM
        grids.append(_rebin_weights(src_edges, dst_edges))
    return grids[0] @ mass @ grids[1].T


def moment_features(view: BodyView) -> np.ndarray:
    """How the load spreads across the body: overall spread and skew across and along, their
    correlation, and the spread across, the share and the offset of the centre in each band of
    BODY_BANDS_MM. Lengths in units of 100 mm."""
    kpa = check_view(view)
    total = kpa.sum()
    mass = kpa / total if total > 0 else kpa
    along = (np.arange(kpa.shape[0]) + 0.5) * view.pitch_mm[0]
    across = (np.arange(kpa.shape[1]) + 0.5) * view.pitch_mm[1]
    a0 = (mass.sum(axis=1) * along).sum()
    c0 = (mass.sum(axis=0) * across).sum()
    da, dc = along[:, None] - a0, across[None, :] - c0
    sa, sc = np.sqrt((mass * da**2).sum()), np.sqrt((mass * dc**2).sum())
    features = [sa / 100, sc / 100, (mass * dc**3).sum() / max(sc, 1.0)**3, (mass * da**3).sum() / max(sa, 1.0)**3,
                (mass * da * dc).sum() / max(sa * sc, 1.0)]
    for low, high in BODY_BANDS_MM:
        rows = (along - a0 >= low) & (along - a0 < high)
        band = mass[rows].sum(axis=0)
        share = band.sum()
        centre = (band * dc[0]).sum() / share if share > 1e-6 else 0.0
        spread = np.sqrt((band * (dc[0] - centre)**2).sum() / share) if share > 1e-6 else 0.0
        features += [share, centre / 100, spread / 100]
    return np.array(features)


def posture_features(view: BodyView) -> np.ndarray:
    """The feature vector the classifier reads: the square root of the canonical map, then the moments."""
    return np.concatenate([np.sqrt(canonical_map(view)).ravel(), moment_features(view)])


class PostureModel:
    """A linear model over posture features: ``probabilities = softmax(weights @ features + bias)``."""

    def __init__(self, classes, weights: np.ndarray, bias: np.ndarray, info: dict | None = None):
        self.classes = tuple(str(c) for c in classes)
        self.weights, self.bias = np.asarray(weights, float), np.asarray(bias, float)
        self.info = dict(info or {})
        n_features = len(posture_features(BodyView(np.ones((4, 4)), (10.0, 10.0), False)))
        unknown = [c for c in self.classes if c not in LYING + ("inclined",)]
        if unknown or self.weights.shape != (len(self.classes), n_features) or self.bias.shape != (len(self.classes),):
            raise DataFileInvalid(f"a posture model needs known lying postures (got unknown {unknown}) and weights of "
                                  f"shape ({len(self.classes)}, {n_features}), got {self.weights.shape}")

    def probabilities(self, features: np.ndarray) -> np.ndarray:
        """Class probabilities for feature rows (n, n_features), shape (n, n_classes)."""
        return _softmax(np.atleast_2d(features) @ self.weights.T + self.bias)

    def classify(self, view: BodyView) -> PostureEstimate:
        """The posture of ``view``: the rules first (out of bed, sitting on the edge), then the classifier."""
        for rule, posture in ((is_out_of_bed, "out-of-bed"), (is_sitting_on_edge, "sitting-edge")):
            if rule(view):
                return PostureEstimate.certain(posture)
        p = self.probabilities(posture_features(view))[0]
        learnt = dict(zip(self.classes, p.tolist()))
        best = self._most_likely(p)
        return PostureEstimate(self.classes[best], float(p[best]), {q: learnt.get(q, 0.0) for q in POSTURES})

    def _most_likely(self, p: np.ndarray) -> int:
        """The class index of the most likely posture within the most likely group: the group is what the alerts
        act on, and a side split between its tilts (0.3 at 30 degrees, 0.3 at 60) is likelier than a back at 0.4."""
        groups = [posture_group(c) for c in self.classes]
        totals: dict[str, float] = {}
        for group, value in zip(groups, p):
            totals[group] = totals.get(group, 0.0) + float(value)
        best_group = max(totals, key=lambda g: totals[g])
        return max((k for k, g in enumerate(groups) if g == best_group), key=lambda k: p[k])

    def save(self, path) -> None:
        """Write the model as a small .npz, its weights in float32 (half the size; a freshly trained model's
        probabilities move by that rounding only, and a loaded one saves and loads back unchanged)."""
        np.savez_compressed(path, classes=np.array(self.classes), weights=self.weights.astype(np.float32),
                            bias=self.bias, info=np.array(json.dumps(self.info)))

    @classmethod
    def load(cls, path) -> PostureModel:
        try:
            with np.load(path, allow_pickle=False) as data:
                return cls(data["classes"], data["weights"].astype(float), data["bias"], json.loads(str(data["info"])))
        except (OSError, KeyError, ValueError) as exc:
            raise DataFileInvalid(f"posture model {path} cannot be read: {exc}") from None


@functools.lru_cache(maxsize=1)
def default_posture_model() -> PostureModel:
    """The shipped model (trained without PmatData S4, S6, S11 and PoPu variation 2), loaded once."""
    with resources.as_file(resources.files("appliance.alerts").joinpath(MODEL_FILE)) as path:
        return PostureModel.load(path)


def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)
