"""Static (memoryless) maps u = F(v): the identified nonlinearities and their JSON form.

Each map is a small frozen dataclass that is callable on numpy arrays and serialises to the
``nonlinearity`` object of the CLI contract (kind, coefficients, breakpoints, points).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True, eq=False)
class PolynomialMap:
    """F(v) = c_0 + c_1 v + ... + c_p v^p (coefficients in ascending powers, from v^0)."""

    coefficients: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "coefficients", np.asarray(self.coefficients, dtype=float))

    def __call__(self, v: np.ndarray) -> np.ndarray:
        """F(v) by Horner's rule, c_p v + c_(p-1), times v, plus c_(p-2), ..., in place (the same
        operations as np.polynomial.polynomial.polyval without its temporaries)."""
        v = np.asarray(v, dtype=float)
        constant, *higher = self.coefficients.tolist()
        if not higher:
            return np.full(v.shape, constant)[()]
        out = higher.pop() * v
        for coefficient in reversed(higher):
            out += coefficient
            out *= v
        out += constant
        return out[()]

    def to_json(self, sample_range: tuple[float, float] | None = None) -> dict:
        lo, hi = sample_range or (-1.0, 1.0)
        grid = np.linspace(lo, hi, 41)
        return {
            "kind": "polynomial",
            "coefficients": self.coefficients.tolist(),
            "points": np.column_stack([grid, self(grid)]).tolist(),
        }


@dataclass(frozen=True, eq=False)
class PiecewiseLinearMap:
    """Continuous piecewise-linear map through the knots (breakpoints[i], values[i]),
    extended beyond the outer knots with the slopes ``slope_left`` and ``slope_right`` plus, when
    given, a quadratic tail: f(c_p) + slope_right (v - c_p) + curvature_right (v - c_p)^2 beyond
    the last knot (and the same on the left), held constant beyond the quadratic's vertex (the
    tail stays monotone): the three ways a map continues beyond its data (the last slope, a
    constant = zero outer slope, a low-order polynomial tail; ``with_tails``)."""

    breakpoints: np.ndarray
    values: np.ndarray
    slope_left: float
    slope_right: float
    curvature_left: float = 0.0
    curvature_right: float = 0.0

    def __post_init__(self) -> None:
        c = np.atleast_1d(np.asarray(self.breakpoints, dtype=float))
        f = np.atleast_1d(np.asarray(self.values, dtype=float))
        if c.size == 0 or c.size != f.size or np.any(np.diff(c) <= 0):
            raise ValueError("breakpoints must be strictly increasing, one value each")
        object.__setattr__(self, "breakpoints", c)
        object.__setattr__(self, "values", f)

    def __call__(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        c, f = self.breakpoints, self.values
        out = np.interp(v, c, f)
        d = _up_to_vertex(np.minimum(v - c[0], 0.0), self.slope_left, self.curvature_left, -1.0)
        out = np.where(v < c[0], f[0] + self.slope_left * d + self.curvature_left * d * d, out)
        d = _up_to_vertex(np.maximum(v - c[-1], 0.0), self.slope_right, self.curvature_right, 1.0)
        return np.where(v > c[-1], f[-1] + self.slope_right * d + self.curvature_right * d * d, out)

    @property
    def slopes(self) -> np.ndarray:
        """Slope on each of the len(breakpoints) + 1 intervals, left to right."""
        inner = np.diff(self.values) / np.diff(self.breakpoints)
        return np.concatenate([[self.slope_left], inner, [self.slope_right]])

    def to_json(self, sample_range: tuple[float, float] | None = None) -> dict:
        c = self.breakpoints
        lo, hi = sample_range or (c[0] - 1.0, c[-1] + 1.0)
        u = np.concatenate([[min(lo, c[0])], c, [max(hi, c[-1])]])
        return {
            "kind": "piecewise_linear",
            "breakpoints": c.tolist(),
            "slopes": self.slopes.tolist(),
            "points": np.column_stack([u, self(u)]).tolist(),
        }


@dataclass(frozen=True, eq=False)
class NonparametricMap:
    """A map known only at points (u_i, F(u_i)), interpolated linearly, held flat outside."""

    u: np.ndarray
    f: np.ndarray

    def __post_init__(self) -> None:
        u = np.asarray(self.u, dtype=float)
        f = np.asarray(self.f, dtype=float)
        order = np.argsort(u, kind="stable")
        object.__setattr__(self, "u", u[order])
        object.__setattr__(self, "f", f[order])

    def __call__(self, v: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(v, dtype=float), self.u, self.f)

    def to_json(self, sample_range: tuple[float, float] | None = None) -> dict:
        return {"kind": "nonparametric", "points": np.column_stack([self.u, self.f]).tolist()}


TAILS = ("slope", "constant", "polynomial")


def _up_to_vertex(d: np.ndarray, slope: float, curvature: float, side: float) -> np.ndarray:
    """The distance d beyond an outer knot (sign ``side``), stopped at the vertex of the tail
    slope d + curvature d^2 when the vertex lies on that side."""
    if curvature == 0.0:
        return d
    vertex = -slope / (2.0 * curvature)
    return np.where(side * (d - vertex) > 0.0, vertex, d) if side * vertex >= 0.0 else d


def with_tails(fmap: PiecewiseLinearMap, lo: float, hi: float, left: str = "slope",
               right: str = "slope") -> PiecewiseLinearMap:
    """``fmap`` on its data range [lo, hi] (extended to the outer knots), continued beyond it as
    ``left`` / ``right``, each one of TAILS: ``slope``, the outer slope (fmap itself);
    ``constant``, held at its value at the edge (a saturation); ``polynomial``, a quadratic
    whose slope keeps changing outwards at the rate between the two outer intervals (the change
    of slope over the distance between their midpoints). Knots are added at the edges."""
    for tail in (left, right):
        if tail not in TAILS:
            raise ValueError(f"tail must be one of {TAILS} (got {tail!r})")
    c, s = fmap.breakpoints, fmap.slopes
    lo, hi = min(float(lo), float(c[0])), max(float(hi), float(c[-1]))
    knots = np.concatenate([[lo] if lo < c[0] else [], c, [hi] if hi > c[-1] else []])
    slopes = np.concatenate([[s[0]] if lo < c[0] else [], s, [s[-1]] if hi > c[-1] else []])
    values = fmap(knots)
    curvature = [0.0, 0.0]
    if knots.size >= 3:
        mid = 0.5 * (knots[1:] + knots[:-1])  # midpoints of the inner intervals
        curvature = [0.5 * (slopes[2] - slopes[1]) / (mid[1] - mid[0]),
                     0.5 * (slopes[-2] - slopes[-3]) / (mid[-1] - mid[-2])]
    if left == "constant":
        slopes[0] = 0.0
    if right == "constant":
        slopes[-1] = 0.0
    return PiecewiseLinearMap(knots, values, float(slopes[0]), float(slopes[-1]),
                              curvature[0] if left == "polynomial" else 0.0,
                              curvature[1] if right == "polynomial" else 0.0)


@dataclass(frozen=True)
class MapParameters:
    """A static map's free parameters and how to rebuild the map from them."""

    size: int
    pack: Callable[[object], np.ndarray]
    unpack: Callable[[np.ndarray], object]


def map_parameters(m: object) -> MapParameters:
    """The free parameters of a map (polynomial: its coefficients; piecewise linear: the knot values and
    the two outer slopes, breakpoints kept; nonparametric: its values) and how to rebuild it: what
    ``refinement`` refines and ``uncertainty`` gives the covariance of. Every such map is linear in them."""
    if isinstance(m, PolynomialMap):
        return MapParameters(m.coefficients.size, lambda x: x.coefficients, PolynomialMap)
    if isinstance(m, PiecewiseLinearMap):
        n = m.values.size

        def unpack(t: np.ndarray) -> PiecewiseLinearMap:
            return replace(m, values=t[:n], slope_left=float(t[n]), slope_right=float(t[n + 1]))

        return MapParameters(n + 2, lambda x: np.concatenate([x.values, [x.slope_left, x.slope_right]]), unpack)
    if isinstance(m, NonparametricMap):
        return MapParameters(m.f.size, lambda x: x.f, lambda t: NonparametricMap(m.u, t))
    raise TypeError(f"no parameters for a {type(m).__name__}")
