"""The extension of ``periodic_disturbance``: the baseline plus sinusoids."""

from __future__ import annotations

import numpy as np

from ...identification.regression import solve_least_squares
from ...identification.runs import Runs, per_run, several
from ...identification.simulation_error import refine, steady_state_filter
from ..evidence import run_waves
from ..hammerstein import HammersteinModel, HammersteinParameters
from .common import Context, ExtendedModel, NotFitted, order_details


def extend_periodic_disturbance(ctx: Context) -> ExtendedModel:
    """y = G[F(v)] + sum_i (c_i cos w_i k + s_i sin w_i k): the baseline plus sinusoids at the
    residual-spectrum lines, frequencies, amplitudes and the Hammerstein part refined together
    on the simulation error. With a separate validation record (no common time axis) the
    amplitudes and phases are re-estimated on it (the frequencies are kept). With several runs a
    disturbance keeps its frequency and amplitude but has its own phase in every run
    (``_runs_fit``)."""
    base, s, skip = ctx.baseline, ctx.split, ctx.skip
    freqs0 = ctx.lines.frequencies
    if freqs0.size == 0:
        raise NotFitted("no spectral line in the estimation residual")
    if s.has_runs:
        return _runs_fit(ctx)
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
    return _extended(model, freqs, np.hypot(amps[0::2], amps[1::2]), output)


def _extended(model: HammersteinModel, freqs: np.ndarray, amplitudes: np.ndarray, output: np.ndarray) -> ExtendedModel:
    details = {"frequencies_rad_per_sample": freqs.tolist(), "amplitudes": amplitudes.tolist(), **order_details(model)}
    return ExtendedModel("periodic_disturbance", "hammerstein + sinusoids", output, details)


def run_sinusoids(freqs: np.ndarray, amplitudes: np.ndarray, phases: np.ndarray, runs: Runs) -> np.ndarray:
    """sum_i A_i cos(w_i k + phi_ir), k the sample within run r (``phases``: lines x runs)."""
    local = np.arange(runs.total) - np.repeat(np.asarray(runs.starts, dtype=int), runs.lengths)
    label = np.repeat(np.arange(runs.count), runs.lengths)
    return np.sum(amplitudes[:, None] * np.cos(freqs[:, None] * local[None, :] + phases[:, label]), axis=0)


def run_phases(freqs: np.ndarray, residual: np.ndarray, runs: Runs, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(amplitude per line, phase per line and run) of the least-squares sinusoids of ``residual``
    (its ``rows``) with every run's own amplitude and phase: c cos + s sin = A cos(w k + phi),
    A the line's mean over the runs."""
    basis = run_waves(freqs, runs)
    cs = solve_least_squares(basis[rows], residual[rows]).reshape(freqs.size, runs.count, 2)
    return np.mean(np.hypot(cs[..., 0], cs[..., 1]), axis=1), np.arctan2(-cs[..., 1], cs[..., 0])


def _runs_fit(ctx: Context) -> ExtendedModel:
    """The extension on a split of runs: every estimation run simulated on its own from rest at its
    first input, the sinusoids' frequencies and amplitudes shared by the runs and a phase per run,
    all refined with the Hammerstein part on the simulation error; on every validation run the
    phases are fitted to its residual (frequencies and amplitudes kept)."""
    base, s = ctx.baseline, ctx.split
    runs = s.est_runs
    freqs0 = ctx.lines.frequencies
    params = HammersteinParameters(base)
    size, nl = params.size, freqs0.size
    eta = base.basis(s.v_est)

    def simulate_theta(theta: np.ndarray) -> np.ndarray:
        m = params.unpack(theta[:size])
        freqs, amps = theta[size : size + nl], theta[size + nl : size + 2 * nl]
        linear = per_run(lambda x: steady_state_filter(m.b, m.a, x), eta @ m.slopes + m.kappa, several(runs))
        return linear + run_sinusoids(freqs, amps, theta[size + 2 * nl :].reshape(nl, runs.count), runs)

    rows = runs.rows(min(ctx.skip, int(runs.lengths.min()) // 5))
    amps0, phases0 = run_phases(freqs0, s.y_est - base.simulate_runs(s.v_est, several(runs)), runs, rows)
    theta = refine(simulate_theta, np.concatenate([params.pack(base), freqs0, amps0, phases0.ravel()]), s.y_est, 40)
    model, freqs, amps = params.unpack(theta[:size]), theta[size : size + nl], theta[size + nl : size + 2 * nl]
    x_val = s.validation_output(model.simulate)
    _, phases = run_phases(freqs, s.y_val - x_val, s.val_runs, np.arange(s.v_val.size))
    return _extended(model, freqs, np.abs(amps), x_val + run_sinusoids(freqs, amps, phases, s.val_runs))
