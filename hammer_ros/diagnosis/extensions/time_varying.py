"""The extension of ``time_varying``: sliding-window re-identification."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import signal

from ...identification.simulation_error import refine, steady_state_filter
from ..hammerstein import HammersteinModel, transient_samples
from .common import Context, ExtendedModel, NotFitted


def extend_time_varying(ctx: Context) -> ExtendedModel:
    """Sliding-window re-identification: the validation record is simulated block by block,
    each block with the baseline re-fitted (A, B and the map's offset; the map's shape kept)
    on the last ``window`` measured samples before it, the state carried over from the
    simulated output. Reports the window test's change point or drift rate. With several
    validation runs every run is simulated on its own from rest (``Split.validation_output``),
    and its windows and carried state stay inside it."""
    base, s = ctx.baseline, ctx.split
    v_all = s.v_all if s.continuous else s.v_val
    y_all = s.y_all if s.continuous else s.y_val
    start = s.n_est if s.continuous else 0
    n_val = s.v_val.size
    runs = s.val_runs
    free = base.order + np.count_nonzero(base.b) + 1
    window = int(np.clip(int(runs.lengths.max()) // 3, 30 * free, 6000))
    window = min(window, start) if start else window
    if window < 20 * free:
        raise NotFitted(f"windows of the baseline's {free} parameters need {20 * free} samples; there are {window}")
    if window >= int(runs.lengths.max()) and runs.count > 1:
        raise NotFitted(f"windows of {window} samples do not fit in validation runs of {int(runs.lengths.max())}")
    block = max(window // 4, 10)
    u_all = base.static(v_all)
    out = s.validation_output(base.simulate)  # kept until a first window of measured data exists
    history_y = base.simulate(v_all[:start]) if start else np.zeros(0)
    # a window reaches back to the record's start (one run), else to its own run's first sample
    segments = [(start, start + n_val, 0)] if runs.count == 1 else [(a, int(b), a) for a, b in zip(runs.starts,
                                                                                                  runs.ends)]
    for first, stop, floor in segments:
        model = base  # every run's re-fits start from the baseline
        for k0 in range(first, stop, block):
            if k0 - window < floor:
                continue
            k1 = min(k0 + block, stop)
            model = _refit_window(model, base, u_all[k0 - window : k0], y_all[k0 - window : k0])
            y_past = np.concatenate([history_y, out[: k0 - start]]) if runs.count == 1 else out[floor:k0]
            out[k0 - start : k1 - start] = _continue(model, u_all + (model.kappa - base.kappa), y_past, k0, k1)
    details = {"window": window, "block": block}
    if ctx.windows.change_point is not None:
        details["change_point"] = int(ctx.windows.change_point)
    if ctx.windows.drift_per_sample is not None:
        details["drift_per_1000_samples"] = 1000.0 * float(ctx.windows.drift_per_sample)
    return ExtendedModel("time_varying", "hammerstein, sliding-window re-identification", out, details)


def _refit_window(model: HammersteinModel, base: HammersteinModel, u: np.ndarray, y: np.ndarray) -> HammersteinModel:
    """A, B and the offset of F re-fitted on the simulation error over one window, from
    ``model`` (``u`` is the baseline map's output; the window's simulation starts at rest)."""
    d = model.delay
    n, nb = model.order, model.b.size - d

    def unpack(theta: np.ndarray) -> HammersteinModel:
        b = np.concatenate([np.zeros(d), theta[n : n + nb]])
        return replace(model, a=np.concatenate([[1.0], theta[:n]]), b=b, kappa=base.kappa + float(theta[-1]))

    def simulate(theta: np.ndarray) -> np.ndarray:
        m = unpack(theta)
        return steady_state_filter(m.b, m.a, u + theta[-1])

    theta0 = np.concatenate([model.a[1:], model.b[d:], [model.kappa - base.kappa]])
    skip = transient_samples(model.linear.poles, u.size)
    refined = unpack(refine(simulate, theta0, y, 15, skip))
    return refined if refined.linear.is_stable() else model


def _continue(model: HammersteinModel, x: np.ndarray, y_past: np.ndarray, k0: int, k1: int) -> np.ndarray:
    """The linear block's response over samples k0..k1-1 to x, continuing from the past
    outputs y_past (which end at sample k0 - 1)."""
    memory = max(model.a.size, model.b.size)
    if k0 < memory or y_past.size < memory:
        return steady_state_filter(model.b, model.a, x[k0:k1])
    zi = signal.lfiltic(model.b, model.a, y_past[::-1][:memory], x[k0 - memory : k0][::-1])
    return signal.lfilter(model.b, model.a, x[k0:k1], zi=zi)[0]
