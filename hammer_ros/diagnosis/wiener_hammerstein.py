"""Wiener-Hammerstein (L-N-L) models y = G2[f(G1[u])], identified from the best linear
approximation.

The method (M. Schoukens & K. Tiels 2017, "Identification of block-oriented nonlinear systems
starting from linear approximations: a survey", Automatica 85, the Wiener-Hammerstein part;
J. Sjoberg, L. Lauwers & J. Schoukens 2012, "Identification of Wiener-Hammerstein models: two
algorithms based on the best split of a linear model applied to the SYSID'09 benchmark
problem", Control Eng. Practice 20(11)):

1. BLA. For a Gaussian-like input the best linear approximation of a Wiener-Hammerstein
   system is G_BLA = c G1 G2 (Bussgang): its poles and zeros are those of the two blocks.
   It is estimated as a linear output-error model of the given order (Steiglitz-McBride
   start, then Levenberg-Marquardt on the simulation error).
2. Split. Near-cancelling pole/zero pairs are dropped; every split of the remaining poles and
   zeros between G1 and G2 (conjugate pairs together, both blocks proper) is scored: with
   x = G1 u and the piecewise-linear map f(x) = eta(x)^T mu + kappa in the point-slope basis
   (paper 001, eqs. 5-11), y = G2[eta(x)] mu + G2(1) kappa is linear in (mu, kappa), so the
   map of each split is one least-squares solve; a split's score is its simulation error.
3. Joint refinement of the best few splits (as Sjoberg et al. 2012 do): Levenberg-Marquardt
   on V = sum_k (y(k) - G2[f(G1[u])](k))^2 over all parameters, both blocks given the full
   order n (the poles and numerator terms a split did not give a block start at zero) and
   the map about 20 segments (breakpoints at quantiles of x) on long records. The Jacobian is
   analytic, made of filtered signals (q the shift operator, f' the map's slope):

       dx/db1_j = q^-j u / A1,            dx/da1_j = -q^-j x / A1,
       dy/dtheta1 = G2[f'(x) dx/dtheta1],
       dy/dmu_i = G2[eta_i(x)],          dy/dkappa = G2(1),
       dy/db2_j = q^-j f(x) / A2,        dy/da2_j = -q^-j y / A2.

   The scale ambiguities (G1 c, f / c; G2 / c, c f) are removed by fixing the largest
   numerator coefficient of each block; a step that leaves a pole outside the unit circle is
   projected back (poles reflected inside) and kept only if it lowers V.

Every filter starts from the steady state of its first input value (the record starts at
rest at u(0)), and so do the Jacobian's filtered signals, so the Jacobian is that of the
simulation itself. A record of several runs (``runs``: separate experiments) is simulated,
filtered and lagged run by run, every run from rest at its first input; the costs sum over
the runs. The normal equations J^T J, J^T r are formed by a numba loop (numpy without
numba). Settings depend on the record's length only: map segments clip(N / 250, 4, 20), the
splits scored on the last SCAN_SAMPLES samples, the KEEP_SPLITS best refined 15 iterations
each, the best one up to 200.

On the SYSID 2009 Wiener-Hammerstein benchmark (order 6, the first 100 000 samples for
estimation, the 78 800 others for test) this gives a test simulation RMSE of 0.36 mV in about
70 s of one core (published best 0.28 mV).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..errors import IdentificationError
from ..identification.linear import LinearModel
from ..identification.piecewise_linear_ls import (
    drop_empty_intervals,
    interval_index,
    point_slope_basis,
    point_slope_map,
)
from ..identification.regression import build_regression, solve_least_squares
from ..identification.runs import Runs, per_run, several
from ..identification.simulation_error import settling_samples, stabilised_denominator
from ..identification.static_maps import PiecewiseLinearMap
from .split import runs_tail

MAX_SEGMENTS = 20
SAMPLES_PER_SEGMENT = 250
KEEP_SPLITS = 3
CANCEL_DISTANCE = 0.05  # a pole and a zero closer than this (relative to the pole's distance to 1) cancel
SCAN_SAMPLES = 30000  # the splits are scored on at most this many (the last) samples


# --------------------------------------------------------------------------- the model


@dataclass(frozen=True, eq=False)
class WienerHammersteinModel:
    """y = back[nonlinearity(front[u])]: two linear blocks around a piecewise-linear map."""

    front: LinearModel
    nonlinearity: PiecewiseLinearMap
    back: LinearModel

    def intermediate(self, u: np.ndarray) -> np.ndarray:
        """x = G1 u, from the steady state at u(0)."""
        return _filter(self.front.b, self.front.a, np.asarray(u, dtype=float))

    def simulate(self, u: np.ndarray) -> np.ndarray:
        """Free-run output from the steady state at u(0)."""
        return _filter(self.back.b, self.back.a, self.nonlinearity(self.intermediate(u)))

    def to_json(self, sample_range: tuple[float, float] | None = None) -> dict:
        """Both blocks (coefficients, poles, zeros, static gain) and the map (breakpoints,
        values at them, outer slopes); ``sample_range``: the range of x the map's points span."""
        f = self.nonlinearity
        return {"front": _block_json(self.front), "back": _block_json(self.back),
                "nonlinearity": {**f.to_json(sample_range), "values": f.values.tolist()}}


