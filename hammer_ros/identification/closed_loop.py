"""Closed-loop records of a Hammerstein plant: the generator of the closed-loop tests and of the
closed-loop measurement (``docs/methods.md``, closed-loop identification).

A Hammerstein plant x = G(q) F[u] under a discrete P or PI controller driven by an external
reference r, with coloured noise w = H(q) e on the measured output:

    y(k) = x(k) + w(k),    u(k) = kp e_c(k) + ki sum_{i<=k} e_c(i),    e_c(k) = r(k) - y(k).

G is strictly proper, so u(k) is computed from y(k) and the loop runs sample by sample. The
noise enters u through the controller: u is correlated with w, which biases every estimator
that treats u as noise-free (Forssell and Ljung, Automatica 1999, sec. 2). ``open_loop_record``
drives the same plant with an input of the same spread, independent of the noise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal

from .linear import LinearModel

StaticMap = Callable[[np.ndarray], np.ndarray]
NOISE_FILTER = LinearModel(np.array([1.0, 0.5]), np.array([1.0, -0.8]))  # H = (1 + 0.5 q^-1) / (1 - 0.8 q^-1)
PREROLL = 200  # samples simulated and dropped: the record starts in steady motion


@dataclass(frozen=True, eq=False)
class LoopRecord:
    """One record: reference r (None in open loop), input u, measured output y, the noise-free
    output x and the noise w = y - x; ``linear`` and ``nonlinearity`` are the true plant."""

    r: np.ndarray | None
    u: np.ndarray
    y: np.ndarray
    x: np.ndarray
    linear: LinearModel
    nonlinearity: StaticMap
    snr_db: float  # 10 log10(var x0 / var w), x0 the noise-free response (closed loop: to r alone)


def cubic_map(u: np.ndarray) -> np.ndarray:
    """F(u) = u + 0.5 u^3 (products, not u**3: the same bits on every CPU)."""
    u = np.asarray(u, dtype=float)
    return u + 0.5 * u * u * u


def random_third_order_plant(rng: np.random.Generator) -> LinearModel:
    """A stable third-order block, relative degree 1: a complex pair (radius 0.6-0.9, angle
    0.2-1.0 rad), a real pole in 0.3-0.9, static gain 1."""
    radius, angle = rng.uniform(0.6, 0.9), rng.uniform(0.2, 1.0)
    poles = [radius * np.exp(1j * angle), radius * np.exp(-1j * angle), rng.uniform(0.3, 0.9)]
    return LinearModel.from_zeros_poles([], poles, 1.0)


def _loop(r: np.ndarray, w: np.ndarray, nonlinearity: StaticMap, linear: LinearModel, kp: float,
          ki: float) -> tuple[np.ndarray, np.ndarray]:
    """(u, x) of the loop of the module docstring, sample by sample (Python floats); an unstable
    loop gives non-finite values (no overflow warning)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return _loop_samples(r, w, nonlinearity, linear, kp, ki)


def _loop_samples(r: np.ndarray, w: np.ndarray, nonlinearity: StaticMap, linear: LinearModel, kp: float,
                  ki: float) -> tuple[np.ndarray, np.ndarray]:
    b, a = linear.b.tolist(), linear.a.tolist()
    n = max(len(a), len(b))
    b, a = b + [0.0] * (n - len(b)), a + [0.0] * (n - len(a))
    f_past = [0.0] * n  # F(u(k-1)), F(u(k-2)), ...
    x_past = [0.0] * n
    u, x = np.empty(r.size), np.empty(r.size)
    integral = 0.0
    for k, (rk, wk) in enumerate(zip(r.tolist(), w.tolist(), strict=True)):
        xk = sum(b[i] * f_past[i - 1] for i in range(1, n)) - sum(a[j] * x_past[j - 1] for j in range(1, n))
        error = rk - (xk + wk)
        integral += error
        uk = kp * error + ki * integral
        f_past = [float(nonlinearity(np.array([uk]))[0]), *f_past[:-1]]
        x_past = [xk, *x_past[:-1]]
        u[k], x[k] = uk, xk
    return u, x


