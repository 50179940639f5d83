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
from ..identification.runs import Runs

MIN_SAMPLES = 60
INITIAL_SAMPLES = 3  # measured outputs averaged for the operating point a separate record starts at
REST_SAMPLES = 1000  # constant-input samples after which a model is taken to be at rest


@dataclass(frozen=True, eq=False)
class Split:
    """(v_est, y_est) to fit on, (v_val, y_val) to validate on. ``continuous``: the validation
    samples follow the estimation samples in time (one record split in two), so a model is
    simulated over both and its validation output continues from its own state; otherwise
    (a separate validation record) the simulation starts at rest at the equilibrium that
    explains its first outputs (``from_rest_at``).

    ``runs_est``, ``runs_val``: the separate experiments (``identification.runs.Runs``) each
    part holds (None: one). Every simulation of the diagnosis goes through
    ``estimation_output`` / ``validation_output`` or ``Runs.simulate``, so no simulation
    crosses a run's boundary: a model's estimation and validation outputs start every run at
    rest at the equilibrium that explains the run's first measured outputs (the fits themselves
    start every run at rest at its first input, the simulators' convention; ``per_run``). A
    split with runs is never ``continuous``."""

    v_est: np.ndarray
    y_est: np.ndarray
    v_val: np.ndarray
    y_val: np.ndarray
    continuous: bool
    judged: np.ndarray | None = None  # the validation samples a model is judged on (None: all; ``coverage``)
    note: str = ""  # how the record was split, in plain words (``auto_split``)
    r_est: np.ndarray | None = None  # closed loop: the external reference over each part (None: open loop)
    r_val: np.ndarray | None = None
    runs_est: Runs | None = None
    runs_val: Runs | None = None

    @property
    def has_runs(self) -> bool:
        """Either part holds several experiments."""
        return any(r is not None and r.count > 1 for r in (self.runs_est, self.runs_val))

    @property
    def est_runs(self) -> Runs:
        """The estimation part's runs (one when none are given)."""
        return self.runs_est if self.runs_est is not None else Runs.one(self.n_est)

    @property
    def val_runs(self) -> Runs:
        """The validation part's runs (one when none are given)."""
        return self.runs_val if self.runs_val is not None else Runs.one(self.v_val.size)

    @property
    def run_count(self) -> int:
        """Separate experiments in both parts: 1 for one record split in two (``continuous``)."""
        return 1 if self.continuous else self.est_runs.count + self.val_runs.count

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

    def estimation_output(self, simulate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The model's free-run output on the estimation samples: simulate(v_est) for one run,
        else every run from rest at the operating point of its first measured outputs
        (``runs_from_rest``), like the validation runs."""
        if self.est_runs.count == 1:
            return simulate(self.v_est)
        return runs_from_rest(simulate, self.v_est, self.y_est, self.est_runs, self.v_est)

    def validation_output(self, simulate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The model's free-run output on the validation samples: continuing its own output
        over the estimation samples, or (separate record, every validation run) from rest at
        the operating point of its first measured outputs (``from_rest_at``)."""
        if self.continuous:
            return simulate(self.v_all)[self.n_est :]
        return runs_from_rest(simulate, self.v_val, self.y_val, self.val_runs, self.v_est)

    def delayed_input(self, samples: int) -> Split:
        """The same split with the input delayed by ``samples`` (a dead time moved into the
        data): over the whole record when continuous, else each record on its own."""
        if samples <= 0:
            return self
        if self.has_runs:
            return replace(self, v_est=self.est_runs.simulate(lambda v: held_back(v, samples), self.v_est),
                           v_val=self.val_runs.simulate(lambda v: held_back(v, samples), self.v_val))
        if self.continuous:
            v = held_back(self.v_all, samples)
            return replace(self, v_est=v[: self.n_est], v_val=v[self.n_est :])
        return replace(self, v_est=held_back(self.v_est, samples), v_val=held_back(self.v_val, samples))

    def reference_input(self, lags: int = REFERENCE_LAGS) -> Split:
        """The same split with the input v replaced by v_r, its part the reference explains (the
        first stage of the two-stage method, ``instrumental.reference_part``): the projection
        v_r(k) = c + sum_{i=0}^{lags} s_i r(k - i) fitted on the estimation part only and applied
        to the validation part (continuing over the whole record when continuous, else on the
        validation record's own reference; every run on its own). Unchanged without a reference."""
        if self.r_est is None or self.r_val is None:
            return self
        theta = projection_coefficients(self.v_est, self.r_est, lags)
        if self.has_runs:
            def project(r: np.ndarray) -> np.ndarray:
                return projection_columns(r, lags) @ theta

            return replace(self, v_est=self.est_runs.simulate(project, self.r_est),
                           v_val=self.val_runs.simulate(project, self.r_val))
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
        tail, runs = runs_tail(self.runs_est, self.n_est, samples)
        return replace(self, v_est=self.v_est[tail], y_est=self.y_est[tail], runs_est=runs)


def runs_tail(runs: Runs | None, total: int, samples: int) -> tuple[slice, Runs | None]:
    """(slice, its runs) of the last ``samples`` of a record of ``total`` samples and ``runs``."""
    tail = slice(max(0, total - samples), None)
    if runs is None or runs.count == 1 or tail.start == 0:
        return tail, runs if tail.start == 0 else None
    lengths = [min(int(b), total) - max(a, tail.start) for a, b in zip(runs.starts, runs.ends)]
    return tail, Runs.from_lengths([n for n in lengths if n > 0])


def per_run(simulate: Callable[[np.ndarray], np.ndarray], x: np.ndarray, runs: Runs | None) -> np.ndarray:
    """simulate(x), or with ``runs`` simulate on every run's samples (rows) on its own, concatenated
    (``Runs.simulate``): filters, delays and lags of the diagnosis never reach into another run."""
    return simulate(x) if runs is None else runs.simulate(simulate, x)


def held_back(v: np.ndarray, samples: int) -> np.ndarray:
    """v(k - samples), the unknown past held at v(0) (the record starts in steady motion)."""
    return delayed(v, samples, float(v[0])) if np.size(v) else np.asarray(v, dtype=float)


def rest_input(simulate: Callable[[np.ndarray], np.ndarray], y0: float, inputs: np.ndarray) -> float:
    """The constant input u0 (searched over the range of ``inputs``) at whose rest the model's
    output is closest to y0: the equilibrium that explains a record's first measured output."""
    return rest_inputs(simulate, [y0], inputs)[0]


def rest_inputs(simulate: Callable[[np.ndarray], np.ndarray], y0s: list[float], inputs: np.ndarray) -> list[float]:
    """``rest_input`` for several first outputs (one per run), the grid of rest levels simulated once."""
    lo, hi = float(np.min(inputs)), float(np.max(inputs))
    grid = np.linspace(lo, hi, 41)
    levels = np.nan_to_num(simulate(np.repeat(grid, REST_SAMPLES))[REST_SAMPLES - 1 :: REST_SAMPLES], nan=np.inf)
    found = []
    for y0 in y0s:
        distance = np.abs(levels - y0)
        i = int(np.argmin(distance))
        a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        if b <= a:
            found.append(float(grid[i]))
            continue
        best = minimize_scalar(lambda u0, y0=y0: abs(simulate(np.full(REST_SAMPLES, u0))[-1] - y0), bounds=(a, b),
                               method="bounded", options={"xatol": 1e-4 * (hi - lo + 1e-12), "maxiter": 25})
        found.append(float(best.x) if best.fun <= distance[i] else float(grid[i]))
    return found


def runs_from_rest(simulate: Callable[[np.ndarray], np.ndarray], v: np.ndarray, y: np.ndarray, runs: Runs,
                   inputs: np.ndarray) -> np.ndarray:
    """simulate on every run of (v, y) on its own, each from rest at the constant input whose rest
    explains the run's first INITIAL_SAMPLES measured outputs (``rest_inputs``, searched over the
    range of ``inputs``), concatenated. One run: ``from_rest_at``."""
    if runs.count == 1:
        return from_rest_at(simulate, v, float(np.mean(y[:INITIAL_SAMPLES])), inputs)
    parts = runs.split(v)
    levels = rest_inputs(simulate, [float(np.mean(part[:INITIAL_SAMPLES])) for part in runs.split(y)], inputs)
    return np.concatenate([simulate(np.concatenate([np.full(REST_SAMPLES, u0), part]))[REST_SAMPLES:]
                           for part, u0 in zip(parts, levels)])


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


def split_runs(v: np.ndarray, y: np.ndarray, runs: Runs, fraction: float = 0.7,
               reference: np.ndarray | None = None) -> Split:
    """A record of several runs split into whole runs: the first runs for estimation, the last
    round((1 - fraction) x count) (at least one, at most count - 1) for validation."""
    if not 0.0 < fraction < 1.0:
        raise UsageError(f"--split: the estimation fraction must be between 0 and 1 (got {fraction})")
    if runs.count < 2:
        return split_record(v, y, fraction, reference)
    v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
    held = int(np.clip(round((1.0 - fraction) * runs.count), 1, runs.count - 1))
    first = runs.count - held
    cut = runs.starts[first]
    lengths = runs.lengths
    estimation = f"runs 1-{first}" if first > 1 else "run 1"
    validation = f"runs {first + 1}-{runs.count}" if held > 1 else f"run {runs.count}"
    note = f"whole runs: estimation on {estimation}, validation on {validation} of {runs.count}"
    split = Split(v[:cut], y[:cut], v[cut:], y[cut:], continuous=False, note=note,
                  runs_est=Runs.from_lengths(lengths[:first]), runs_val=Runs.from_lengths(lengths[first:]))
    split = with_reference(split, reference, slice(None, cut), slice(cut, None))
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
