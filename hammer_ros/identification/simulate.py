"""Simulators of the block structures, shared by every method, test and the demo plant.

Every simulator takes the input sequence first, then the blocks; the maps are any callables
on numpy arrays (the static_maps classes or plain functions such as ``np.tanh``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import signal

from .compiled_loops import feedback_loop, play
from .linear import LinearModel
from .static_maps import PiecewiseLinearMap

StaticMap = Callable[[np.ndarray], np.ndarray]
COMPILED_PLAY_SAMPLES = 100_000


def simulate_hammerstein(v: np.ndarray, nonlinearity: StaticMap, linear: LinearModel) -> np.ndarray:
    """y = G(q) F[v]: static map F, then the linear block G (paper 000, Fig. 1)."""
    return linear.simulate(nonlinearity(np.asarray(v, dtype=float)))


def simulate_parallel(
    v: np.ndarray, nonlinearity: StaticMap, branch: LinearModel, parallel_path: LinearModel
) -> np.ndarray:
    """y = H2(q) F[v] + H1(q) v: a Hammerstein branch (F, then H2) in parallel with the linear
    path H1, the feedforward system of paper 003, Fig. 3 and eq. (18)."""
    return simulate_hammerstein(v, nonlinearity, branch) + parallel_path.simulate(v)


def simulate_feedback(v: np.ndarray, feedback: StaticMap, linear: LinearModel) -> np.ndarray:
    """y = G(q)[v - h(y)]: the non-linear feedback model of paper 001, eq. 39."""
    return simulate_hammerstein_feedback(v, np.asarray, feedback, linear)


def simulate_hammerstein_feedback(
    v: np.ndarray, nonlinearity: StaticMap, feedback: StaticMap, linear: LinearModel
) -> np.ndarray:
    """y = G(q)[F(v) - h(y)]: the Hammerstein/non-linear feedback model of paper 001, eq. 2.

    G must be strictly proper (b_0 = 0, no algebraic loop). From zero initial conditions
    (the input of G is 0 before k = 0), the feedforward part B(q) F(v) is computed at once and
    the feedback recursion

        y(k) = [B(q) F(v)](k) - sum_{i>=1} b_i h(y(k-i)) - sum_{j>=1} a_j y(k-j)

    runs sample by sample: for a PiecewiseLinearMap h in the compiled loop of
    ``compiled_loops.feedback_loop`` (numba; its pure-Python fallback without numba or with
    HAMMER_ROS_NO_NUMBA=1), for any other h on Python floats, h called on one-element arrays.
    """
    v = np.asarray(v, dtype=float)
    b, a = linear.b, linear.a
    if b[0] != 0.0:
        raise ValueError("the linear block of a feedback loop must be strictly proper (b_0 = 0)")
    forced = np.convolve(np.asarray(nonlinearity(v), dtype=float), b)[: v.size]
    if isinstance(feedback, PiecewiseLinearMap):
        return feedback_loop(forced, b[1:], a[1:], feedback.breakpoints, feedback.values, feedback.slopes,
                             feedback.curvature_left, feedback.curvature_right)
    forced = forced.tolist()
    h = _scalar_function(feedback)
    b_past, a_past = b[1:].tolist(), a[1:].tolist()
    lead = max(len(b_past), len(a_past))
    y = [0.0] * (lead + v.size)  # y[lead + k] = y(k); zeros before k = 0
    hy = [0.0] * (lead + v.size)  # h(y(k)) with the same offset; 0 = no input before k = 0
    for k in range(lead, lead + v.size):
        acc = forced[k - lead]
        for i, bi in enumerate(b_past, start=1):
            acc -= bi * hy[k - i]
        for j, aj in enumerate(a_past, start=1):
            acc -= aj * y[k - j]
        y[k] = acc
        hy[k] = h(acc)
    return np.asarray(y[lead:])


def _scalar_function(fn: StaticMap) -> Callable[[float], float]:
    """fn as a float -> float function for sample-by-sample recursions."""
    return lambda x: float(np.asarray(fn(np.array([x])), dtype=float).reshape(-1)[0])


def play_operator(v: np.ndarray, width: float, initial: float | None = None) -> np.ndarray:
    """The play (backlash) operator of total dead band ``width`` (Krasnosel'skii-Pokrovskii):

        z(k) = min(max(z(k-1), v(k) - width/2), v(k) + width/2),   z(-1) = initial (default v(0)),

    i.e. the output stays put while the input moves inside the gap and is dragged along,
    ``width/2`` behind, once the input pushes against either side of it.
    """
    x = np.asarray(v, dtype=float)
    if x.size == 0:
        return x.copy()
    # compiled from COMPILED_PLAY_SAMPLES on: below, the Python loop takes less than importing numba
    return play(x, 0.5 * max(float(width), 0.0), float(x[0] if initial is None else initial),
                compiled=None if x.size >= COMPILED_PLAY_SAMPLES else False)


def add_noise(x: np.ndarray, noise_to_signal: float, seed=None) -> np.ndarray:
    """x plus white Gaussian noise whose standard deviation is ``noise_to_signal`` times
    std(x) (paper 000 sec. 4.3: "noise-to-signal ratios of 4% to 6%")."""
    rng = np.random.default_rng(seed)
    return x + noise_to_signal * np.std(x) * rng.standard_normal(np.shape(x))


class HammersteinStream:
    """y = G(q) F[v] computed chunk by chunk (a live plant): the state of the linear block
    carries over between calls, so concatenated chunks give exactly ``simulate_hammerstein``
    on the concatenated input."""

    def __init__(self, nonlinearity: StaticMap, linear: LinearModel) -> None:
        self.nonlinearity, self.linear = nonlinearity, linear
        self._state = np.zeros(max(linear.a.size, linear.b.size) - 1)

    def __call__(self, v: np.ndarray) -> np.ndarray:
        y, self._state = signal.lfilter(self.linear.b, self.linear.a, self.nonlinearity(np.asarray(v, float)),
                                         zi=self._state)
        return y
