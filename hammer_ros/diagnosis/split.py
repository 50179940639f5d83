"""Estimation and validation data, and the free-run simulation of a model on the validation part."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize_scalar

from ..errors import UsageError
from ..identification.instrumental import (
    REFERENCE_LAGS,
    check_reference,
    projection_coefficients,
    projection_columns,
)
from ..identification.regression import delayed

MIN_SAMPLES = 60
INITIAL_SAMPLES = 3  # measured outputs averaged for the operating point a separate record starts at
REST_SAMPLES = 1000  # constant-input samples after which a model is taken to be at rest


@dataclass(frozen=True, eq=False)
class Split:
    """(v_est, y_est) to fit on, (v_val, y_val) to validate on. ``continuous``: the validation
    samples follow the estimation samples in time (one record split in two), so a model is
    simulated over both and its validation output continues from its own state; otherwise
    (a separate validation record) the simulation starts at rest at v_val(0)."""

    v_est: np.ndarray
    y_est: np.ndarray
    v_val: np.ndarray
    y_val: np.ndarray
    continuous: bool
    judged: np.ndarray | None = None  # the validation samples a model is judged on (None: all; ``coverage``)
    note: str = ""  # how the record was split, in plain words (``auto_split``)
    r_est: np.ndarray | None = None  # closed loop: the external reference over each part (None: open loop)
    r_val: np.ndarray | None = None

    @property
    def judged_rows(self) -> np.ndarray:
        """Indices of the validation samples a model is judged on."""
        return np.arange(self.v_val.size) if self.judged is None else np.flatnonzero(self.judged)

    def validation_rms(self, output: np.ndarray) -> float:
        """RMS of y_val - output over the judged validation samples."""
        rows = self.judged_rows
        return float(np.sqrt(np.mean((self.y_val[rows] - np.asarray(output)[rows]) ** 2)))

    def judged_record(self, estimation: np.ndarray, validation: np.ndarray) -> np.ndarray:
        """A signal over the whole record (its estimation and validation parts) without the
        validation samples that are not judged."""
        return np.concatenate([estimation, np.asarray(validation)[self.judged_rows]])

    @property
    def n_est(self) -> int:
        return self.v_est.size

    @property
    def v_all(self) -> np.ndarray:
        return np.concatenate([self.v_est, self.v_val])

    @property
    def y_all(self) -> np.ndarray:
        return np.concatenate([self.y_est, self.y_val])

    def validation_output(self, simulate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The model's free-run output on the validation samples: continuing its own output
        over the estimation samples, or (separate record) from rest at the operating point of
        the first measured outputs (``from_rest_at``)."""
        if self.continuous:
            return simulate(self.v_all)[self.n_est :]
        return from_rest_at(simulate, self.v_val, float(np.mean(self.y_val[:INITIAL_SAMPLES])), self.v_est)

    def delayed_input(self, samples: int) -> Split:
        """The same split with the input delayed by ``samples`` (a dead time moved into the
        data): over the whole record when continuous, else each record on its own."""
        if samples <= 0:
            return self
        if self.continuous:
            v = held_back(self.v_all, samples)
            return replace(self, v_est=v[: self.n_est], v_val=v[self.n_est :])
        return replace(self, v_est=held_back(self.v_est, samples), v_val=held_back(self.v_val, samples))

    def reference_input(self, lags: int = REFERENCE_LAGS) -> Split:
        """The same split with the input v replaced by v_r, its part the reference explains (the
        first stage of the two-stage method, ``instrumental.reference_part``): the projection
        v_r(k) = c + sum_{i=0}^{lags} s_i r(k - i) fitted on the estimation part only and applied
        to the validation part (continuing over the whole record when continuous, else on the
        validation record's own reference). Unchanged without a reference."""
        if self.r_est is None or self.r_val is None:
            return self
        theta = projection_coefficients(self.v_est, self.r_est, lags)
        if self.continuous:
            v = projection_columns(np.concatenate([self.r_est, self.r_val]), lags) @ theta
            return replace(self, v_est=v[: self.n_est], v_val=v[self.n_est :])
        return replace(self, v_est=projection_columns(self.r_est, lags) @ theta,
                       v_val=projection_columns(self.r_val, lags) @ theta)

    def estimation_tail(self, samples: int) -> Split:
        """The same split with only the last ``samples`` estimation samples (to bound the cost
        of slow fits on long records); validation unchanged."""
        if samples >= self.n_est:
            return self
        return replace(self, v_est=self.v_est[-samples:], y_est=self.y_est[-samples:])


