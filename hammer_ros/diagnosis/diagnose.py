"""The diagnosis: baseline, evidence, extensions, decision.

1. Baseline (``hammerstein.fit_baseline``) on the estimation part, free-run on the validation
   part.
2. Evidence on what the simulation gets wrong: the Billings-Voon / Billings-Zhu residual tests
   (validation residual), the cause tests of ``evidence`` (regression signatures on the
   validation residual, spectral lines on the estimation residual, windows over the whole
   record).
3. The causes whose test failed are ranked by the share of the residual their signature
   explains; the extension of each of the best ``MAX_CANDIDATES`` (that explain at least
   ``RELATIVE_SHARE`` of what the best one explains) is fitted on the estimation part and
   simulated on the validation part.
4. The cause is the candidate with the largest validation gain (baseline RMS / extended
   RMS), if that gain is at least ``MIN_GAIN``; otherwise ``none``. A cause is thus named
   only when its evidence supports it and its extension improves the validation fit.
   When no signature is significant, or no supported extension gains enough, but the residual
   tests say the baseline is inadequate (a poor baseline blurs every signature, e.g. an output
   map that is not invertible), every other extension with a start of its own is fitted, and
   one is named only at a gain of at least ``BLIND_MIN_GAIN`` (``found_by`` says which way the
   cause was found).
5. Compound explanations (``chain``): the extended model's own residual is tested again and
   extended while a step gains at least 5 % on the validation data; ``steps`` lists the chain,
   ``extended`` and ``gain`` describe its last model.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from ..identification.result import fit_percent, rms_error, strict_json
from ..identification.runs import Runs
from .chain import Chain, Step, extend_chain
from .closed_loop import closed_loop_evidence
from .coverage import input_coverage
from .evidence import (
    CauseTest,
    LineTest,
    WindowTest,
    correlation_shape_test,
    signature_tests,
    spectral_lines,
    windowed_variation,
)
from .extensions import EXTENSIONS, NUMERICAL_FAILURES, Context, ExtendedModel, failure_reason
from .hammerstein import HammersteinModel, fit_baseline, select_dead_time, transient_samples
from .residual_tests import CorrelationTest, Evidence, residual_tests
from .split import MIN_SAMPLES, Split, split_record

MIN_GAIN = 1.05
INSTRUMENTED_INPUT = "reference_part"  # ``baseline.input`` with a reference: the models run on v_r, not v
BLIND_MIN_GAIN = 1.15  # without a significant signature, a cause must gain this much
# extensions that are simulation models of the input alone (not time_varying: it re-fits on the measured
# validation output, so any model error looks like a gain; not periodic_disturbance: it needs spectral lines)
BLIND_CAUSES = ("output_feedback", "output_nonlinearity", "input_dynamics", "parallel_path", "unmodeled_dynamics")
MAX_CANDIDATES = 5  # of the 8 causes with a signature test
RELATIVE_SHARE = 0.2
TIE_BLOCKS = 20  # blocks of the validation errors for the test of two candidates' difference
TIED_CONFIDENCE = 0.5  # factor of the confidence when another candidate is within noise of the named one


@dataclass(frozen=True)
class ModelScore:
    structure: str
    rms: float
    fit_percent: float

    def to_json(self) -> dict:
        return {"structure": self.structure, "rms": float(self.rms), "fit_percent": float(self.fit_percent)}


@dataclass(frozen=True)
class Diagnosis:
    """The ``diagnose --json`` document (``to_json``); ``candidates`` holds the validation gain
    of every extension that was fitted, ``details`` the numbers of the chosen one."""

    baseline: ModelScore
    cause: str
    confidence: float
    evidence: tuple[Evidence, ...]
    extended: ModelScore | None
    gain: float | None
    candidates: tuple[tuple[str, float], ...] = ()
    details: dict = field(default_factory=dict)
    baseline_model: dict = field(default_factory=dict)
    steps: tuple[Step, ...] = ()
    chain_stopped: str | None = None
    not_fitted: tuple[tuple[str, str], ...] = ()  # (cause, one-line reason) of every extension tried in vain
    coverage: dict = field(default_factory=dict)  # ``InputCoverage.to_json``: what the validation could judge
    split_note: str = ""  # how the record was split (``--split auto``)

    def to_json(self) -> dict:
        doc = {
            "baseline": {**self.baseline.to_json(), **self.baseline_model},
            "cause": self.cause,
            "confidence": float(self.confidence),
            "evidence": [e.to_json() for e in self.evidence],
            "extended": None if self.extended is None else {**self.extended.to_json(), **self.details},
            "gain": None if self.gain is None else {"rms_ratio": float(self.gain)},
            "candidates": [{"cause": c, "rms_ratio": float(g)} for c, g in self.candidates],
            "steps": [s.to_json() for s in self.steps],
            "chain_stopped": self.chain_stopped,
            "not_fitted": [{"cause": c, "reason": r} for c, r in self.not_fitted],
            "input_coverage": self.coverage,
        }
        if self.split_note:
            doc["split"] = self.split_note
        return strict_json(doc)


@dataclass(frozen=True, eq=False)
class DiagnosisRun:
    """A diagnosis with everything the report draws."""

    diagnosis: Diagnosis
    split: Split
    baseline: HammersteinModel
    baseline_output: np.ndarray  # free-run on the validation part
    correlation_tests: tuple[CorrelationTest, ...]
    cause_tests: tuple[CauseTest, ...]
    lines: LineTest
    windows: WindowTest
    extensions: dict  # cause -> ExtendedModel (every one fitted)
    chain: Chain | None = None  # the compound explanation that starts at the named cause

    @property
    def extended(self) -> ExtendedModel | None:
        """The final model of the chain (the first cause's extension when the chain has one step)."""
        return None if self.chain is None else self.chain.final


def _score(structure: str, split: Split, y_sim: np.ndarray) -> ModelScore:
    """RMS and fit of a validation output on the judged validation samples."""
    rows = split.judged_rows
    return ModelScore(structure, rms_error(split.y_val[rows], y_sim[rows]), fit_percent(split.y_val[rows], y_sim[rows]))


def diagnose(split: Split, order: int | None = None, delay: int | None = None) -> DiagnosisRun:
    """The diagnosis of the record in ``split`` (``order``: the user's nominal order; None =
    chosen on the estimation data). Without a given ``delay`` a dead time is searched first
    (``select_dead_time``) and moved into the input of every model. With a reference in the
    split (closed loop) every model is fitted and judged on the reference's part of the input
    (``Split.reference_input``, the two-stage method); the ``closed_loop`` row stays on the
    measured input."""
    measured = split
    split = split.reference_input()
    dead_time = 0 if delay is not None else select_dead_time(split.v_est, split.y_est, order, split.runs_est)
    split = split.delayed_input(dead_time)
    measured_v_val = measured.delayed_input(dead_time).v_val
    base = fit_baseline(split.v_est, split.y_est, order, delay, split.runs_est)
    skip = transient_samples(base.linear.poles, split.n_est)
    coverage = input_coverage(split.v_est, split.v_val, min(skip, split.v_val.size // 5), split.runs_val)
    judgeable = coverage.passed or int(np.count_nonzero(coverage.covered)) >= MIN_SAMPLES
    if judgeable:
        split = replace(split, judged=coverage.judged())
    x_est = split.estimation_output(base.simulate)
    x_val = split.validation_output(base.simulate)
    e_val = split.y_val - x_val
    val_runs = split.val_runs
    val_skip = 0 if split.continuous else min(skip, int(val_runs.lengths.min()) // 5)
    rows = split.judged_rows[split.judged_rows >= val_skip] if val_runs.count == 1 else np.intersect1d(
        split.judged_rows, val_runs.rows(val_skip))  # every validation run starts at rest: its transient left out
    tested_runs = _runs_of(val_runs, rows) if split.has_runs else None

    correlation = tuple(residual_tests(split.v_val[rows], split.y_val[rows], e_val[rows], runs=tested_runs))
    if split.est_runs.count == 1:
        lines = spectral_lines((split.y_est - x_est)[skip:], [split.v_est[skip:], x_est[skip:]])
    else:  # every estimation run without its own transient, Bartlett's average of the runs' periodograms
        est = split.est_runs.rows(min(skip, int(split.est_runs.lengths.min()) // 5))
        lines = spectral_lines((split.y_est - x_est)[est], [split.v_est[est], x_est[est]],
                               runs=_runs_of(split.est_runs, est))
    windows = windowed_variation(split.judged_record(split.y_est, split.y_val),
                                 split.judged_record(x_est, x_val), skip,
                                 runs=_judged_runs(split) if split.has_runs else None)
    shape = correlation_shape_test(split.v_est, split.y_est, runs=split.runs_est)
    cause_tests = tuple(signature_tests(base, split.v_val, x_val, e_val, rows, runs=split.runs_val)) + (
        lines.cause_test(), windows.cause_test()) + ((shape,) if shape is not None else ())

    ctx = Context(split, base, lines, windows)
    supported = sorted((t for t in cause_tests if t.supports), key=lambda t: -t.explained)[:MAX_CANDIDATES]
    if supported:  # causes whose signature explains little next to the best one are not fitted
        supported = [t for t in supported if t.explained >= RELATIVE_SHARE * supported[0].explained]
    baseline_score = _score("hammerstein", split, x_val)
    extensions: dict[str, ExtendedModel] = {}
    gains: dict[str, float] = {}
    not_fitted: dict[str, str] = {}

    def fit(candidates: list[str]) -> None:
        for candidate in candidates:
            try:
                extended = EXTENSIONS[candidate](ctx)
            except NUMERICAL_FAILURES as error:
                not_fitted[candidate] = failure_reason(error)
                suggested = getattr(error, "suggests", None)
                if suggested is not None and suggested not in extensions and suggested not in not_fitted:
                    fit([suggested])
                continue
            if not np.all(np.isfinite(extended.validation_output)):
                not_fitted[candidate] = "its simulation is not finite on the validation input"
                continue
            extensions[candidate] = extended
            gains[candidate] = baseline_score.rms / max(split.validation_rms(extended.validation_output), 1e-300)

    fit(list(dict.fromkeys(t.cause for t in supported)))
    found_by = "signature"
    cause = max(gains, key=gains.get) if gains else "none"

    def gains_enough(c: str, least: float) -> bool:
        """At least ``least``, and below BLIND_MIN_GAIN significantly so (a few per cent of RMS on a
        short validation part is not evidence)."""
        return gains[c] >= least and (gains[c] >= BLIND_MIN_GAIN
                                      or _beats_the_baseline(split, extensions[c].validation_output, x_val))

    if cause != "none" and not gains_enough(cause, MIN_GAIN):
        cause = "none"
    if cause == "none" and not all(t.evidence().passed for t in correlation):
        signed = dict(gains)
        fit([c for c in BLIND_CAUSES if c in EXTENSIONS and c not in signed])
        blind = {c: g for c, g in gains.items() if c not in signed and gains_enough(c, BLIND_MIN_GAIN)}
        if blind:
            cause = max(blind, key=blind.get)
            found_by = "a search of every extension (no significant signature led to a gain; the residual tests failed)"
    coverage_json = coverage.to_json()
    if not judgeable:  # hardly a validation sample in the estimation range: nothing to name a cause from
        cause, found_by = "none", ""
        coverage_json["judged_on"] += (f"; only {int(np.count_nonzero(coverage.covered))} validation samples are "
                                       f"covered (fewer than {MIN_SAMPLES}): every sample is judged and no cause is "
                                       "named")
    # the candidates the validation data cannot tell from the named one: said (``within_noise_of``, a low
    # confidence), not hidden behind a few per cent of RMS
    tied = _within_noise(split, extensions, gains, cause) if cause != "none" else []
    evidence = (coverage.evidence(), *(t.evidence() for t in correlation), *(t.evidence for t in cause_tests))
    confidence = _confidence(cause, gains, evidence) * (TIED_CONFIDENCE if tied else 1.0)
    evidence += (closed_loop_evidence(measured_v_val[rows], e_val[rows], reference=split.r_est is not None,
                                      runs=tested_runs),)
    chain = None if cause == "none" else extend_chain(split, extensions[cause], baseline_score.rms, skip)
    final = None if chain is None else chain.final
    extended_score = None if final is None else _score(final.structure, split, final.validation_output)
    details = {} if chain is None else {**extensions[cause].details, "found_by": found_by}
    if chain is not None and tied:
        details["within_noise_of"] = tied
    if chain is not None and len(chain.models) > 1:
        details["further_steps"] = [{"cause": m.cause, **m.details} for m in chain.models[1:]]
    diagnosis = Diagnosis(
        baseline=baseline_score,
        cause=cause,
        confidence=confidence,
        evidence=evidence,
        extended=extended_score,
        gain=None if extended_score is None else baseline_score.rms / max(extended_score.rms, 1e-300),
        candidates=tuple(sorted(gains.items(), key=lambda kv: -kv[1])),
        details=details,
        baseline_model={"order": base.order, "delay": base.delay, "dead_time": dead_time,
                        **({"input": INSTRUMENTED_INPUT} if split.r_est is not None else {}),
                        "poles": [[float(p.real), float(p.imag)] for p in base.linear.poles],
                        "nonlinearity": base.nonlinearity.to_json((float(np.min(split.v_est)),
                                                                    float(np.max(split.v_est))))},
        steps=() if chain is None else chain.steps,
        chain_stopped=None if chain is None else chain.stopped,
        not_fitted=tuple(not_fitted.items()) + (() if chain is None else chain.not_fitted),
        coverage=coverage_json,
        split_note=split.note,
    )
    return DiagnosisRun(diagnosis, split, base, x_val, correlation, cause_tests, lines, windows, extensions, chain)


def _runs_of(runs: Runs, rows: np.ndarray) -> Runs:
    """The runs of the samples ``rows`` (sorted indices into a record of ``runs``) taken out."""
    return Runs.from_labels(np.repeat(np.arange(runs.count), runs.lengths)[rows])


def _judged_runs(split: Split) -> Runs:
    """The runs of ``Split.judged_record`` (the estimation runs, then the validation runs' judged samples)."""
    label = np.concatenate([np.repeat(np.arange(split.est_runs.count), split.est_runs.lengths),
                            split.est_runs.count + np.repeat(np.arange(split.val_runs.count),
                                                             split.val_runs.lengths)[split.judged_rows]])
    return Runs.from_labels(label)


def _block_t(split: Split, first: np.ndarray, second: np.ndarray) -> tuple[float, int]:
    """(t, blocks) of two validation outputs' errors: over TIE_BLOCKS consecutive blocks of the
    judged validation samples, the log ratio of the two mean squared errors in each block, t-tested
    against 0 (negative: ``first`` predicts better). Block means are nearly independent when the
    errors are slowly correlated; the log ratio keeps a few blocks of large errors (a step of the
    input) from deciding alone. (0, 0) with fewer than 4 blocks of 10 samples."""
    rows = split.judged_rows
    blocks = min(TIE_BLOCKS, rows.size // 10)
    if blocks < 4:
        return 0.0, 0
    a, b = (split.y_val - first)[rows], (split.y_val - second)[rows]
    floor = 1e-12 * float(np.mean(b**2)) + 1e-300
    ratios = np.array([np.log((np.mean(x**2) + floor) / (np.mean(z**2) + floor))
                       for x, z in zip(np.array_split(a, blocks), np.array_split(b, blocks))])
    spread = float(np.std(ratios, ddof=1))
    return (float(np.mean(ratios)) / (spread / np.sqrt(blocks)) if spread > 0 else 0.0), blocks


def _beats_the_baseline(split: Split, output: np.ndarray, baseline: np.ndarray) -> bool:
    """An extension's validation errors are significantly below the baseline's (``_block_t``,
    one-sided 95 %): a gain of a few per cent on a short validation part is not evidence."""
    t, blocks = _block_t(split, output, baseline)
    return blocks == 0 or t < -float(stats.t.ppf(0.95, blocks - 1))


def _within_noise(split: Split, extensions: dict[str, ExtendedModel], gains: dict[str, float],
                  best: str) -> list[str]:
    """The other candidates (gain >= MIN_GAIN) whose validation errors the best one's do not beat
    significantly (``_block_t``, |t| below the two-sided 95 % point)."""
    tied = []
    for other, gain in sorted(gains.items(), key=lambda kv: -kv[1]):
        if other == best or gain < MIN_GAIN:
            continue
        t, blocks = _block_t(split, extensions[best].validation_output, extensions[other].validation_output)
        if blocks and abs(t) < float(stats.t.ppf(0.975, blocks - 1)):
            tied.append(other)
    return tied


def _confidence(cause: str, gains: dict[str, float], evidence: tuple[Evidence, ...]) -> float:
    """0..1. A named cause: how far its gain is above 1 (0.63 at a gain of 1.15) times how
    clearly it beats the runner-up. ``none``: high when every test passes, lower when tests
    fail or an extension came close to MIN_GAIN."""
    if cause != "none":
        g = gains[cause]
        runner_up = max([v for c, v in gains.items() if c != cause] + [1.0])
        strength = 1.0 - np.exp(-np.log(g) / np.log(1.15))
        separation = float(np.clip(1.0 - np.log(max(runner_up, 1.0)) / np.log(g), 0.0, 1.0))
        return float(np.clip(strength * (0.5 + 0.5 * separation), 0.0, 1.0))
    failed = sum(1 for e in evidence if not e.passed) / max(len(evidence), 1)
    closest = max([*gains.values(), 1.0])
    near = float(np.clip(np.log(closest) / np.log(MIN_GAIN), 0.0, 1.0))
    return float(np.clip((1.0 - 0.5 * failed) * (1.0 - 0.5 * near), 0.0, 1.0))


def diagnose_record(v: np.ndarray, y: np.ndarray, order: int | None = None, delay: int | None = None,
                    split: float = 0.7, reference: np.ndarray | None = None) -> Diagnosis:
    """The diagnosis of one record (e.g. the live node's window): the first ``split`` of it
    for estimation, the rest for validation (``reference``: a closed loop's, ``diagnose``).
    Pure function of its arguments."""
    return diagnose(split_record(v, y, split, reference), order, delay).diagnosis
