"""Sample-by-sample loops compiled with numba, each with a pure-Python fallback that gives the same
numbers (same operations in the same order; the tests compare the two to 1e-12).

The loops here are the spread and the distinct values of a record and the condition of a
correlation matrix (``spread_figures``, ``distinct_values``, ``toeplitz_condition``: what the checks
of a solve read) and the feedback recursion of the
Hammerstein / non-linear feedback model of paper 001, eq. 2, y = G(q)[f(v) - h(y)] with G = B/A
strictly proper:

    y(k) = [B(q) f(v)](k) - sum_{i>=1} b_i h(y(k-i)) - sum_{j>=1} a_j y(k-j),

with h a continuous piecewise-linear map (knots c_1 < ... < c_p, values h(c_i), the slopes of the
p + 1 intervals, eqs. 5-11 of paper 001 in knot form) evaluated inside the loop, and quadratic
tails beyond the outer knots, held constant beyond their vertex (``PiecewiseLinearMap``'s
``curvature_left`` / ``curvature_right``; 0 = the outer slope continued).

numba is imported on the first call only (``import hammer_ros`` stays light); the kernels are
compiled with ``cache=True`` and ``nogil=True``: the first run of a fresh install compiles them
(2.4 s CPU measured on the loaded 2-core test machine), later processes load them from numba's
cache (1.2 s CPU there, most of it numba's own import). The fallback runs when numba cannot be
imported or when the environment variable ``HAMMER_ROS_NO_NUMBA`` is ``1``.
"""

from __future__ import annotations

import math
import os
import types

import numpy as np

_KERNELS: dict = {}


def numba_enabled() -> bool:
    """True unless HAMMER_ROS_NO_NUMBA=1 or numba cannot be imported (read at every call)."""
    if os.environ.get("HAMMER_ROS_NO_NUMBA", "") == "1":
        return False
    return _kernel("feedback") is not None


def _kernel(name: str):
    if name not in _KERNELS:
        try:
            _KERNELS.update(_compile())
        except ImportError:
            _KERNELS.update(feedback=None, cascade=None, play=None, servo=None, physical_servo=None, spread=None,
                            distinct=None, condition=None)
    return _KERNELS[name]


def _chosen(name: str, compiled: bool | None):
    """The kernel ``name`` when the compiled form is chosen (``compiled`` None: when numba is enabled),
    None for the Python form; ImportError when it is forced without numba."""
    if not (numba_enabled() if compiled is None else compiled):
        return None
    kernel = _kernel(name)
    if kernel is None:
        raise ImportError("numba is not available")
    return kernel


def _compile() -> dict:
    import numba

    jit = numba.njit(cache=True, nogil=True)
    # the loops call the compiled map: each is compiled from its own code with that name bound
    scope = {**globals(), "_map_value": jit(_map_value)}
    scope_sum = {**globals(), "interleaved_sum": jit(interleaved_sum)}
    return {"feedback": jit(types.FunctionType(_feedback_core.__code__, scope, "_feedback_core")),
            "cascade": jit(types.FunctionType(_cascade_core.__code__, scope, "_cascade_core")),
            "play": jit(_play_core),
            "servo": jit(types.FunctionType(_servo_core.__code__, scope, "_servo_core")),
            "physical_servo": jit(_physical_servo_core),
            "spread": jit(types.FunctionType(_spread_core.__code__, scope_sum, "_spread_core")),
            "distinct": jit(_distinct_core),
            "condition": jit(types.FunctionType(_condition_core.__code__, {**globals(), "_condition": jit(_condition)},
                                                "_condition_core"))}


def spread_figures(x: np.ndarray, step_fraction: float = 0.0, compiled: bool | None = None
                   ) -> tuple[float, float, float, bool]:
    """(std, max, min, moves) of a finite, non-empty x in two passes (the mean, then the deviations and
    the extremes: ``np.std``'s value to rounding, each sum as four interleaved partial sums); ``moves``:
    whether some change between consecutive samples is non-zero and at most ``step_fraction`` x std
    (False for 0).
    ``compiled`` as in ``feedback_loop``."""
    kernel = _chosen("spread", compiled)
    if kernel is not None:
        std, high, low, moves = kernel(np.ascontiguousarray(x, dtype=float).ravel(), float(step_fraction))
        return float(std), float(high), float(low), bool(moves)
    return _spread_core(np.asarray(x, dtype=float).ravel().tolist(), float(step_fraction))


def _spread_core(x, step_fraction):
    count = len(x)
    mean = interleaved_sum(x, 0.0, False) / count
    squares, high, low = interleaved_sum(x, mean, True), x[0], x[0]
    for k in range(count):
        high = x[k] if x[k] > high else high
        low = x[k] if x[k] < low else low
    std = math.sqrt(squares / count)
    bound = step_fraction * std
    for k in range(1, count if step_fraction > 0.0 else 0):
        change = abs(x[k] - x[k - 1])
        if 0.0 < change <= bound:
            return std, high, low, True
    return std, high, low, False


