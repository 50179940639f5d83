"""``identify --refine``: any method's estimate refined on the simulation error.

The papers' estimators (CLS, NLS, LS, PLLS, Billings-Fakhouri, semiparametric) minimise an
equation error or match correlations; with noise on the output their free-run simulation is
biased. ``refine_result`` starts from the method's own estimate and minimises

    V(theta) = sum_{k >= skip} (y(k) - y_sim(k; theta))^2

over every part the estimate has: the linear block G = B/A (all a_i; b_i from the relative
degree on, the largest |b_i| fixed when a static map carries the scale), the input map F
(piecewise-linear values and outer slopes, breakpoints kept; nonparametric values), the
feedback map h of the non-linear feedback models
(paper 001 eq. 2: y = G[F(v) - h(y)]) and the parallel path of the feedforward system
(paper 003 sec. 3). Levenberg-Marquardt from the estimate (``simulation_error.refine``);
y_sim is simulated from rest like the method's own ``simulate``, and the first ``skip``
samples (the slowest pole's settling, at most a fifth of the record) are left out of V.
The estimate is returned unchanged when the refinement does not lower V. A second start, the
equation-error ARX fit with an affine map (``affine.affine_start``), is refined beside the
method's own, and the smaller V is kept (V of every refined start with the fewest samples
skipped): on a step or a ramp the correlation methods' estimate can start the descent in a poor
local minimum, and its slow poles would skip the step's transient.

A polynomial F (CLS, NLS, Billings-Fakhouri: the papers' parametrisation for their regressions)
is refined as the piecewise-linear map through its values at ``POLYNOMIAL_KNOTS`` quantiles of
the input: a cubic fitted to a saturation or a dead zone runs away in the tails of the data,
and the simulation error would bend the poles to make up for it (on 20 random plants with a
saturating map, 30 dB noise: pole RSS p90 0.20 with the cubic refined, see the closing note).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from .affine import affine_start
from .linear import LinearModel
from .result import IdentificationResult
from .runs import Runs, rest_length
from .simulate import simulate_feedback, simulate_hammerstein_feedback
from .simulation_error import refine, settling_samples, stabilised_denominator
from .static_maps import MapParameters, PiecewiseLinearMap, PolynomialMap, map_parameters
from .uncertainty import Uncertainty, guarded, propagate, regression_covariance

MAX_ITERATIONS = 50  # LM iterations (each costs a simulation per parameter for the Jacobian)
POLYNOMIAL_KNOTS = 11  # quantiles of the input at which a polynomial F becomes piecewise linear


@dataclass(frozen=True, eq=False)
class _Structure:
    """How theta maps to (G, F, h, parallel path) for one estimate."""

    result: IdentificationResult
    path: LinearModel | None

    @property
    def free_b(self) -> np.ndarray:
        b = self.result.linear.b
        first = int(np.argmax(np.abs(b) > 0)) if np.any(b) else 0
        if self.result.feedback_nonlinearity is not None:
            first = max(first, 1)  # the loop needs b_0 = 0 (no algebraic loop)
        free = np.arange(first, b.size)
        if self.result.nonlinearity is not None and free.size:  # F carries the scale: fix one b
            free = free[free != first + int(np.argmax(np.abs(b[first:])))]
        return free

    def maps(self) -> list[tuple[str, MapParameters]]:
        r = self.result
        return [(name, map_parameters(m)) for name, m in (("nonlinearity", r.nonlinearity),
                                                            ("feedback_nonlinearity", r.feedback_nonlinearity))
                if m is not None]

    def pack(self) -> np.ndarray:
        r = self.result
        parts = [r.linear.a[1:], r.linear.b[self.free_b]]
        parts += [p.pack(getattr(r, name)) for name, p in self.maps()]
        if self.path is not None:
            parts += [self.path.b, self.path.a[1:]]
        return np.concatenate(parts)

    def unpack(self, theta: np.ndarray) -> tuple[LinearModel, dict, LinearModel | None]:
        r = self.result
        n = r.linear.a.size - 1
        a = stabilised_denominator(np.concatenate([[1.0], theta[:n]]))
        b = r.linear.b.copy()
        free = self.free_b
        b[free] = theta[n : n + free.size]
        k = n + free.size
        maps = {}
        for name, p in self.maps():
            maps[name] = p.unpack(theta[k : k + p.size])
            k += p.size
        path = None
        if self.path is not None:
            nb = self.path.b.size
            path = LinearModel(theta[k : k + nb], stabilised_denominator(np.concatenate([[1.0], theta[k + nb :]])))
        return LinearModel(b, a), maps, path

    def simulator(self, theta: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        linear, maps, path = self.unpack(theta)
        f, h = maps.get("nonlinearity"), maps.get("feedback_nonlinearity")

        def simulate(v: np.ndarray) -> np.ndarray:
            v = np.asarray(v, dtype=float)
            if h is not None:
                y = (simulate_hammerstein_feedback(v, f, h, linear) if f is not None
                     else simulate_feedback(v, h, linear))
            else:
                y = linear.simulate(f(v) if f is not None else v)
            return y + path.simulate(v) if path is not None else y

        return simulate


def piecewise_linear_from(f: PolynomialMap, v: np.ndarray, knots: int = POLYNOMIAL_KNOTS) -> PiecewiseLinearMap:
    """The piecewise-linear map through f at ``knots`` quantiles of v (from the 1 % to the 99 %
    quantile), continued with f's slopes at the outer knots."""
    c = np.unique(np.quantile(v, np.linspace(0.01, 0.99, knots)))
    slope = np.polynomial.polynomial.polyder(f.coefficients) if f.coefficients.size > 1 else np.zeros(1)
    outer = np.polynomial.polynomial.polyval(c[[0, -1]], slope)
    return PiecewiseLinearMap(c, f(c), float(outer[0]), float(outer[1]))


