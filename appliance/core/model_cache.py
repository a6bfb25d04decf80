"""A built reconstruction model, and its cache on disk.

Building means meshing, assembling, solving, differentiating and choosing lambda:
a fraction of a second on the 16-electrode sensors, seconds on a 32-electrode tank.
A built model is saved under the hash of everything it depends on (the layout as
TOML, the protocol, the options, mesh density, pixels, contact impedance, the file
format and the package version), written atomically, so a restart loads it in
milliseconds and a change to any input builds a new one.

>>> from appliance.core.layouts import get_layout
>>> from appliance.core.protocols import default_protocol
>>> setup = ModelSetup(get_layout("grid-4x4"), default_protocol(get_layout("grid-4x4")))
>>> len(setup.key())
64
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import scipy.sparse as sp

import appliance
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
from appliance.errors import ReconstructionError
from appliance.files import write_atomic

FORMAT_VERSION = 2

LINEAR_LIMIT = 0.05
"""Below this largest relative change the one-step image is taken as it is, without the
forward solve that checks it (the linearisation's error grows with the square of the change)."""


@dataclass(frozen=True)
class ModelSetup:
    """Everything a reconstruction model depends on."""

    layout: Layout
    protocol: Protocol
    options: ReconstructionOptions = ReconstructionOptions()
    density: float = 1.0
    pixels: tuple[int, int] | None = None
    contact_impedance_ohm_m2: float = DEFAULT_CONTACT_IMPEDANCE_OHM_M2

    def key(self) -> str:
        """SHA-256 (hex) of the setup, the file format and the package version."""
        description = {
            "layout": layout_to_toml(self.layout),
            "protocol": hashlib.sha256(np.ascontiguousarray(self.protocol.readings, dtype=np.int64)).hexdigest(),
            "options": dataclasses.asdict(self.options),
            "density": self.density, "pixels": self.pixels, "contact": self.contact_impedance_ohm_m2,
            "format": FORMAT_VERSION, "version": appliance.__version__,
        }
        return hashlib.sha256(json.dumps(description, sort_keys=True).encode()).hexdigest()


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
    """A setup built: its mesh and reconstructor; the forward model is rebuilt on first need."""

    setup: ModelSetup
    mesh: Mesh
    reconstructor: Reconstructor
    _dropped: dict = field(default_factory=dict, repr=False)

    @cached_property
    def forward(self) -> ForwardModel:
        """The forward model, for iterating (built from the stored mesh)."""
        return build_fem_model(self.setup.layout, self.mesh,
                               contact_impedance_ohm_m2=self.setup.contact_impedance_ohm_m2)

    def for_readings(self, missing: np.ndarray) -> Reconstructor:
        """The reconstructor without the ``missing`` readings (bool mask), built once per mask."""
        if not missing.any():
            return self.reconstructor
        key = np.packbits(missing).tobytes()
        if key not in self._dropped:
            self._dropped[key] = without_readings(self.reconstructor, missing)
        return self._dropped[key]

    def reconstruct(self, frame: np.ndarray, reference: np.ndarray, iterate: str = "auto"
                    ) -> tuple[np.ndarray, dict]:
        """The image (rows, cols) of relative change, and how it was made.

        Readings that are NaN in either frame are dropped. ``iterate`` is ``auto``
        (iterate when the forward model at the one-step image misses the data by more than
        MISFIT_LIMIT noise deviations, rms; checked only if the image changes some pixel
        by more than LINEAR_LIMIT), ``always`` or ``never``.
        """
        if iterate not in ("auto", "always", "never"):
            raise ReconstructionError(f"iterate must be auto, always or never, got {iterate!r}")
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

        missing = ~(np.isfinite(frame) & np.isfinite(reference))
        r = self.for_readings(missing)
        return localise(self.forward, r, frame, reference, image, sign)


def build_model(setup: ModelSetup, progress=None) -> ReconstructionModel:
    """Mesh, forward model, Jacobian on the pixels, reconstruction matrix; ``progress(step, share)``
    is told each step as it starts."""
    report = progress or (lambda step, share: None)
    report("meshing", 0.0)
    mesh = mesh_layout(setup.layout, setup.density)
    report("assembling the forward model", 0.1)
    forward = build_fem_model(setup.layout, mesh, contact_impedance_ohm_m2=setup.contact_impedance_ohm_m2)
    report("solving and differentiating", 0.3)
    grid = pixel_grid(setup.layout, *(setup.pixels or (None, None)))
    linear = linear_model(forward, setup.protocol, grid)
    report("choosing lambda and the reconstruction matrix", 0.6)
    reconstructor = build_reconstructor(linear, setup.options)
    report("done", 1.0)
    model = ReconstructionModel(setup, mesh, reconstructor)
    model.__dict__["forward"] = forward
    return model


def model_path(setup: ModelSetup, cache_dir: Path) -> Path:
    """Where ``cache_dir`` keeps the model of ``setup``."""
    return Path(cache_dir) / f"model-{setup.key()}.npz"


def cached_model(setup: ModelSetup, cache_dir: Path, progress=None) -> tuple[ReconstructionModel, bool]:
    """The model of ``setup`` from ``cache_dir`` if it is there, else built and saved.

    Returns the model and whether it was loaded. An unreadable cache file is rebuilt.
    """
    path = model_path(setup, cache_dir)
    if path.exists():
        try:
            return load_model(path, setup), True
        except (OSError, ValueError, KeyError):
            pass
    model = build_model(setup, progress)
    save_model(model, path)
    return model, False


def save_model(model: ReconstructionModel, path: Path) -> None:
    """Write ``model`` to ``path`` atomically (a temporary file, then a rename)."""
    r, linear = model.reconstructor, model.reconstructor.linear
    arrays = {
        "nodes": model.mesh.nodes, "triangles": model.mesh.triangles, "contact": model.mesh.contact,
        "inside": linear.grid.inside, "jacobian": linear.jacobian, "reference": linear.reference,
        "areas": linear.areas_mm2, "map_data": linear.mapping.data, "map_indices": linear.mapping.indices,
        "map_indptr": linear.mapping.indptr, "usable": r.usable,
        "scalars": np.array([r.lam, r.achieved_noise_figure, linear.grid.width_mm, linear.grid.height_mm]),
        "key": np.array(model.setup.key()),
    }
    if r.matrix is not None:
        arrays["matrix"] = r.matrix
    else:
        form = r.normal_form
        arrays.update(normal=form.normal, prior=form.prior, weights=form.weights)
        if form.left is not None:
            arrays["left"] = form.left
    if r.sensitivity is not None:
        arrays["sensitivity"] = r.sensitivity
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_atomic(path, buffer.getvalue())


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
