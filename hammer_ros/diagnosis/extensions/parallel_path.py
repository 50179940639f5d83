"""The extension of ``parallel_path``: a linear path beside the Hammerstein branch
(feedforward system)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import signal

from ...errors import IdentificationError
from ...identification.billings_fakhouri import identify_feedforward
from ...identification.linear import LinearModel
from ...identification.piecewise_linear_ls import rank_one_factors
from ...identification.regression import build_regression, solve_least_squares
from ...identification.runs import Runs, per_run, several
from ...identification.simulation_error import refine, stabilised_denominator, steady_state_filter
from ..hammerstein import HammersteinModel, HammersteinParameters
from .common import Context, ExtendedModel, map_plot, order_details

PATH_ORDER = 2  # order of the parallel path
IMPULSE_LENGTH = 400


def linear_fit(u: np.ndarray, target: np.ndarray, order: int, delay: int,
               runs: Runs | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of an ARX fit of target on u (shared builder), stabilised (``runs``: no regressor
    reaches into another run)."""
    reg = build_regression(target, u, order, delay, runs=runs)
    theta = solve_least_squares(reg.phi, reg.target)
    a, coefficients = reg.split(theta)
    b = np.concatenate([np.zeros(delay), coefficients[:, 0]])
    return b, stabilised_denominator(np.concatenate([[1.0], a]))


@dataclass(frozen=True, eq=False)
class Feedforward:
    """y = G1[F(v)] + G2[v]: the Hammerstein branch and the linear path (b2, a2)."""

    branch: HammersteinModel
    b2: np.ndarray
    a2: np.ndarray

    def simulate(self, v: np.ndarray, basis: np.ndarray | None = None, runs: Runs | None = None) -> np.ndarray:
        """Free-run output from rest at v(0) (``basis``: eta(v), when known; ``runs``: every run
        from rest at its own first input)."""
        m = self.branch
        basis = m.basis(v) if basis is None else basis
        if several(runs) is not None:
            return per_run(lambda p: self.simulate(p[:, 0], p[:, 1:]), np.column_stack([v, basis]), runs)
        branch = steady_state_filter(m.b, m.a, basis @ m.slopes + m.kappa)
        return branch + steady_state_filter(self.b2, self.a2, v)


def _refine_feedforward(start: Feedforward, v: np.ndarray, y: np.ndarray, eta: np.ndarray, skip: int,
                        runs: Runs | None = None) -> Feedforward:
    """The feedforward model minimising the simulation error from ``start`` (the branch's
    largest numerator coefficient fixed, as in the baseline; ``runs``: summed over the runs)."""
    params = HammersteinParameters(start.branch)
    size, order = params.size, start.a2.size - 1

    def unpack(theta: np.ndarray) -> Feedforward:
        return Feedforward(params.unpack(theta[:size]), theta[size + order :],
                           np.concatenate([[1.0], theta[size : size + order]]))

    theta0 = np.concatenate([params.pack(start.branch), start.a2[1:], start.b2])
    return unpack(refine(lambda t: unpack(t).simulate(v, eta, runs), theta0, y, 40, skip))


def extend_parallel_path(ctx: Context) -> ExtendedModel:
    """Feedforward system y = G1[F(v)] + G2[v] (paper 003 sec. 3, Fig. 3): started from the
    baseline plus a second-order path fitted to its residual, from the common-denominator
    least-squares fit (``_common_denominator_start``; the baseline may have absorbed a slow
    path into its own dynamics), and from the Billings-Fakhouri correlation estimate
    (``billings_fakhouri.identify_feedforward``, exact for a Gaussian input) when it applies;
    the start with the smallest simulation error after refinement wins. On a record of several
    runs every regression, correlation and simulation is run by run (``Context``)."""
    base, s, skip, runs = ctx.baseline, ctx.split, ctx.skip, ctx.runs
    v, y = s.v_est, s.y_est
    eta = base.basis(v)
    b2, a2 = linear_fit(v, y - ctx.estimation_simulation(base.simulate), PATH_ORDER, 0, runs)
    starts = [Feedforward(base, b2, a2), _common_denominator_start(ctx), _billings_fakhouri_start(ctx)]
    fits = [_refine_feedforward(start, v, y, eta, skip, runs) for start in starts if start is not None]
    costs = [float(np.sum((y - f.simulate(v, eta, runs))[skip:] ** 2)) for f in fits]
    best = fits[int(np.nanargmin(costs))]
    path = LinearModel(best.b2, best.a2)
    details = {"branch": order_details(best.branch), "parallel_path": {
        "b": path.b.tolist(), "a": path.a[1:].tolist(), "poles": [[float(p.real), float(p.imag)] for p in path.poles]}}
    maps = (map_plot("F (Hammerstein branch)", best.branch.static, v),)
    return ExtendedModel("parallel_path", "feedforward (hammerstein + linear path)",
                         s.validation_output(best.simulate), details, maps, best.simulate)


