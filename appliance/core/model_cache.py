"""A built reconstruction model, and its cache on disk.

Building means meshing, assembling, solving, differentiating and choosing lambda:
a fraction of a second on the 16-electrode sensors, seconds on a 32-electrode tank.
A built model is saved under the hash of everything it depends on (the layout as
TOML, the protocol, the options, mesh density, pixels, contact impedance, the
contacts fitted to a reference if any, the file format and the package version),
written atomically, so a restart loads it in milliseconds and a change to any
input builds a new one.

:meth:`ReconstructionModel.for_reference` fits every electrode's contact and the sheet's
conductance to each empty-mat reference (:mod:`appliance.core.contact_fit`) and, if the
setup asks, relinearises there. Relinearised models are cached too, the newest few of
each setup, so a restart with the same reference loads its model instead of building it.

>>> from appliance.core.named_layouts import get_layout
>>> from appliance.core.protocols import default_protocol
>>> setup = ModelSetup(get_layout("grid-4x4"), default_protocol(get_layout("grid-4x4")))
>>> len(setup.key())
64
"""

from __future__ import annotations

import ctypes
import dataclasses
import hashlib
import json
import os
import platform
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import scipy.sparse as sp

import appliance
from appliance.core.contact_fit import ContactFit, ContactPrior, fit_contacts
from appliance.core.fem import DEFAULT_CONTACT_IMPEDANCE_OHM_M2, build_fem_model
from appliance.core.forward import ForwardModel
from appliance.core.iterative import MISFIT_LIMIT, iterative_reconstruct, one_step_misfit
from appliance.core.layout_files import layout_to_toml
from appliance.core.layouts import Layout
from appliance.core.mesh import Mesh, mesh_layout
from appliance.core.pixels import PixelGrid, pixel_grid
from appliance.core.protocols import SERIAL_ELECTRODES, Protocol, default_protocol
from appliance.core.reconstruct import (
    LinearModel, NormalForm, ReconstructionOptions, Reconstructor, build_reconstructor, linear_model,
    without_readings,
)
from appliance.errors import ConfigError, ReconstructionError
from appliance.files import write_atomic

FORMAT_VERSION = 3

FITTED_KEPT = 3
"""Fitted models kept in the cache for each setup (the newest): one per reference taken, and an
engineer may take several in a session; older ones are removed as new ones are saved."""

RELINEARISE_LOG = 0.2
"""A fit whose every contact lies within this of a model's (20 %), or within three of its own standard
deviations where that is wider, is served by that model's linearisation: one contact 50 % off moves the
readings by 1.4e-3 of their size where contacts matter most (near ideal; benchmarks/mismatch.md), 20 % by
under half that, below the noise; a difference the fit cannot tell from noise is none; and relinearising
costs a model build."""
FITS_KEPT = 2
"""References whose fitted models a model keeps at hand (the one in use, and a probe's or the last one)."""
CONTACT_FIT_MODES = ("off", "track", "relinearise")
AFFORDABLE_FIT_ELECTRODES = 32
"""Up to this many electrodes a setup fits its contacts to every reference by default (``track``): it
takes well under a second. A bed fits on request: 2 s on grid-8x16 and about 40 s (0.6 GB) on
grid-16x32, paid again at every restart, where relinearising is a second model build (about half a
minute) that moves the bed's images less than their scatter (benchmarks/mismatch.md)."""

DROPPED_KEPT_BYTES = 8 * 2**20
"""What the reconstructors for sets of missing readings may keep together, the least recently used
forgotten first (the newest is kept whatever it takes). A bed set keeps about 2.3 MB an electrode
(:class:`appliance.core.reconstruct.NormalForm`; at most a pixel-square factor, 28 MiB), so this holds a
fault and the contact that flickers beside it (a set of one electrode and one of two), and a night of
faults stays well within the 32 MiB the monitor may grow by, which glibc's arenas and a frame's work space
share (benchmarks/memory.md); a small mat's set is its R, well under a megabyte."""

LINEAR_LIMIT = 0.05
"""Below this largest relative change the one-step image is taken as it is, without the
forward solve that checks it (the linearisation's error grows with the square of the change)."""


