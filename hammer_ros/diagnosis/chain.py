"""Compound explanations: a chain of causes, each step extending the model of the step before.

Real systems often show two effects at once (a tank's square-root outflow *and* its overflow).
After the first cause is named and its extension M_1 fitted (``diagnose``), the model M_k of
step k is taken as one block (a simulator of the input), the free-run residual e = y - M_k(u)
on the validation data is tested for the signatures of the effects a block around M_k can
express, and each supported follow-up is fitted on the estimation data around M_k:

| cause | step k + 1 | fitted by |
|---|---|---|
| ``output_nonlinearity`` | y = N(M_k(u)), N piecewise linear | least squares (linear in N) |
| ``parallel_path`` | y = M_k(u) + G[u] | equation error, then simulation error |
| ``unmodeled_dynamics`` | y = H[M_k(u)], H linear of order 2 | simulation error from H = 1 |
| ``input_dynamics`` | y = M_k(L_p[u]), L_p = (1 - p) / (1 - p q^-1) | scan of p, then a scalar search |
| ``time_varying`` | y = M_k(u) + c_0 + c_1 k / N (a drifting offset) | least squares (linear in c) |

The drift is a follow-up of one record split in two only (``Split.continuous``): k counts the
samples from the start of the estimation data, so the validation samples continue its time
axis; a separate validation record has no known place on it. Its signature is tested on the
residual of the whole record (``drifts``), the others' on the validation residual.

The follow-up with the largest validation gain rms_k / rms_(k+1) is the next step when that gain
is at least ``MIN_STEP_GAIN``; the chain stops when no signature is significant, when no
follow-up gains enough, when the model cannot be extended as one block, or after ``MAX_STEPS``
steps, and says which. Every map that meets inputs beyond the estimation range chooses, on
held-back estimation data, how it continues (``continuation``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal
from scipy.optimize import minimize_scalar

from ..identification.regression import solve_least_squares
from ..identification.runs import Runs
from ..identification.simulation_error import refine, stabilised_denominator, steady_state_filter
from ..identification.static_maps import PiecewiseLinearMap
from .evidence import DYNAMIC_POLES, dynamics_basis, hinges, partial_f_test, trend_test
from .extensions import NUMERICAL_FAILURES, ExtendedModel, failure_reason, linear_fit, map_on, map_plot
from .hammerstein import quantile_partition
from .split import Split, per_run

MAX_STEPS = 3
MIN_STEP_GAIN = 1.05
HELD_BACK = 0.2  # share of the estimation data on which a map's continuation is chosen
INPUT_POLES = (0.2, 0.4, 0.6, 0.75, 0.85, 0.92, 0.96, 0.98)  # first scan of the input low-pass

Simulator = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Step:
    """One step of the chain: its cause, its model's structure, the validation RMS and the gain
    over the step before (the baseline for the first step)."""

    cause: str
    structure: str
    rms: float
    gain: float

    def to_json(self) -> dict:
        return {"cause": self.cause, "structure": self.structure, "rms": float(self.rms), "gain": float(self.gain)}


@dataclass(frozen=True, eq=False)
class Chain:
    """The steps in order, the model of each, why the chain stopped, and the follow-ups that
    could not be fitted (cause, one-line reason)."""

    steps: tuple[Step, ...]
    models: tuple[ExtendedModel, ...]
    stopped: str
    not_fitted: tuple[tuple[str, str], ...] = ()

    @property
    def final(self) -> ExtendedModel:
        return self.models[-1]


def follow_up_signatures(v: np.ndarray, x: np.ndarray, runs: Runs | None = None) -> dict[str, np.ndarray]:
    """The regressors whose significance in the residual of a model with output x (input v)
    supports each follow-up: a static map of the output, linear dynamics of the input, linear
    dynamics of the output, and a static map of low-pass filtered inputs beyond one of the
    input itself (``runs``: every filter and lag starts anew at each run)."""
    smooth = [per_run(lambda u, p=p: signal.lfilter([1.0 - p], [1.0, -p], u, zi=[p * u[0]])[0], v, runs)
              for p in DYNAMIC_POLES[1:]]
    return {
        "output_nonlinearity": hinges(x),
        "parallel_path": per_run(dynamics_basis, v, runs),
        "unmodeled_dynamics": per_run(dynamics_basis, x, runs),
        "input_dynamics": np.column_stack([hinges(s, 3) for s in smooth]),
    }


def drifts(split: Split, model: ExtendedModel, skip: int) -> bool:
    """The signature of a drift: on one record split in two, the level of the model's free-run
    residual of the *whole* record moves along it (``trend_test``; a drift shows most as the
    change of the residual's level from the estimation to the validation samples, which the
    validation residual alone cannot show)."""
    if not split.continuous:
        return False
    x = model.simulate(split.v_all)
    x = split.judged_record(x[: split.n_est], x[split.n_est :])
    y = split.judged_record(split.y_est, split.y_val)
    t_value, critical = trend_test(y - x, np.column_stack([np.ones_like(x), x]), skip)
    return t_value > critical


def extend_chain(split: Split, first: ExtendedModel, baseline_rms: float, skip: int) -> Chain:
    """The chain that starts with the extension ``first`` (see the module docstring)."""
    first_rms = split.validation_rms(first.validation_output)
    steps = [Step(first.cause, first.structure, first_rms, baseline_rms / max(first_rms, 1e-300))]
    models = [first]
    val_runs = split.val_runs
    val_skip = 0 if split.continuous else min(skip, int(val_runs.lengths.min()) // 5)
    rows = split.judged_rows[split.judged_rows >= val_skip] if val_runs.count == 1 else np.intersect1d(
        split.judged_rows, val_runs.rows(val_skip))
    failures: list[tuple[str, str]] = []

    def stop(reason: str) -> Chain:
        return Chain(tuple(steps), tuple(models), reason, tuple(failures))

    while True:
        model = models[-1]
        if len(steps) >= MAX_STEPS:
            return stop(f"the cap of {MAX_STEPS} steps")
        if model.simulate is None:
            return stop(f"the {model.cause} model is re-fitted along the record, not one simulator of the input that "
                        "a further step could extend")
        x_val = model.validation_output
        e_val = split.y_val - x_val
        supported = []
        for cause, columns in follow_up_signatures(split.v_val, x_val, split.runs_val).items():
            f_value, critical, _ = partial_f_test(e_val, np.column_stack([np.ones_like(x_val), x_val]), columns,
                                                  rows)
            if f_value > critical:
                supported.append(cause)
        if drifts(split, model, skip):
            supported.append("time_varying")
        if not supported:
            return stop("no signature of a further effect in the validation residual")
        fits = {}
        for cause in supported:
            try:
                fitted = FOLLOW_UPS[cause](split, model, skip)
            except NUMERICAL_FAILURES as error:
                failures.append((cause, f"step {len(steps) + 1}: {failure_reason(error)}"))
                continue
            if np.all(np.isfinite(fitted.validation_output)):
                fits[cause] = fitted
            else:
                failures.append((cause, f"step {len(steps) + 1}: its simulation is not finite on the validation input"))
        gains = {c: steps[-1].rms / max(split.validation_rms(f.validation_output), 1e-300) for c, f in fits.items()}
        if not gains:
            return stop(f"no follow-up could be fitted for {', '.join(supported)}")
        best = max(gains, key=gains.get)
        if gains[best] < MIN_STEP_GAIN:
            return stop(f"the best further step ({best}) gains x{gains[best]:.3f} on validation data, less than "
                        f"x{MIN_STEP_GAIN}")
        fitted = fits[best]
        steps.append(Step(best, fitted.structure, split.validation_rms(fitted.validation_output), gains[best]))
        models.append(fitted)


# --------------------------------------------------------------------------- follow-ups


def _output_map(x: np.ndarray, y: np.ndarray, skip: int) -> tuple[PiecewiseLinearMap, str]:
    """N with y ~ N(x): piecewise linear on quantiles of x (more segments on longer records),
    least squares; beyond the estimation range it either continues its last slopes or stays
    constant (saturation), whichever predicts the held-back last HELD_BACK of the data better
    from a fit on the rest."""
    x, y = x[skip:], y[skip:]
    count = int(np.clip(x.size // 400, 4, 16))

    def fit(xs: np.ndarray, ys: np.ndarray) -> PiecewiseLinearMap:
        partition = quantile_partition(xs, count)
        return map_on(partition, max(1, partition.size // 2), xs, ys)

    cut = int(round((1.0 - HELD_BACK) * x.size))
    early = fit(x[:cut], y[:cut])
    lo, hi = float(np.min(x[:cut])), float(np.max(x[:cut]))
    errors = {"last slope": float(np.sum((y[cut:] - early(x[cut:])) ** 2)),
              "constant": float(np.sum((y[cut:] - early(np.clip(x[cut:], lo, hi))) ** 2))}
    continuation = min(errors, key=errors.get)
    final = fit(x, y)
    if continuation == "constant":
        final = constant_beyond(final, float(np.min(x)), float(np.max(x)))
    return final, continuation


def constant_beyond(m: PiecewiseLinearMap, lo: float, hi: float) -> PiecewiseLinearMap:
    """m on [lo, hi] and constant outside (a saturation at the ends of the data)."""
    c = np.concatenate([[lo], m.breakpoints[(m.breakpoints > lo) & (m.breakpoints < hi)], [hi]])
    return PiecewiseLinearMap(c, m(c), 0.0, 0.0)


def follow_output_nonlinearity(split: Split, model: ExtendedModel, skip: int) -> ExtendedModel:
    """y = N(M(u)) (a sensor or an output stage after the model)."""
    inner = model.simulate
    x = split.estimation_output(inner)
    n_map, continuation = _output_map(x, split.y_est, skip)

    def simulate(u: np.ndarray) -> np.ndarray:
        return n_map(inner(u))

    details = {"output_map": {"breakpoints": n_map.breakpoints.tolist(), "values": n_map.values.tolist(),
                              "continuation": continuation}}
    return ExtendedModel("output_nonlinearity", f"{model.structure} + output map", split.validation_output(simulate),
                         details, (map_plot("N (output map)", n_map, x),), simulate)


def _filter_refined(source: np.ndarray, target: np.ndarray, b0: np.ndarray, a0: np.ndarray,
                    offset: np.ndarray, skip: int, runs: Runs | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of B/A minimising ||target - offset - B/A source||^2 from (b0, a0) (``runs``: B/A
    from rest at every run's first sample)."""
    nb = b0.size

    def simulate_theta(theta: np.ndarray) -> np.ndarray:
        a = stabilised_denominator(np.concatenate([[1.0], theta[nb:]]))
        return offset + per_run(lambda z: steady_state_filter(theta[:nb], a, z), source, runs)

    theta = refine(simulate_theta, np.concatenate([b0, a0[1:]]), target, 30, skip)
    return theta[:nb], stabilised_denominator(np.concatenate([[1.0], theta[nb:]]))