def _impulse_fit(numerator: np.ndarray, denominator: np.ndarray, order: int,
                 delay: int) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of the given order fitted to the impulse response of numerator/denominator."""
    impulse = np.eye(1, IMPULSE_LENGTH, 0)[0]
    return linear_fit(impulse, signal.lfilter(numerator, denominator, impulse), order, delay)


def _common_denominator_start(ctx: Context) -> Feedforward | None:
    """A start from one least-squares solve: y = [B(q) F(v) + C(q) v] / A(q) with A of order
    n + PATH_ORDER (both paths' poles), i.e. PLLS (paper 001 eq. 23) with the input itself as
    one more channel; B F by rank one (eqs. 35-38); then G1 (order n) and G2 (order
    PATH_ORDER) fitted to the impulse responses of B/A and C/A."""
    base, s, skip = ctx.baseline, ctx.split, ctx.skip
    v, y = s.v_est, s.y_est
    try:
        reg = build_regression(y, np.column_stack([base.basis(v), v]), base.order + PATH_ORDER, 0, runs=ctx.runs)
    except ValueError:
        return None
    theta = solve_least_squares(np.column_stack([reg.phi, np.ones(reg.rows.size)])[skip:], reg.target[skip:])
    a, coefficients = reg.split(theta[:-1])
    b, mu = rank_one_factors(coefficients[:, :-1], None, a)
    if not np.all(np.isfinite(b)) or abs(np.sum(b)) < 1e-12:
        return None
    den = stabilised_denominator(np.concatenate([[1.0], a]))
    b1, a1 = _impulse_fit(b, den, base.order, base.delay)
    b2, a2 = _impulse_fit(coefficients[:, -1], den, PATH_ORDER, 0)
    branch = replace(base, a=a1, b=b1[: base.b.size], slopes=mu, kappa=float(theta[-1] / np.sum(b)))
    return Feedforward(branch, b2, a2) if np.any(branch.b) else None


def _billings_fakhouri_start(ctx: Context) -> Feedforward | None:
    """The Billings-Fakhouri feedforward estimate (paper 003 sec. 3) on this module's
    structure: its branch polynomial projected on the baseline's piecewise-linear basis, its
    parallel path re-fitted at PATH_ORDER."""
    base, s = ctx.baseline, ctx.split
    v, y = s.v_est, s.y_est
    try:
        fit = identify_feedforward(v, y, base.order, max(base.delay, 1), poly=3, runs=ctx.runs)
    except (IdentificationError, np.linalg.LinAlgError, ValueError):
        return None
    if not (fit.branch.is_stable() and fit.parallel_path.is_stable()) or fit.branch.a.size != base.a.size:
        return None
    coefficients = solve_least_squares(np.column_stack([base.basis(v), np.ones(v.size)]), fit.nonlinearity(v))
    b = np.zeros_like(base.b)
    b[: min(b.size, fit.branch.b.size)] = fit.branch.b[: b.size]
    branch = replace(base, a=stabilised_denominator(fit.branch.a), b=b, slopes=coefficients[:-1],
                     kappa=float(coefficients[-1]))
    b2, a2 = _impulse_fit(fit.parallel_path.b, fit.parallel_path.a, PATH_ORDER, 0)
    return Feedforward(branch, b2, a2) if np.any(b) else None