def closed_loop_record(linear: LinearModel, nonlinearity: StaticMap, samples: int, snr_db: float, kp: float,
                       ki: float = 0.0, reference_std: float = 1.0, seed: int = 0,
                       noise_filter: LinearModel = NOISE_FILTER) -> LoopRecord:
    """A closed-loop record (module docstring) with a white Gaussian reference of std
    ``reference_std`` and coloured noise H(q) e scaled so that var(x) / var(w) is ``snr_db``
    (with x the output of the loop without noise: the reference's share of the output; the
    noise fed back through the controller adds to x)."""
    if linear.b[0] != 0.0:
        raise ValueError("the plant of a loop must be strictly proper (b_0 = 0): u(k) is computed from y(k)")
    rng = np.random.default_rng(seed)
    total = samples + PREROLL
    r = reference_std * rng.standard_normal(total)
    coloured = signal.lfilter(noise_filter.b, noise_filter.a, rng.standard_normal(total))
    coloured /= np.std(coloured)
    scale = np.std(_loop(r, np.zeros(total), nonlinearity, linear, kp, ki)[1][PREROLL:]) * 10 ** (-snr_db / 20)
    u, x = _loop(r, scale * coloured, nonlinearity, linear, kp, ki)
    if not np.all(np.isfinite(u)):
        raise ValueError(f"the loop is unstable (kp {kp:.3g}, ki {ki:.3g})")
    keep = slice(PREROLL, None)
    return LoopRecord(r[keep], u[keep], (x + scale * coloured)[keep], x[keep], linear, nonlinearity, snr_db)


def open_loop_record(linear: LinearModel, nonlinearity: StaticMap, samples: int, snr_db: float,
                     input_std: float, seed: int = 0, noise_filter: LinearModel = NOISE_FILTER) -> LoopRecord:
    """The same plant and noise colour in open loop: white Gaussian u of std ``input_std``
    (e.g. the closed loop's std(u)), noise independent of u at ``snr_db``."""
    rng = np.random.default_rng(seed)
    total = samples + PREROLL
    u = input_std * rng.standard_normal(total)
    x = linear.simulate(nonlinearity(u))
    w = signal.lfilter(noise_filter.b, noise_filter.a, rng.standard_normal(total))
    w *= np.std(x[PREROLL:]) / np.std(w[PREROLL:]) * 10 ** (-snr_db / 20)
    keep = slice(PREROLL, None)
    return LoopRecord(None, u[keep], (x + w)[keep], x[keep], linear, nonlinearity, snr_db)


def stability_limit(linear: LinearModel, slope: float = 1.0) -> float:
    """The largest proportional gain kp for which A(q) + kp slope B(q) (the loop linearised at
    a map slope ``slope``) keeps every root inside the unit circle (bisection, to 1e-3)."""
    b = np.concatenate([linear.b, np.zeros(max(0, linear.a.size - linear.b.size))])
    a = np.concatenate([linear.a, np.zeros(max(0, linear.b.size - linear.a.size))])
    low, high = 0.0, 100.0
    while high - low > 1e-3:
        mid = 0.5 * (low + high)
        low, high = (mid, high) if np.max(np.abs(np.roots(a + mid * slope * b))) < 1.0 else (low, mid)
    return low


def random_loop_pair(seed: int, samples: int = 4000, snr_range: tuple[float, float] = (4.0, 8.0),
                     integral: bool = False) -> tuple[LoopRecord, LoopRecord]:
    """(closed loop, open loop) of one random third-order plant with the cubic map, feedback
    dominated (a joint holding position): a P (or, ``integral``, PI with ki = kp / 10)
    controller with kp drawn in 0.7-0.9 of the linearised loop's stability limit at unit slope
    (lowered by 15 % until the loop with the cubic map stays bounded), a white reference of std
    0.2, coloured output noise at an SNR drawn in ``snr_range``; the open-loop record has the
    closed loop's input spread and the same SNR."""
    rng = np.random.default_rng(seed)
    linear = random_third_order_plant(rng)
    kp = rng.uniform(0.7, 0.9) * stability_limit(linear, slope=1.0)
    snr = rng.uniform(*snr_range)
    while True:
        ki = 0.1 * kp if integral else 0.0
        try:
            closed = closed_loop_record(linear, cubic_map, samples, snr, kp, ki, reference_std=0.2, seed=seed + 1)
            if np.max(np.abs(closed.u)) < 5.0:
                break
        except ValueError:
            pass
        kp *= 0.85
    return closed, open_loop_record(linear, cubic_map, samples, snr, float(np.std(closed.u)), seed=seed + 2)
