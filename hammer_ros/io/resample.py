"""A CSV/NPZ time column with uneven steps, put onto a uniform grid (or refused with the reason).

With h the median step of ``t`` over all runs (each run's time may restart), a record whose
steps all lie within ``EVEN_JITTER`` h of h is evenly sampled and left as it is. Otherwise
every run is resampled onto t_0 + k h (t_0 its first stamp, up to its last): the response y
interpolated linearly, the input v (and a reference r) held at its last sample at or before
the grid point (zero-order hold: a command holds its value until the next one). Refused when
t does not increase within a run, or when a run has a gap longer than ``MAX_GAP_STEPS`` h
(a silence, not jitter: cut the record into runs with a ``run`` column).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import UsageError
from ..identification.runs import Runs
from ..identification.trust import ModelWarning

EVEN_JITTER = 0.01  # steps within 1 % of the median step are evenly sampled
MAX_GAP_STEPS = 5.0  # a step longer than this many median steps is a gap


@dataclass(frozen=True, eq=False)
class Resampled:
    """The signals on the uniform grid ``t`` (``r`` None when there is no reference), their runs
    (None: one run) and the ``irregular_sampling`` warning (None when t was even)."""

    t: np.ndarray
    v: np.ndarray
    y: np.ndarray
    r: np.ndarray | None
    runs: Runs | None
    warning: ModelWarning | None


def uniform_grid(source: str, t: np.ndarray, v: np.ndarray, y: np.ndarray, r: np.ndarray | None = None,
                 runs: Runs | None = None) -> Resampled:
    """The record on a uniform grid (module docstring); a UsageError naming ``source`` when t is too
    irregular."""
    t = np.asarray(t, dtype=float)
    parts = (runs or Runs.one(t.size)).slices()
    steps = [np.diff(t[part]) for part in parts]
    for part, dt in zip(parts, steps):
        if dt.size and not np.all(dt > 0):
            row = part.start + int(np.argmax(~(dt > 0))) + 1
            raise UsageError(f"{source}: column 't' does not increase at row {row + 1} ({t[row - 1]:g} -> {t[row]:g})")
    all_steps = np.concatenate(steps)
    if all_steps.size == 0:
        return Resampled(t, v, y, r, runs, None)
    h = float(np.median(all_steps))
    if np.max(np.abs(all_steps - h)) <= EVEN_JITTER * h:
        return Resampled(t, v, y, r, runs, None)
    for part, dt in zip(parts, steps):
        if dt.size and dt.max() > MAX_GAP_STEPS * h:
            row = part.start + int(np.argmax(dt)) + 1
            raise UsageError(f"{source}: column 't' has a gap of {dt.max():.4g} s ({dt.max() / h:.1f} median steps of "
                             f"{h:.4g} s) at row {row + 1}: too irregular to resample (split it into runs with a "
                             f"'run' column)")
    grids, vs, ys, rs = [], [], [], []
    for part in parts:
        tp = t[part]
        grid = tp[0] + h * np.arange(int(np.floor((tp[-1] - tp[0]) / h * (1 + 1e-9))) + 1)
        held = np.clip(np.searchsorted(tp, grid + 1e-9 * h, side="right") - 1, 0, tp.size - 1)
        grids.append(grid)
        vs.append(np.asarray(v)[part][held])
        ys.append(np.interp(grid, tp, np.asarray(y)[part]))
        if r is not None:
            rs.append(np.asarray(r)[part][held])
    lengths = [g.size for g in grids]
    warning = ModelWarning("irregular_sampling", f"{source}: 't' steps from {all_steps.min() * 1e3:.3g} to "
                                                 f"{all_steps.max() * 1e3:.3g} ms: resampled onto a uniform "
                                                 f"{h * 1e3:.3g} ms grid (output interpolated linearly, input held), "
                                                 f"{t.size} -> {sum(lengths)} samples")
    return Resampled(np.concatenate(grids), np.concatenate(vs), np.concatenate(ys),
                     None if r is None else np.concatenate(rs),
                     None if runs is None else Runs.from_lengths(lengths), warning)
