"""Regression builders shared by every least-squares method (CLS, NLS, LS, PLLS, diagnosis).

The same builder is used on raw signals (v(k), y(k)) and on correlation functions
(phi_vv(tau), phi_yv(tau)): paper 000 step 1 of CLS is exactly the ARX / mu-Markov
regression with the correlation functions as "input-output" data.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import as_strided
from scipy.linalg import lapack

from ..errors import IdentificationError
from .runs import Runs, several

QR_RANK_TOLERANCE = 1e-10  # least_squares_qr hands R with |r_ii| below this x max |r_jj| to the SVD


def delayed(x: np.ndarray, lag: int, initial: float = 0.0) -> np.ndarray:
    """x(k - lag), the first ``lag`` values (the record's unknown past) set to ``initial``."""
    x = np.asarray(x, dtype=float)
    if lag <= 0:
        return x
    return np.concatenate([np.full(min(lag, x.size), initial), x[: max(x.size - lag, 0)]])


def lagged_columns(x: np.ndarray, lags, rows: np.ndarray) -> np.ndarray:
    """Columns x(k - l) for l in ``lags`` at sample indices k in ``rows``.

    ``x`` may be 1-D (one channel) or 2-D (N x p basis functions f_1..f_p); a 2-D input
    gives p adjacent columns per lag, ordered lag-major: f_1(k-l), ..., f_p(k-l), as in
    Bai's theta (paper 000, sec. 3.2).
    """
    x = np.asarray(x, dtype=float)
    x2 = x[:, None] if x.ndim == 1 else x
    lags = np.asarray(lags if isinstance(lags, np.ndarray) else list(lags), dtype=int)
    if lags.size == 0:
        return np.zeros((rows.size, 0))
    block = np.take(x2, rows[:, None] - lags[None, :], axis=0)  # (rows, lags, p); x2[index], gathered faster
    return block.reshape(rows.size, -1)


@dataclass(frozen=True, eq=False)
class Regression:
    """Z = Phi theta + E with theta = [a_1..a_n | input coefficients per input lag].

    ``output_lags`` and ``input_lags`` record which lags the columns hold; the output
    columns are negated so that theta holds the denominator coefficients a_j directly.
    """

    phi: np.ndarray
    target: np.ndarray
    rows: np.ndarray
    output_lags: np.ndarray
    input_lags: np.ndarray
    channels: int

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a_1..a_n, input coefficients as an (input lags x channels) matrix)."""
        n = self.output_lags.size
        return theta[:n], theta[n:].reshape(self.input_lags.size, self.channels)


@functools.lru_cache(maxsize=64)
def markov_lags(order: int, delay: int, mu: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Output and input lags of the mu-Markov model, paper 000 eq. (3):

        y(k) = -sum_{j=1}^{n} alpha_j y(k-mu+1-j) + sum_{i=d}^{d+mu-1} h_i v(k-i)
               + sum_{i=d+1}^{n} beta_i v(k-mu+1-i),

    mu = 1 gives the ARX model of eq. (1): output lags 1..n, input lags d..n. Both end at the
    largest lag n + mu - 1 (``largest_lag``). Cached (read-only arrays): a streaming solve asks for
    the same lags every time.
    """
    if order < 1 or delay < 0 or mu < 1 or delay > order:
        raise ValueError(f"need order >= 1, 0 <= delay <= order, mu >= 1 (got {order}, {delay}, {mu})")
    output_lags = np.arange(1, order + 1) + mu - 1
    markov = np.arange(delay, delay + mu)
    tail = np.arange(delay + 1, order + 1) + mu - 1
    input_lags = np.concatenate([markov, tail])
    output_lags.flags.writeable = input_lags.flags.writeable = False
    return output_lags, input_lags


def largest_lag(order: int, mu: int = 1) -> int:
    """The largest lag of ``markov_lags`` (output and input alike): n + mu - 1, eq. (3)."""
    return order + mu - 1