def follow_parallel_path(split: Split, model: ExtendedModel, skip: int) -> ExtendedModel:
    """y = M(u) + G[u], G of order 2 (paper 003's feedforward structure around M)."""
    inner, v = model.simulate, split.v_est
    x = split.estimation_output(inner)
    b0, a0 = linear_fit(v, split.y_est - x, 2, 0, split.runs_est)
    b, a = _filter_refined(v, split.y_est, b0, a0, x, skip, split.runs_est)

    def simulate(u: np.ndarray) -> np.ndarray:
        return inner(u) + steady_state_filter(b, a, u)

    details = {"parallel_path": {"b": b.tolist(), "a": a[1:].tolist()}}
    return ExtendedModel("parallel_path", f"{model.structure} + linear path", split.validation_output(simulate),
                         details, (), simulate)


def follow_unmodeled_dynamics(split: Split, model: ExtendedModel, skip: int) -> ExtendedModel:
    """y = H[M(u)], H of order 2 started at H = 1 (dynamics the model's blocks lack)."""
    inner = model.simulate
    x = split.estimation_output(inner)
    b, a = _filter_refined(x, split.y_est, np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.zeros(x.size),
                           skip, split.runs_est)

    def simulate(u: np.ndarray) -> np.ndarray:
        return steady_state_filter(b, a, inner(u))

    poles = np.roots(a)
    details = {"output_dynamics": {"b": b.tolist(), "a": a[1:].tolist(),
                                   "poles": [[float(p.real), float(p.imag)] for p in poles]}}
    return ExtendedModel("unmodeled_dynamics", f"{model.structure} + output dynamics",
                         split.validation_output(simulate), details, (), simulate)


