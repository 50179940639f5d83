"""Static (memoryless) maps u = F(v): the identified nonlinearities and their JSON form.

Each map is a small frozen dataclass that is callable on numpy arrays and serialises to the
``nonlinearity`` object of the CLI contract (kind, coefficients, breakpoints, points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class PolynomialMap:
    """F(v) = c_0 + c_1 v + ... + c_p v^p (coefficients in ascending powers, from v^0)."""

    coefficients: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "coefficients", np.asarray(self.coefficients, dtype=float))

    def __call__(self, v: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(np.asarray(v, dtype=float), self.coefficients)

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
    extended beyond the outer knots with the slopes ``slope_left`` and ``slope_right``."""

    breakpoints: np.ndarray
    values: np.ndarray
    slope_left: float
    slope_right: float

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
        out = np.where(v < c[0], f[0] + self.slope_left * (v - c[0]), out)
        return np.where(v > c[-1], f[-1] + self.slope_right * (v - c[-1]), out)

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