def build_regression(
    y: np.ndarray, v: np.ndarray, order: int, delay: int, mu: int = 1, start: int | None = None,
    runs: Runs | None = None,
) -> Regression:
    """Regression of the ARX (mu = 1) or mu-Markov model (paper 000, eqs. 1 and 3).

    ``v`` is the input (1-D) or a matrix of basis functions of it (N x p, for NLS and PLLS).
    Rows are k = start..N-1 with ``start`` defaulting to the largest lag; with ``runs`` (several
    experiments concatenated) only the rows whose lags stay in their own run, ``start`` samples
    into it at least (``Runs.rows``).
    """
    y = np.asarray(y, dtype=float)
    v = np.asarray(v, dtype=float)
    if v.shape[0] != y.shape[0]:
        raise ValueError(f"input and output lengths differ ({v.shape[0]} vs {y.shape[0]})")
    output_lags, input_lags = markov_lags(order, delay, mu)
    first = largest_lag(order, mu)
    start = first if start is None else max(start, first)
    runs = several(runs)
    rows = np.arange(start, y.shape[0]) if runs is None else runs.rows(first, first=start)
    if rows.size == 0:
        raise ValueError(f"too few samples ({y.shape[0]}) for lags up to {first}")
    phi = np.concatenate([-lagged_columns(y, output_lags, rows), lagged_columns(v, input_lags, rows)], axis=1)
    channels = 1 if v.ndim == 1 else v.shape[1]
    return Regression(phi, y[rows], rows, output_lags, input_lags, channels)


def solve_least_squares(phi: np.ndarray, target: np.ndarray) -> np.ndarray:
    """theta minimising ||target - phi theta||_2 (QR / SVD based, never the normal equations).
    Non-finite data give NaN coefficients without calling LAPACK (whose DLASCL would print its
    complaint on stdout, into the one JSON document a command prints)."""
    phi, target = np.asarray(phi, dtype=float), np.asarray(target, dtype=float)
    if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(target))):
        return np.full((phi.shape[1], *target.shape[1:]), np.nan)
    theta, *_ = np.linalg.lstsq(phi, target, rcond=None)
    return theta


