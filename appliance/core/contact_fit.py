"""Each electrode's contact impedance and the sheet's conductance, fitted to the empty-mat reference.

The reconstruction is linearised at a homogeneous sheet; the reference frame says
which sheet and which contacts. With a uniform sheet of conductance sigma and a
drive current I the readings are

    v = (I / sigma) F(sigma z_1, ..., sigma z_L)

where F is the model at unit conductance and current, so the data fix the scale
s = I / sigma and the contact impedances at unit conductance, zeta_l = sigma z_l
(what the model is built with); with the drive current known, also sigma and each
z_l. Log s and log zeta are fitted by Gauss-Newton, the readings weighted by their
noise plus a share of each reading for the model's own error (its mesh), with a
Gaussian prior on log zeta: each electrode about a common level
(``ContactPrior.spread_log``), the common level about the nominal
(``ContactPrior.common_log``). The scale has no prior: the readings fix it.

What the readings can determine. Four-electrode readings (the grid protocols)
see a contact only through the current a floating electrode carries past the
sheet and through how the drive current spreads over a face. Both fade as the
contact grows poor against the sheet (z sigma / area well above 1, where the
model's nominal lies on the 100 mm sensors): there a 50 % change of one contact
moves the readings by less than 1e-4 of their size, below the noise, and the prior
keeps the contact at nominal, as it should, since the image cannot feel it either.
Near ideal contacts (z sigma / area ~ 0.01-0.1, a saline mat) a contact moves the
readings by about 1e-3 and the readings fix it. Readings on driven electrodes (the
KTC tank's) see their contacts directly. :class:`ContactFit` states what was
determined: each contact's posterior deviation, and the eigenvalues of the
readings' information against the prior's.

A broken electrode's readings are missing (NaN): its contact is then seen only
through what it shunts as a floating electrode, and the prior holds the rest.

Refreshing. Every new empty-mat reference refits (the monitor's fresh start and
restart, the engineer's capture, which is refused while the mat reads loaded;
``ReconstructionModel.for_reference`` on any empty frame). A refit from a loaded
mat is not offered: on the 16-electrode sensor a 20 mm load moves all but about 3 %
of the readings by more than the noise, so there are no unloaded readings to fit,
and a contact cannot be told from the conductance beside its face without an empty
reference. Drift shows as the change between fits of successive references.

>>> ContactPrior().spread_log
0.5
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from appliance.core.fem import face_mass_matrices, with_contact_impedance
from appliance.core.forward import ForwardModel, factorise, transfer_readings
from appliance.core.mesh import Mesh
from appliance.core.protocols import Protocol
from appliance.core.regularisation import NoiseModel
from appliance.errors import ConfigError, ReconstructionError

MAX_ITERATIONS = 12
STEP_TOLERANCE = 1e-3
"""Stop once no log contact impedance moves by more than this (0.1 %) in a step ..."""
OBJECTIVE_TOLERANCE = 0.1
"""... or once a step lowers the objective (chi-squared plus prior) by less than this: a tenth of what
one standard deviation of any parameter is worth, where poorly determined contacts drift slowly."""
MAX_STEP_LOG = 3.0
"""The largest change of any log contact impedance in one step (a factor 20): the readings are far
from linear in a contact across decades, and the line search halves what overshoots. Each step is a
solve of every electrode's field, most of a fit's cost on a bed."""
LOG_RANGE = float(np.log(1e4))
"""Fitted contacts stay within 1e-4 to 1e4 times the nominal."""
ACCEPT_MISFIT = 4.0
"""A fit that leaves the reference more than this many noise deviations unexplained (rms, the model's
error included) is not taken: a homogeneous sheet with contacts cannot be what was measured, and
contacts fitted to the rest would stand in for whatever is missing (the KTC tank's third dimension,
an uneven liquid). The same limit calls for iteration in :mod:`appliance.core.iterative`."""
SOLVE_COLUMNS = 64
"""Electrode fields solved at once: bounds the memory of a bed's solves to a few tens of megabytes."""
_MM2_PER_M2 = 1e6


