"""Eigensystem realization algorithm (ERA): Markov parameters -> minimal state-space model.

Juang, *Applied System Identification* (1994), ch. 5; paper 000 (Lum & Bernstein) obtains the
poles and zeros of every identified mu-Markov model this way (sec. 4.2, footnote 1).

Given the Markov parameters h_0 = D, h_k = C A^(k-1) B (k >= 1) of a SISO system, the r x s
Hankel matrices

    H(0)[i, j] = h_(1+i+j),   H(1)[i, j] = h_(2+i+j),   0 <= i < r, 0 <= j < s,

use h_1 .. h_(r+s). With the rank-n truncated SVD H(0) ~ U_n S_n V_n^T the balanced
realisation is

    A = S_n^(-1/2) U_n^T H(1) V_n S_n^(-1/2),   B = S_n^(1/2) V_n^T e_1,
    C = e_1^T U_n S_n^(1/2),                    D = h_0.

Default Hankel size: all available parameters, split as evenly as possible (r = ceil(M/2),
s = floor(M/2) for h_1..h_M). With paper 000's mu = 30 Markov parameters of a relative-degree-1
plant (M = 30) this is the 15 x 15 Hankel matrix, which reproduces the mu-Markov columns of
its Tables 1-6 (the noisy estimated tail is averaged over the most rows and columns).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from ..errors import IdentificationError
from .linear import LinearModel, characteristic_polynomial

_TINY = np.finfo(float).tiny


@dataclass(frozen=True, eq=False)
class StateSpaceRealization:
    """x(k+1) = A x(k) + B v(k), y(k) = C x(k) + D v(k) (SISO; B is n x 1, C is 1 x n),
    with the Hankel singular values it was cut from (their drop after index n tells how
    well the data support the chosen order)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: float
    hankel_singular_values: np.ndarray

    @property
    def order(self) -> int:
        return self.A.shape[0]

    def markov_parameters(self, count: int) -> np.ndarray:
        """h_0 = D, h_k = C A^(k-1) B for k = 1 .. count-1."""
        out = np.empty(count)
        out[0] = self.D
        x = self.B[:, 0]
        for k in range(1, count):
            out[k] = float(self.C[0] @ x)
            x = self.A @ x
        return out

    def to_linear_model(self, delay: int = 0) -> LinearModel:
        """The transfer function C (zI - A)^-1 B + D as a ``LinearModel`` (q^-1 coefficients:
        dividing numerator and denominator, both of degree n in z, by z^n). The first
        ``delay`` numerator coefficients (h_0 .. h_(d-1) = 0 for a known relative degree d)
        are set to exact zeros: the realisation reproduces them only up to rounding, and a
        1e-17 leading coefficient would show up as a spurious zero near infinity."""
        den = characteristic_polynomial(self.A)
        # SISO: C (zI - A)^-1 B = [det(zI - A + BC) - det(zI - A)] / det(zI - A) (matrix determinant lemma)
        num = characteristic_polynomial(self.A - self.B @ self.C) - den + self.D * den
        num[:delay] = 0.0
        return LinearModel(num, den)


def eigensystem_realization(
    markov: np.ndarray, order: int, rows: int | None = None, columns: int | None = None
) -> StateSpaceRealization:
    """ERA (Juang 1994) of order ``order`` from ``markov`` = [h_0, h_1, ..., h_M].

    ``rows`` x ``columns`` is the Hankel size (default: ceil(M/2) x floor(M/2), i.e. every
    parameter used); rows + columns <= M is required since H(1) needs h_(rows+columns).
    """
    h = np.asarray(markov, dtype=float).ravel()
    available = h.size - 1
    if rows is None and columns is None:
        rows, columns = (available + 1) // 2, available // 2
    elif rows is None:
        rows = available - columns
    elif columns is None:
        columns = available - rows
    if rows < 1 or columns < 1 or rows + columns > available:
        raise IdentificationError(
            f"ERA: a {rows} x {columns} Hankel matrix needs {rows + columns + 1} Markov parameters, got {h.size}"
        )
    if order < 1 or order > min(rows, columns):
        raise IdentificationError(
            f"ERA: order {order} needs a Hankel matrix of at least {order} x {order} "
            f"(have {rows} x {columns}; estimate more Markov parameters, e.g. a larger --mu)"
        )
    first, second = _hankel_indices(rows, columns)
    h0, h1 = h[first], h[second]
    u, s, vt = _svd(h0)
    if s[order - 1] <= 1e-14 * max(s[0], _TINY):
        raise IdentificationError(
            f"ERA: the Markov parameters have rank {int(np.sum(s > 1e-14 * s[0]))} < order {order}"
        )
    root = np.sqrt(s[:order])
    un, vn = u[:, :order], vt[:order].T
    a = (un.T @ h1 @ vn) / root[:, None] / root[None, :]
    b = (root * vn[0])[:, None]
    c = (un[0] * root)[None, :]
    return StateSpaceRealization(a, b, c, float(h[0]), s)


def _svd(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.linalg.svd(matrix)`` (full U and V^T) of a real matrix: the same LAPACK dgesdd call, without
    numpy's per-call overhead."""
    u, s, vt, info = lapack.dgesdd(matrix)
    if info != 0:
        raise np.linalg.LinAlgError("SVD did not converge")
    return u, s, vt


@functools.lru_cache(maxsize=16)
def _hankel_indices(rows: int, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """The indices 1 + i + j of H(0) and 2 + i + j of H(1) into [h_0, h_1, ...] (cached, read-only:
    the streaming engine solves with one size)."""
    index = np.arange(rows)[:, None] + np.arange(columns)[None, :]
    first, second = 1 + index, 2 + index
    first.flags.writeable = second.flags.writeable = False
    return first, second


def era_linear_model(markov: np.ndarray, order: int, delay: int = 0) -> LinearModel:
    """The ``LinearModel`` (poles, zeros) of the order-``order`` ERA realisation with the
    default Hankel size, relative degree ``delay``."""
    return eigensystem_realization(markov, order).to_linear_model(delay)