@dataclass(frozen=True)
class ModelSetup:
    """Everything a reconstruction model depends on.

    ``contact_fit`` says what is done with each reference's contacts and conductance
    (:meth:`ReconstructionModel.for_reference`): ``off``; ``track`` fits and reports them;
    ``relinearise`` also images with the model linearised at the fit. By default (None)
    ``track`` up to AFFORDABLE_FIT_ELECTRODES electrodes, else ``off``. Relinearising is not
    the default: it moves one-step images by less than their noise, places fitted regions
    better on near-ideal contacts, and with those contacts leaves the sheet over each face
    less determined, which the iteration of wide, heavy loads feels (benchmarks/mismatch.md).
    ``fitted_contact_ohm_m2`` holds a fit's contacts, at unit sheet conductance, where the
    model is then linearised instead of at the nominal ``contact_impedance_ohm_m2``.
    """

    layout: Layout
    protocol: Protocol
    options: ReconstructionOptions = ReconstructionOptions()
    density: float = 1.0
    pixels: tuple[int, int] | None = None
    contact_impedance_ohm_m2: float = DEFAULT_CONTACT_IMPEDANCE_OHM_M2
    contact_fit: str | None = None
    fitted_contact_ohm_m2: tuple[float, ...] | None = None

    def key(self) -> str:
        """SHA-256 (hex) of the setup, the file format and the package version (not ``contact_fit``, which
        builds nothing: a fitted model has its contacts in its own key)."""
        description = {**self._images(), "format": FORMAT_VERSION, "version": appliance.__version__}
        return hashlib.sha256(json.dumps(description, sort_keys=True).encode()).hexdigest()

    def image_key(self) -> str:
        """SHA-256 (hex) of what the setup's images follow from, and nothing else: a pressure calibration
        fitted to them holds as long as this does, whatever file format the model is cached in."""
        return hashlib.sha256(json.dumps(self._images(), sort_keys=True).encode()).hexdigest()

    def _images(self) -> dict:
        return {
            "layout": layout_to_toml(self.layout),
            "protocol": hashlib.sha256(np.ascontiguousarray(self.protocol.readings, dtype=np.int64).tobytes())
                               .hexdigest(),
            "options": dataclasses.asdict(self.options),
            "density": self.density, "pixels": self.pixels, "contact": self.contact_impedance_ohm_m2,
            "fitted": None if self.fitted_contact_ohm_m2 is None else [float(z) for z in self.fitted_contact_ohm_m2],
        }

    def __post_init__(self):
        if self.contact_fit not in (None, *CONTACT_FIT_MODES):
            raise ConfigError(f"unknown contact fit {self.contact_fit!r}: use one of {', '.join(CONTACT_FIT_MODES)}")

    @property
    def contact_fit_mode(self) -> str:
        """``contact_fit``, or its default for this layout."""
        if self.contact_fit is None:
            return "track" if self.layout.n_electrodes <= AFFORDABLE_FIT_ELECTRODES else "off"
        return self.contact_fit

    @property
    def nominal(self) -> ModelSetup:
        """The setup without fitted contacts."""
        return dataclasses.replace(self, fitted_contact_ohm_m2=None)

    @property
    def contact_ohm_m2(self) -> np.ndarray:
        """Each electrode's contact impedance the model is linearised at (at unit sheet conductance)."""
        if self.fitted_contact_ohm_m2 is not None:
            return np.array(self.fitted_contact_ohm_m2, dtype=float)
        return np.full(self.layout.n_electrodes, float(self.contact_impedance_ohm_m2))


BED_OPTIONS = ReconstructionOptions("gn-laplace", target_fraction=60.0 / 900.0, target_contrast=-0.3)
"""How a bed-size mat is reconstructed: Gauss-Newton with Laplace's prior, lambda trained on 60 mm spots
(a heel or an occiput) thinned by 30 %. On grid-16x32 it finds 98 % of the loaded spots of people left
out of every fit, where GREIT's blurred target finds 78 % (benchmarks/bed.md)."""
BED_DENSITY = 0.5
"""The reconstruction mesh of a bed-size mat: half the default density (benchmarks/bed.md has what the
full one would add, and what it costs)."""


