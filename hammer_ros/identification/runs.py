"""Runs: separate experiments held in one concatenated record.

Real recordings come as runs: several files, a ``run`` column, a bag whose streams stop for
longer than ``max_gap``. They are held as concatenated arrays plus the first sample of every run.
A run is a separate experiment, so nothing may use samples of two runs at once:

- a regressor row k of lags up to L exists only where k - L is in k's run (``rows``);
- a correlation product y(k) x(k - tau) only where both samples are in one run (``correlation.cross_correlation``
  with ``runs``: the eq. 8 estimator of paper 000 summed over the runs' centres);
- a free-run simulation starts again at every run (``simulate``), each run from its own initial
  condition: at rest at the run's first input value (``settle`` samples of that value simulated
  first and dropped, ``simulation_error.preroll_simulate``; ``rest_length`` of the model's poles).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Runs:
    """Run i holds samples ``starts[i]`` .. ``starts[i+1] - 1`` (the last run ends at ``total``)."""

    starts: tuple[int, ...]
    total: int

    def __post_init__(self) -> None:
        starts = self.starts
        if not starts or starts[0] != 0 or any(b <= a for a, b in itertools.pairwise(starts)) or starts[-1] >= max(
                self.total, 1):
            raise ValueError(f"run starts {starts} do not cut a record of {self.total} samples into runs")

    @classmethod
    def one(cls, total: int) -> Runs:
        """A single run: the whole record."""
        return cls((0,), total)

    @classmethod
    def from_lengths(cls, lengths: Sequence[int]) -> Runs:
        """Runs of the given lengths, concatenated in order (empty runs dropped)."""
        lengths = [int(n) for n in lengths if int(n) > 0]
        ends = np.cumsum(lengths)
        return cls(tuple(int(s) for s in np.concatenate([[0], ends[:-1]])), int(ends[-1]) if lengths else 0)

    @classmethod
    def from_labels(cls, labels: np.ndarray) -> Runs:
        """Consecutive samples with one label form a run (a ``run`` column); a label may come back later
        as a new run."""
        labels = np.asarray(labels)
        changes = np.flatnonzero(labels[1:] != labels[:-1]) + 1
        return cls(tuple(int(s) for s in np.concatenate([[0], changes])), int(labels.size))

    @property
    def count(self) -> int:
        return len(self.starts)

    @property
    def ends(self) -> np.ndarray:
        return np.append(np.asarray(self.starts[1:], dtype=int), self.total)

    @property
    def lengths(self) -> np.ndarray:
        return self.ends - np.asarray(self.starts, dtype=int)

    def slices(self) -> list[slice]:
        return [slice(a, int(b)) for a, b in zip(self.starts, self.ends)]

    def split(self, x: np.ndarray) -> list[np.ndarray]:
        """x cut into its runs."""
        x = np.asarray(x)
        if x.shape[0] != self.total:
            raise ValueError(f"a signal of {x.shape[0]} samples for runs of {self.total}")
        return [x[s] for s in self.slices()]

    def rows(self, back: int, ahead: int = 0, first: int = 0) -> np.ndarray:
        """Sample indices k with k - back and k + ahead in k's run (and k - back >= its start + ``first``
        - back, i.e. at least ``first`` samples into the run): the rows of a regression of lags up to
        ``back``, the centres of a correlation of lags up to ``back`` = ``ahead``."""
        lo = max(back, first)
        return np.concatenate([np.arange(a + lo, int(b) - ahead) for a, b in zip(self.starts, self.ends)]
                              + [np.zeros(0, dtype=int)]).astype(int)

    def simulate(self, simulate: Callable[[np.ndarray], np.ndarray], v: np.ndarray, settle: int = 0,
                 at_rest: Sequence[bool] | None = None) -> np.ndarray:
        """The free-run output of ``simulate`` started anew at every run, concatenated. A run ``at_rest``
        starts after ``settle`` samples of its first input value (dropped), i.e. at rest at its first
        input when ``settle`` covers the model's settling time (``rest_length``); another run starts from
        the simulator's own initial state (zero). Default: every run of several at rest, one run from the
        simulator's own state (``initial_states`` chooses from the data)."""
        if at_rest is None:
            if self.count == 1:
                return simulate(v)
            at_rest = (True,) * self.count
        if self.count == 1 and not at_rest[0]:
            return simulate(v)
        from .simulation_error import preroll_simulate

        return np.concatenate([np.asarray(preroll_simulate(simulate, part, settle) if rest else simulate(part),
                                          dtype=float) for part, rest in zip(self.split(v), at_rest)])

    def initial_states(self, simulate: Callable[[np.ndarray], np.ndarray], v: np.ndarray, y: np.ndarray,
                       settle: int) -> tuple[bool, ...]:
        """Per run, how a model's simulation starts: at rest at the run's first input (True) or from
        zero state (False), whichever explains the run's first ``settle`` samples better. A record that
        starts at rest away from zero (a servo held at its set point) and one that starts from zero (a
        simulation from zero state, the papers' examples) are both taken as they are; the choice is
        made once, with the method's estimate, and kept while the model is refined."""
        choice = []
        for part, y_part in zip(self.split(v), self.split(np.asarray(y, dtype=float))):
            head = part[: max(min(settle, part.size), 1)]  # a causal simulation of the head alone: its outputs
            errors = [float(np.sum((y_part[: head.size] - np.asarray(out, dtype=float)) ** 2))
                      for out in (Runs.one(head.size).simulate(simulate, head, settle, (rest,))
                                  for rest in (False, True))]
            choice.append(bool(np.isfinite(errors[1]) and (errors[1] < errors[0] or not np.isfinite(errors[0]))))
        return tuple(choice)

    def window(self, start: int, stop: int) -> Runs:
        """The runs of samples start .. stop - 1 alone (a run cut by the window keeps its part)."""
        cuts = [s - start for s in self.starts if start < s < stop]
        return Runs((0, *cuts), stop - start)

    def select(self, indices: Sequence[int]) -> tuple[np.ndarray, Runs]:
        """(the sample indices, the runs) of the runs numbered ``indices``, in that order."""
        parts = [np.arange(self.starts[i], int(self.ends[i])) for i in indices]
        return np.concatenate(parts).astype(int), Runs.from_lengths([p.size for p in parts])

    def describe(self) -> str:
        """'8 runs of 600-1200 samples' (for messages)."""
        lo, hi = int(self.lengths.min()), int(self.lengths.max())
        size = f"{lo}" if lo == hi else f"{lo}-{hi}"
        return f"{self.count} run{'s' if self.count > 1 else ''} of {size} samples"