def _low_pass(p: float) -> Simulator:
    return lambda u: steady_state_filter(np.array([1.0 - p]), np.array([1.0, -p]), u)


def follow_input_dynamics(split: Split, model: ExtendedModel, skip: int) -> ExtendedModel:
    """y = M(L_p[u]) with the unit-gain low-pass L_p = (1 - p) / (1 - p q^-1) (a filter ahead of
    everything the model holds): p from a scan, then a bounded scalar search."""
    inner, y = model.simulate, split.y_est

    def cost(p: float) -> float:
        with np.errstate(all="ignore"):
            r = (y - split.estimation_output(lambda u: inner(_low_pass(p)(u))))[skip:]
        value = float(np.sum(r**2))
        return value if np.isfinite(value) else np.inf

    costs = [cost(p) for p in INPUT_POLES]
    i = int(np.argmin(costs))
    lo = INPUT_POLES[i - 1] if i > 0 else 0.0
    hi = INPUT_POLES[i + 1] if i + 1 < len(INPUT_POLES) else 0.995
    found = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3, "maxiter": 12})
    p = float(found.x) if found.fun < costs[i] else INPUT_POLES[i]
    low_pass = _low_pass(p)

    def simulate(u: np.ndarray) -> np.ndarray:
        return inner(low_pass(u))

    return ExtendedModel("input_dynamics", f"low-pass + {model.structure}", split.validation_output(simulate),
                         {"input_pole": p}, (), simulate)


