"""Two first-order storages in series, each with a level-dependent outflow: the non-linear
feedback of ``output_feedback`` when the fed-back level is not only the measured one.

Two tanks in cascade (each drains through its own outlet, Bernoulli: q = k sqrt(h)), two thermal
masses in series, a pressure vessel behind a reservoir: the second storage is filled by what
leaves the first, so its inflow is a static map of the first storage's level, which no output
feedback y = G[f(u) - h(y)] can express (h sees y only). The model, in discrete time:

    x1(k+1) = x1(k) + f(u(k)) - h1(x1(k))       the first storage, filled through f
    x2(k+1) = x2(k) + g(x1(k+1)) - h2(x2(k))    the second, filled by g of the first level
    y(k) = x2(k)

f, h1, g and h2 continuous piecewise linear (paper 001's point-slope form, eqs. 5-11). It is the
series connection of two of paper 001's loops (eq. 2 with G = q^-1 / (1 - q^-1), first order)
with the map g *between* them, which also carries a saturation of the first level (an overflow
that caps what the first storage can pass on). Linear maps give the linear cascade
G(q) = g' q^-1 / ((1 - p1 q^-1)(1 - p2 q^-1)), p_i = 1 - h_i': a second-order block with real
poles, which is where the starts come from.

The representation: x1's scale is set by the start (the knots of h1 and g are fixed quantiles of
the start's x1), h1 and h2 vanish at their primary knot (their offsets are f's and g's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import IdentificationError
from ..identification.compiled_loops import storage_cascade
from ..identification.piecewise_linear_ls import point_slope_basis, point_slope_map
from ..identification.regression import solve_least_squares
from ..identification.simulation_error import steady_state_filter
from ..identification.static_maps import PiecewiseLinearMap, with_tails
from .hammerstein import HammersteinModel, quantile_partition

Simulator = Callable[[np.ndarray], np.ndarray]
LEVEL_BREAKPOINTS = 3  # breakpoints of h1, g (on the first level) and h2 (on the output)
REST_LEVELS = 9  # constant inputs at which ``plausible_rest`` looks at the rest state
MIN_POLE, MAX_POLE = 0.05, 0.9995  # the real poles a storage can have (leak 1 - p per sample)


@dataclass(frozen=True, eq=False)
class CascadeLayout:
    """theta <-> (f, h1, g, h2) on fixed partitions: f on ``f_part`` (the baseline's), h1 and g
    on ``x_part`` (the first level), h2 on ``y_part`` (the output); primary indices in the
    middle. theta = [slopes of f, f(c_r), slopes of h1, slopes of g, g(x_r), slopes of h2]."""

    f_part: np.ndarray
    x_part: np.ndarray
    y_part: np.ndarray
    delay: int

    @staticmethod
    def primary(partition: np.ndarray) -> int:
        return max(1, partition.size // 2)

    def sizes(self) -> tuple[int, int, int, int]:
        """The lengths of theta's parts for f, h1, g and h2."""
        return self.f_part.size + 2, self.x_part.size + 1, self.x_part.size + 2, self.y_part.size + 1

    def maps(self, theta: np.ndarray) -> tuple[PiecewiseLinearMap, ...]:
        """(f, h1, g, h2) of theta."""
        nf, n1, ng, _ = self.sizes()
        parts = np.split(np.asarray(theta, dtype=float), np.cumsum([nf, n1, ng]))
        f_map = point_slope_map(self.f_part, self.primary(self.f_part), parts[0][:-1], float(parts[0][-1]))
        h1 = point_slope_map(self.x_part, self.primary(self.x_part), parts[1], 0.0)
        g = point_slope_map(self.x_part, self.primary(self.x_part), parts[2][:-1], float(parts[2][-1]))
        h2 = point_slope_map(self.y_part, self.primary(self.y_part), parts[3], 0.0)
        return f_map, h1, g, h2

    def pack(self, f_map: PiecewiseLinearMap, h1: PiecewiseLinearMap, g: PiecewiseLinearMap,
             h2: PiecewiseLinearMap) -> np.ndarray:
        """theta of maps already on this layout's partitions (h1, h2 zero at their primary knot)."""
        def value_at_primary(m: PiecewiseLinearMap, part: np.ndarray) -> float:
            return float(m(np.array([part[self.primary(part) - 1]]))[0])
        return np.concatenate([f_map.slopes, [value_at_primary(f_map, self.f_part)], h1.slopes, g.slopes,
                               [value_at_primary(g, self.x_part)], h2.slopes])

    def drive(self, v: np.ndarray, f_map: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """f(v) delayed by ``delay`` - 1 samples (the cascade itself delays by one)."""
        drive = np.asarray(f_map(v), dtype=float)
        shift = self.delay - 1
        return np.concatenate([np.full(shift, drive[0]), drive[: drive.size - shift]]) if shift > 0 else drive

    def simulate(self, theta: np.ndarray, v: np.ndarray, level: float, preroll: int,
                 tails: tuple | None = None) -> np.ndarray:
        """The cascade's output for v, started at rest at the constant input ``level`` (``preroll``
        samples of it simulated first from empty storages and dropped); ``tails``: (v range, f
        tails, y range, h2 tails) of ``with_tails`` for the input map f and the output's outflow h2."""
        f_map, h1, g, h2 = self.maps(theta)
        if tails is not None:
            f_map, h2 = with_tails(f_map, *tails[0], *tails[1]), with_tails(h2, *tails[2], *tails[3])
        drive = self.drive(np.concatenate([np.full(preroll, level), v]), f_map)
        return storage_cascade(drive, h1, g, h2)[preroll:]

    def runner(self, v: np.ndarray, preroll: int) -> Callable[[np.ndarray], np.ndarray]:
        """[level, theta] -> the output for v (the refinement's inner loop)."""
        return lambda extended: self.simulate(extended[1:], v, extended[0], preroll)


def linear_cascade_start(base: HammersteinModel, f_part: np.ndarray, poles: tuple[float, float],
                         v: np.ndarray, delay: int) -> tuple[CascadeLayout, np.ndarray]:
    """(layout, theta) of the linear cascade with real poles (p1, p2), first storage first, and
    the baseline's static behaviour: f fills the first storage so that its level at rest is the
    baseline's steady output G(1) F(v), h_i(x) = (1 - p_i)(x - c_i), and g(x) = (1 - p2)(x - c_y)
    passes that level on with unit gain (x2 = x1 at rest)."""
    p1, p2 = poles
    steady = float(np.sum(base.b) / np.sum(base.a)) * base.static(v)
    r = CascadeLayout.primary(f_part)
    coefficients = solve_least_squares(np.column_stack([point_slope_basis(v, f_part, r), np.ones(v.size)]), steady)
    first_level = steady_state_filter(np.array([0.0, 1.0 - p1]), np.array([1.0, -p1]), steady)
    x_part = quantile_partition(first_level, LEVEL_BREAKPOINTS)
    y_part = quantile_partition(steady, LEVEL_BREAKPOINTS)
    layout = CascadeLayout(f_part, x_part, y_part, delay)
    x_c = x_part[layout.primary(x_part) - 1]
    y_c = y_part[layout.primary(y_part) - 1]

    def linear(part: np.ndarray, slope: float, value: float) -> PiecewiseLinearMap:
        return point_slope_map(part, layout.primary(part), np.full(part.size + 1, slope), value)

    f_map = point_slope_map(f_part, r, (1.0 - p1) * coefficients[:-1], (1.0 - p1) * (coefficients[-1] - x_c))
    theta = layout.pack(f_map, linear(x_part, 1.0 - p1, 0.0), linear(x_part, 1.0 - p2, (1.0 - p2) * (x_c - y_c)),
                        linear(y_part, 1.0 - p2, 0.0))
    return layout, theta


def storage_poles(poles: np.ndarray) -> tuple[float, float] | None:
    """The two slowest poles of the baseline's block as storages' real poles, slowest first (a
    complex pole counts with its radius), clipped to (MIN_POLE, MAX_POLE); None below order 2.
    A block of higher order starts the cascade from its dominant pair (the faster poles of an
    actuator or a sensor are left to the storages' maps)."""
    if np.size(poles) < 2:
        return None
    radii = np.sort(np.clip(np.where(np.abs(np.imag(poles)) > 1e-9, np.abs(poles), np.real(poles)),
                            MIN_POLE, MAX_POLE))[::-1]
    return float(radii[0]), float(radii[1])


def plausible_rest(layout: CascadeLayout, theta: np.ndarray, v: np.ndarray, y: np.ndarray, preroll: int) -> bool:
    """Whether the cascade's rest states for REST_LEVELS constant inputs across the range of v
    lie within the measured output range widened by its span on each side: a model whose
    equilibrium for an input the record contains is far from anything measured (a storage
    that drains without bound, because the record never settles there) is not kept, however
    well it follows the record."""
    grid = np.linspace(float(np.min(v)), float(np.max(v)), REST_LEVELS)
    rest = np.array([layout.simulate(theta, np.full(1, u0), u0, preroll)[0] for u0 in grid])
    span = float(np.ptp(y))
    return bool(np.all(np.isfinite(rest)) and np.all(rest >= np.min(y) - span) and np.all(rest <= np.max(y) + span))


def random_storage_poles(rng: np.random.Generator, poles: tuple[float, float]) -> tuple[float, float]:
    """The poles with their time constants scaled by exp(N(0, 0.5)), in random order."""
    moved = [float(np.clip(p ** np.exp(0.5 * rng.standard_normal()), MIN_POLE, MAX_POLE)) for p in poles]
    return (moved[0], moved[1]) if rng.random() < 0.5 else (moved[1], moved[0])


def cascade_starts(base: HammersteinModel, f_part: np.ndarray, v: np.ndarray, level: float, preroll: int,
                   delay: int, random_starts: int) -> list[tuple[CascadeLayout, Simulator, np.ndarray]]:
    """The starts of the cascade as (layout, runner of [initial level, theta] on v, [level, theta]):
    the baseline's two slowest poles (``storage_poles``) in both orders, then ``random_starts``
    moved at random (``random_storage_poles``), each a ``linear_cascade_start`` with its own knots
    of x1; none below order 2."""
    poles = storage_poles(base.linear.poles)
    if poles is None:
        return []
    rng = np.random.default_rng(0)
    starts = []
    for pair in [poles, poles[::-1]] + [random_storage_poles(rng, poles) for _ in range(random_starts)]:
        try:
            layout, theta = linear_cascade_start(base, f_part, pair, v, delay)
        except (IdentificationError, np.linalg.LinAlgError, ValueError):
            continue
        starts.append((layout, layout.runner(v, preroll), np.concatenate([[level], theta])))
    return starts
