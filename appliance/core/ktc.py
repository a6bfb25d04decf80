"""The Kuopio Tomography Challenge 2023 data: its tank as a layout, its patterns as a protocol.

The tank is a 230 mm disc of saline with 32 electrodes on its wall, 11.3 mm wide,
electrode 1 at the top and the numbers rising counter-clockwise (seen with y up, as
the challenge draws it). Their wall contact is modelled as a 2 mm-deep rim sector
with a near-ideal contact. A data file holds, for each of 76 current patterns
(``Inj``, one electrode in and one out, about 1.4 to 1.5 mA; the skip-one patterns
7-9, 15-17, 23-25 and 31-1 come twice, once among the pairs with electrodes 1, 9,
17 and 25), the 31 adjacent
differences U_j - U_j+1 (``Mpat``); ``Uel`` stacks them pattern by pattern. Readings
a difficulty level removes are NaN and stay NaN here: the reconstruction drops them
as it would a broken electrode's.

The challenge's images are 256 x 256 pixels over the square around the tank, row 0
at the top; in our coordinates (y down from the top-left corner of that square)
that is the row-major pixel grid of the layout.

>>> layout = ktc_layout()
>>> layout.n_electrodes, layout.sheet.radius_mm
(32, 115.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.core.layouts import KTC_ELECTRODES, ktc_layout
from appliance.core.model_cache import ModelSetup
from appliance.core.protocols import Protocol
from appliance.core.reconstruct import ReconstructionOptions
from appliance.core.regularisation import NoiseModel
from appliance.errors import DataFileInvalid

CONTACT_IMPEDANCE_OHM_M2 = 2e-8
"""Near ideal: a thousandth of the sheet's resistance over an electrode face at unit conductance."""

IMAGE_SIZE = 256
LEVELS = range(1, 8)


@dataclass(frozen=True)
class KtcData:
    """One data file: its protocol, and readings divided by each pattern's current (ohms, NaN = missing)."""

    protocol: Protocol
    transfer_ohm: np.ndarray
    current_ma: np.ndarray


def load_ktc(path: Path) -> KtcData:
    """Read a challenge data file (``Inj``/``Injref``, ``Uel``/``Uelref``, ``Mpat``).

    Raises
    ------
    DataFileInvalid
        The file is missing, is not a MAT file, or its arrays do not have the
        challenge's shapes; the message names the file and the array.
    """
    import scipy.io

    path = Path(path)
    if not path.is_file():
        raise DataFileInvalid(f"KTC data file {path} does not exist")
    try:
        data = scipy.io.loadmat(path)
    except (ValueError, OSError, scipy.io.matlab.MatReadError) as exc:
        raise DataFileInvalid(f"KTC data file {path} is not a MAT file: {exc}") from None
    inj = _array(data, path, ("Inj", "Injref"))
    uel = _array(data, path, ("Uel", "Uelref")).ravel().astype(float)
    mpat = _array(data, path, ("Mpat",))
    if inj.shape[0] != KTC_ELECTRODES or mpat.shape != (KTC_ELECTRODES, KTC_ELECTRODES - 1):
        raise DataFileInvalid(f"KTC data file {path}: Inj must be 32 x patterns and Mpat 32 x 31, got "
                              f"{inj.shape} and {mpat.shape}")
    if uel.size != inj.shape[1] * mpat.shape[1]:
        raise DataFileInvalid(f"KTC data file {path}: Uel has {uel.size} readings, the patterns give "
                              f"{inj.shape[1] * mpat.shape[1]}")
    rows, currents = [], []
    for j in range(inj.shape[1]):
        column = np.nan_to_num(inj[:, j])
        pos, neg = int(np.argmax(column)) + 1, int(np.argmin(column)) + 1
        if column[pos - 1] <= 0 or column[neg - 1] >= 0 or np.count_nonzero(column) != 2:
            raise DataFileInvalid(f"KTC data file {path}: current pattern {j + 1} is not one electrode in, "
                                  f"one out")
        currents.append(column[pos - 1])
        for m in range(mpat.shape[1]):
            plus, minus = int(np.argmax(mpat[:, m])) + 1, int(np.argmin(mpat[:, m])) + 1
            rows.append((pos, neg, plus, minus))
    current = np.repeat(np.array(currents), mpat.shape[1])
    protocol = Protocol(np.array(rows), KTC_ELECTRODES, name=f"ktc-{path.stem}")
    return KtcData(protocol, uel / current, np.array(currents))


def _array(data: dict, path: Path, names: tuple[str, ...]) -> np.ndarray:
    for name in names:
        if name in data:
            return np.asarray(data[name])
    raise DataFileInvalid(f"KTC data file {path} has none of {', '.join(names)}")


def removed_electrodes(level: int) -> list[int]:
    """The electrodes whose data difficulty level ``level`` removes: 1 to 2 (level - 1)."""
    return list(range(1, 2 * (level - 1) + 1))


SEGMENT_LOG_RATIO = 1.0
"""A pixel is an inclusion where its conductivity differs from the water's by more than a factor
e^1 either way (chosen on the four training targets, one value for all)."""

PIXELS = (32, 32)
NOISE = NoiseModel(relative=1e-3, absolute=1e-2)
"""The challenge gives no noise figures; a 1 % floor (of the rms reading) stands for the
model's error on real data (the reference fits the model to about 5 %)."""


ITERATE = "always"
"""The challenge's inclusions are metal and plastic, far outside the linear range every time;
with a 1 % noise floor the one-step check would not always see it."""


def ktc_setup(protocol: Protocol) -> ModelSetup:
    """The reconstruction set-up used for the challenge's data: Gauss-Newton with Laplace's prior on
    32 x 32 pixels (iterate it: :data:`ITERATE`)."""
    return ModelSetup(ktc_layout(), protocol, ReconstructionOptions("gn-laplace", noise=NOISE, target_contrast=-0.5),
                      pixels=PIXELS, contact_impedance_ohm_m2=CONTACT_IMPEDANCE_OHM_M2)


def segment(image: np.ndarray, log_ratio: float = SEGMENT_LOG_RATIO) -> np.ndarray:
    """The challenge's 256 x 256 labels of a relative-change image over the tank's square:
    0 water, 1 resistive (conductivity below e^-log_ratio of the water's), 2 conductive
    (above e^log_ratio). The log-conductivity image is resampled, then classed."""
    image = np.asarray(image, dtype=float)
    log_image = np.log(np.clip(1.0 + np.nan_to_num(image), 1e-6, None))
    resampled = to_challenge_grid(log_image)
    labels = np.zeros(resampled.shape, dtype=np.uint8)
    labels[resampled < -log_ratio] = 1
    labels[resampled > log_ratio] = 2
    return labels


def to_challenge_grid(image: np.ndarray) -> np.ndarray:
    """Resample an image over the tank's square (row 0 at the top) to 256 x 256 by bilinear
    interpolation between pixel centres; NaN pixels count as zero."""
    from scipy.ndimage import map_coordinates

    image = np.nan_to_num(np.asarray(image, dtype=float))
    rows, cols = image.shape
    y = (np.arange(IMAGE_SIZE) + 0.5) * rows / IMAGE_SIZE - 0.5
    x = (np.arange(IMAGE_SIZE) + 0.5) * cols / IMAGE_SIZE - 0.5
    yy, xx = np.meshgrid(y, x, indexing="ij")
    return map_coordinates(image, [yy, xx], order=1, mode="nearest")
