"""Readings to an image of relative conductivity change, one matrix-vector product a frame.

Every algorithm is precomputed into one matrix R (pixels x readings) from the
linearised model at the homogeneous reference: J, the change of each reading per
unit relative change of each pixel (sigma = sigma_ref (1 + x)). A frame is

    x = R (v - v_ref) / s

where s scales the model to the sheet (its conductance, the drive current) by a
least-squares fit of the measured reference to the model's. A pressed region,
less conductive, comes out negative.

Algorithms:

* ``backprojection``: the thesis's eq. 3.4.2, normalised changes (v - v_ref) / v_ref
  back-projected by the sensitivity S of eq. 3.4.1 (from the model, or from an
  experimental calibration), then scaled once so that a change at one pixel alone
  reads, on average, at its true size (reference readings below 5 % of the rms
  reading are taken at that floor, so that none blows up the image);
* ``gn-tikhonov``, ``gn-noser``, ``gn-laplace``: one-step Gauss-Newton,
  R = (J^T W J + lambda P)^-1 J^T W, readings weighted by their noise (W), priors
  from :mod:`appliance.core.regularisation`;
* ``greit``: a GREIT-style reconstructor trained on single-pixel targets, each to
  be imaged as a blurred spot: R = D (J^T W J + lambda I)^-1 J^T W.

Lambda comes from a stated rule (by default the expected image error under the
noise model, :mod:`appliance.core.regularisation`) and is stored with the
reconstructor, as is the noise figure it gives.
When a reading or an electrode fails, :func:`without_readings` rebuilds R from J
in milliseconds, keeping lambda (a factored bed model updates its factor instead, :class:`NormalForm`).

>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.protocols import default_protocol
>>> from appliance.core.fem import build_fem_model
>>> from appliance.core.pixels import pixel_grid
>>> layout = get_layout("grid-4x4")
>>> linear = linear_model(build_fem_model(layout), default_protocol(layout), pixel_grid(layout))
>>> r = build_reconstructor(linear)
>>> r.matrix.shape
(256, 448)
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from appliance.core.forward import ForwardModel, solve_electrodes
from appliance.core.jacobian import pixel_jacobian
from appliance.core.pixels import PixelGrid, element_pixel_map, pixel_areas_mm2
from appliance.core.protocols import Protocol
from appliance.core.regularisation import (
    ExpectedErrorSpectrum, NoiseModel, choose_lambda, minimise_lambda, noise_figure, prior_matrix,
)
from appliance.errors import ConfigError, ReconstructionError

ALGORITHMS = ("greit", "gn-laplace", "gn-noser", "gn-tikhonov", "backprojection")
DEFAULT_ALGORITHM = "greit"


@dataclass(frozen=True)
class LinearModel:
    """The model linearised at the homogeneous reference, on a pixel grid.

    Attributes
    ----------
    protocol : Protocol
    grid : PixelGrid
    jacobian : ndarray, shape (n_readings, n_pixels)
        Volts per amp per unit relative change of each imaged pixel, at unit conductivity.
    reference : ndarray, shape (n_readings,)
        The homogeneous readings, volts per amp at unit conductivity.
    areas_mm2 : ndarray, shape (n_pixels,)
        Sheet area each imaged pixel stands for.
    mapping : sparse matrix, shape (n_elements, n_pixels)
        Share of each forward element's area in each pixel.

    A J of more than ``SINGLE_PRECISION_LIMIT`` entries is kept in single precision (see there).
    """

    protocol: Protocol
    grid: PixelGrid
    jacobian: np.ndarray
    reference: np.ndarray
    areas_mm2: np.ndarray
    mapping: sp.csr_matrix

    def __post_init__(self):
        dtype = jacobian_dtype(self.jacobian.size)
        if self.jacobian.dtype != dtype:                      # e.g. a model cached before this rule
            object.__setattr__(self, "jacobian", self.jacobian.astype(dtype))


SINGLE_PRECISION_LIMIT = 6_000_000
"""Readings x pixels beyond which J is kept in single precision. A bed mat's J (14,786 x 1,920) is then
114 MB rather than 227, and the product with it that every frame makes reads half the bytes, which is most
of a frame's time. Rounding J to 24 bits moves it by 6e-8 of itself, far below the model's own error
(the mat is not the model to better than a per cent) and the readings' noise; the matrices built from
it (J^T W J and what follows) are formed in double precision, and benchmarks/frame_cost.md measures
how far the images move."""


def jacobian_dtype(size: int) -> type:
    """The precision a Jacobian of ``size`` entries is kept in (``SINGLE_PRECISION_LIMIT``)."""
    return np.float32 if size > SINGLE_PRECISION_LIMIT else np.float64


def times_transpose(jacobian: np.ndarray, v: np.ndarray) -> np.ndarray:
    """J^T v in double precision, reading J in the precision it is kept in (no double copy of it)."""
    return (jacobian.T @ v.astype(jacobian.dtype, copy=False)).astype(np.float64, copy=False)


def times(jacobian: np.ndarray, x: np.ndarray) -> np.ndarray:
    """J x in double precision, as :func:`times_transpose`."""
    return (jacobian @ x.astype(jacobian.dtype, copy=False)).astype(np.float64, copy=False)


def linear_model(model: ForwardModel, protocol: Protocol, grid: PixelGrid) -> LinearModel:
    """Linearise ``model`` at unit conductivity onto the pixels of ``grid``."""
    sigma = np.ones(model.n_elements)
    fields = solve_electrodes(model, sigma)
    mapping = element_pixel_map(model, grid)
    dtype = jacobian_dtype(len(protocol) * mapping.shape[1])
    j = pixel_jacobian(model, sigma, protocol, mapping, fields, relative=True, dtype=dtype)
    return LinearModel(protocol, grid, j, fields.readings(protocol), pixel_areas_mm2(model, mapping), mapping)


LAMBDA_RULES = ("expected-error", "noise-figure")


@dataclass(frozen=True)
class ReconstructionOptions:
    """Choices that shape a reconstructor; stored with it (and in the model cache's key).

    Attributes
    ----------
    algorithm : str
    noise : NoiseModel
        The readings' noise, which weights them and sets the regularisation.
    lambda_rule : str
        ``expected-error`` or ``noise-figure`` (see :mod:`appliance.core.regularisation`).
    noise_figure : float
        The target of the noise-figure rule.
    target_fraction : float
        Diameter of the training spots of the expected-error rule, as a share of the
        sheet's shorter side (0.2: 20 mm on the 100 mm sensors).
    target_contrast : float
        Their relative conductivity change (-0.4: the liquid thinned by 40 %).
    desired_blur_px : float
        Width (standard deviation, pixels) of the spot GREIT images a change as.
    """

    algorithm: str = DEFAULT_ALGORITHM
    noise: NoiseModel = NoiseModel()
    lambda_rule: str = "expected-error"
    noise_figure: float = 0.5
    target_fraction: float = 0.2
    target_contrast: float = -0.4
    desired_blur_px: float = 0.75

    def __post_init__(self):
        if self.algorithm not in ALGORITHMS:
            raise ConfigError(f"unknown algorithm {self.algorithm!r}: use one of {', '.join(ALGORITHMS)}")
        if self.lambda_rule not in LAMBDA_RULES:
            raise ConfigError(f"unknown lambda rule {self.lambda_rule!r}: use one of {', '.join(LAMBDA_RULES)}")
        if not self.noise_figure > 0 or not self.target_fraction > 0 or self.target_contrast == 0:
            raise ConfigError(f"noise figure and target size must be positive, contrast non-zero: {self}")


DENSE_LIMIT = 6_000_000
"""Pixels x readings beyond which R is kept as its factors rather than as one matrix. A bed
mat at 30 mm pixels has an R of 1,920 x 14,786 (227 MB), and each set of missing readings
would cost another; its factors are two pixel-square matrices and J, which the model keeps
anyway, and a set of missing readings adds a low-rank update of them (:class:`NormalForm`)."""


@dataclass(frozen=True)
class NormalForm:
    """R = L (N + lambda P)^-1 J^T W kept as its parts, applied to a frame's changes directly.

    ``normal`` is J^T W J over the readings the model was built with, ``prior`` P, ``weights`` W
    (zero on the unusable readings), ``left`` GREIT's desired-image blur L (None for Gauss-Newton).
    A frame costs one product with J^T and one with the pixel-square ``operator``: about what R itself costs.

    A set of missing readings (:meth:`without`) shares ``base``, the full set's form, its matrices
    and its Cholesky factor, and keeps lambda P as it was: with B B^T the dropped readings' part of
    N, (N - B B^T + lambda P)^-1 = A^-1 + C S^-1 C^T (A = N + lambda P, C = A^-1 B, S = I - B^T C),
    exact, by the Woodbury identity. ``update`` holds C and S's Cholesky factor: a few megabytes an
    electrode on the bed mat, and a frame costs two products with C more. Where C and S would take
    more than a factor of their own, or S is not positive definite, the set keeps its own factor
    (``update`` None). Keeping lambda P rather than scaling the prior with the readings left (as a
    fresh build's :func:`appliance.core.regularisation.prior_matrix` would) keeps the regularisation
    of the pixels far from a failed electrode what it was; benchmarks/memory.md measures how little
    it moves the images.
    """

    normal: np.ndarray
    prior: np.ndarray
    weights: np.ndarray
    left: np.ndarray | None
    lam: float
    base: NormalForm | None = None
    update: tuple[np.ndarray, tuple] | None = None

    @cached_property
    def solve(self):
        """x -> (N' + lambda P)^-1 x over the usable readings' N', factorised once."""
        if self.base is None:
            return spd_solver(self.normal + self.lam * self.prior)
        assert self.update is not None              # a set without an update had its own factor made by without()
        full, (c, s) = self.base.solve, self.update
        return lambda x: full(x) + c @ sla.cho_solve(s, c.T @ x, check_finite=False)

    @cached_property
    def _sparse_prior(self) -> sp.csr_matrix:
        """P as a sparse matrix: every prior here is diagonal or a few neighbours a pixel."""
        return sp.csr_matrix(self.prior if self.base is None else self.base._sparse_prior)

    def nbytes(self) -> int:
        """Bytes this form keeps of its own: the full set's matrices and factor, or a set of missing
        readings' weights and update (or its own factor), whose base it shares."""
        own = self.weights.nbytes
        if self.base is None:                     # N, P, the factor and the operator
            return own + 4 * self.normal.nbytes + (0 if self.left is None else self.left.nbytes)
        if self.update is None:
            return own + self.normal.nbytes
        c, (s, _) = self.update
        return own + c.nbytes + s.nbytes

    @cached_property
    def operator(self) -> np.ndarray:
        """L A^-1 (A^-1 for Gauss-Newton) of the full set as one pixel-square matrix, which takes a frame
        from J^T W dv to its image in one product: half the bytes of the two triangular solves with the
        factor, and no product with L after them. Kept in double precision: an image is a difference of
        large terms (by up to A's condition number, about 1e4 on the bed mat), which single precision would
        round to a few parts in 1e4. Made a block of columns at a time, so that making it needs no second
        pixel-square matrix."""
        n = len(self.normal)
        out = np.empty((n, n))
        for start in range(0, n, NOISE_BLOCK):
            block = slice(start, min(start + NOISE_BLOCK, n))
            columns = np.eye(n, block.stop - start, -start) if self.left is None else self.left[block].T
            out[block] = self.solve(columns).T                # rows of L A^-1 = (A^-1 L^T)^T, A symmetric
        return out

    def apply(self, jacobian: np.ndarray, delta: np.ndarray) -> np.ndarray:
        """The image of reading changes ``delta`` (zero on unusable readings), before scaling."""
        y = times_transpose(jacobian, self.weights * delta)
        if self.base is None:
            return self.operator @ y
        if self.update is None:                                # a set with its own factor
            x = self.solve(y)
            return x if self.left is None else self.left @ x
        c, s = self.update                                     # the full set's image and Woodbury's correction
        correction = c @ sla.cho_solve(s, c.T @ y, check_finite=False)
        return self.base.operator @ y + (correction if self.left is None else self.left @ correction)

    def noise_figure(self, jacobian: np.ndarray, noise_std: np.ndarray, target: np.ndarray,
                     areas: np.ndarray) -> float:
        """As :func:`appliance.core.regularisation.noise_figure`, without forming R: with W = S^-1 the
        image noise R S R^T is L A^-1 N A^-1 L^T = L (A^-1 - lambda A^-1 P A^-1) L^T (A = N + lambda P),
        of which only the diagonal is needed, NOISE_BLOCK pixels at a time, with the sparse P."""
        signal = np.where(noise_std > 0, times(jacobian, target), 0.0)   # unusable readings: std 0
        snr_in = np.linalg.norm(signal) / np.sqrt(np.sum(noise_std**2))
        image = self.solve(times_transpose(jacobian, self.weights * signal))
        n = len(target)
        variance = np.empty(n)
        for start in range(0, n, NOISE_BLOCK):
            block = slice(start, min(start + NOISE_BLOCK, n))
            if self.left is None:
                columns = np.zeros((n, block.stop - start))
                columns[block, :] = np.eye(block.stop - start)
            else:
                columns = self.left[block].T
            y = self.solve(columns)                                       # A^-1 L^T e_p
            variance[block] = (np.einsum("ij,ij->j", columns, y)
                               - self.lam * np.einsum("ij,ij->j", y, self._sparse_prior @ y))
        if self.left is not None:
            image = self.left @ image
        snr_out = np.sqrt(np.sum(areas * image**2)) / np.sqrt(np.sum(areas * variance))
        return float(snr_in / snr_out)

    def without(self, jacobian: np.ndarray, drop: np.ndarray) -> NormalForm:
        """The same with the readings ``drop`` (bool) removed, lambda P kept: an update of the full
        set's factor (see the class)."""
        if self.base is not None:
            return self.base.without(jacobian, np.asarray(drop, dtype=bool) | (self.weights == 0))
        drop = np.asarray(drop, dtype=bool) & (self.weights > 0)
        removed = (jacobian[drop] * np.sqrt(self.weights[drop])[:, None]).T          # B, (pixels, k), double
        weights = np.where(drop, 0.0, self.weights)
        n, k = removed.shape
        update = None
        if k * (n + k) < n * n:
            c = self.solve(removed)
            with contextlib.suppress(np.linalg.LinAlgError):     # S not positive definite: a factor of its own
                update = c, sla.cho_factor(np.eye(k) - removed.T @ c)
        form = NormalForm(self.normal, self.prior, weights, self.left, self.lam, self, update)
        if update is None:
            a = self.normal - removed @ removed.T
            a += self.lam * self.prior
            form.__dict__["solve"] = spd_solver(a)        # frozen fields; the cache beside them, as cached_property
        return form


NOISE_BLOCK = 256
"""Pixels whose image noise is computed at once: a bed's noise figure then needs a few megabytes of
work space rather than two pixel-square matrices."""


@dataclass(frozen=True)
class Reconstructor:
    """A precomputed reconstruction: ``matrix`` (n_pixels, n_readings) and what made it.

    ``usable`` marks the readings it uses (the others have zero columns); ``lam``
    and ``achieved_noise_figure`` record the regularisation. On a mat whose R would be
    too large (beyond ``DENSE_LIMIT`` entries) ``matrix`` is None and R is kept as its
    factors, ``normal_form``.
    """

    linear: LinearModel
    options: ReconstructionOptions
    matrix: np.ndarray | None
    usable: np.ndarray
    lam: float
    achieved_noise_figure: float
    sensitivity: np.ndarray | None = None
    normal_form: NormalForm | None = None

    @property
    def grid(self) -> PixelGrid:
        return self.linear.grid

    def reconstruct(self, frame: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """The image (rows, cols) of relative conductivity change between ``reference`` and ``frame``.

        Both are readings in protocol order (volts); NaN marks a missing reading,
        which :func:`without_readings` must have dropped first.
        """
        return self.grid.image(self.pixels(frame, reference))

    def pixels(self, frame: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """As :meth:`reconstruct`, the imaged pixels only, shape (n_pixels,).

        Computed in float64 whatever the inputs' precision.
        """
        delta = np.subtract(frame, reference, dtype=np.float64)
        if not self._all_usable:
            delta = np.where(self.usable, delta, 0.0)
        if not np.isfinite(delta).all():
            raise ReconstructionError("frame or reference has a missing or non-finite reading that the "
                                      "reconstructor still uses; drop it with without_readings first")
        if self.matrix is not None:
            image = self.matrix @ delta
        else:
            assert self.normal_form is not None         # one of the two is always built
            image = self.normal_form.apply(self.linear.jacobian, delta)
        return image / self.scale(reference)

    @cached_property
    def _all_usable(self) -> bool:
        return bool(self.usable.all())

    @cached_property
    def _model_reference(self) -> tuple[np.ndarray, float, np.ndarray]:
        """The model's usable reference readings, their square sum, and their deviations from their mean
        scaled to unit length (so a frame's correlation with them is one dot product)."""
        m = self.linear.reference if self._all_usable else self.linear.reference[self.usable]
        centred = m - m.mean()
        return m, float(m @ m), centred / np.sqrt(centred @ centred)

    def scale(self, reference: np.ndarray) -> float:
        """Measured over modelled reference readings (least squares over the usable readings)."""
        s = self._reference_fit(reference)[1]
        if not np.isfinite(s) or s <= 0:
            raise ReconstructionError(
                f"the reference readings do not match this layout's model (fitted scale {s:.3g}); is the "
                f"frame from another layout or protocol, or are the measuring leads reversed?")
        return s

    def check_reference(self, reference: np.ndarray, minimum: float = 0.9) -> float:
        """The correlation of the measured reference with the model's; refused below ``minimum``.

        Real references correlate above 0.99 with their layout's model (0.995 for the
        KTC2023 tank); a frame from another layout or a mis-wired mat does not.
        """
        correlation = self._reference_fit(reference)[0]
        if not correlation >= minimum:
            raise ReconstructionError(
                f"the reference readings correlate {correlation:.2f} with this layout's model (at least "
                f"{minimum} expected): is the frame from another layout or protocol, or is the mat mis-wired?")
        return correlation

    def _reference_fit(self, reference: np.ndarray) -> tuple[float, float]:
        """(Pearson's correlation, least-squares scale) of ``reference`` against the model's reference over
        the usable readings (NaN correlation for a flat or non-finite one). The last reference's are kept:
        a monitor images every frame against the same reference, and comparing its bytes costs a tenth of
        fitting it again."""
        v = np.asarray(reference, dtype=np.float64)
        key = v.tobytes()
        last = self.__dict__.get("_last_reference_fit")
        if last is not None and last[0] == key:
            return last[1]
        m, mm, unit = self._model_reference
        v = v if self._all_usable else v[self.usable]
        centred = v - v.mean()
        spread = float(centred @ centred)
        fit = (float(centred @ unit) / np.sqrt(spread) if spread > 0 else float("nan"), float(v @ m) / mm)
        self.__dict__["_last_reference_fit"] = (key, fit)       # frozen fields; a cache beside them, as cached_property
        return fit


def build_reconstructor(linear: LinearModel, options: ReconstructionOptions | None = None,
                        usable: np.ndarray | None = None, lam: float | None = None,
                        sensitivity: np.ndarray | None = None) -> Reconstructor:
    """Precompute the reconstruction matrix.

    Parameters
    ----------
    usable : ndarray of bool, shape (n_readings,), optional
        Readings to use; by default all.
    lam : float, optional
        Regularisation; by default chosen by the noise-figure rule.
    sensitivity : ndarray, shape (n_pixels, n_readings), optional
        For ``backprojection``: the experimental S of eq. 3.4.1 (V_p - V_H), rows in
        imaged-pixel order; by default the model's.
    """
    options = options or ReconstructionOptions()
    n = len(linear.reference)
    usable = np.ones(n, dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    if usable.shape != (n,):
        raise ConfigError(f"usable mask needs {n} entries, got shape {usable.shape}")
    if usable.sum() < 2:
        raise ReconstructionError(f"only {int(usable.sum())} of {n} readings are usable: nothing can be "
                                  f"reconstructed")
    std = options.noise.std(linear.reference)
    weights = np.where(usable, 1.0 / std**2, 0.0)
    used_std = np.where(usable, std, 0.0)
    if linear.jacobian.size > DENSE_LIMIT and options.algorithm != "backprojection":
        return _normal_form_reconstructor(linear, options, usable, weights, used_std, lam)
    j = np.where(usable[:, None], linear.jacobian, 0.0)
    build, parts = _builder(options, linear, j, weights, usable, sensitivity)
    figure = lambda r: noise_figure(r, j, used_std, _centre_target(linear.grid), linear.areas_mm2)   # noqa: E731
    if lam is None and options.algorithm != "backprojection":
        if options.lambda_rule == "noise-figure":
            lam, _ = choose_lambda(build, figure, options.noise_figure)
        else:
            normal, prior, _, left = parts
            lam = _expected_error_lambda(linear, options, normal, prior, left)
    lam = 0.0 if lam is None else lam
    matrix = build(lam)
    return Reconstructor(linear, options, matrix, usable, lam, figure(matrix), sensitivity)


def _expected_error_lambda(linear, options, normal, prior, left) -> float:
    targets = _training_targets(linear.grid, options)
    desired = targets if left is None else left @ targets
    return minimise_lambda(ExpectedErrorSpectrum(normal, prior, targets, desired, linear.areas_mm2, left))


def _normal_form_reconstructor(linear, options, usable, weights, used_std, lam) -> Reconstructor:
    """A Gauss-Newton or GREIT reconstructor kept as its factors (see :class:`NormalForm`)."""
    j = linear.jacobian
    normal = np.zeros((j.shape[1], j.shape[1]))
    for start in range(0, len(j), NORMAL_BLOCK):              # J^T W J without a copy of J
        part = j[start:start + NORMAL_BLOCK].astype(np.float64)
        normal += (part.T * weights[start:start + NORMAL_BLOCK]) @ part
    algorithm = options.algorithm
    prior = prior_matrix(algorithm[3:] if algorithm.startswith("gn-") else "tikhonov", normal, linear.grid)
    left = _desired_image(linear.grid, linear.areas_mm2, options.desired_blur_px) if algorithm == "greit" else None
    target = _centre_target(linear.grid)
    build = lambda value: NormalForm(normal, prior, weights, left, value)                  # noqa: E731
    figure = lambda form: form.noise_figure(j, used_std, target, linear.areas_mm2)         # noqa: E731
    if lam is None:
        if options.lambda_rule == "noise-figure":
            lam, _ = choose_lambda(build, figure, options.noise_figure)
        else:
            lam = _expected_error_lambda(linear, options, normal, prior, left)
    form = build(lam)
    return Reconstructor(linear, options, None, usable, lam, figure(form), None, form)


NORMAL_BLOCK = 2048
"""Readings per block when forming J^T W J."""


def without_readings(r: Reconstructor, drop: np.ndarray) -> Reconstructor:
    """``r`` rebuilt without the readings marked in ``drop`` (bool, n_readings), same lambda (and on a
    factored model the same lambda P, :class:`NormalForm`)."""
    drop = np.asarray(drop)
    if drop.shape != r.usable.shape or drop.dtype != bool:
        raise ConfigError(f"the readings to drop need a mask of {len(r.usable)} booleans, got {drop.dtype} "
                          f"of shape {drop.shape}")
    usable = r.usable & ~drop
    if r.normal_form is not None:
        if usable.sum() < 2:
            raise ReconstructionError(f"only {int(usable.sum())} of {len(usable)} readings are usable: "
                                      f"nothing can be reconstructed")
        form = r.normal_form.without(r.linear.jacobian, ~usable)
        std = np.where(usable, r.options.noise.std(r.linear.reference), 0.0)
        figure = form.noise_figure(r.linear.jacobian, std, _centre_target(r.grid), r.linear.areas_mm2)
        return Reconstructor(r.linear, r.options, None, usable, r.lam, figure, None, form)
    return build_reconstructor(r.linear, r.options, usable, r.lam, r.sensitivity)


def readings_using(protocol: Protocol, electrodes) -> np.ndarray:
    """Mask of the readings that drive or measure on any of ``electrodes`` (1-based numbers)."""
    return np.asarray(np.isin(protocol.readings, np.asarray(list(electrodes))).any(axis=1))


def _builder(options, linear, j, weights, usable, sensitivity):
    """A function of lambda giving the reconstruction matrix, and the parts it is made of
    (J^T W J, the prior, J^T W and GREIT's blur, or None for backprojection)."""
    algorithm = options.algorithm
    jw = j.T * weights                                             # J^T W, (n_pixels, n_readings)
    normal = jw @ j
    if algorithm.startswith("gn-"):
        prior = prior_matrix(algorithm[3:], normal, linear.grid)
        return (lambda lam: solve_spd(normal + lam * prior, jw)), (normal, prior, jw, None)
    if algorithm == "greit":
        prior = prior_matrix("tikhonov", normal, linear.grid)
        blur = _desired_image(linear.grid, linear.areas_mm2, options.desired_blur_px)
        return (lambda lam: blur @ solve_spd(normal + lam * prior, jw)), (normal, prior, jw, blur)
    return _backprojection(linear, j, usable, sensitivity), None


def solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve a x = b for a symmetric positive (semi-)definite ``a``."""
    return spd_solver(a)(b)


def spd_solver(a: np.ndarray):
    """b -> a^-1 b for a symmetric positive (semi-)definite ``a``, factorised once."""
    try:
        factor = sla.cho_factor(a)
    except np.linalg.LinAlgError:
        # Laplace's prior is singular on constants; a tiny lambda with few readings can leave
        # the sum only semi-definite, where a least-squares solve still gives a finite answer.
        inverse = np.linalg.pinv(a, hermitian=True)
        return lambda b: inverse @ b
    return lambda b: sla.cho_solve(factor, b, check_finite=False)   # the factor was checked as it was made


def _desired_image(grid: PixelGrid, areas: np.ndarray, blur_px: float) -> np.ndarray:
    """D: column q is the spot a unit change at pixel q should be imaged as, same integral."""
    c = grid.centres_mm[grid.inside_index] / np.array(grid.pixel_mm)
    d2 = ((c[:, None, :] - c[None, :, :]) ** 2).sum(axis=2)
    spots = np.exp(-0.5 * d2 / blur_px**2)
    return spots * (areas / (areas @ spots))[None, :]


def _backprojection(linear: LinearModel, j: np.ndarray, usable: np.ndarray, sensitivity):
    """The thesis's eq. 3.4.2 as a matrix on v - v_ref, independent of lambda."""
    ref = linear.reference
    if sensitivity is not None:
        # a reading unusable while the calibration object lay on some pixel is unusable for all
        usable = usable & np.isfinite(sensitivity).all(axis=0)
        sensitivity = np.nan_to_num(sensitivity)
    floor = 0.05 * np.sqrt(np.mean(ref[usable] ** 2))
    safe = np.where(np.abs(ref) < floor, np.copysign(floor, ref), ref)
    if sensitivity is None:
        s = -np.sign(ref)[None, :] * j.T            # eq. 3.4.1 linearised for an insulating object
    else:
        s = np.where(usable[None, :], sensitivity, 0.0)
        s = s * np.sign(ref)[None, :]
    totals = s.sum(axis=1, keepdims=True)
    totals[totals == 0] = 1.0
    b = s / totals / safe[None, :]
    b = np.where(usable[None, :], b, 0.0)
    # One scale for the whole image, so that a change at a pixel alone reads, on average
    # over the sheet, at its true size and sign; per-pixel scaling would divide by the
    # near-zero responses over the electrodes.
    response = np.einsum("pr,rp->p", b, j)
    matrix = b / (linear.areas_mm2 @ response / linear.areas_mm2.sum())
    return lambda lam: matrix


def _training_targets(grid: PixelGrid, options: ReconstructionOptions) -> np.ndarray:
    """Spots of the expected size and contrast centred on every imaged pixel, one per column."""
    c = grid.centres_mm[grid.inside_index]
    radius = 0.5 * options.target_fraction * min(grid.width_mm, grid.height_mm)
    d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
    spots = (d <= max(radius, 0.5 * min(grid.pixel_mm))).astype(float)
    return spots * options.target_contrast


def _centre_target(grid: PixelGrid) -> np.ndarray:
    """A small change (the four or so pixels nearest the centre) for the noise figure."""
    c = grid.centres_mm[grid.inside_index]
    centre = np.array([grid.width_mm, grid.height_mm]) / 2
    d = np.linalg.norm(c - centre, axis=1)
    return (d <= np.sort(d)[min(3, len(d) - 1)] + 1e-9).astype(float) * 0.1


def with_options(r: Reconstructor, **changes) -> Reconstructor:
    """``r`` rebuilt with some options changed (lambda chosen anew)."""
    return build_reconstructor(r.linear, dataclasses.replace(r.options, **changes), r.usable, None, r.sensitivity)
