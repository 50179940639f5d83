"""The free run of a polynomial Hammerstein model on one run, compiled: what
``IdentificationResult.free_run`` computes for the streaming engine's common model (CLS's
y = B(q)/A(q) F(v) with F a polynomial), in one numba loop instead of four ``lfilter`` calls and
their array copies (``Runs.initial_states`` and ``Runs.simulate`` of one run).

The operations are the reference's, in its order: F(v) by Horner's rule as ``PolynomialMap``, then
the transposed direct form II recursion of ``scipy.signal.lfilter`` (a_0 = 1, as ``LinearModel`` holds it),

    y(k) = z_0 + b_0 u(k),   z_i = z_(i+1) + u(k) b_(i+1) - y(k) a_(i+1),   z_(n-1) = u(k) b_n - y(k) a_n,

so the simulation equals the reference's bit for bit where the compiler does not fuse a product
and a sum (``test_free_run_kernel`` compares them to 1e-12). The start is chosen as
``Runs.initial_states`` chooses it: at rest at F(v(0)) (``settle`` samples of it first) or from
zero state, whichever explains the first min(settle, N) samples of y better.

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


def hammerstein_free_run(simulate, v: np.ndarray, y: np.ndarray, settle: int) -> np.ndarray | None:
    """The free-run output of ``simulate`` (an ``IdentificationResult.simulate``) on the one run (v, y),
    started at rest or from zero state (module docstring), when ``simulate`` is a polynomial Hammerstein
    model (``partial(simulate_hammerstein, nonlinearity=PolynomialMap, linear=...)``) and numba is
    available; None otherwise (the caller simulates with ``Runs``)."""
    parts = _polynomial_hammerstein(simulate)
    if parts is None or not numba_enabled():
        return None
    coefficients, b, a = parts
    v = np.ascontiguousarray(v, dtype=float)
    y = np.ascontiguousarray(y, dtype=float)
    if v.size == 0 or y.size != v.size:
        return None
    out = np.empty(v.size)
    _kernel()(v, y, coefficients, b, a, int(settle), out)
    return out


def _polynomial_hammerstein(simulate) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(F's coefficients, b, a, both of one length) of a polynomial Hammerstein simulator, or None."""
    if not isinstance(simulate, partial) or simulate.func is not simulate_hammerstein or simulate.args:
        return None
    nonlinearity, linear = simulate.keywords.get("nonlinearity"), simulate.keywords.get("linear")
    if not isinstance(nonlinearity, PolynomialMap) or linear is None or set(simulate.keywords) != {"nonlinearity",
                                                                                                      "linear"}:
        return None
    length = max(linear.a.size, linear.b.size)  # LinearModel holds a_0 = 1 (it divides by a_0)
    b, a = (np.concatenate([c, np.zeros(length - c.size)]) for c in (linear.b, linear.a))
    return np.ascontiguousarray(nonlinearity.coefficients, dtype=float), b, a


def _kernel():
    if not _KERNEL:
        import numba

        jit = numba.njit(cache=True, nogil=True)
        polynomial = jit(_polynomial)  # each loop compiled from its own code with its callees bound
        recursion = jit(types.FunctionType(_filter.__code__, {**globals(), "_polynomial": polynomial}, "_filter"))
        _KERNEL.append(jit(types.FunctionType(_free_run_core.__code__, {**globals(), "_filter": recursion},
                                              "_free_run_core")))
    return _KERNEL[0]


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
    """``lfilter``'s recursion over u = F(v[start:stop]) from state z (updated), into out[start:stop]."""
    taps = b.size
    for k in range(start, stop):
        x = _polynomial(c, v[k])
        if taps == 1:
            out[k] = x * b[0]
            continue
        yk = z[0] + b[0] * x
        for i in range(taps - 2):
            z[i] = z[i + 1] + x * b[i + 1] - yk * a[i + 1]
        z[taps - 2] = x * b[taps - 1] - yk * a[taps - 1]
        out[k] = yk


def _free_run_core(v, y, c, b, a, settle, out):
    head = max(min(settle, v.size), 1)
    zero = np.zeros(max(b.size - 1, 1))
    rest = zero.copy()
    held = np.full(1, v[0])
    scratch = np.empty(1)
    for _ in range(settle):  # at rest at v(0): settle samples of it first (``preroll_simulate``)
        _filter(held, c, b, a, rest, 0, 1, scratch)
    errors = np.zeros(2)
    for which in range(2):  # the head from zero state, then at rest
        z = zero.copy() if which == 0 else rest.copy()
        _filter(v, c, b, a, z, 0, head, out)
        for k in range(head):
            errors[which] += (y[k] - out[k]) ** 2
    at_rest = np.isfinite(errors[1]) and (errors[1] < errors[0] or not np.isfinite(errors[0]))
    _filter(v, c, b, a, rest if at_rest else zero, 0, v.size, out)
