"""The extension of ``unmodeled_dynamics``: the Hammerstein model of a higher order."""

from __future__ import annotations

import numpy as np

from ...errors import IdentificationError
from ...identification.runs import several
from ..hammerstein import SELECTION_SAMPLES, bic, fit_hammerstein, refine_hammerstein
from ..split import runs_tail
from .common import Context, ExtendedModel, NotFitted, order_details

MAX_EXTRA_ORDER = 4
MAX_ORDER = 8


def extend_unmodeled_dynamics(ctx: Context) -> ExtendedModel:
    """Orders n+1 .. n+4 (at most 8) on the baseline's partition, upwards until two orders in a
    row do not improve; the one with the smallest simulation-error BIC on the estimation data
    (its last SELECTION_SAMPLES samples; the chosen model is then refined on all of them),
    if it beats the baseline's. Besides the PLLS start, each order is started from the
    baseline's denominator times a few extra modes (``_extra_modes``): a slow or a resonant
    mode the equation-error start tends to miss. With several estimation runs every fit and
    simulation takes each run on its own, from rest at its first input."""
    base, s = ctx.baseline, ctx.split
    tail, runs = runs_tail(several(s.runs_est), s.n_est, SELECTION_SAMPLES)
    v, y = s.v_est[tail], s.y_est[tail]
    skip = min(ctx.skip, v.size // 5)
    best, best_score = None, bic(y[skip:], base.simulate_runs(v, runs)[skip:], base.parameter_count())
    misses = 0
    for order in range(base.order + 1, min(base.order + MAX_EXTRA_ORDER, MAX_ORDER) + 1):
        starts = tuple(np.convolve(base.a, extra) for extra in _extra_modes(order - base.order))
        try:
            model = fit_hammerstein(v, y, order, base.delay, base.partition, free_knots=False, denominators=starts,
                                    runs=runs)
        except (IdentificationError, np.linalg.LinAlgError, ValueError):
            continue
        score = bic(y[skip:], model.simulate_runs(v, runs)[skip:], model.parameter_count())
        if score < best_score:
            best, best_score, misses = model, score, 0
        else:
            misses += 1
            if misses == 2:  # two orders in a row without improvement: stop
                break
    if best is None:
        raise NotFitted(f"no order from {base.order + 1} up lowers the baseline's simulation-error BIC")
    if v.size < s.n_est:
        best = refine_hammerstein(best, s.v_est, s.y_est, iterations=15, runs=several(s.runs_est))
    return ExtendedModel("unmodeled_dynamics", f"hammerstein order {best.order}", s.validation_output(best.simulate),
                         order_details(best), simulate=best.simulate)


def _extra_modes(count: int) -> list[np.ndarray]:
    """Denominator factors of degree ``count`` (1 or 2; none above): real poles from fast to
    slow, lightly damped pairs across the band."""
    if count == 1:
        return [np.array([1.0, -p]) for p in (0.6, 0.9, 0.97)]
    if count == 2:
        pairs = [np.real(np.poly([0.93 * np.exp(1j * w), 0.93 * np.exp(-1j * w)])) for w in (0.3, 0.8, 1.5, 2.3)]
        return [*pairs, np.real(np.poly([0.6, 0.95]))]
    return []