def follow_drift(split: Split, model: ExtendedModel, skip: int) -> ExtendedModel:
    """y = M(u) + c_0 + c_1 k / N, k = 0, 1, ... from the start of the estimation data (N of
    them): an offset that drifts along the record (a sensor, a leak, the temperature), c by
    least squares on the estimation residual. One record split in two only: the validation
    samples continue the time axis (k = N, N + 1, ...)."""
    if not split.continuous:
        raise ValueError("a drift needs the validation samples to follow the estimation samples in time")
    inner, n = model.simulate, split.n_est
    ramp = np.column_stack([np.ones(n), np.arange(n) / n])
    c = solve_least_squares(ramp[skip:], (split.y_est - inner(split.v_est))[skip:])

    def simulate(u: np.ndarray) -> np.ndarray:
        return inner(u) + c[0] + c[1] * np.arange(np.size(u)) / n

    details = {"drift": {"offset": float(c[0]), "per_sample": float(c[1] / n)}}
    return ExtendedModel("time_varying", f"{model.structure} + drifting offset", split.validation_output(simulate),
                         details, (), simulate)


FOLLOW_UPS: dict[str, Callable[[Split, ExtendedModel, int], ExtendedModel]] = {
    "output_nonlinearity": follow_output_nonlinearity,
    "parallel_path": follow_parallel_path,
    "unmodeled_dynamics": follow_unmodeled_dynamics,
    "input_dynamics": follow_input_dynamics,
    "time_varying": follow_drift,
}
