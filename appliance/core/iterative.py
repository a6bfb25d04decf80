"""Iterative regularised Gauss-Newton, for changes too large for the one-step linear image.

Far from the reference the readings stop being linear in the conductivity: a
metal object or a fully pressed region is imaged too faint and too wide by a
one-step reconstruction, and its readings are left badly unexplained. Then we
solve the non-linear problem: the log of each pixel's conductivity ratio, eta,
minimising

    || W^1/2 (d - (F(eta) - F(0))) ||^2 + lambda || eta ||_P^2

by Gauss-Newton with a backtracking line search, re-solving the forward model and
its Jacobian at every step. Working in log conductivity keeps every element
positive and treats insulating and conducting changes alike. Lambda, the prior
and the noise weights are those of the one-step reconstructor, so the two agree
for small changes.

:func:`one_step_misfit` tells when this is needed: it solves the forward model at the
one-step image and measures how far its readings are from the data, in units of the
noise. (The linear residual cannot tell: Gauss-Newton fits the data linearly almost
exactly while overshooting the change it images.)

>>> MAX_ITERATIONS
12
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.core.forward import ForwardModel, solve_electrodes
from appliance.core.jacobian import jacobian
from appliance.core.reconstruct import Reconstructor, solve_spd
from appliance.core.regularisation import prior_matrix
from appliance.errors import ReconstructionError, SolverError

MAX_ITERATIONS = 12
LOG_LIMIT = float(np.log(1e4))      # conductivity stays within 1e-4 to 1e4 of the reference's
STEP_TOLERANCE = 1e-3
"""Stop once no pixel's log conductivity moves by more than this in one step."""

LAMBDA_FLOOR = 1e-4
"""The least regularisation the non-linear fit takes, relative to the data's (lambda tr P against tr J^T W J).
The one-step rule may choose far less: at the floor of its search (1e-12) on the 16-electrode sensors and the
8-electrode grid-2x4, whose one-step GREIT image its desired-image blur holds. Gauss-Newton with no
regularisation follows the model's error instead of the data, into images the machine's rounding decides: a
100 mmHg square on grid-2x4@100x200 came out at its place on one CPU and at the mat's far corner on another.
1e-4 lies below what the rule chooses where it finds an optimum inside its range (grid-4x4: 3.3e-4), so those
mats iterate as before."""
MISFIT_LIMIT = 4.0
AFFORDABLE_ELECTRODES = 32      # beyond this one step takes tens of seconds (~25 s on a 128-electrode bed)
"""A one-step image that leaves more than this many noise standard deviations of the data
unexplained, per reading on average (rms), calls for iteration."""


@dataclass(frozen=True)
class IterativeResult:
    """The image's pixels (relative change, n_pixels), and how the iteration went."""

    pixels: np.ndarray
    iterations: int
    misfit_history: tuple


def one_step_misfit(model: ForwardModel, r: Reconstructor, frame: np.ndarray, reference: np.ndarray,
                    pixels: np.ndarray | None = None) -> float:
    """Rms over usable readings of (data - (F(x) - F(0))) / noise for the one-step image x.

    The image is clipped to conductivities of at least 1 % of the reference's: a one-step
    image can overshoot below zero, which no sheet can do.
    """
    u, linear = r.usable, r.linear
    x = r.pixels(frame, reference) if pixels is None else pixels
    data = (frame - reference)[u] / r.scale(reference)
    sigma = np.maximum(1.0 + linear.mapping @ x, 0.01)
    predicted = solve_electrodes(model, sigma).readings(linear.protocol)[u] - linear.reference[u]
    std = r.options.noise.std(linear.reference)[u]
    return float(np.sqrt(np.mean(((data - predicted) / std) ** 2)))


def iterative_reconstruct(model: ForwardModel, r: Reconstructor, frame: np.ndarray, reference: np.ndarray,
                          max_iterations: int = MAX_ITERATIONS) -> IterativeResult:
    """Reconstruct ``frame`` against ``reference`` non-linearly, starting from the one-step image.

    ``model`` must be the forward model ``r`` was linearised from.
    """
    linear, u = r.linear, r.usable
    if model.n_elements != linear.mapping.shape[0]:
        raise ReconstructionError("the forward model is not the one the reconstructor was built from")
    data = np.where(u, (frame - reference) / r.scale(reference), 0.0)
    weights = np.where(u, 1.0 / r.options.noise.std(linear.reference) ** 2, 0.0)
    j0 = linear.jacobian * u[:, None]
    # The prior lambda was chosen for: GREIT's inner solve is Tikhonov's.
    kind = r.options.algorithm[3:] if r.options.algorithm.startswith("gn-") else "tikhonov"
    normal = (j0.T * weights) @ j0
    prior = prior_matrix(kind, normal, linear.grid)
    penalty = max(r.lam, LAMBDA_FLOOR * np.trace(normal) / np.trace(prior)) * prior
    f0 = linear.reference

    def evaluate(eta):
        sigma = np.exp(linear.mapping @ eta)
        fields = solve_electrodes(model, sigma)
        residual = data - np.where(u, fields.readings(linear.protocol) - f0, 0.0)
        return sigma, fields, residual, float(residual @ (weights * residual) + eta @ penalty @ eta)

    start = np.log(np.clip(1.0 + r.pixels(frame, reference), 0.05, 20.0))
    eta = start
    sigma, fields, residual, objective = evaluate(eta)
    history = [objective]
    for _ in range(max_iterations):
        j = (linear.mapping.T @ jacobian(model, sigma, linear.protocol, fields, relative=True).T).T * u[:, None]
        jw = j.T * weights
        gradient = jw @ residual - penalty @ eta
        step = solve_spd(jw @ j + penalty, gradient)
        length = 1.0
        while length > 1e-3:
            # A wild step (near-saturated data) could ask for conductivities no sheet has, or that
            # the solver cannot take: keep log-conductivity within LOG_LIMIT and halve on failure.
            trial = np.clip(eta + length * step, -LOG_LIMIT, LOG_LIMIT)
            try:
                t_sigma, t_fields, t_residual, t_objective = evaluate(trial)
            except SolverError:
                t_objective = np.inf
            if t_objective < objective:
                break
            length /= 2
        else:
            break                                        # no step lowers the objective: converged
        eta, sigma, fields, residual, objective = trial, t_sigma, t_fields, t_residual, t_objective
        history.append(objective)
        if np.max(np.abs(length * step)) < STEP_TOLERANCE:
            break
    return IterativeResult(np.expm1(eta), len(history) - 1, tuple(history))


def affordable_iterate(n_electrodes: int) -> str:
    """How a monitor of ``n_electrodes`` should iterate: always where a step fits in a frame, never on a bed.

    Iterating images heavy presses at their true depth on the thesis's 16-electrode
    mat; on a 128-electrode bed each step re-solves and re-differentiates a model of
    6020 readings, far longer than a frame, so the one-step image is what a bed gets.
    """
    return "always" if n_electrodes <= AFFORDABLE_ELECTRODES else "never"