def is_bed(layout: Layout) -> bool:
    """Whether ``layout`` is a bed-size mat (a grid of more electrodes than a serial front end reads)."""
    return layout.is_grid and layout.n_electrodes > SERIAL_ELECTRODES


def default_setup(layout: Layout, protocol: Protocol | None = None) -> ModelSetup:
    """The reconstruction the appliance uses on ``layout``: its default protocol, and on a bed-size mat
    :data:`BED_OPTIONS` at :data:`BED_DENSITY`; the library's defaults elsewhere."""
    protocol = protocol or default_protocol(layout)
    if is_bed(layout):
        return ModelSetup(layout, protocol, BED_OPTIONS, density=BED_DENSITY)
    return ModelSetup(layout, protocol)


@dataclass
class ReconstructionModel:
    """A setup built: its mesh and reconstructor; the forward model is rebuilt on first need.

    ``cache_dir`` is where the models fitted to its references are cached (set by
    :func:`cached_model`); ``contact_fit`` is the fit that chose this model for a reference,
    if one did in this process.
    """

    setup: ModelSetup
    mesh: Mesh
    reconstructor: Reconstructor
    cache_dir: Path | None = None
    contact_fit: ContactFit | None = None
    _dropped: OrderedDict = field(default_factory=OrderedDict, repr=False)
    _fits: dict = field(default_factory=dict, repr=False)

    @cached_property
    def forward(self) -> ForwardModel:
        """The forward model, for iterating (built from the stored mesh)."""
        return build_fem_model(self.setup.layout, self.mesh, contact_impedance_ohm_m2=self.setup.contact_ohm_m2)

    def fit_contacts(self, reference: np.ndarray, prior: ContactPrior = ContactPrior()) -> ContactFit:
        """Every electrode's contact impedance and the scale fitted to the empty-mat ``reference``
        (:mod:`appliance.core.contact_fit`), about the setup's nominal contact impedance."""
        return fit_contacts(self.forward, self.mesh, self.setup.protocol, reference,
                            self.setup.contact_impedance_ohm_m2, self.setup.options.noise, prior,
                            start_ohm_m2=self.setup.fitted_contact_ohm_m2)

    def for_reference(self, reference: np.ndarray, progress=None) -> ReconstructionModel:
        """The model to image frames against ``reference`` with, its ``contact_fit`` the fit made to it.

        The setup's ``contact_fit`` decides: ``off`` returns this model as it is; ``track``
        a copy of it with the fit attached; ``relinearise`` the model linearised at the fit.
        The fit is made once per reference. A fit that leaves the reference unexplained
        (``ContactFit.accepted`` false: the model lacks more than contacts can supply, and
        the contacts would only stand in for it) keeps the nominal linearisation. A model
        whose contacts are all within RELINEARISE_LOG of the fit's serves as it is;
        otherwise the fitted setup's model is loaded from ``cache_dir`` or built on this
        mesh (``progress`` as for :func:`build_model`), and cached.
        """
        mode = self.setup.contact_fit_mode
        if mode == "off":
            return self
        digest = hashlib.sha256(np.ascontiguousarray(reference, dtype=np.float64).tobytes()).hexdigest()
        if digest not in self._fits:
            self.for_readings(~np.isfinite(reference)).check_reference(reference)   # the plainer error first
            fit = self.fit_contacts(reference)
            if mode == "track":
                contacts, tolerance = self.setup.contact_ohm_m2, np.zeros(self.setup.layout.n_electrodes)
            elif fit.accepted:
                contacts, tolerance = fit.contact_ohm_m2, np.maximum(RELINEARISE_LOG, 3 * fit.sd_log_contact)
            else:
                contacts, tolerance = self.setup.nominal.contact_ohm_m2, np.zeros(self.setup.layout.n_electrodes)
            model = self._linearised_at(contacts, tolerance, progress)
            model.contact_fit = fit
            model._fits = {digest: model}                   # it images this reference itself
            self._fits = {**dict(list(self._fits.items())[-(FITS_KEPT - 1):]), digest: model}
        return self._fits[digest]

    def _linearised_at(self, contacts: np.ndarray, tolerance: np.ndarray, progress) -> ReconstructionModel:
        """A model linearised within ``tolerance`` (log, per electrode) of ``contacts``: this one, one
        already fitted here or in the cache, or a new one."""
        def close(other: np.ndarray) -> bool:
            return bool(np.all(np.abs(np.log(contacts / other)) <= tolerance))

        for known in (self, *self._fits.values()):
            if close(known.setup.contact_ohm_m2):
                same = dataclasses.replace(known, _dropped=known._dropped, _fits={})
                if "forward" in known.__dict__:
                    same.__dict__["forward"] = known.forward
                return same
        cached = [c for c in cached_fits(self.setup, self.cache_dir) if close(c)] if self.cache_dir else []
        chosen = cached[0] if cached else contacts
        fitted = None if close(self.setup.nominal.contact_ohm_m2) else tuple(float(z) for z in chosen)
        setup = dataclasses.replace(self.setup, fitted_contact_ohm_m2=fitted)
        if self.cache_dir is not None:
            model, _ = cached_model(setup, self.cache_dir, progress, mesh=self.mesh)
        else:
            model = build_model(setup, progress, mesh=self.mesh)
        if self.reconstructor.sensitivity is not None:          # an experimental sensitivity stays as it was given
            r = model.reconstructor
            model.reconstructor = build_reconstructor(r.linear, r.options, r.usable,
                                                      sensitivity=self.reconstructor.sensitivity)
        return model

    def for_readings(self, missing: np.ndarray) -> Reconstructor:
        """The reconstructor without the ``missing`` readings (bool mask), built once per mask while it
        is among the most recently used within DROPPED_KEPT_BYTES."""
        if not missing.any():
            return self.reconstructor
        key = np.packbits(missing).tobytes()
        if key in self._dropped:
            self._dropped.move_to_end(key)
            return self._dropped[key]
        r = self._dropped[key] = without_readings(self.reconstructor, missing)
        while len(self._dropped) > 1 and sum(map(kept_bytes, self._dropped.values())) > DROPPED_KEPT_BYTES:
            self._dropped.popitem(last=False)
        return_freed_memory()
        return r

    def matrix_bytes(self) -> int:
        """Bytes the model's matrices take: the Jacobian and what its reconstructor keeps (:func:`kept_bytes`)."""
        return self.reconstructor.linear.jacobian.nbytes + kept_bytes(self.reconstructor)

    def reconstruct(self, frame: np.ndarray, reference: np.ndarray, iterate: str = "auto"
                    ) -> tuple[np.ndarray, dict]:
        """The image (rows, cols) of relative change, and how it was made.

        Readings that are NaN in either frame are dropped. ``iterate`` is ``auto``
        (iterate when the forward model at the one-step image misses the data by more than
        MISFIT_LIMIT noise deviations, rms; checked only if the image changes some pixel
        by more than LINEAR_LIMIT), ``always`` or ``never``. The model used is
        :meth:`for_reference`'s.
        """
        if iterate not in ("auto", "always", "never"):
            raise ReconstructionError(f"iterate must be auto, always or never, got {iterate!r}")
        model = self.for_reference(reference)
        if model is not self:
            return model.reconstruct(frame, reference, iterate)
        if self.reconstructor.options.algorithm == "backprojection":
            if iterate == "always":
                raise ReconstructionError("backprojection has no regularisation to iterate with; use a "
                                          "Gauss-Newton or GREIT reconstructor to iterate")
            iterate = "never"
        missing = ~(np.isfinite(frame) & np.isfinite(reference))
        r = self.for_readings(missing)
        correlation = r.check_reference(reference)
        pixels = r.pixels(frame, reference)
        misfit = None
        if iterate == "auto" and np.max(np.abs(pixels)) > LINEAR_LIMIT:
            misfit = one_step_misfit(self.forward, r, frame, reference, pixels)
        info = {"usable_readings": int(r.usable.sum()), "reference_correlation": correlation,
                "one_step_misfit": misfit, "iterations": 0}
        if iterate == "always" or (misfit is not None and misfit > MISFIT_LIMIT):
            result = iterative_reconstruct(self.forward, r, frame, reference)
            pixels = result.pixels
            info["iterations"] = result.iterations
        return r.grid.image(pixels), info


    def regions(self, frame: np.ndarray, reference: np.ndarray, image: np.ndarray | None = None,
                sign: float = -1.0) -> list:
        """The pressed (``sign`` -1) or firmer (+1) regions of ``frame``, each fitted to the
        readings for its position, size, depth and uncertainty (:mod:`appliance.core.localise`)."""
        from appliance.core.localise import localise

        model = self.for_reference(reference)
        missing = ~(np.isfinite(frame) & np.isfinite(reference))
        r = model.for_readings(missing)
        return localise(model.forward, r, frame, reference, image, sign)