def frequency_response(block: LinearModel, points: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """(w in rad/sample, |G(e^jw)| in dB) of a block, for the report."""
    w, h = signal.freqz(block.b, block.a, worN=points)
    return w, 20.0 * np.log10(np.maximum(np.abs(h), 1e-12))


def _block_json(block: LinearModel) -> dict:
    def roots(r: np.ndarray) -> list:
        return [[float(p.real), float(p.imag)] for p in r]

    gain = block.dc_gain if abs(np.sum(block.a)) > 1e-12 else None
    return {"b": block.b.tolist(), "a": block.a.tolist(), "poles": roots(block.poles), "zeros": roots(block.zeros),
            "dc_gain": None if gain is None or not np.isfinite(gain) else float(gain)}


# --------------------------------------------------------------------------- filtered signals


def _filter(b: np.ndarray, a: np.ndarray, s: np.ndarray) -> np.ndarray:
    """B/A applied to s (a vector, or each row of a matrix: signals in rows, samples along the
    last axis, the layout lfilter is fastest on) from the steady state of its first value."""
    b, a = np.asarray(b, dtype=float), np.asarray(a, dtype=float)
    length = max(a.size, b.size)
    b, a = np.pad(b, (0, length - b.size)), np.pad(a, (0, length - a.size))
    if s.shape[-1] == 0 or length == 1:
        return b[0] / a[0] * s
    if abs(a.sum()) < 1e-9 * np.abs(a).sum():
        return signal.lfilter(b, a, s, axis=-1)
    gain = b.sum() / a.sum()
    state = np.cumsum((b[1:] - a[1:] * gain)[::-1])[::-1] / a[0]
    zi = state * s[0] if s.ndim == 1 else s[:, :1] * state[None, :]
    return signal.lfilter(b, a, s, axis=-1, zi=zi)[0]


def _filter_runs(b: np.ndarray, a: np.ndarray, s: np.ndarray, runs: Runs | None) -> np.ndarray:
    """``_filter`` started anew at every run (samples along the last axis)."""
    if runs is None:
        return _filter(b, a, s)
    return np.concatenate([_filter(b, a, s[..., piece]) for piece in runs.slices()], axis=-1)


def _run_evaluator(make, u: np.ndarray, runs: Runs | None):
    """``make(u)``, an ``evaluate(theta, jacobian)`` of ``_levenberg_marquardt`` on one record,
    or with ``runs`` the evaluators of every run joined: outputs and Jacobian columns concatenated
    along the samples (every run simulated from rest at its first input)."""
    if runs is None:
        return make(u)
    evaluators = [make(part) for part in runs.split(u)]

    def evaluate(theta: np.ndarray, jacobian: bool):
        parts = [e(theta, jacobian) for e in evaluators]
        return (np.concatenate([p[0] for p in parts]),
                np.concatenate([p[1] for p in parts], axis=1) if jacobian else None)

    return evaluate


def _held(s: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Rows s(k - j) for j in ``lags``, the past held at s(0)."""
    out = np.empty((len(lags), s.size))
    for i, j in enumerate(lags):
        out[i, :j] = s[0]
        out[i, j:] = s[: s.size - j]
    return out


# --------------------------------------------------------------------------- normal equations

_GRAM: list = []


def _gram_core(j, r, gram, vector):  # pragma: no cover - compiled by numba
    rows, samples = j.shape
    for a in range(rows):
        for b in range(a, rows):
            total = 0.0
            for t in range(samples):
                total += j[a, t] * j[b, t]
            gram[a, b] = total
            gram[b, a] = total
        total = 0.0
        for t in range(samples):
            total += j[a, t] * r[t]
        vector[a] = total


def _normal_equations(j: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J J^T, J r) for J with one row per parameter. Compiled with numba when it is available
    (single-threaded: a threaded BLAS product of this shape is many times slower on a loaded
    machine than one core's loop), else numpy."""
    if not _GRAM:
        try:
            import numba

            _GRAM.append(numba.njit(cache=True, nogil=True, fastmath=True)(_gram_core))
        except ImportError:
            _GRAM.append(None)
    if _GRAM[0] is None or j.shape[0] < 2:
        return j @ j.T, j @ r
    gram, vector = np.empty((j.shape[0], j.shape[0])), np.empty(j.shape[0])
    _GRAM[0](np.ascontiguousarray(j), np.ascontiguousarray(r), gram, vector)
    return gram, vector


# --------------------------------------------------------------------------- Levenberg-Marquardt


def _levenberg_marquardt(evaluate, project, theta: np.ndarray, y: np.ndarray, skip: int, iterations: int,
                         tolerance: float = 1e-9) -> tuple[np.ndarray, float]:
    """theta minimising sum_{k >= skip} (y(k) - y_sim(k))^2 (Marquardt's diagonal scaling).

    ``evaluate(theta, jacobian)`` returns (y_sim, J^T or None: one row per parameter);
    ``project(theta)`` returns a theta with stable blocks (or None when it cannot). Stops after
    ``iterations`` Jacobians or when a step lowers the cost by less than ``tolerance`` of it."""
    target = y[skip:]
    y_sim, jac = evaluate(theta, True)
    r = y_sim[skip:] - target
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        jtj, grad = _normal_equations(jac[:, skip:], r)
        diag = np.maximum(np.diag(jtj), 1e-12 * max(float(np.max(np.diag(jtj))), 1e-300))
        improved = False
        for _ in range(12):
            try:
                step = np.linalg.solve(jtj + lam * np.diag(diag), -grad)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            candidate = project(theta + step)
            if candidate is not None:
                with np.errstate(all="ignore"):
                    trial = evaluate(candidate, False)[0][skip:] - target
                trial_cost = float(trial @ trial) if np.all(np.isfinite(trial)) else np.inf
                if trial_cost < cost:
                    gain = cost - trial_cost
                    theta, cost = candidate, trial_cost
                    lam = max(lam / 3.0, 1e-9)
                    improved = True
                    break
            lam *= 4.0
        if not improved or gain < tolerance * cost:
            break
        y_sim, jac = evaluate(theta, True)
        r = y_sim[skip:] - target
    return theta, cost


def _stable(a: np.ndarray, margin: float = 0.9995) -> np.ndarray | None:
    """a itself when its roots are inside ``margin``, else the roots reflected inside."""
    if a.size <= 1 or np.all(np.abs(np.roots(a)) < margin):
        return a
    projected = stabilised_denominator(a, margin)
    return projected if np.all(np.isfinite(projected)) else None


# --------------------------------------------------------------------------- BLA (output error)


def fit_output_error(u: np.ndarray, y: np.ndarray, order: int, delay: int = 0,
                     iterations: int = 60, runs: Runs | None = None) -> LinearModel:
    """The linear output-error model y = B/A u + c of the given order and relative degree
    (numerator b_delay..b_order): Steiglitz-McBride from ARX, then Levenberg-Marquardt on the
    simulation error (analytic Jacobian: dy/db_j = q^-j u/A, dy/da_j = -q^-j y/A). ``runs``:
    every prefilter, regressor and simulation within one run."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    runs = several(runs)
    a = np.ones(1)
    for _ in range(5):  # Steiglitz-McBride: ARX on the data prefiltered by 1/A
        def prefiltered(x: np.ndarray, a: np.ndarray = a) -> np.ndarray:
            return per_run(lambda part: signal.lfilter([1.0], a, part), x, runs)

        reg = build_regression(prefiltered(y), prefiltered(u), order, delay, runs=runs)
        ones = prefiltered(np.ones(u.size))[reg.rows]
        theta = solve_least_squares(np.column_stack([reg.phi, ones]), reg.target)
        a_coef, b_coef = reg.split(theta[:-1])
        a = stabilised_denominator(np.concatenate([[1.0], a_coef]))
    b = np.concatenate([np.zeros(delay), b_coef[:, 0]])
    lags = np.arange(delay, order + 1)
    skip = min(settling_samples(np.roots(a), cap=u.size // 5), u.size // 5)

    def unpack(theta):
        bb = np.zeros(order + 1)
        bb[lags] = theta[order : order + lags.size]
        return np.concatenate([[1.0], theta[:order]]), bb, theta[-1]

    def evaluator(u: np.ndarray):
        def evaluate(theta, jacobian):
            aa, bb, c = unpack(theta)
            out = _filter(bb, aa, u)
            if not jacobian:
                return out + c, None
            du = _held(_filter([1.0], aa, u), lags)
            dy = -_held(_filter([1.0], aa, out), np.arange(1, order + 1))
            return out + c, np.vstack([dy, du, np.ones((1, u.size))])

        return evaluate

    def project(theta):
        aa = _stable(np.concatenate([[1.0], theta[:order]]))
        return None if aa is None else np.concatenate([aa[1:], theta[order:]])

    offset = float(np.mean(y - _filter_runs(b, a, u, runs)))
    theta, _ = _levenberg_marquardt(_run_evaluator(evaluator, u, runs), project,
                                    np.concatenate([a[1:], b[lags], [offset]]), y, skip, iterations)
    aa, bb, _ = unpack(theta)
    return LinearModel(bb, aa)


# --------------------------------------------------------------------------- splits of the BLA


def _groups(roots: np.ndarray) -> list[np.ndarray]:
    """The roots as real singletons and conjugate pairs."""
    roots = np.asarray(roots, dtype=complex)
    out, used = [], np.zeros(roots.size, dtype=bool)
    for i, r in enumerate(roots):
        if used[i]:
            continue
        used[i] = True
        if abs(r.imag) > 1e-9 * max(1.0, abs(r)):
            others = [k for k in range(roots.size) if not used[k]]
            k = min(others, key=lambda k: abs(roots[k] - np.conj(r))) if others else None
            if k is not None:
                used[k] = True
                out.append(np.array([r, roots[k]]))
                continue
        out.append(np.array([r.real + 0j]))
    return out


def _without_cancellations(poles: np.ndarray, zeros: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poles and zeros without the pairs closer than CANCEL_DISTANCE of the pole's distance
    to z = 1 (a pair that cancels in the BLA carries no information about the split)."""
    poles, zeros = list(poles), list(zeros)
    changed = True
    while changed:
        changed = False
        for p in poles:
            if not zeros:
                break
            k = int(np.argmin([abs(z - p) for z in zeros]))
            if abs(zeros[k] - p) < CANCEL_DISTANCE * max(abs(1.0 - p), 0.02):
                if abs(p.imag) > 1e-9:  # drop the conjugate pair too
                    conj_p = min(poles, key=lambda q: abs(q - np.conj(p)))
                    rest = [z for i, z in enumerate(zeros) if i != k]
                    if not rest:
                        continue
                    kc = int(np.argmin([abs(z - np.conj(zeros[k])) for z in rest]))
                    poles = [q for q in poles if q is not p and q is not conj_p]
                    zeros = [z for i, z in enumerate(rest) if i != kc]
                else:
                    poles = [q for q in poles if q is not p]
                    zeros.pop(k)
                changed = True
                break
    return np.array(poles, dtype=complex), np.array(zeros, dtype=complex)


def essential_order(block: LinearModel) -> int:
    """The poles of ``block`` left when its near-cancelling pole/zero pairs are dropped (as in
    the split): 0 for a block that is a static gain in all but a cancelling pair."""
    return int(_without_cancellations(block.poles, block.zeros)[0].size)


def _block(zeros: list[np.ndarray], poles: list[np.ndarray]) -> LinearModel | None:
    z = np.concatenate(zeros) if zeros else np.zeros(0, dtype=complex)
    p = np.concatenate(poles) if poles else np.zeros(0, dtype=complex)
    if z.size > p.size:
        return None
    num = np.real(np.poly(z)) if z.size else np.ones(1)
    den = np.real(np.poly(p)) if p.size else np.ones(1)
    return LinearModel(np.concatenate([np.zeros(p.size - z.size), num]), den)


def splits(bla: LinearModel) -> list[tuple[LinearModel, LinearModel]]:
    """Every (G1, G2) whose poles and zeros are the BLA's (near-cancelling pairs dropped), both
    blocks proper; G2 carries the BLA's gain (up to the scale of the map)."""
    poles, zeros = _without_cancellations(bla.poles, bla.zeros)
    pole_groups, zero_groups = _groups(poles), _groups(zeros)
    out = []
    for pick_p in itertools.product((0, 1), repeat=len(pole_groups)):
        for pick_z in itertools.product((0, 1), repeat=len(zero_groups)):
            g1 = _block([g for g, s in zip(zero_groups, pick_z) if s], [g for g, s in zip(pole_groups, pick_p) if s])
            g2 = _block([g for g, s in zip(zero_groups, pick_z) if not s],
                        [g for g, s in zip(pole_groups, pick_p) if not s])
            if g1 is not None and g2 is not None:
                out.append((g1, g2))
    return out


def map_segments(samples: int) -> int:
    """Segments of the piecewise-linear map: about SAMPLES_PER_SEGMENT samples each, 4 to 20."""
    return int(np.clip(samples // SAMPLES_PER_SEGMENT, 4, MAX_SEGMENTS))


def _partition(x: np.ndarray, segments: int) -> np.ndarray:
    knots = np.unique(np.quantile(x, np.arange(1, segments) / segments))
    return drop_empty_intervals(x, knots)


def _map_start(x: np.ndarray, y: np.ndarray, back: LinearModel, segments: int,
               skip: int, runs: Runs | None = None) -> tuple[np.ndarray, int, np.ndarray, float, float]:
    """(partition, primary, slopes, kappa, cost): the map on ``segments`` quantile intervals of
    x, fitted by least squares through ``back`` (``_map_fit``)."""
    partition = _partition(x, segments)
    primary = max(1, partition.size // 2)
    return (partition, primary, *_map_fit(x, y, back, partition, primary, skip, runs))


def _map_fit(x: np.ndarray, y: np.ndarray, back: LinearModel, partition: np.ndarray, primary: int,
             skip: int, runs: Runs | None = None) -> tuple[np.ndarray, float, float]:
    """(slopes, kappa, cost): y ~ G2[eta(x)] mu + G2(1) kappa by least squares (``runs``: G2
    from rest at every run's start)."""
    basis = np.vstack([point_slope_basis(x, partition, primary).T, np.ones((1, x.size))])
    columns = _filter_runs(back.b, back.a, basis, runs)[:, skip:]
    gram, vector = _normal_equations(columns, y[skip:])
    theta = np.linalg.solve(gram + 1e-12 * np.trace(gram) * np.eye(gram.shape[0]), vector)
    r = y[skip:] - theta @ columns
    return theta[:-1], float(theta[-1]), float(r @ r)


# --------------------------------------------------------------------------- joint refinement


class _Parameters:
    """theta = [a1_1..a1_n1, b1 free, a2_1..a2_n2, b2 free, mu, kappa], the largest numerator
    coefficient of each block fixed. ``full_order``: both blocks of order n (numerators over
    lags delay..n and 0..n); else each block keeps the order and relative degree of its split."""

    def __init__(self, front: LinearModel, back: LinearModel, order: int, delay: int, partition: np.ndarray,
                 primary: int, full_order: bool = True):
        self.partition, self.primary = partition, primary
        self.n1, self.n2 = (order, order) if full_order else (front.order, back.order)
        self.b1 = _padded(front.b, self.n1 + 1)
        self.b2 = _padded(back.b, self.n2 + 1)
        lags1 = np.arange(delay if full_order else front.delay, self.n1 + 1)
        lags2 = np.arange(0 if full_order else back.delay, self.n2 + 1)
        self.fixed1 = lags1[int(np.argmax(np.abs(self.b1[lags1])))]
        self.fixed2 = lags2[int(np.argmax(np.abs(self.b2[lags2])))]
        self.lags1, self.lags2 = lags1[lags1 != self.fixed1], lags2[lags2 != self.fixed2]
        self.slices = np.cumsum([0, self.n1, self.lags1.size, self.n2, self.lags2.size, partition.size + 1, 1])

    def pack(self, front: LinearModel, back: LinearModel, slopes: np.ndarray, kappa: float) -> np.ndarray:
        a1, a2 = _padded(front.a, self.n1 + 1), _padded(back.a, self.n2 + 1)
        b1, b2 = _padded(front.b, self.n1 + 1), _padded(back.b, self.n2 + 1)
        return np.concatenate([a1[1:], b1[self.lags1], a2[1:], b2[self.lags2], slopes, [kappa]])

    def unpack(self, theta: np.ndarray):
        s = self.slices
        a1 = np.concatenate([[1.0], theta[s[0] : s[1]]])
        b1 = self.b1.copy()
        b1[self.lags1] = theta[s[1] : s[2]]
        a2 = np.concatenate([[1.0], theta[s[2] : s[3]]])
        b2 = self.b2.copy()
        b2[self.lags2] = theta[s[3] : s[4]]
        return a1, b1, a2, b2, theta[s[4] : s[5]], float(theta[s[5]])

    def project(self, theta: np.ndarray) -> np.ndarray | None:
        s = self.slices
        a1 = _stable(np.concatenate([[1.0], theta[s[0] : s[1]]]))
        a2 = _stable(np.concatenate([[1.0], theta[s[2] : s[3]]]))
        if a1 is None or a2 is None:
            return None
        out = theta.copy()
        out[s[0] : s[1]], out[s[2] : s[3]] = a1[1:], a2[1:]
        return out

    def model(self, theta: np.ndarray) -> WienerHammersteinModel:
        a1, b1, a2, b2, mu, kappa = self.unpack(theta)
        return WienerHammersteinModel(LinearModel(b1, a1), point_slope_map(self.partition, self.primary, mu, kappa),
                                      LinearModel(b2, a2))

    def evaluator(self, u: np.ndarray):
        partition, primary = self.partition, self.primary
        lags_a1, lags_a2 = np.arange(1, self.n1 + 1), np.arange(1, self.n2 + 1)

        def evaluate(theta: np.ndarray, jacobian: bool):
            a1, b1, a2, b2, mu, kappa = self.unpack(theta)
            x = _filter(b1, a1, u)
            w = point_slope_map(partition, primary, mu, kappa)(x)
            y = _filter(b2, a2, w)
            if not jacobian:
                return y, None
            dx = np.vstack([-_held(_filter([1.0], a1, x), lags_a1), _held(_filter([1.0], a1, u), self.lags1)])
            slope = mu[interval_index(x, partition)]
            d_front = _filter(b2, a2, slope[None, :] * dx)
            eta = point_slope_basis(x, partition, primary).T
            d_map = _filter(b2, a2, np.vstack([eta, np.ones((1, u.size))]))
            d_back = np.vstack([-_held(_filter([1.0], a2, y), lags_a2), _held(_filter([1.0], a2, w), self.lags2)])
            return y, np.vstack([d_front, d_back, d_map])

        return evaluate


def _padded(c: np.ndarray, size: int) -> np.ndarray:
    c = np.asarray(c, dtype=float)
    return np.pad(c, (0, max(0, size - c.size)))[:size] if c.size <= size else c[:size]


# --------------------------------------------------------------------------- the fit


@dataclass(frozen=True, eq=False)
class WienerHammersteinFit:
    """The fitted model, the BLA it started from, the split scores and the final cost."""

    model: WienerHammersteinModel
    bla: LinearModel
    split_costs: tuple[float, ...]
    rms: float  # simulation RMS on the estimation data (after the transient)
    segments: int
    delay: int  # the BLA's relative degree, G1's first free numerator lag


def fit_wiener_hammerstein(u: np.ndarray, y: np.ndarray, order: int, delay: int = 0,
                           segments: int | None = None, keep: int = KEEP_SPLITS, iterations: int = 200,
                           scout_iterations: int = 15, full_order: bool = True,
                           direct_term: bool = False, runs: Runs | None = None) -> WienerHammersteinFit:
    """Wiener-Hammerstein model of total order ``order`` (the BLA's) on (u, y): BLA, scan of
    the pole/zero splits with the map by least squares, joint Levenberg-Marquardt refinement
    of the ``keep`` best splits (``scout_iterations`` each, both blocks of order ``order``),
    then of the best one (up to ``iterations``). ``delay``: the BLA's relative degree and G1's
    first free numerator lag (G1's lower coefficients keep the split's values; G2's numerator is
    free from lag 0); ``direct_term``: also fit with ``delay`` 0 and keep the fit with the
    smaller estimation RMS (the refinement from the split can stall in either). ``segments``: of
    the map (default from the record's length, ``map_segments``). ``full_order`` False: each
    block keeps its split's order (n poles in all, the structure of a Hammerstein model of order
    n; for comparisons of structures), which stalls well above the full-order optimum on long
    records. ``runs``: every filter and simulation run by run (the module's docstring)."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    runs = several(runs)
    if order < 1:
        raise IdentificationError("a Wiener-Hammerstein model needs an order of at least 1")
    if direct_term and delay > 0:
        fits = [fit_wiener_hammerstein(u, y, order, d, segments, keep, iterations, scout_iterations, full_order,
                                       runs=runs) for d in (delay, 0)]
        return min(fits, key=lambda fit: fit.rms)
    bla = fit_output_error(u, y, order, delay, runs=runs)
    segments = segments or map_segments(u.size)
    skip = min(settling_samples(bla.poles, cap=u.size // 5), u.size // 5)
    scan, scan_runs = runs_tail(runs, u.size, SCAN_SAMPLES)
    scan_runs = several(scan_runs)
    u_scan, y_scan = u[scan], y[scan]
    scan_skip = min(skip, u_scan.size // 5)
    scored = []
    for front, back in splits(bla):
        x = _filter_runs(front.b, front.a, u_scan, scan_runs)
        scale = float(np.std(u_scan)) / max(float(np.std(x)), 1e-300)
        if not np.isfinite(scale) or scale == 0.0:
            continue
        front = front.scaled(scale)
        x = x * scale
        try:
            *_, cost = _map_start(x, y_scan, back, segments, scan_skip, scan_runs)
        except IdentificationError:
            continue
        scored.append((cost, front, back))
    if not scored:
        raise IdentificationError("no split of the best linear approximation could be fitted")
    scored.sort(key=lambda s: s[0])
    best = None
    for _, front, back in scored[:keep]:
        x = _filter_runs(front.b, front.a, u, runs)
        try:
            partition, primary, mu, kappa, _ = _map_start(x, y, back, segments, skip, runs)
        except IdentificationError:
            continue
        params = _Parameters(front, back, order, delay, partition, primary, full_order)
        theta, cost = _levenberg_marquardt(_run_evaluator(params.evaluator, u, runs), params.project,
                                           params.pack(front, back, mu, kappa), y, skip, scout_iterations)
        if best is None or cost < best[0]:
            best = (cost, params, theta)
    if best is None:
        raise IdentificationError("no split of the best linear approximation could be refined")
    _, params, theta = best
    theta, cost = _levenberg_marquardt(_run_evaluator(params.evaluator, u, runs), params.project, theta, y, skip,
                                       iterations)
    model = params.model(theta)
    rms = float(np.sqrt(cost / max(y.size - skip, 1)))
    return WienerHammersteinFit(model, bla, tuple(s[0] for s in scored), rms, segments, delay)


def fit_nested_hammerstein(u: np.ndarray, y: np.ndarray, order: int, delay: int = 0, segments: int | None = None,
                           iterations: int = 200, runs: Runs | None = None) -> WienerHammersteinFit:
    """The Hammerstein model nested in the L-N-L structure, G1 = 1: G2 of ``order`` started from
    the BLA, the map on quantiles of u (``segments``), refined by the same Levenberg-Marquardt
    on the simulation error as ``fit_wiener_hammerstein``. The yardstick of the input-dynamics
    extension: what the L-N-L model gains over it is the front filter's, not a better optimiser's."""
    return _fit_nested(u, y, order, delay, segments, iterations, dynamics_first=False, runs=runs)


def fit_nested_wiener(u: np.ndarray, y: np.ndarray, order: int, delay: int = 0, segments: int | None = None,
                      iterations: int = 200, front: LinearModel | None = None,
                      bla: LinearModel | None = None, runs: Runs | None = None) -> WienerHammersteinFit:
    """The Wiener model nested in the L-N-L structure, G2 = 1: y = f(G1[u]), G1 started from
    ``front`` or else from the BLA of ``order`` (Bussgang: the BLA of a Wiener system is c G1;
    an even map makes it vanish, hence the other start), scaled to the input's spread, the map
    on quantiles of G1[u], refined by the same Levenberg-Marquardt. All dynamics before a static
    output map (a sensor, a rectifier, a clamp after the plant): what the L-N-L model gains over
    it is the back filter's. ``bla``: the BLA when already known (it also sets the samples
    left out as the transient, so fits from several fronts compare on the same samples)."""
    return _fit_nested(u, y, order, delay, segments, iterations, dynamics_first=True, front=front, bla=bla, runs=runs)


def _fit_nested(u: np.ndarray, y: np.ndarray, order: int, delay: int, segments: int | None, iterations: int,
                dynamics_first: bool, front: LinearModel | None = None, bla: LinearModel | None = None,
                runs: Runs | None = None) -> WienerHammersteinFit:
    """The L-N-L model with one block the identity and the other the BLA (or ``front``),
    refined (see the two callers; ``runs``: run by run)."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    runs = several(runs)
    bla = fit_output_error(u, y, order, delay, runs=runs) if bla is None else bla
    segments = segments or map_segments(u.size)
    skip = min(settling_samples(bla.poles, cap=u.size // 5), u.size // 5)
    identity = LinearModel(np.ones(1), np.ones(1))
    if dynamics_first:
        block = bla if front is None else front
        x = _filter_runs(block.b, block.a, u, runs)
        scale = float(np.std(u)) / max(float(np.std(x)), 1e-300)
        if not np.isfinite(scale) or scale == 0.0:
            raise IdentificationError("the linear block is zero: no start for the Wiener model")
        front, back = block.scaled(scale), identity
    else:
        front, back = identity, bla
    x = _filter_runs(front.b, front.a, u, runs)
    partition, primary, mu, kappa, _ = _map_start(x, y, back, segments, skip, runs)
    params = _Parameters(front, back, order, delay, partition, primary, full_order=False)
    theta, cost = _levenberg_marquardt(_run_evaluator(params.evaluator, u, runs), params.project,
                                       params.pack(front, back, mu, kappa), y, skip, iterations)
    rms = float(np.sqrt(cost / max(y.size - skip, 1)))
    return WienerHammersteinFit(params.model(theta), bla, (), rms, segments, delay)
