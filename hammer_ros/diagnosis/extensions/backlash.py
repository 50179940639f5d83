"""The extension of ``backlash``: a play operator before the Hammerstein model."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from ...errors import IdentificationError
from ...identification.piecewise_linear_ls import drop_empty_intervals, point_slope_basis
from ...identification.regression import solve_least_squares
from ...identification.simulate import play_operator
from ...identification.simulation_error import steady_state_filter
from ..hammerstein import fit_hammerstein
from .common import Context, ExtendedModel, NotFitted, map_plot, order_details


def _same_levels(v: np.ndarray, knots: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Breakpoints for a signal z derived from v: the quantiles of z at the levels (empirical
    CDF of v) where the baseline's breakpoints sit, so that the map keeps its layout."""
    levels = np.clip(np.mean(np.asarray(v)[:, None] <= np.asarray(knots)[None, :], axis=0), 0.0, 1.0)
    return drop_empty_intervals(z, np.unique(np.quantile(z, levels)))


def extend_backlash(ctx: Context) -> ExtendedModel:
    """y = G[F(P_w(v))]: the play width w from a grid and a bounded scalar search on the
    simulation error with G fixed at the baseline's (F re-fitted by least squares for each w),
    then the Hammerstein model on P_w(v) refined as the baseline is. Every run on its own on a
    record of several runs (the play operator and G from rest at the run's first input)."""
    base, s, skip = ctx.baseline, ctx.split, ctx.skip
    v, y = s.v_est, s.y_est

    def played(width: float) -> np.ndarray:
        return ctx.estimation_simulation(lambda u: play_operator(u, width))

    def cost(width: float) -> float:
        z = played(width)
        try:
            partition = _same_levels(v, base.partition, z)
        except IdentificationError:
            return np.inf
        columns = np.column_stack([point_slope_basis(z, partition, max(1, partition.size // 2)), np.ones(z.size)])
        filtered = ctx.estimation_simulation(
            lambda part: np.column_stack([steady_state_filter(base.b, base.a, c) for c in part.T]), columns)
        theta = solve_least_squares(filtered[skip:], y[skip:])
        return float(np.sum((y[skip:] - filtered[skip:] @ theta) ** 2))

    scale = float(np.std(v))
    grid = scale * np.array([0.0, 0.03, 0.07, 0.12, 0.2, 0.3, 0.42, 0.56, 0.75, 1.0, 1.3])
    costs = [cost(w) for w in grid]
    i = int(np.argmin(costs))
    if i == 0:
        raise NotFitted("the best play width is zero: no backlash in the estimation data")
    lo, hi = grid[i - 1], grid[min(i + 1, grid.size - 1)]
    found = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 0.01 * scale, "maxiter": 12})
    width = float(found.x) if found.fun < costs[i] else float(grid[i])
    z = played(width)
    model = fit_hammerstein(z, y, base.order, base.delay, _same_levels(v, base.partition, z), runs=ctx.runs)

    def simulate(u: np.ndarray) -> np.ndarray:
        return model.simulate(play_operator(u, width))

    details = {"width": width, **order_details(model)}
    maps = (map_plot("F after the play operator", model.static, z),)
    return ExtendedModel("backlash", "play operator + hammerstein", s.validation_output(simulate), details, maps,
                         simulate)
