"""The extension of ``periodic_disturbance``: the baseline plus sinusoids."""

from __future__ import annotations

import numpy as np

from ...identification.regression import solve_least_squares
from ...identification.simulation_error import refine, steady_state_filter
from ..hammerstein import HammersteinParameters
from .common import Context, ExtendedModel, NotFitted, order_details


def extend_periodic_disturbance(ctx: Context) -> ExtendedModel:
    """y = G[F(v)] + sum_i (c_i cos w_i k + s_i sin w_i k): the baseline plus sinusoids at the
    residual-spectrum lines, frequencies, amplitudes and the Hammerstein part refined together
    on the simulation error. With a separate validation record (no common time axis) the
    amplitudes and phases are re-estimated on it (the frequencies are kept)."""
    base, s, skip = ctx.baseline, ctx.split, ctx.skip
    freqs0 = ctx.lines.frequencies
    if freqs0.size == 0:
        raise NotFitted("no spectral line in the estimation residual")
    v, y = s.v_est, s.y_est
    params = HammersteinParameters(base)
    size, nl = params.size, freqs0.size
    eta = base.basis(v)
    k_est = np.arange(v.size)

    def waves(freqs: np.ndarray, k: np.ndarray) -> np.ndarray:
        return np.column_stack([f(w * k) for w in freqs for f in (np.cos, np.sin)])

    def simulate_theta(theta: np.ndarray) -> np.ndarray:
        m = params.unpack(theta[:size])
        freqs, amps = theta[size : size + nl], theta[size + nl :]
        return steady_state_filter(m.b, m.a, eta @ m.slopes + m.kappa) + waves(freqs, k_est) @ amps

    residual = y - base.simulate(v)
    amps0 = solve_least_squares(waves(freqs0, k_est)[skip:], residual[skip:])
    theta = refine(simulate_theta, np.concatenate([params.pack(base), freqs0, amps0]), y, 40, skip)
    model, freqs, amps = params.unpack(theta[:size]), theta[size : size + nl], theta[size + nl :]
    if s.continuous:
        k_val = np.arange(s.n_est, s.n_est + s.v_val.size)
        output = s.validation_output(model.simulate) + waves(freqs, k_val) @ amps
    else:
        x_val = s.validation_output(model.simulate)
        basis = waves(freqs, np.arange(s.v_val.size))
        output = x_val + basis @ solve_least_squares(basis, s.y_val - x_val)
    amplitudes = np.hypot(amps[0::2], amps[1::2])
    details = {"frequencies_rad_per_sample": freqs.tolist(), "amplitudes": amplitudes.tolist(),
               **order_details(model)}
    return ExtendedModel("periodic_disturbance", "hammerstein + sinusoids", output, details)