def kept_bytes(r: Reconstructor) -> int:
    """Bytes ``r`` keeps beyond its linear model: its R, or its factored form's own arrays and factor
    (for a set of missing readings, what it adds to the full set's, which it shares)."""
    own = r.usable.nbytes + (0 if r.sensitivity is None else r.sensitivity.nbytes)
    if r.matrix is not None:
        return own + r.matrix.nbytes
    assert r.normal_form is not None            # one of the two is always built
    return own + r.normal_form.nbytes()


def return_freed_memory() -> None:
    """Hand the pages freed since back to the system. glibc keeps a freed block that is not at the top of
    its heap, so a monitor would hold the work space of every set of missing readings it built and of its
    frames; other C libraries have no malloc_trim, and need nothing done."""
    if platform.libc_ver()[0] == "glibc":
        ctypes.CDLL(None).malloc_trim(0)


def build_model(setup: ModelSetup, progress=None, mesh: Mesh | None = None) -> ReconstructionModel:
    """Mesh (unless the setup's ``mesh`` is given), forward model, Jacobian on the pixels, reconstruction
    matrix; ``progress(step, share)`` is told each step as it starts, and at the end what the model's
    matrices take."""
    report = progress or (lambda step, share: None)
    report("meshing", 0.0)
    mesh = mesh if mesh is not None else mesh_layout(setup.layout, setup.density)
    report("assembling the forward model", 0.1)
    forward = build_fem_model(setup.layout, mesh, contact_impedance_ohm_m2=setup.contact_ohm_m2)
    report("solving and differentiating", 0.3)
    grid = pixel_grid(setup.layout, *(setup.pixels or (None, None)))
    linear = linear_model(forward, setup.protocol, grid)
    report("choosing lambda and the reconstruction matrix", 0.6)
    reconstructor = build_reconstructor(linear, setup.options)
    model = ReconstructionModel(setup, mesh, reconstructor)
    model.__dict__["forward"] = forward
    report(f"done: its matrices take {model.matrix_bytes() / 2**20:.1f} MiB", 1.0)
    return model