def interleaved_sum(x, centre, squared):
    """sum(x - centre) or, ``squared``, sum((x - centre)^2), in four interleaved partial sums (four
    independent additions per step instead of one chain)."""
    count = len(x)
    s0 = s1 = s2 = s3 = 0.0
    k = 0
    while k + 4 <= count:
        d0, d1, d2, d3 = x[k] - centre, x[k + 1] - centre, x[k + 2] - centre, x[k + 3] - centre
        if squared:
            d0, d1, d2, d3 = d0 * d0, d1 * d1, d2 * d2, d3 * d3
        s0, s1, s2, s3 = s0 + d0, s1 + d1, s2 + d2, s3 + d3
        k += 4
    total = (s0 + s1) + (s2 + s3)
    for j in range(k, count):
        d = x[j] - centre
        total += d * d if squared else d
    return total


def distinct_values(x: np.ndarray, compiled: bool | None = None) -> int:
    """The number of distinct values of a finite x (``np.unique(x).size``; -0.0 and 0.0 are one).
    ``compiled`` as in ``feedback_loop``."""
    kernel = _chosen("distinct", compiled)
    if kernel is not None:
        return int(kernel(np.ascontiguousarray(x, dtype=float).ravel()))
    return _distinct_core(np.asarray(x, dtype=float).ravel())


def toeplitz_condition(phi: np.ndarray, centre: int, size: int, compiled: bool | None = None) -> float:
    """cond(R) = lambda_max / lambda_min of the symmetric Toeplitz matrix R[i, j] = r(|i - j|), i, j < ``size``,
    r(k) = (phi[centre + k] + phi[centre - k]) / 2 (a correlation function, index ``centre`` = lag 0); inf
    when lambda_max <= 0 or lambda_min <= 1e-300 lambda_max. The eigenvalues by LAPACK dsyevd (lower
    triangle, eigenvalues only) compiled as in Python (``linear.symmetric_eigenvalues``: scipy's LAPACK,
    which numba calls too), so the same numbers. ``compiled`` as in ``feedback_loop`` (entries not finite:
    the Python form, as LAPACK answers them there)."""
    phi = np.ascontiguousarray(phi, dtype=float)
    kernel = _chosen("condition", compiled)
    if kernel is not None and np.isfinite(phi[centre - size + 1 : centre + size]).all():
        return float(kernel(phi, int(centre), int(size)))
    from .linear import symmetric_eigenvalues

    one_sided = 0.5 * (phi[centre : centre + size] + phi[centre::-1][:size])
    index = np.arange(size)
    return _condition(symmetric_eigenvalues(one_sided[np.abs(index[:, None] - index[None, :])]))


def _condition_core(phi, centre, size):
    matrix = np.empty((size, size))
    for i in range(size):
        for j in range(size):
            k = abs(i - j)
            matrix[i, j] = 0.5 * (phi[centre + k] + phi[centre - k])
    return _condition(np.linalg.eigvalsh(matrix))


def _condition(eigenvalues):
    """lambda_max / lambda_min of ascending eigenvalues, inf for a matrix not positive definite."""
    if eigenvalues[-1] <= 0 or eigenvalues[0] <= eigenvalues[-1] * 1e-300:
        return np.inf
    return eigenvalues[-1] / eigenvalues[0]


def _distinct_core(x):
    ordered = np.sort(x)
    count = 1 if ordered.size else 0
    for k in range(1, ordered.size):
        count += ordered[k] != ordered[k - 1]
    return count


def feedback_loop(forced: np.ndarray, b_past: np.ndarray, a_past: np.ndarray, knots: np.ndarray,
                  values: np.ndarray, slopes: np.ndarray, curvature_left: float = 0.0,
                  curvature_right: float = 0.0, compiled: bool | None = None) -> np.ndarray:
    """y(k) = forced(k) - sum_i b_past[i-1] h(y(k-i)) - sum_j a_past[j-1] y(k-j), from zero initial
    conditions (y = h(y) = 0 before k = 0), with h the piecewise-linear map (knots, values,
    slopes of the len(knots) + 1 intervals, quadratic tails). ``compiled``: None = numba when
    available (``numba_enabled``), True/False to force one of the two implementations."""
    args = (np.ascontiguousarray(forced, dtype=float), np.ascontiguousarray(b_past, dtype=float),
            np.ascontiguousarray(a_past, dtype=float), np.ascontiguousarray(knots, dtype=float),
            np.ascontiguousarray(values, dtype=float), np.ascontiguousarray(slopes, dtype=float),
            float(curvature_left), float(curvature_right))
    kernel = _chosen("feedback", compiled)
    if kernel is not None:
        lead = max(args[1].size, args[2].size)
        y, hy = np.zeros(lead + args[0].size), np.zeros(lead + args[0].size)
        kernel(*args, y, hy)
        return y[lead:]
    return _feedback_loop_python(*args)


