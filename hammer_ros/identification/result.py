"""The result of an identification: the model, its parts, and the contract's JSON form."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from .free_run_kernel import hammerstein_fit, hammerstein_free_run, polynomial_hammerstein, remember_roots
from .linear import LinearModel
from .runs import Runs, rest_length
from .trust import ModelWarning, model_warnings, warnings_json


def rms_error(y: np.ndarray, y_sim: np.ndarray) -> float:
    """rms = sqrt(mean((y - y_sim)^2))."""
    y, y_sim = np.asarray(y, float), np.asarray(y_sim, float)
    return math.sqrt(((y - y_sim) ** 2).mean())


def fit_percent(y: np.ndarray, y_sim: np.ndarray) -> float:
    """fit = 100 (1 - ||y - y_sim|| / ||y - mean(y)||) (the NRMSE fit of MATLAB's compare)."""
    return fit_and_rms(y, y_sim)[0]


def fit_and_rms(y: np.ndarray, y_sim: np.ndarray) -> tuple[float, float]:
    """(``fit_percent``, ``rms_error``) of one simulation from one residual: rms = ||y - y_sim|| / sqrt(N)."""
    y, y_sim = np.asarray(y, float), np.asarray(y_sim, float)
    if y.size == 0:
        return float("nan"), float("nan")
    error, spread = _norm(y - y_sim), _norm(y - y.sum() / y.size)  # y.mean()
    fit = float("nan") if spread == 0.0 else float(100.0 * (1.0 - error / spread))
    return fit, error / math.sqrt(y.size)


def _norm(x: np.ndarray) -> float:
    """||x||_2 = sqrt(x . x), as np.linalg.norm computes it for a real array (without its dispatch)."""
    x = x.ravel(order="K")
    return math.sqrt(x @ x)


def _roots_json(roots: np.ndarray) -> list[list[float]]:
    return [[r.real, r.imag] for r in np.asarray(roots, dtype=complex).tolist()]


@dataclass(frozen=True)
class Evaluation:
    """A model on a record (``IdentificationResult.evaluate``): its free-run fit percent and rms, and
    its own warnings there."""

    fit: float
    rms: float
    warnings: tuple[ModelWarning, ...]


@dataclass(frozen=True, eq=False)
class IdentificationResult:
    """An identified model.

    ``simulate`` maps an input sequence to the model's free-run output (the whole model:
    nonlinearity, linear block and any feedback path), so fit and rms are computed the same
    way for every method. ``gain`` is the method's gain figure (for CLS/NLS: h1_hat / h1 in
    paper 000's tables, i.e. the first Markov parameter of the identified chain).
    """

    method: str
    linear: LinearModel
    simulate: Callable[[np.ndarray], np.ndarray]
    order: int | None = None
    gain: float | None = None
    nonlinearity: Any = None
    feedback_nonlinearity: Any = None
    markov: np.ndarray | None = None
    extra: dict = field(default_factory=dict)
    uncertainty: Any = None  # an uncertainty.Uncertainty: the sds of poles, zeros, gain and map

    @property
    def poles(self) -> np.ndarray:
        return self.linear.poles

    @property
    def zeros(self) -> np.ndarray:
        return self.linear.zeros

    @cached_property
    def _polynomial_hammerstein(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``free_run_kernel.polynomial_hammerstein`` of the simulator (the model is immutable)."""
        return polynomial_hammerstein(self.simulate)

    @cached_property
    def _rest_length(self) -> int:
        """``runs.rest_length`` of the poles: the samples of a start at rest."""
        return rest_length(self.linear.poles)

    def free_run(self, v: np.ndarray, y: np.ndarray, runs: Runs | None = None) -> np.ndarray:
        """The model's free-run output on the record (v, y): every run simulated from its own start,
        at rest at its first input or from zero state, whichever explains its first samples
        (``Runs.initial_states``)."""
        runs = Runs.one(np.size(v)) if runs is None else runs
        settle = self._rest_length
        if runs.count == 1 and self._polynomial_hammerstein is not None:  # CLS's model: one compiled loop,
            compiled = hammerstein_free_run(self._polynomial_hammerstein, v, y, settle)  # the same numbers
            if compiled is not None:
                return compiled
        return runs.simulate(self.simulate, v, settle, runs.initial_states(self.simulate, v, y, settle))

    def window_fit(self, v: np.ndarray, y: np.ndarray) -> tuple[float, float]:
        """(fit percent, rms) of the free run on the one run (v, y): ``fit_and_rms(y, free_run(v, y))``,
        for a polynomial Hammerstein model (CLS's) with its roots computed compiled when it has none yet
        (``free_run_kernel.remember_roots``: bit for bit) and the free run, fit and rms in one compiled
        call (``hammerstein_fit``: the same free run, the figures' sums interleaved, so equal to
        rounding); what the streaming engine's solves take."""
        if self._polynomial_hammerstein is not None:
            remember_roots(self.linear)
            compiled = hammerstein_fit(self._polynomial_hammerstein, v, y, self._rest_length)
            if compiled is not None:
                return compiled
        return fit_and_rms(y, self.free_run(v, y))

    def evaluate(self, v: np.ndarray, y: np.ndarray, runs: Runs | None = None,
                 input_assumptions: bool = True, compiled: bool = False) -> Evaluation:
        """The model on the record (v, y): its free-run fit and rms (``free_run``) and its own warnings
        there (``trust.model_warnings``; ``input_assumptions=False``: without ``input_not_white``, for a
        caller that reads only the ``UNTRUSTED`` ones). ``compiled`` (one run): fit and rms by
        ``window_fit`` (equal to rounding), as the streaming engine evaluates."""
        y = np.asarray(y, dtype=float)
        fit, rms = (self.window_fit(v, y) if compiled and runs is None
                    else fit_and_rms(y, self.free_run(v, y, runs)))
        return Evaluation(fit, rms, model_warnings(self, np.asarray(v, dtype=float), y, fit, input_assumptions))

    def to_json(self, v: np.ndarray | None = None, y: np.ndarray | None = None, runs: Runs | None = None,
                warnings: Sequence[ModelWarning] = (), evaluation: Evaluation | None = None) -> dict:
        """The ``identify --json`` document; fit_percent and rms when data (v, y) is given (with
        ``free_run``: every run from its own start). ``warnings``: the given ones (e.g. the record's)
        and, with data, the model's own (``trust.model_warnings``). ``evaluation``: ``evaluate(v, y,
        runs)`` when the caller has it."""
        doc: dict[str, Any] = {
            "method": self.method,
            "order": int(self.order if self.order is not None else self.linear.order),
            "poles": _roots_json(self.linear.poles),
            "zeros": _roots_json(self.linear.zeros),
        }
        if self.gain is not None:
            doc["gain"] = float(self.gain)
        doc["stable"] = self.linear.is_stable()  # all poles inside the unit circle
        doc["a"] = self.linear.a[1:].tolist()
        doc["b"] = self.linear.b.tolist()
        if self.markov is not None:
            doc["markov"] = np.asarray(self.markov, dtype=float).tolist()
        v = None if v is None else np.asarray(v, dtype=float)
        sample_range = None if v is None else (float(v.min()), float(v.max()))
        if self.nonlinearity is not None:
            doc["nonlinearity"] = self.nonlinearity.to_json(sample_range)
        if self.feedback_nonlinearity is not None:
            doc["feedback_nonlinearity"] = self.feedback_nonlinearity.to_json(
                None if y is None else (float(np.min(y)), float(np.max(y)))
            )
        if self.uncertainty is not None:
            self.uncertainty.add_to(doc, self.nonlinearity)
        if v is not None and y is not None:
            evaluation = self.evaluate(v, y, runs) if evaluation is None else evaluation
            doc["fit_percent"], doc["rms"] = _finite_or_none(evaluation.fit), _finite_or_none(evaluation.rms)
            warnings = (*warnings, *evaluation.warnings)
        doc["warnings"] = warnings_json(warnings)
        for key, value in self.extra.items():
            doc.setdefault(key, value)
        return doc


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def strict_json(value: Any) -> Any:
    """A copy that ``json.dumps(..., allow_nan=False)`` accepts: NaN/inf become null, numpy
    scalars and arrays Python numbers and lists, tuples lists."""
    if isinstance(value, dict):
        return {str(k): strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [strict_json(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    return value