def model_path(setup: ModelSetup, cache_dir: Path) -> Path:
    """Where ``cache_dir`` keeps the model of ``setup``; a fitted model's name starts with its nominal's key."""
    if setup.fitted_contact_ohm_m2 is None:
        return Path(cache_dir) / f"model-{setup.key()}.npz"
    return Path(cache_dir) / f"model-{setup.nominal.key()}-fitted-{setup.key()[:16]}.npz"


def cached_model(setup: ModelSetup, cache_dir: Path, progress=None, mesh: Mesh | None = None
                 ) -> tuple[ReconstructionModel, bool]:
    """The model of ``setup`` from ``cache_dir`` if it is there, else built (on ``mesh`` if given) and saved.

    Returns the model and whether it was loaded. An unreadable cache file is rebuilt. Saving a
    fitted model removes all but the newest FITTED_KEPT of its setup's fitted models.
    """
    path = model_path(setup, cache_dir)
    if path.exists():
        try:
            model = load_model(path, setup)
            model.cache_dir = Path(cache_dir)
            return model, True
        except (OSError, ValueError, KeyError):
            pass
    model = build_model(setup, progress, mesh)
    model.cache_dir = Path(cache_dir)
    save_model(model, path)
    if setup.fitted_contact_ohm_m2 is not None:
        fitted = sorted(Path(cache_dir).glob(f"model-{setup.nominal.key()}-fitted-*.npz"),
                        key=lambda p: p.stat().st_mtime, reverse=True)
        for old in fitted[FITTED_KEPT:]:
            old.unlink(missing_ok=True)
    return model, False