@dataclass(frozen=True)
class ContactPrior:
    """What is believed of the contacts before the reference is read, in natural-log units.

    Attributes
    ----------
    spread_log : float
        Standard deviation of one electrode's log contact impedance about the mat's
        common level (0.5: most within a factor 1.6; uniform draws within +-50 % have 0.29).
    common_log : float
        Standard deviation of the common level about the nominal (2.3: a factor of 10),
        which also carries the sheet's unknown conductance (zeta = sigma z).
    model_error : float
        Share of each reading the model itself may miss (the default mesh is within
        0.4 to 0.8 % of converged readings, benchmarks/forward.md), added to the noise
        in quadrature, so the fit does not bend the contacts to the mesh's error.
    """

    spread_log: float = 0.5
    common_log: float = 2.3
    model_error: float = 5e-3

    def __post_init__(self):
        if not (self.spread_log > 0 and self.common_log > 0 and self.model_error >= 0):
            raise ConfigError(f"contact prior needs positive spreads and a non-negative model error, got {self}")

    def precision(self, n: int) -> np.ndarray:
        """The inverse of spread^2 I + common^2 1 1^T (n x n)."""
        share = self.common_log**2 / (self.spread_log**2 + n * self.common_log**2)
        return (np.eye(n) - share) / self.spread_log**2

    @property
    def sd_log(self) -> float:
        """Each electrode's prior standard deviation of log contact impedance."""
        return float(np.hypot(self.spread_log, self.common_log))


@dataclass(frozen=True)
class ContactFit:
    """Contact impedances and scale fitted to a reference, and how well the readings determined them.

    Attributes
    ----------
    contact_ohm_m2 : ndarray, shape (n_electrodes,)
        Each contact impedance at unit sheet conductance (sigma z): what the model is built with.
    nominal_ohm_m2 : ndarray, shape (n_electrodes,)
        The prior's centre, the same way.
    scale : float
        Reference volts per model volt: drive current over sheet conductance (ohm per amp times amps).
    sd_log_contact : ndarray, shape (n_electrodes,)
        Posterior standard deviation of each log contact impedance (the prior's is ``ContactPrior.sd_log``).
    information : ndarray
        Eigenvalues, largest first, of the readings' information on log contact impedance
        against the prior's: above 1 the readings determine that direction better than
        the prior (``determined`` counts them), below it the prior holds it.
    misfit_nominal, misfit : float
        Rms of the weighted residual of the reference at the nominal contacts and at the fit.
    iterations : int
    usable : ndarray of bool
        The readings fitted (the others were missing).
    """

    contact_ohm_m2: np.ndarray
    nominal_ohm_m2: np.ndarray
    scale: float
    sd_log_contact: np.ndarray
    information: np.ndarray
    misfit_nominal: float
    misfit: float
    iterations: int
    usable: np.ndarray

    @property
    def determined(self) -> int:
        return int(np.count_nonzero(self.information > 1.0))

    @property
    def accepted(self) -> bool:
        """Whether the model explains the reference at the fit (rms residual within ACCEPT_MISFIT)."""
        return self.misfit <= ACCEPT_MISFIT

    def sheet_conductance_s(self, current_a: float) -> float:
        """The sheet's conductance for a drive of ``current_a`` amps (the readings in volts)."""
        return float(current_a / self.scale)

    def contact_impedance_ohm_m2(self, current_a: float) -> np.ndarray:
        """Each electrode's contact impedance, ohm m^2, for a drive of ``current_a`` amps."""
        return self.contact_ohm_m2 / self.sheet_conductance_s(current_a)

    def summary(self) -> dict:
        """The fit as plain numbers, for a log line or a stored state."""
        ratio = self.contact_ohm_m2 / self.nominal_ohm_m2
        return {"accepted": self.accepted, "contact_ohm_m2": [float(z) for z in self.contact_ohm_m2],
                "contact_over_nominal": [float(np.min(ratio)), float(np.median(ratio)), float(np.max(ratio))],
                "sd_log_contact": [float(v) for v in self.sd_log_contact], "determined": self.determined,
                "scale": self.scale, "misfit_nominal": self.misfit_nominal, "misfit": self.misfit,
                "usable": int(self.usable.sum()), "iterations": self.iterations}

    def describe(self) -> str:
        """One line: what was fitted and how well the readings determined it."""
        low, mid, high = self.summary()["contact_over_nominal"]
        verdict = "taken" if self.accepted else f"not taken (the model misses the reference by more than " \
                                                 f"{ACCEPT_MISFIT:g} noise deviations)"
        return (f"contacts {mid:.3g} times nominal (electrodes {low:.3g} to {high:.3g}, each within a factor "
                f"{np.exp(np.median(self.sd_log_contact)):.3g} typically), {self.determined} of "
                f"{len(self.contact_ohm_m2)} directions set by the readings; reference misfit "
                f"{self.misfit_nominal:.2f} -> {self.misfit:.2f} noise deviations; {verdict}")


