"""Discrete-time SISO linear blocks: transfer functions, simulation, poles/zeros, RSS error.

Convention (paper 000, eqs. 1-2): coefficients are in powers of the delay operator q^-1,

    y(k) = -sum_{j=1}^{n} a_j y(k-j) + sum_{i=0}^{m} b_i v(k-i),

stored as ``a = [1, a_1, ..., a_n]`` and ``b = [b_0, ..., b_m]`` (``b_i = 0`` for i < d, the
relative degree), i.e. G(q) = B(q^-1) / A(q^-1), the argument order of ``scipy.signal.lfilter``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import signal
from scipy.linalg import lapack
from scipy.optimize import linear_sum_assignment


@dataclass(frozen=True, eq=False)
class LinearModel:
    """G(z) = (b_0 + b_1 z^-1 + ... + b_m z^-m) / (1 + a_1 z^-1 + ... + a_n z^-n)."""

    b: np.ndarray
    a: np.ndarray

    def __post_init__(self) -> None:
        b = np.array(self.b, dtype=float, ndmin=1, copy=None)
        a = np.array(self.a, dtype=float, ndmin=1, copy=None)
        if a.size == 0 or a[0] == 0.0:
            raise ValueError("denominator must start with a non-zero coefficient")
        object.__setattr__(self, "b", b / a[0])
        object.__setattr__(self, "a", a / a[0])

    @classmethod
    def from_zeros_poles(cls, zeros, poles, dc_gain: float = 1.0) -> LinearModel:
        """The block with the given zeros and poles (in z), relative degree n - m, scaled to
        the static gain ``dc_gain`` (paper 000 normalises G1 and G2 to static gain 1)."""
        num = np.real(np.poly(np.asarray(zeros, dtype=complex))) if len(zeros) else np.ones(1)
        den = np.real(np.poly(np.asarray(poles, dtype=complex)))
        delay = len(den) - len(num)
        if delay < 0:
            raise ValueError("improper transfer function: more zeros than poles")
        b = np.concatenate([np.zeros(delay), num])
        model = cls(b, den)
        return cls(b * dc_gain / model.dc_gain, den)

    @property
    def order(self) -> int:
        return self.a.size - 1

    @property
    def delay(self) -> int:
        """Relative degree d: index of the first non-zero numerator coefficient."""
        nz = np.flatnonzero(self.b)
        return int(nz[0]) if nz.size else 0

    @property
    def dc_gain(self) -> float:
        return float(np.sum(self.b) / np.sum(self.a))

    @cached_property
    def _zpk(self) -> tuple[np.ndarray, np.ndarray]:
        """(zeros, poles), sorted (``_sorted_roots``) and computed once: the model is immutable."""
        length = max(self.a.size, self.b.size)
        # both polynomials in z of degree length - 1: the shorter one's missing powers are roots at 0
        z = _polynomial_roots(self.b.tolist(), length) if self.b.any() else []
        p = _polynomial_roots(self.a.tolist(), length)
        # cancel the common roots at the origin introduced by equal-length padding
        while 0j in z and 0j in p:
            z.remove(0j)
            p.remove(0j)
        return _sorted_roots(z), _sorted_roots(p)

    @property
    def poles(self) -> np.ndarray:
        return self._zpk[1].copy()

    @property
    def zeros(self) -> np.ndarray:
        return self._zpk[0].copy()

    def simulate(self, v: np.ndarray) -> np.ndarray:
        """Free-run response to the input sequence ``v`` from zero initial conditions."""
        return signal.lfilter(self.b, self.a, np.asarray(v, dtype=float))

    def markov_parameters(self, count: int) -> np.ndarray:
        """Impulse response h_0, ..., h_{count-1} (the Markov parameters, paper 000 sec. 2)."""
        impulse = np.zeros(count)
        impulse[0] = 1.0
        return self.simulate(impulse)

    def scaled(self, factor: float) -> LinearModel:
        return LinearModel(self.b * factor, self.a)

    def is_stable(self) -> bool:
        return all(abs(pole) < 1.0 for pole in self._zpk[1].tolist())


def _polynomial_roots(coefficients: list[float], length: int) -> list[complex]:
    """``np.roots`` of ``coefficients`` (not all zero) padded with zeros to ``length``: the eigenvalues
    of the companion matrix of the coefficients from the first to the last non-zero one, then a root
    at 0 per trailing zero (np.roots' matrix and LAPACK call, without its padding and argument
    handling; a polynomial of an identified model has a handful of coefficients)."""
    nonzero = [i for i, c in enumerate(coefficients) if c != 0.0]
    first, last = nonzero[0], nonzero[-1]
    roots = []
    if last > first:
        companion = np.eye(last - first, k=-1)
        companion[0] = [-c / coefficients[first] for c in coefficients[first + 1 : last + 1]]
        roots = eigenvalues(companion).tolist()
    return roots + [0j] * (length - 1 - last)


def characteristic_polynomial(matrix: np.ndarray) -> np.ndarray:
    """det(zI - A) of a real matrix, ``np.poly(A)``: the product of the factors z - lambda over the
    eigenvalues in turn, as np.poly's convolutions (complex when some eigenvalues are; they come in
    conjugate pairs, so the result is real), on Python numbers (a realisation has a handful of
    eigenvalues) and without np.poly's argument handling and conjugate-pair check."""
    roots = eigenvalues(matrix).tolist()
    coefficients = [1.0] + [0.0] * len(roots)  # of z^n, z^(n-1), ..., 1
    for k, root in enumerate(roots, start=1):  # times (z - root): c_i -= root c_(i-1), from the top
        for i in range(k, 0, -1):
            coefficients[i] -= root * coefficients[i - 1]
    return np.array(coefficients).real.copy()


