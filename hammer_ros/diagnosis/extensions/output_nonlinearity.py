"""The extension of ``output_nonlinearity``: a map after the dynamics (Hammerstein-Wiener
or Wiener)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ...identification.piecewise_linear_ls import point_slope_basis, point_slope_map
from ...identification.regression import solve_least_squares
from ...identification.result import rms_error
from ...identification.simulation_error import refine, steady_state_filter
from ..hammerstein import HammersteinParameters, quantile_partition
from .common import Context, ExtendedModel, map_plot, order_details

OUTPUT_MAP_BREAKPOINTS = 6


def extend_output_nonlinearity(ctx: Context) -> ExtendedModel:
    """Hammerstein-Wiener y = N(G[F(v)]): N piecewise linear on quantiles of the baseline's
    output x, started from the least-squares fit of y on x, then everything refined on the
    simulation error (G's largest coefficient fixed, as in the baseline). A start of its own,
    which does not depend on the baseline: the Wiener model y = N(G[v]) (``Context.nested_wiener``,
    F linear), started from the best linear approximation and from the L-N-L fit's G1; where the
    output map is not invertible (a rectifier, a clamp) the Hammerstein baseline is a poor start
    and the Wiener fit is the one that finds the map. The one with the smaller simulation error
    on the estimation data is kept. Every fit run by run on a record of several runs (``Context``)."""
    hammerstein_wiener = _hammerstein_wiener(ctx)
    wiener = ctx.nested_wiener
    if isinstance(wiener, Exception):
        return hammerstein_wiener
    s, skip = ctx.split, ctx.skip
    if rms_error(s.y_est[skip:], ctx.estimation_simulation(hammerstein_wiener.simulate)[skip:]) <= wiener.rms:
        return hammerstein_wiener
    model = wiener.model
    x = ctx.estimation_simulation(model.intermediate)
    details = {"order": model.front.order, "delay": model.front.delay,
               "poles": [[float(p.real), float(p.imag)] for p in model.front.poles],
               "wiener": model.to_json((float(np.min(x)), float(np.max(x))))}
    maps = (map_plot("N (output map)", model.nonlinearity, x),)
    return ExtendedModel("output_nonlinearity", "wiener (L-N)",
                         s.validation_output(model.simulate), details, maps, model.simulate)


def _hammerstein_wiener(ctx: Context) -> ExtendedModel:
    """The Hammerstein-Wiener model from the baseline (``extend_output_nonlinearity``)."""
    base, s, skip = ctx.baseline, ctx.split, ctx.skip
    v, y = s.v_est, s.y_est
    x = ctx.estimation_simulation(base.simulate)
    partition = quantile_partition(x[skip:], OUTPUT_MAP_BREAKPOINTS)
    primary = max(1, partition.size // 2)
    zeta = point_slope_basis(x, partition, primary)
    init = solve_least_squares(np.column_stack([zeta, np.ones(x.size)])[skip:], y[skip:])
    params = HammersteinParameters(base)
    eta = base.basis(v)
    size = params.size

    def output_map(theta: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        return point_slope_map(partition, primary, theta[size:-1], float(theta[-1]))

    def simulate_theta(theta: np.ndarray) -> np.ndarray:
        m = params.unpack(theta[:size])
        inner = ctx.estimation_simulation(lambda w: steady_state_filter(m.b, m.a, w), eta @ m.slopes + m.kappa)
        return point_slope_basis(inner, partition, primary) @ theta[size:-1] + theta[-1]

    theta = refine(simulate_theta, np.concatenate([params.pack(base), init]), y, 40, skip)
    inner_model, n_map = params.unpack(theta[:size]), output_map(theta)

    def simulate(u: np.ndarray) -> np.ndarray:
        return n_map(inner_model.simulate(u))

    inner = ctx.estimation_simulation(inner_model.simulate)
    maps = (map_plot("F (input map)", inner_model.static, v), map_plot("N (output map)", n_map, inner))
    details = {"output_breakpoints": partition.tolist(), **order_details(inner_model)}
    return ExtendedModel("output_nonlinearity", "hammerstein-wiener", s.validation_output(simulate), details, maps,
                         simulate)