def _parallel_path(result: IdentificationResult) -> LinearModel | None:
    path = result.extra.get("parallel_path")
    if not path:
        return None
    return LinearModel(np.asarray(path["b"], dtype=float), np.concatenate([[1.0], np.asarray(path["a"], float)]))


def refine_result(result: IdentificationResult, v: np.ndarray, y: np.ndarray, runs: Runs | None = None,
                  max_iterations: int = MAX_ITERATIONS) -> IdentificationResult:
    """The estimate ``result`` refined on the simulation error of (v, y) (module docstring):
    a polynomial F is refined both as it is and as ``piecewise_linear_from`` it, and the one
    with the smaller V is kept. With ``runs``, every run is simulated from rest at its first input
    (``Runs.simulate``, settling as the method's estimate). The JSON keeps the method's name and adds ``refined``:
    {cost_start (V of the method's estimate), cost, samples_skipped, map}; Markov parameters
    are recomputed from the refined block, the method's gain figure is dropped (it describes
    the method's own estimate)."""
    v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
    runs = Runs.one(v.size) if runs is None else runs
    settle = rest_length(result.linear.poles)
    at_rest = runs.initial_states(result.simulate, v, y, settle)  # chosen once, with the method's estimate
    knots = np.unique(v).size > 2  # two input levels: the map stays affine (``affine.degraded_to_gain``)
    starts = [result]
    if knots and isinstance(result.nonlinearity, PolynomialMap):
        starts.append(replace(result, nonlinearity=piecewise_linear_from(result.nonlinearity, v)))
    if (start := affine_start(result, v, y, runs)) is not None:  # a start that holds on steps too
        if knots and isinstance(start.nonlinearity, PolynomialMap):
            start = replace(start, nonlinearity=piecewise_linear_from(start.nonlinearity, v))
        starts.append(start)
    fits = []
    for start in starts:
        structure = _Structure(start, _parallel_path(start))
        theta0 = structure.pack()

        def simulate_theta(theta: np.ndarray, structure: _Structure = structure) -> np.ndarray:
            return runs.simulate(structure.simulator(theta), v, settle, at_rest)

        start_skip = min(settling_samples(start.linear.poles), v.size // 5)
        theta = refine(simulate_theta, theta0, y, max_iterations * (theta0.size + 1), start_skip)
        fits.append((start_skip, simulate_theta(theta), structure, theta))
    # compared on the fewest samples skipped: a slow start's long skip may hide a step's transient
    skip = min(fit[0] for fit in fits)
    cost, structure, theta = min(((_cost(y_sim, y, skip), structure, theta) for _, y_sim, structure, theta in fits),
                                 key=lambda fit: fit[0])
    linear, maps, path = structure.unpack(theta)
    extra = dict(result.extra)
    f = maps.get("nonlinearity")
    extra["refined"] = {"cost_start": _cost(runs.simulate(result.simulate, v, settle, at_rest), y, skip),
                        "cost": cost, "samples_skipped": int(skip),
                        "map": None if f is None else type(f).__name__}
    if path is not None:
        extra["parallel_path"] = {**extra["parallel_path"], "a": path.a[1:].tolist(), "b": path.b.tolist(),
                                  "poles": [[float(p.real), float(p.imag)] for p in path.poles],
                                  "zeros": [[float(q.real), float(q.imag)] for q in path.zeros]}
    markov = None
    if result.markov is not None:
        impulse = np.zeros(np.asarray(result.markov).size)
        impulse[0] = 1.0
        markov = linear.simulate(impulse)
    return replace(result, linear=linear, simulate=structure.simulator(theta), gain=None, markov=markov,
                   nonlinearity=maps.get("nonlinearity", result.nonlinearity),
                   feedback_nonlinearity=maps.get("feedback_nonlinearity", result.feedback_nonlinearity),
                   extra=extra, uncertainty=guarded(_refined_uncertainty, structure, theta, v, y, skip,
                                                    lambda simulate: runs.simulate(simulate, v, settle, at_rest)))


def _refined_uncertainty(structure: _Structure, theta: np.ndarray, v: np.ndarray, y: np.ndarray,
                         skip: int, over_runs: Callable) -> Uncertainty | None:
    """The bounds of the prediction-error (output-error) estimate: with J = d y_sim / d theta (forward
    differences) and r = y - y_sim, Cov(theta) = (J^T J)^-1 S (J^T J)^-1, S the batch-means sum of
    the influences J_k r_k (``uncertainty.regression_covariance`` with Phi = J); for white output
    noise this is the Gauss-Newton sigma^2 (J^T J)^-1 (Ljung, *System Identification* 1999, eq. 9.18),
    and it stays right for coloured noise. Propagated through ``_Structure.unpack`` to the poles,
    zeros and the input map's parameters. None when the Jacobian is not finite. ``over_runs``
    simulates a simulator of v over the record's runs (``refine_result``)."""
    def simulate(t: np.ndarray) -> np.ndarray:
        return over_runs(structure.simulator(t))[skip:]

    nominal = simulate(theta)
    steps = 1e-6 * np.maximum(np.abs(theta), 1e-3)
    with np.errstate(all="ignore"):
        jacobian = np.column_stack([(simulate(theta + step * unit) - nominal) / step
                                    for step, unit in zip(steps, np.eye(theta.size), strict=True)])
    if not np.all(np.isfinite(jacobian)):
        return None
    covariance = regression_covariance(jacobian, y[skip:] - nominal)
    names = [name for name, _ in structure.maps()]
    maps = dict(structure.maps())

    def figures(t: np.ndarray):
        linear, unpacked, _ = structure.unpack(t)
        packed = maps["nonlinearity"].pack(unpacked["nonlinearity"]) if "nonlinearity" in names else np.zeros(0)
        return linear.poles, linear.zeros, packed

    poles_std, zeros_std, map_covariance = propagate(figures, theta, covariance)
    return Uncertainty(poles_std, zeros_std, None, map_covariance if "nonlinearity" in names else None,
                       "refined: output-error sandwich (Gauss-Newton Hessian, batch-means residuals), "
                       "first-order propagation")


def _cost(y_sim: np.ndarray, y: np.ndarray, skip: int) -> float:
    with np.errstate(all="ignore"):
        value = float(np.sum((y - y_sim)[skip:] ** 2))
    return value if np.isfinite(value) else np.inf