def rest_length(poles: np.ndarray) -> int:
    """Samples of a constant input after which a model with these poles is at rest (its slowest mode
    decayed to 1e-9: three times ``simulation_error.settling_samples``' 0.1 %, at most 6000)."""
    from .simulation_error import settling_samples

    return 3 * settling_samples(np.asarray(poles))


def several(runs: Runs | None) -> Runs | None:
    """``runs`` when it holds more than one run, else None (one run is the continuous record:
    every method then takes its path without runs, bit for bit)."""
    return runs if runs is not None and runs.count > 1 else None


def per_run(function: Callable[[np.ndarray], np.ndarray], x: np.ndarray, runs: Runs | None) -> np.ndarray:
    """``function`` (a causal filter or simulator, at rest before its input) applied to every run of x
    alone (along axis 0), concatenated; ``function(x)`` without several runs."""
    runs = several(runs)
    return function(x) if runs is None else runs.simulate(function, x)


def concatenate(parts: Sequence[tuple[np.ndarray, Runs | None]]) -> Runs:
    """The runs of records laid end to end (a record without runs is one run)."""
    lengths: list[int] = []
    for x, runs in parts:
        lengths += list(runs.lengths) if runs is not None else [int(np.size(x))]
    return Runs.from_lengths(lengths)
