"""Input coverage: can the validation data judge the model at all?

A model estimated on inputs in [lo, hi] is an extrapolation beyond them: its map continues with
its last slopes, which says nothing about the physics there. Before judging, the validation
input is compared with the estimation input (for the Hammerstein baseline and every extension
the map's input is the command v itself): the ``input_range`` evidence row gives the fraction of
validation samples whose input lies outside the estimation range widened by RANGE_MARGIN of its
span, against COVERAGE_BOUND. When it fails, every model is judged on the covered samples only:
those whose input, and the ``memory`` inputs before it (the baseline's settling time: the part
of the past the output still remembers; never before the start of the sample's run), lie in
range. ``auto_split`` chooses an estimation part that covers the validation part where the record allows it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..identification.runs import Runs, several
from .residual_tests import Evidence
from .split import Split, check_split, with_reference

COVERAGE_BOUND = 0.02  # share of validation samples outside the estimation range above which the row fails
RANGE_MARGIN = 0.02  # share of the estimation range by which it is widened on either side
AUTO_VALIDATION_SHARES = (0.3, 0.25, 0.2)  # validation parts that ``auto_split`` tries, at the end or the start


@dataclass(frozen=True, eq=False)
class InputCoverage:
    """How the validation input lies in the estimation range: the widened range [low, high], the
    share of validation samples outside it, and ``covered``, the validation samples whose input
    and previous ``memory`` inputs lie inside."""

    low: float
    high: float
    validation_low: float
    validation_high: float
    outside: float
    covered: np.ndarray
    memory: int

    @property
    def passed(self) -> bool:
        return self.outside <= COVERAGE_BOUND

    def evidence(self) -> Evidence:
        return Evidence("input_range", self.outside, COVERAGE_BOUND, self.passed)

    def judged(self) -> np.ndarray | None:
        """The validation samples to judge on: the covered ones when the row fails, else all."""
        return None if self.passed else self.covered

    def to_json(self) -> dict:
        n, kept = self.covered.size, int(np.count_nonzero(self.covered))
        if self.passed:
            text = (f"the validation input lies in the estimation range ({100 * self.outside:.1f} % of its samples "
                    f"outside, at most {100 * COVERAGE_BOUND:.0f} % allowed): every validation sample is judged")
        else:
            text = (f"{100 * self.outside:.1f} % of the validation samples have an input outside the estimation range "
                    f"[{self.low:.4g}, {self.high:.4g}] (the validation input spans [{self.validation_low:.4g}, "
                    f"{self.validation_high:.4g}]): there the models extrapolate, so they are judged only on the "
                    f"{kept} of {n} validation samples whose input and previous {self.memory} inputs lie in range, "
                    "and no cause is named from the rest")
        return {"estimation_range": [self.low, self.high], "validation_range": [self.validation_low,
                                                                               self.validation_high],
                "outside": self.outside, "bound": COVERAGE_BOUND, "judged_samples": kept if not self.passed else n,
                "validation_samples": n, "memory": self.memory, "judged_on": text}


def input_coverage(v_est: np.ndarray, v_val: np.ndarray, memory: int, runs: Runs | None = None) -> InputCoverage:
    """The coverage of ``v_val`` by the range of ``v_est`` (module docstring); ``runs``: the runs of
    ``v_val``, each starting at rest, so a sample's memory stops at its run's first sample."""
    lo, hi = float(np.min(v_est)), float(np.max(v_est))
    margin = RANGE_MARGIN * (hi - lo)
    lo, hi = lo - margin, hi + margin
    inside = (v_val >= lo) & (v_val <= hi)
    memory = int(max(memory, 0))
    # covered: no sample outside among this one and the memory before it
    count = np.concatenate([[0], np.cumsum(~inside)])
    k = np.arange(v_val.size)
    runs = several(runs)
    first = 0 if runs is None else np.repeat(np.asarray(runs.starts, dtype=int), runs.lengths)
    covered = count[k + 1] - count[np.maximum(k - memory, first)] == 0
    return InputCoverage(lo, hi, float(np.min(v_val)), float(np.max(v_val)), float(np.mean(~inside)), covered, memory)


def auto_split(v: np.ndarray, y: np.ndarray, reference: np.ndarray | None = None) -> Split:
    """An estimation part that covers the validation input's range where the record allows it:
    the validation part is the last or the first 30 %, 25 % or 20 % of the record (in that order
    of preference: the default, the last 30 %, first), the first of these whose input lies in the
    rest's range (``input_range`` passes, without memory); else the one with the smallest share
    outside. A validation part at the start is a separate record for the models (simulated from
    rest at its first outputs' operating point), the estimation part the rest of the record.
    ``Split.note`` says what was picked; ``reference`` (closed loop) is cut like the record."""
    v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
    candidates = []
    for share in AUTO_VALIDATION_SHARES:
        cut = int(round((1.0 - share) * v.size))
        candidates.append((f"the last {100 * share:.0f} %", with_reference(
            Split(v[:cut], y[:cut], v[cut:], y[cut:], True), reference, slice(None, cut), slice(cut, None))))
        cut = int(round(share * v.size))
        candidates.append((f"the first {100 * share:.0f} %", with_reference(
            Split(v[cut:], y[cut:], v[:cut], y[:cut], False), reference, slice(cut, None), slice(None, cut))))
    scored = [(input_coverage(s.v_est, s.v_val, 0).outside, i, name, s) for i, (name, s) in enumerate(candidates)]
    passing = [c for c in scored if c[0] <= COVERAGE_BOUND]
    outside, _, name, split = passing[0] if passing else min(scored, key=lambda c: (c[0], c[1]))
    check_split(split)
    verdict = "covers" if outside <= COVERAGE_BOUND else f"covers best ({100 * outside:.1f} % of it outside)"
    return replace(split, note=f"--split auto: validation on {name} of the record, estimation on the rest, whose "
                               f"input range {verdict} the validation input")