def eigenvalues(matrix: np.ndarray) -> np.ndarray:
    """``np.linalg.eigvals`` of a real square matrix (a real array when every eigenvalue is real): one
    direct LAPACK dgeev call (eigenvalues only), without numpy's per-call overhead; a solve of the
    streaming engine needs four (the ERA realisation's polynomials and the model's poles and zeros)."""
    if not np.isfinite(matrix).all():
        raise np.linalg.LinAlgError("Array must not contain infs or NaNs")
    real, imaginary, _, _, info = lapack.dgeev(matrix, compute_vl=0, compute_vr=0)
    if info != 0:
        raise np.linalg.LinAlgError("Eigenvalues did not converge")
    if not imaginary.any():
        return real
    values = real.astype(complex)
    values.imag = imaginary
    return values


def symmetric_eigenvalues(matrix: np.ndarray) -> np.ndarray:
    """``np.linalg.eigvalsh`` of a real symmetric matrix (ascending; its lower triangle is used): the same
    LAPACK dsyevd call, without numpy's per-call overhead (the streaming engine's excitation check
    needs one per solve)."""
    values, _, info = lapack.dsyevd(matrix, compute_v=0, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("Eigenvalues did not converge")
    return values


def _sorted_roots(roots: list[complex]) -> np.ndarray:
    """The roots as a complex array ordered by real, then imaginary part, imaginary parts below 1e-12
    set to 0 (real + 0.0 turns a -0.0 into 0.0, as numpy's real + 0j)."""
    snapped = [complex(r.real + 0.0, 0.0) if abs(r.imag) < 1e-12 else complex(r) for r in roots]
    return np.array(sorted(snapped, key=lambda r: (r.real, r.imag)), dtype=complex)


def root_rss_error(true_roots, estimated_roots) -> float:
    """Root-sum-square error between two sets of poles (or zeros), paper 000 section 4.2:

        e_rss = sqrt(|z_1 - z1_hat|^2 + ... + |z_n - zn_hat|^2)

    after matching each true root one-to-one with its closest estimate (the assignment that
    minimises the sum of squared distances). Unmatched roots, when the counts differ, add
    their squared modulus, so a model of the wrong order is never scored as exact.
    """
    t = np.atleast_1d(np.asarray(true_roots, dtype=complex))
    e = np.atleast_1d(np.asarray(estimated_roots, dtype=complex))
    if t.size == 0 or e.size == 0:
        return float(np.sqrt(np.sum(np.abs(t) ** 2) + np.sum(np.abs(e) ** 2)))
    cost = np.abs(t[:, None] - e[None, :]) ** 2
    rows, cols = linear_sum_assignment(cost)
    total = cost[rows, cols].sum()
    total += np.sum(np.abs(np.delete(t, rows)) ** 2) + np.sum(np.abs(np.delete(e, cols)) ** 2)
    return float(np.sqrt(total))


def match_roots(true_roots, estimated_roots) -> np.ndarray:
    """The estimate assigned to each true root by the one-to-one closest matching of
    ``root_rss_error`` (paper 000 sec. 4.2), in the order of ``true_roots``; NaN where there
    are fewer estimates than true roots."""
    t = np.atleast_1d(np.asarray(true_roots, dtype=complex))
    e = np.atleast_1d(np.asarray(estimated_roots, dtype=complex))
    out = np.full(t.size, np.nan + 0j)
    if t.size and e.size:
        rows, cols = linear_sum_assignment(np.abs(t[:, None] - e[None, :]) ** 2)
        out[rows] = e[cols]
    return out
