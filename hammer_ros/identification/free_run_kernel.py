"""The free run of a polynomial Hammerstein model on one run, compiled: what
``IdentificationResult.free_run`` computes for the streaming engine's common model (CLS's
y = B(q)/A(q) F(v) with F a polynomial), in one numba loop instead of four ``lfilter`` calls and
their array copies (``Runs.initial_states`` and ``Runs.simulate`` of one run); and, for the
engine's solves, the model's fit on the window in one call (``hammerstein_fit``: the free run, fit
and rms) and the roots of its linear block (``remember_roots``).

The operations are the reference's, in its order: F(v) by Horner's rule as ``PolynomialMap``, then
the transposed direct form II recursion of ``scipy.signal.lfilter`` (a_0 = 1, as ``LinearModel`` holds it),

    y(k) = z_0 + b_0 u(k),   z_i = z_(i+1) + u(k) b_(i+1) - y(k) a_(i+1),   z_(n-1) = u(k) b_n - y(k) a_n,

so the simulation equals the reference's bit for bit where the compiler does not fuse a product
and a sum (``test_free_run_kernel`` compares them to 1e-12). The start is chosen as
``Runs.initial_states`` chooses it: at rest at F(v(0)) (``settle`` samples of it first) or from
zero state, whichever explains the first min(settle, N) samples of y better; the run goes on from the
chosen start's state after them (the head simulated once per start).

``remember_roots`` computes the linear block's roots as ``LinearModel`` does (its companion
matrices, the same LAPACK dgeev call through numba's binding of scipy's LAPACK, the same sorting and
cancelling of roots at 0: equal bit for bit, ``test_free_run_kernel``) and keeps them as the model's;
``hammerstein_fit``'s fit and rms are those of ``result.fit_and_rms`` with the sums taken in four
interleaved partial sums (equal to rounding, 1e-12).

numba is imported on the first call (``import hammer_ros`` stays light); ``cache=True``,
``nogil=True``. None without numba (``compiled_loops.numba_enabled``): the caller runs the reference.
"""

from __future__ import annotations

import types
from functools import partial

import numpy as np

from .compiled_loops import numba_enabled
from .simulate import simulate_hammerstein
from .static_maps import PolynomialMap

_KERNEL: list = []


def hammerstein_free_run(parts: tuple[np.ndarray, np.ndarray, np.ndarray], v: np.ndarray, y: np.ndarray,
                         settle: int) -> np.ndarray | None:
    """The free-run output on the one run (v, y) of the polynomial Hammerstein model ``parts``
    (``polynomial_hammerstein``), started at rest or from zero state (module docstring); None without
    numba or for an empty or uneven record (the caller simulates with ``Runs``)."""
    if not numba_enabled():
        return None
    coefficients, b, a = parts
    v = np.ascontiguousarray(v, dtype=float)
    y = np.ascontiguousarray(y, dtype=float)
    if v.size == 0 or y.size != v.size:
        return None
    out = np.empty(v.size)
    _kernel()(v, y, coefficients, b, a, int(settle), out)
    return out


def hammerstein_fit(parts: tuple[np.ndarray, np.ndarray, np.ndarray], v: np.ndarray, y: np.ndarray,
                    settle: int) -> tuple[float, float] | None:
    """(fit percent, rms) of the free run (``hammerstein_free_run``) of the polynomial Hammerstein model
    ``parts`` (``polynomial_hammerstein``) on the one run (v, y), in one compiled call; None where the
    reference decides (no numba, an empty or uneven record)."""
    v = np.ascontiguousarray(v, dtype=float)
    y = np.ascontiguousarray(y, dtype=float)
    if v.size == 0 or y.size != v.size or not numba_enabled():
        return None
    fit, rms = _kernel(1)(v, y, *parts, int(settle))
    return float(fit), float(rms)


def remember_roots(linear) -> None:
    """Compute a ``LinearModel``'s (zeros, poles) compiled and keep them as its ``_zpk`` (the cached
    property's own algorithm and LAPACK call: bit for bit); nothing when it has them, without numba, or
    when its coefficients are not finite (the property then raises as before)."""
    if "_zpk" in linear.__dict__ or not numba_enabled():
        return
    ok, zeros, poles = _kernel(2)(linear.b, linear.a)
    if ok:
        linear.__dict__["_zpk"] = (zeros, poles)