def fit_contacts(model: ForwardModel, mesh: Mesh, protocol: Protocol, reference, nominal_ohm_m2, noise: NoiseModel,
                 prior: ContactPrior = ContactPrior(), start_ohm_m2=None) -> ContactFit:
    """Fit every electrode's contact impedance and the scale to the ``reference`` readings.

    Parameters
    ----------
    model : ForwardModel
        A finite-element model of ``mesh`` (any contact impedances: only its sheet is used).
    reference : ndarray, shape (n_readings,)
        The empty mat's readings in protocol order, volts; NaN marks a missing reading.
    nominal_ohm_m2 : float or ndarray
        The prior's centre: contact impedance at unit sheet conductance.
    noise : NoiseModel
        The readings' noise.
    start_ohm_m2 : ndarray, optional
        Where to start (a previous fit); by default the nominal.

    Raises
    ------
    ReconstructionError
        A reference of the wrong length, an infinite reading, too few usable readings,
        or readings whose fitted scale is not positive (another layout, reversed leads).
    """
    v = np.asarray(reference, dtype=np.float64)
    if v.shape != (len(protocol),):
        raise ReconstructionError(f"the reference has {v.size} readings, the protocol {len(protocol)}: is it from "
                                  f"another layout or protocol?")
    infinite = np.flatnonzero(np.isinf(v))
    if infinite.size:
        k = int(infinite[0])
        raise ReconstructionError(f"reference reading {k + 1} ({', '.join(map(str, protocol.readings[k]))}) is "
                                  f"infinite; a reading the front end could not take must be NaN")
    n_el = model.n_electrodes
    usable = np.isfinite(v)
    if usable.sum() < n_el + 2:
        raise ReconstructionError(f"only {int(usable.sum())} of {len(v)} reference readings are usable: too few to "
                                  f"fit {n_el} contact impedances and the scale")
    nominal = np.log(np.broadcast_to(np.asarray(nominal_ohm_m2, dtype=float), (n_el,)))
    if not np.all(np.isfinite(nominal)):
        raise ConfigError("the nominal contact impedance must be positive and finite")
    data = v[usable]
    std = np.hypot(noise.std(data), prior.model_error * data)
    problem = _Problem(model, mesh, protocol, usable, data / std, std, nominal, prior.precision(n_el))

    theta = nominal.copy() if start_ohm_m2 is None else np.clip(np.log(np.asarray(start_ohm_m2, dtype=float)),
                                                                nominal - LOG_RANGE, nominal + LOG_RANGE)
    state = problem.evaluate(theta)
    misfit_nominal = state.misfit if start_ohm_m2 is None else problem.evaluate(nominal).misfit
    iterations = 0
    for iterations in range(1, MAX_ITERATIONS + 1):     # noqa: B007  (the count is reported after the loop)
        reduced, gradient = problem.linearise(state)
        normal = reduced.T @ reduced + problem.precision
        step = sla.solve(normal, gradient, assume_a="pos")
        step *= min(1.0, MAX_STEP_LOG / max(np.max(np.abs(step)), 1e-300))
        length = 1.0
        while length > 1e-3:
            trial = problem.evaluate(np.clip(theta + length * step, nominal - LOG_RANGE, nominal + LOG_RANGE))
            # Take the step if it earns a quarter of what the linearisation promised: a step far into the
            # ideal-contact limit, where the readings stop changing, lowers the objective a little and stalls.
            delta = trial.theta - theta
            promised = 2 * gradient @ delta - delta @ normal @ delta
            if state.objective - trial.objective >= 0.25 * promised:
                break
            length /= 2
        else:
            break                                           # no step lowers the objective: converged
        moved, gained = np.max(np.abs(trial.theta - theta)), state.objective - trial.objective
        theta, state = trial.theta, trial
        if moved < STEP_TOLERANCE or gained < OBJECTIVE_TOLERANCE:
            break
    reduced, _ = problem.linearise(state)
    information = reduced.T @ reduced
    covariance = np.linalg.inv(information + problem.precision)
    values, vectors = np.linalg.eigh(problem.precision)
    prior_root = (vectors / np.sqrt(values)) @ vectors.T                 # the prior covariance's square root
    eigen = np.sort(np.linalg.eigvalsh(prior_root @ information @ prior_root))[::-1]
    return ContactFit(np.exp(theta), np.exp(nominal), state.scale, np.sqrt(np.diag(covariance)), np.maximum(eigen, 0.0),
                      misfit_nominal, state.misfit, iterations, usable)