def _feedback_loop_python(forced, b_past, a_past, knots, values, slopes, curvature_left, curvature_right):
    """The fallback: the kernel's own source run by Python on lists (indexing lists is several
    times faster than indexing arrays element by element)."""
    lead = max(len(b_past), len(a_past))
    y, hy = [0.0] * (lead + len(forced)), [0.0] * (lead + len(forced))
    _feedback_core(forced.tolist(), b_past.tolist(), a_past.tolist(), knots.tolist(), values.tolist(),
                   slopes.tolist(), curvature_left, curvature_right, y, hy)
    return np.asarray(y[lead:], dtype=float)


def _map_value(knots, values, slopes, curvature_left, curvature_right, x):
    """h(x) of the piecewise-linear map (knots, values h(c_i), slopes of the p + 1 intervals) with
    quadratic tails held constant beyond their vertex."""
    p = len(knots)
    lo, hi = 0, p  # bisect_left on the knots: knots[lo-1] < x <= knots[lo]
    while lo < hi:
        mid = (lo + hi) // 2
        if knots[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    if lo == 0:
        d = x - knots[0]
        if curvature_left != 0.0:  # the quadratic tail is held constant beyond its vertex
            vertex = -slopes[0] / (2.0 * curvature_left)
            if d < vertex <= 0.0:
                d = vertex
        return values[0] + slopes[0] * d + curvature_left * d * d
    if lo == p:
        d = x - knots[p - 1]
        if curvature_right != 0.0:
            vertex = -slopes[p] / (2.0 * curvature_right)
            if 0.0 <= vertex < d:
                d = vertex
        return values[p - 1] + slopes[p] * d + curvature_right * d * d
    return values[lo - 1] + slopes[lo] * (x - knots[lo - 1])


def _feedback_core(forced, b_past, a_past, knots, values, slopes, curvature_left, curvature_right, y, hy):
    """The recursion on y[lead:], hy[lead:] (lead = max(len(b_past), len(a_past)) zeros before k = 0)."""
    nb, na = len(b_past), len(a_past)
    lead = max(nb, na)
    for k in range(lead, lead + len(forced)):
        acc = forced[k - lead]
        for i in range(nb):
            acc -= b_past[i] * hy[k - 1 - i]
        for j in range(na):
            acc -= a_past[j] * y[k - 1 - j]
        y[k] = acc
        hy[k] = _map_value(knots, values, slopes, curvature_left, curvature_right, acc)


def storage_cascade(drive: np.ndarray, first, between, second, compiled: bool | None = None) -> np.ndarray:
    """y(k) = x2(k) of two first-order storages in series, from empty storages (x1 = x2 = 0 at k = 0):

        x1(k+1) = x1(k) + drive(k) - h1(x1(k)),    x2(k+1) = x2(k) + g(x1(k+1)) - h2(x2(k)),

    ``first`` = h1, ``between`` = g, ``second`` = h2, each a ``PiecewiseLinearMap`` (knots,
    values, slopes, quadratic tails as in ``feedback_loop``). ``compiled`` as in ``feedback_loop``."""
    args = [np.ascontiguousarray(drive, dtype=float)]
    for m in (first, between, second):
        args += [*_map_arrays(m), float(m.curvature_left), float(m.curvature_right)]
    return _recursion("cascade", _cascade_core, args, compiled)


def _map_arrays(m) -> list[np.ndarray]:
    """(knots, values, slopes) of a ``PiecewiseLinearMap`` as contiguous float arrays."""
    return [np.ascontiguousarray(part, dtype=float) for part in (m.breakpoints, m.values, m.slopes)]


def _recursion(name: str, core, args: list, compiled: bool | None) -> np.ndarray:
    """Run the recursion ``core(*args, y)`` whose output y has the length of ``args[0]``: its numba
    kernel ``name`` (``compiled`` as in ``feedback_loop``), or the core itself on lists."""
    kernel = _chosen(name, compiled)
    if kernel is not None:
        y = np.empty(args[0].size)
        kernel(*args, y)
        return y
    y = [0.0] * args[0].size
    core(*[a.tolist() if isinstance(a, np.ndarray) else a for a in args], y)
    return np.asarray(y, dtype=float)


def _cascade_core(drive, k1, v1, s1, l1, r1, kg, vg, sg, lg, rg, k2, v2, s2, l2, r2, y):
    """The recursion of ``storage_cascade``: each map as (knots, values, slopes, curvatures)."""
    x1, x2 = 0.0, 0.0
    for k in range(len(drive)):
        y[k] = x2
        outflow = _map_value(k2, v2, s2, l2, r2, x2)
        x1 = x1 + drive[k] - _map_value(k1, v1, s1, l1, r1, x1)
        x2 = x2 + _map_value(kg, vg, sg, lg, rg, x1) - outflow


def play(v: np.ndarray, half: float, initial: float, compiled: bool | None = None) -> np.ndarray:
    """The play operator's recursion z(k) = min(max(z(k-1), v(k) - half), v(k) + half), z(-1) = initial."""
    v = np.ascontiguousarray(v, dtype=float)
    kernel = _chosen("play", compiled)
    if kernel is not None:
        out = np.empty(v.size)
        kernel(v, float(half), float(initial), out)
        return out
    out = [0.0] * v.size
    _play_core(v.tolist(), float(half), float(initial), out)
    return np.asarray(out, dtype=float)


def _play_core(v, half, initial, out):
    z = initial
    for k in range(len(v)):
        value = v[k]
        if value - half > z:
            z = value - half
        elif value + half < z:
            z = value + half
        out[k] = z


def servo_loop(u: np.ndarray, y0: float, error_map, gravity_map, friction_map, coulomb: float = 0.0,
               compiled: bool | None = None) -> np.ndarray:
    """y(k) of a system inside its own position loop, from rest at y0 (y(0) = y(-1) = y0):

        y(k+1) = y(k) + w(k) + f(u(k) - y(k)) - h(y(k)) - phi(w(k)) - c sign(w(k)),    w(k) = y(k) - y(k-1),

    the non-linear feedback loop of paper 001 (eq. 2, G = q^-1 / (1 - q^-1)^2) with the map f
    on the loop error (``error_map``: the controller's gain and its saturation), h on the output
    (``gravity_map``) and phi on the output's difference (``friction_map``: viscous and Coulomb
    friction; c: the Coulomb friction's step at w = 0), each a ``PiecewiseLinearMap``. ``compiled``
    as in ``feedback_loop``."""
    args = [np.ascontiguousarray(u, dtype=float), float(y0), float(coulomb)]
    for m in (error_map, gravity_map, friction_map):
        args += _map_arrays(m)
    return _recursion("servo", _servo_core, args, compiled)


def _servo_core(u, y0, coulomb, fk, fv, fs, hk, hv, hs, pk, pv, ps, y):
    """The recursion of ``servo_loop``: each map as (knots, values, slopes); a run that leaves
    every finite bound stays there (inf), which the refinement rejects."""
    previous, current = y0, y0
    for k in range(len(u)):
        y[k] = current
        w = current - previous
        acc = (_map_value(fk, fv, fs, 0.0, 0.0, u[k] - current) - _map_value(hk, hv, hs, 0.0, 0.0, current)
               - _map_value(pk, pv, ps, 0.0, 0.0, w))
        if w > 0.0:
            acc -= coulomb
        elif w < 0.0:
            acc += coulomb
        previous = current
        current = current + w + acc
        if not abs(current) < 1e150:
            current = 1e150
            previous = 1e150


def physical_servo_loop(u: np.ndarray, y0: float, gain: float, torque_limit: float, gravity: float,
                        gravity_angle: float, viscous: float, coulomb: float,
                        compiled: bool | None = None) -> np.ndarray:
    """y(k) of ``servo_loop`` with its maps in their physical form, from rest at y0:

        w(k+1) = w(k) + sat_T(K (u(k) - y(k))) - G sin(y(k) - p) - B w(k) - C sign(w(k)),    y(k+1) = y(k) + w(k+1),

    a proportional controller of gain K saturating at the torque limit T, the gravity of a
    pendulum whose angle y is in radians (vanishing at y = p) and viscous (B) and Coulomb (C)
    friction, in units of the output per sample^2. ``compiled`` as in ``feedback_loop``."""
    args = [np.ascontiguousarray(u, dtype=float), float(y0), float(gain), float(torque_limit), float(gravity),
            float(gravity_angle), float(viscous), float(coulomb)]
    return _recursion("physical_servo", _physical_servo_core, args, compiled)


def _physical_servo_core(u, y0, gain, limit, gravity, angle, viscous, coulomb, y):
    """The recursion of ``physical_servo_loop`` (a run that leaves every finite bound stays there)."""
    current, w = y0, 0.0
    for k in range(len(u)):
        y[k] = current
        torque = min(max(gain * (u[k] - current), -limit), limit)
        acc = torque - gravity * math.sin(current - angle) - viscous * w
        if w > 0.0:
            acc -= coulomb
        elif w < 0.0:
            acc += coulomb
        w = w + acc
        current = current + w
        if not abs(current) < 1e150:
            current = 1e150
            w = 0.0