def polynomial_hammerstein(simulate) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(F's coefficients, b, a, both of one length) of a polynomial Hammerstein simulator
    (``partial(simulate_hammerstein, nonlinearity=PolynomialMap, linear=...)``), or None."""
    if not isinstance(simulate, partial) or simulate.func is not simulate_hammerstein or simulate.args:
        return None
    nonlinearity, linear = simulate.keywords.get("nonlinearity"), simulate.keywords.get("linear")
    if not isinstance(nonlinearity, PolynomialMap) or linear is None or set(simulate.keywords) != {"nonlinearity",
                                                                                                      "linear"}:
        return None
    length = max(linear.a.size, linear.b.size)  # LinearModel holds a_0 = 1 (it divides by a_0)
    b, a = (np.concatenate([c, np.zeros(length - c.size)]) for c in (linear.b, linear.a))
    return np.ascontiguousarray(nonlinearity.coefficients, dtype=float), b, a


def _kernel(which: int = 0):
    """0: ``_free_run_core``, 1: ``_fit_core``, 2: ``_cancelled_roots`` (compiled on the first call)."""
    if not _KERNEL:
        import numba
        from numba.np.linalg import _LAPACK  # numba's own binding of scipy's LAPACK (what np.linalg.eigvals calls)

        jit = numba.njit(cache=True, nogil=True)

        def bound(function, **callees):  # each loop compiled from its own code with its callees bound
            return jit(types.FunctionType(function.__code__, {**globals(), **callees}, function.__name__))

        dgeev = _LAPACK().numba_ez_rgeev(numba.types.float64)  # dgeev after its workspace query
        from .cls_numerics import sorted_roots  # ``linear._sorted_roots``, compiled
        from .compiled_loops import interleaved_sum

        recursion = bound(_filter, _polynomial=jit(_polynomial))
        free_run = bound(_free_run_core, _filter=recursion)
        roots = bound(_cancelled_roots, _polynomial_roots=bound(_polynomial_roots, _dgeev=dgeev),
                      _sorted_roots=sorted_roots)
        _KERNEL.extend([free_run, bound(_fit_core, _free_run_core=free_run, interleaved_sum=jit(interleaved_sum)),
                        roots])
    return _KERNEL[which]


def _polynomial(c, x):
    """F(x) by Horner's rule as ``PolynomialMap.__call__``: c_p x, plus c_(p-1), times x, ..., plus c_0."""
    if c.size == 1:
        return c[0]
    out = c[c.size - 1] * x
    for i in range(c.size - 2, 0, -1):
        out += c[i]
        out *= x
    return out + c[0]


def _filter(v, c, b, a, z, start, stop, out):
    """``lfilter``'s recursion over u = F(v[start:stop]) from state z (updated), into out[start:stop].
    Up to order 4 the state is held in scalars, which stay in registers (an array's would go through
    memory at every sample: the compiler cannot tell its stores from out's), in the same operations."""
    taps = b.size
    if taps == 1:
        for k in range(start, stop):
            out[k] = _polynomial(c, v[k]) * b[0]
    elif taps == 2:
        z0, b0, b1, a1 = z[0], b[0], b[1], a[1]
        for k in range(start, stop):
            x = _polynomial(c, v[k])
            yk = z0 + b0 * x
            z0 = x * b1 - yk * a1
            out[k] = yk
        z[0] = z0
    elif taps == 3:
        z0, z1, b0, b1, b2, a1, a2 = z[0], z[1], b[0], b[1], b[2], a[1], a[2]
        for k in range(start, stop):
            x = _polynomial(c, v[k])
            yk = z0 + b0 * x
            z0 = z1 + x * b1 - yk * a1
            z1 = x * b2 - yk * a2
            out[k] = yk
        z[0], z[1] = z0, z1
    elif taps == 4:
        z0, z1, z2, b0, b1, b2, b3, a1, a2, a3 = z[0], z[1], z[2], b[0], b[1], b[2], b[3], a[1], a[2], a[3]
        for k in range(start, stop):
            x = _polynomial(c, v[k])
            yk = z0 + b0 * x
            z0 = z1 + x * b1 - yk * a1
            z1 = z2 + x * b2 - yk * a2
            z2 = x * b3 - yk * a3
            out[k] = yk
        z[0], z[1], z[2] = z0, z1, z2
    elif taps == 5:
        z0, z1, z2, z3, b0, b1, b2, b3, b4 = z[0], z[1], z[2], z[3], b[0], b[1], b[2], b[3], b[4]
        a1, a2, a3, a4 = a[1], a[2], a[3], a[4]
        for k in range(start, stop):
            x = _polynomial(c, v[k])
            yk = z0 + b0 * x
            z0 = z1 + x * b1 - yk * a1
            z1 = z2 + x * b2 - yk * a2
            z2 = z3 + x * b3 - yk * a3
            z3 = x * b4 - yk * a4
            out[k] = yk
        z[0], z[1], z[2], z[3] = z0, z1, z2, z3
    else:
        for k in range(start, stop):
            x = _polynomial(c, v[k])
            yk = z[0] + b[0] * x
            for i in range(taps - 2):
                z[i] = z[i + 1] + x * b[i + 1] - yk * a[i + 1]
            z[taps - 2] = x * b[taps - 1] - yk * a[taps - 1]
            out[k] = yk


def _free_run_core(v, y, c, b, a, settle, out):
    head = max(min(settle, v.size), 1)
    rest = np.zeros(max(b.size - 1, 1))
    _filter(np.full(settle, v[0]), c, b, a, rest, 0, settle, np.empty(settle))  # at rest at v(0): settle samples of it
    zero = np.zeros(rest.size)
    first = np.empty(head)
    _filter(v, c, b, a, zero, 0, head, first)  # the head from zero state, then at rest (into out)
    _filter(v, c, b, a, rest, 0, head, out)
    errors = np.zeros(2)
    for k in range(head):
        errors[0] += (y[k] - first[k]) ** 2
    for k in range(head):
        errors[1] += (y[k] - out[k]) ** 2
    at_rest = np.isfinite(errors[1]) and (errors[1] < errors[0] or not np.isfinite(errors[0]))
    if not at_rest:
        out[:head] = first
    _filter(v, c, b, a, rest if at_rest else zero, head, v.size, out)  # on from the chosen start's state


def _fit_core(v, y, c, b, a, settle):
    """(fit, rms): ``fit_and_rms`` of ``IdentificationResult.free_run``'s output on (v, y)."""
    out = np.empty(v.size)
    _free_run_core(v, y, c, b, a, settle, out)
    for k in range(y.size):
        out[k] = y[k] - out[k]
    error = np.sqrt(interleaved_sum(out, 0.0, True))  # noqa: F821 (bound by _kernel)
    spread = np.sqrt(interleaved_sum(y, interleaved_sum(y, 0.0, False) / y.size, True))  # noqa: F821
    fit = np.nan if spread == 0.0 else 100.0 * (1.0 - error / spread)
    return fit, error / np.sqrt(y.size)


def _cancelled_roots(b, a):
    """(ok, zeros, poles), ``LinearModel._zpk``: the roots of b and a as polynomials in z of one degree
    (roots at 0 for the shorter one's missing powers), the common roots at 0 cancelled, each sorted;
    not ok when a coefficient is not finite."""
    none = np.zeros(0, np.complex128)
    for x in (b, a):
        for value in x:
            if not np.isfinite(value):
                return False, none, none
    length = max(a.size, b.size)
    any_b = False
    for x in b:
        any_b = any_b or x != 0.0
    zeros = _polynomial_roots(b, length) if any_b else np.zeros(0, np.complex128)
    poles = _polynomial_roots(a, length)
    keep_z, keep_p = np.ones(zeros.size, np.bool_), np.ones(poles.size, np.bool_)
    while True:  # ``while 0j in z and 0j in p``: remove the first of each
        i = j = -1
        for k in range(zeros.size):
            if keep_z[k] and zeros[k] == 0j:
                i = k
                break
        for k in range(poles.size):
            if keep_p[k] and poles[k] == 0j:
                j = k
                break
        if i < 0 or j < 0:
            break
        keep_z[i] = keep_p[j] = False
    return True, _sorted_roots(zeros[keep_z]), _sorted_roots(poles[keep_p])  # noqa: F821 (cls_numerics.sorted_roots, bound by _kernel)


def _polynomial_roots(coefficients, length):
    """``linear._polynomial_roots``: the eigenvalues of the companion matrix of the coefficients from the
    first to the last non-zero one (LAPACK dgeev, eigenvalues only: scipy's, as ``linear.eigenvalues``
    calls it; of a small matrix its result does not depend on the workspace), then a root at 0 per
    trailing zero; unsorted, in LAPACK's order."""
    first = last = -1
    for i in range(coefficients.size):
        if coefficients[i] != 0.0:
            last = i
            if first < 0:
                first = i
    n = last - first
    out = np.zeros(max(n, 0) + length - 1 - last, np.complex128)
    if n > 0:
        companion = np.zeros((n, n))  # column-major below: its transpose, C-ordered
        for i in range(1, n):
            companion[i - 1, i] = 1.0
        for j in range(n):
            companion[j, 0] = -coefficients[first + 1 + j] / coefficients[first]
        real, imaginary, unused = np.empty(n), np.empty(n), np.empty(1)
        info = _dgeev(100, 78, 78, n, companion.ctypes, n, real.ctypes, imaginary.ctypes,  # noqa: F821 (bound by _kernel)
                      unused.ctypes, 1, unused.ctypes, 1)  # kind 'd', eigenvalues only ('N', 'N')
        if info != 0:
            raise ValueError("Eigenvalues did not converge")
        for i in range(n):
            out[i] = complex(real[i], imaginary[i])
    return out