def contact_sensitivity(model: ForwardModel, mesh: Mesh, protocol: Protocol, contact_ohm_m2) -> np.ndarray:
    """d(reading) / d(log contact impedance) of every reading and electrode at ``contact_ohm_m2`` (unit sheet
    conductance and current), shape (n_readings, n_electrodes): what the fit linearises."""
    n = len(protocol)
    problem = _Problem(model, mesh, protocol, np.ones(n, dtype=bool), np.zeros(n), np.ones(n),
                       np.zeros(model.n_electrodes), np.eye(model.n_electrodes))
    theta = np.log(np.broadcast_to(np.asarray(contact_ohm_m2, dtype=float), (model.n_electrodes,)))
    transfer, potentials = problem._solve(np.exp(theta))
    return problem._sensitivity(_State(theta, 1.0, transfer, potentials, np.zeros(n), 0.0, 0.0))


@dataclass(frozen=True)
class _State:
    theta: np.ndarray
    scale: float
    transfer: np.ndarray
    face_potentials: np.ndarray
    modelled: np.ndarray            # F at theta over the usable readings, whitened
    objective: float
    misfit: float


class _Problem:
    """The weighted least-squares problem of one reference, its model solved at any contacts."""

    def __init__(self, model, mesh, protocol, usable, whitened, std, nominal, precision):
        self.model, self.mesh, self.protocol, self.usable = model, mesh, protocol, usable
        self.whitened, self.std, self.nominal, self.precision = whitened, std, nominal, precision
        self.faces = face_mass_matrices(mesh, model.n_electrodes)
        nodes = np.concatenate([nodes for nodes, _ in self.faces])
        self.face_rows = np.split(np.arange(len(nodes)), np.cumsum([len(n) for n, _ in self.faces])[:-1])
        self.face_map = sp.csr_matrix(model.node_map[nodes])

    def evaluate(self, theta: np.ndarray) -> _State:
        transfer, potentials = self._solve(np.exp(theta))
        f = transfer_readings(transfer, self.protocol)[self.usable] / self.std
        scale = float(f @ self.whitened) / float(f @ f)
        if not np.isfinite(scale) or scale <= 0:
            raise ReconstructionError(f"the reference readings do not match this layout's model (fitted scale "
                                      f"{scale:.3g}); is the frame from another layout or protocol, or are the "
                                      f"measuring leads reversed?")
        residual = self.whitened - scale * f
        deviation = theta - self.nominal
        objective = float(residual @ residual + deviation @ self.precision @ deviation)
        return _State(theta, scale, transfer, potentials, f, objective, float(np.sqrt(np.mean(residual**2))))

    def linearise(self, state: _State) -> tuple[np.ndarray, np.ndarray]:
        """The whitened sensitivity to log contact with the scale's direction projected out (the scale is
        fitted exactly at every contact), and the objective's descent direction."""
        f = state.modelled
        sensitivity = state.scale * self._sensitivity(state) / self.std[:, None]
        reduced = sensitivity - np.outer(f, f @ sensitivity) / (f @ f)
        residual = self.whitened - state.scale * f
        return reduced, reduced.T @ residual - self.precision @ (state.theta - self.nominal)

    def _solve(self, contact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Transfer impedances and face-node potentials for a unit current into each electrode."""
        model = with_contact_impedance(self.model, self.mesh, contact)
        system = factorise(model, np.ones(model.n_elements))
        e = sp.csc_matrix(model.electrodes)
        columns = np.flatnonzero(np.diff(e.indptr))
        transfer = np.zeros((model.n_electrodes, model.n_electrodes))
        potentials = np.zeros((self.face_map.shape[0], model.n_electrodes))
        for start in range(0, len(columns), SOLVE_COLUMNS):
            block = columns[start:start + SOLVE_COLUMNS]
            x, _ = system.solve(e[:, block].toarray())
            transfer[:, block] = e.T @ x
            potentials[:, block] = self.face_map @ x
        return transfer, potentials

    def _sensitivity(self, state: _State) -> np.ndarray:
        """d(reading) / d(log contact impedance of each electrode), usable readings only.

        The face term of electrode l is M_l / zeta_l acting on u - U_l, so by the adjoint
        method dV/dlog zeta_l = (u_cd - U_l,cd)^T M_l (u_ab - U_l,ab) / zeta_l.
        """
        a, b, c, d = (self.protocol.readings[self.usable] - 1).T
        out = np.empty((len(a), self.model.n_electrodes))
        contact = np.exp(state.theta) * _MM2_PER_M2
        for l, ((_, mass), rows) in enumerate(zip(self.faces, self.face_rows)):
            w = state.face_potentials[rows] - state.transfer[l][None, :]
            s = w.T @ (mass @ w)
            out[:, l] = (s[c, a] - s[c, b] - s[d, a] + s[d, b]) / contact[l]
        return out