def least_squares_qr(phi: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``solve_least_squares`` by one Householder QR of the augmented [phi | target] (LAPACK
    dgeqrf, Q never formed): with R the triangle of phi's columns and z the first n entries of
    Q^T target, theta solves R theta = z. The same solution for a tall phi of full rank, about
    3-6x faster than the SVD on the problems of CLS (101 x 36, 4000 x 4); a phi that is not tall,
    non-finite data or an R with |r_ii| < QR_RANK_TOLERANCE max |r_jj| (nearly rank deficient,
    where the minimum-norm solution is the defined answer) go to ``solve_least_squares``."""
    phi, target = np.asarray(phi, dtype=float), np.asarray(target, dtype=float)
    rows, n = phi.shape
    if rows <= n or n == 0:
        return solve_least_squares(phi, target)
    targets = target.reshape(rows, -1)
    augmented = np.empty((rows, n + targets.shape[1]), order="F")
    augmented[:, :n], augmented[:, n:] = phi, targets
    if not np.isfinite(augmented).all():
        return solve_least_squares(phi, target)
    qr, _, _, info = lapack.dgeqrf(augmented, overwrite_a=True)
    diagonal = np.abs(qr.diagonal()[:n])
    if info != 0 or not diagonal.min() > QR_RANK_TOLERANCE * diagonal.max():
        return solve_least_squares(phi, target)
    theta, info = lapack.dtrtrs(qr[:n, :n], qr[:n, n:])
    if info != 0:
        return solve_least_squares(phi, target)
    return theta.reshape((n, *target.shape[1:]))


def fit_regression(
    y: np.ndarray, v: np.ndarray, order: int, delay: int, mu: int = 1, intercept: bool = False,
    runs: Runs | None = None,
) -> tuple[Regression, np.ndarray]:
    """Build the ARX / mu-Markov regression of y on v (rows within ``runs``) and solve it by least squares.

    With ``intercept`` a constant column is added and its coefficient dropped from the
    returned theta: the estimate of (a, b) is then invariant to constant offsets of y and v.

    Raises IdentificationError (naming order, delay, mu) when the record - or the number of
    correlation lags, when y and v are correlation functions - is too short for the model.
    """
    try:
        reg = build_regression(y, v, order, delay, mu, runs=runs)
    except ValueError as exc:
        raise IdentificationError(f"--order/--delay/--mu: {exc}") from None
    phi = np.concatenate([reg.phi, np.ones((reg.rows.size, 1))], axis=1) if intercept else reg.phi
    if reg.rows.size < phi.shape[1]:
        raise IdentificationError(
            f"{reg.rows.size} regression rows for {phi.shape[1]} parameters "
            f"(order {order}, delay {delay}, mu {mu}): record or --tau-max too short"
        )
    theta = least_squares_qr(phi, reg.target)
    return reg, theta[: reg.phi.shape[1]]


def polynomial_basis(v: np.ndarray, degree: int, constant: bool = False) -> np.ndarray:
    """Columns v, v^2, ..., v^degree (f_l = v^l, paper 000 Remark 3), with a leading column of
    ones when ``constant``; column-major (each column contiguous, as CLS step 2 filters them)."""
    v = np.asarray(v, dtype=float)
    first = 1 if constant else 0
    basis = np.empty((v.size, first + degree), order="F")
    if constant:
        basis[:, 0] = 1.0
    if degree:
        basis[:, first] = v
    for column in range(first + 1, first + degree):  # v^l = v^(l-1) v, the products in turn
        basis[:, column] = basis[:, column - 1] * v
    return basis


def fir_valid(x: np.ndarray, taps: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """out[:, j] = np.convolve(x[:, j], taps, "valid") for every column of x (N x q) by matmuls
    (``out`` a new (N - m + 1) x q array when None; returned):
    output k is the window x(k .. k + m - 1) times the reversed m taps. With k = i m + r, the
    windows of one phase r (i = 0, 1, ...) do not overlap, so over the whole blocks of m outputs
    each (column, phase) is one BLAS matrix-vector product on a strided view of the column; the
    last rows mod m outputs are one more (small) product."""
    x = np.asfortranarray(x)
    m, (n, q) = taps.size, x.shape
    if out is None:
        out = np.empty((n - m + 1, q), order="F")
    blocks, step, reversed_taps = (n - m + 1) // m, x.itemsize, taps[::-1].copy()
    windows = as_strided(x, (q, m, blocks, m), (x.strides[1], step, m * step, step))  # [j, r, i, :]
    out[: blocks * m].T.reshape(q, blocks, m)[...] = (windows @ reversed_taps).transpose(0, 2, 1)
    tail = x[blocks * m :]
    out[blocks * m :] = (as_strided(tail, (q, n - m + 1 - blocks * m, m), (x.strides[1], step, step))
                         @ reversed_taps).T
    return out


def filtered_basis(basis: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """The columns of ``basis`` (N x q, its first column a constant) through the FIR ``taps``
    (lags 0 .. m - 1), the rows from lag m - 1 on: the regressors B(q^-1) f_l(v) of CLS step 2
    (paper 000 sec. 3.1), (N - m + 1) x q, column-major."""
    out = np.empty((basis.shape[0] - taps.size + 1, basis.shape[1]), order="F")
    out[:, 0] = basis[0, 0] * taps.sum()  # the constant column's FIR
    fir_valid(basis[:, 1:], taps, out[:, 1:])
    return out


def filtered_output(y: np.ndarray, lags: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """A(q^-1) y = y(k) + sum_j a_j y(k - l_j), y = 0 before the record (np.convolve(y, A)[:N]),
    by one shifted sum per lag."""
    out = np.array(y, dtype=float)
    for lag, a in zip(np.asarray(lags).tolist(), np.asarray(coefficients, dtype=float).tolist(), strict=True):
        out[lag:] += a * y[: y.size - lag]
    return out