def cached_fits(setup: ModelSetup, cache_dir: Path) -> list[np.ndarray]:
    """The contacts of the fitted models of ``setup``'s nominal in ``cache_dir``, newest first."""
    out = []
    paths = sorted(Path(cache_dir).glob(f"model-{setup.nominal.key()}-fitted-*.npz"),
                   key=lambda p: p.stat().st_mtime, reverse=True)
    for path in paths:
        try:
            with np.load(path) as f:
                out.append(np.array(f["contacts"], dtype=float))
        except (OSError, ValueError, KeyError):
            continue
    return out


def save_model(model: ReconstructionModel, path: Path) -> None:
    """Write ``model`` to ``path`` atomically (a temporary file, then a rename)."""
    r, linear = model.reconstructor, model.reconstructor.linear
    arrays = {
        "nodes": model.mesh.nodes, "triangles": model.mesh.triangles, "contact": model.mesh.contact,
        "inside": linear.grid.inside, "jacobian": linear.jacobian, "reference": linear.reference,
        "areas": linear.areas_mm2, "map_data": linear.mapping.data, "map_indices": linear.mapping.indices,
        "map_indptr": linear.mapping.indptr, "usable": r.usable,
        "scalars": np.array([r.lam, r.achieved_noise_figure, linear.grid.width_mm, linear.grid.height_mm]),
        "contacts": model.setup.contact_ohm_m2, "key": np.array(model.setup.key()),
    }
    if r.matrix is not None:
        arrays["matrix"] = r.matrix
    else:
        form = r.normal_form
        assert form is not None                 # a reconstructor without a matrix has its normal form
        arrays.update(normal=form.normal, prior=form.prior, weights=form.weights)
        if form.left is not None:
            arrays["left"] = form.left
    if r.sensitivity is not None:
        arrays["sensitivity"] = r.sensitivity
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, lambda out: np.savez(out, **arrays))


def load_model(path: Path, setup: ModelSetup) -> ReconstructionModel:
    """Read a model saved by :func:`save_model` for ``setup``.

    Raises
    ------
    ValueError
        The file was saved for another setup.
    """
    with np.load(path) as f:
        if str(f["key"]) != setup.key():
            raise ValueError(f"{path} holds a model of another setup")
        lam, figure, width, height = f["scalars"]
        inside = f["inside"]
        grid = PixelGrid(inside.shape[0], inside.shape[1], float(width), float(height), inside)
        mapping = sp.csr_matrix((f["map_data"], f["map_indices"], f["map_indptr"]),
                                shape=(len(f["triangles"]), grid.n_inside))
        linear = LinearModel(setup.protocol, grid, f["jacobian"], f["reference"], f["areas"], mapping)
        sensitivity = f["sensitivity"] if "sensitivity" in f.files else None
        if "matrix" in f.files:
            reconstructor = Reconstructor(linear, setup.options, f["matrix"], f["usable"], float(lam),
                                          float(figure), sensitivity)
        else:
            form = NormalForm(f["normal"], f["prior"], f["weights"], f["left"] if "left" in f.files else None,
                              float(lam))
            reconstructor = Reconstructor(linear, setup.options, None, f["usable"], float(lam), float(figure),
                                          None, form)
        mesh = Mesh(f["nodes"], f["triangles"], f["contact"])
    return ReconstructionModel(setup, mesh, reconstructor)


def default_cache_dir() -> Path:
    """``$APPLIANCE_CACHE_DIR``, else ``$XDG_CACHE_HOME/appliance``, else ``~/.cache/appliance``."""
    if os.environ.get("APPLIANCE_CACHE_DIR"):
        return Path(os.environ["APPLIANCE_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "appliance"