def held_back(v: np.ndarray, samples: int) -> np.ndarray:
    """v(k - samples), the unknown past held at v(0) (the record starts in steady motion)."""
    return delayed(v, samples, float(v[0])) if np.size(v) else np.asarray(v, dtype=float)


def rest_input(simulate: Callable[[np.ndarray], np.ndarray], y0: float, inputs: np.ndarray) -> float:
    """The constant input u0 (searched over the range of ``inputs``) at whose rest the model's
    output is closest to y0: the equilibrium that explains a record's first measured output."""
    lo, hi = float(np.min(inputs)), float(np.max(inputs))
    grid = np.linspace(lo, hi, 41)
    levels = simulate(np.repeat(grid, REST_SAMPLES))[REST_SAMPLES - 1 :: REST_SAMPLES]
    distance = np.abs(np.nan_to_num(levels, nan=np.inf) - y0)
    i = int(np.argmin(distance))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    if b <= a:
        return float(grid[i])
    found = minimize_scalar(lambda u0: abs(simulate(np.full(REST_SAMPLES, u0))[-1] - y0), bounds=(a, b),
                            method="bounded", options={"xatol": 1e-4 * (hi - lo + 1e-12), "maxiter": 25})
    return float(found.x) if found.fun <= distance[i] else float(grid[i])


def from_rest_at(simulate: Callable[[np.ndarray], np.ndarray], v: np.ndarray, y0: float,
                 inputs: np.ndarray) -> np.ndarray:
    """simulate(v) started at rest at the constant input ``rest_input`` (searched over the range
    of ``inputs``): the unknown initial state of a separate record, taken as the equilibrium that
    explains its first measured output."""
    u0 = rest_input(simulate, y0, inputs)
    return simulate(np.concatenate([np.full(REST_SAMPLES, u0), v]))[REST_SAMPLES:]


def split_record(v: np.ndarray, y: np.ndarray, fraction: float = 0.7, reference: np.ndarray | None = None) -> Split:
    """The first ``fraction`` of the record for estimation, the rest for validation
    (``reference``: the closed loop's reference r, split alike)."""
    if not 0.0 < fraction < 1.0:
        raise UsageError(f"--split: the estimation fraction must be between 0 and 1 (got {fraction})")
    v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
    cut = int(round(fraction * v.size))
    split = with_reference(Split(v[:cut], y[:cut], v[cut:], y[cut:], continuous=True), reference, slice(None, cut),
                           slice(cut, None))
    check_split(split)
    return split


def with_reference(split: Split, reference: np.ndarray | None, est: slice, val: slice) -> Split:
    """``split`` with the record's reference cut like its estimation (``est``) and validation
    (``val``) parts (None: unchanged)."""
    if reference is None:
        return split
    r = check_reference(reference, split.n_est + split.v_val.size)
    return replace(split, r_est=r[est], r_val=r[val])


def check_split(split: Split) -> None:
    for part, n in (("estimation", split.n_est), ("validation", split.v_val.size)):
        if n < MIN_SAMPLES:
            raise UsageError(f"the {part} part has {n} samples; the diagnosis needs at least {MIN_SAMPLES}")
    for name, x in (("input", split.v_est), ("output", split.y_est)):
        if np.ptp(x) == 0.0:
            raise UsageError(f"the {name} is constant over the estimation part: nothing to identify")
