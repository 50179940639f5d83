"""The identification methods by their CLI names, and the options they share.

Each entry names the module and function that implement it; every such function has the
signature ``fn(v, y, options, **kwargs) -> IdentificationResult`` and takes the excitation
``v`` and the response ``y`` as 1-D arrays of equal length.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import UsageError
from .affine import degraded_to_gain
from .result import IdentificationResult
from .runs import Runs


@dataclass(frozen=True)
class IdentifyOptions:
    """Options of ``hammer-ros identify`` (None = the method's documented default)."""

    order: int = 3
    delay: int = 1
    mu: int | None = None
    poly: int = 3
    partition: tuple[float, ...] | None = None
    tau_max: int | None = None
    harmonic: tuple[Any, Any] | None = None  # (v, y) of the single-harmonic record
    feedback_partition: tuple[float, ...] | None = None  # PLLS: breakpoints d of the feedback map h(y)
    reference: np.ndarray | None = None  # closed loop: the external reference r, the instrument (``instrumental``)
    runs: Runs | None = None  # separate experiments laid end to end (``runs``); None: one continuous record


METHODS: dict[str, tuple[str, str, dict]] = {
    "cls-arx": ("correlation_least_squares", "identify_cls", {"structure": "arx"}),
    "cls-markov": ("correlation_least_squares", "identify_cls", {"structure": "markov"}),
    "nls-arx": ("correlation_least_squares", "identify_nls", {"structure": "arx"}),
    "nls-markov": ("correlation_least_squares", "identify_nls", {"structure": "markov"}),
    "ls-arx": ("correlation_least_squares", "identify_ls", {"structure": "arx"}),
    "ls-markov": ("correlation_least_squares", "identify_ls", {"structure": "markov"}),
    "plls-hammerstein": ("piecewise_linear_ls", "identify_plls", {"structure": "hammerstein"}),
    "plls-feedback": ("piecewise_linear_ls", "identify_plls", {"structure": "feedback"}),
    "plls-hammerstein-feedback": (
        "piecewise_linear_ls",
        "identify_plls",
        {"structure": "hammerstein_feedback"},
    ),
    "bf-hammerstein": ("billings_fakhouri", "identify_bf", {"structure": "hammerstein"}),
    "bf-feedforward": ("billings_fakhouri", "identify_bf", {"structure": "feedforward"}),
    "semiparametric": ("semiparametric", "identify_semiparametric", {}),
}


# methods whose bounds come from subseries; semiparametric: poles and zeros only (its map comes from
# the single-harmonic record, which is not resampled)
SUBSERIES_METHODS = ("bf-hammerstein", "bf-feedforward", "semiparametric")
REFERENCE_METHODS = ("cls-arx", "cls-markov", "plls-hammerstein")  # the ones with an instrumented form


def identify(method: str, v: np.ndarray, y: np.ndarray, options: IdentifyOptions) -> IdentificationResult:
    """Run the method called ``method`` (a key of METHODS) on the record (v, y)."""
    try:
        module_name, function_name, kwargs = METHODS[method]
    except KeyError:
        raise UsageError(f"--method: unknown method {method!r} (choose from {', '.join(METHODS)})") from None
    if options.reference is not None and method not in REFERENCE_METHODS:
        raise UsageError(f"--reference: not for {method} (instrumented methods: {', '.join(REFERENCE_METHODS)})")
    module = importlib.import_module(f"{__package__}.{module_name}")
    v, y, function = np.asarray(v, float), np.asarray(y, float), getattr(module, function_name)
    result = degraded_to_gain(function(v, y, options, **kwargs), v)  # two input levels: an affine map
    if method in SUBSERIES_METHODS:  # no tractable covariance: subseries bounds (uncertainty.subseries_uncertainty)
        from .uncertainty import guarded, subseries_uncertainty

        bounds = guarded(lambda: subseries_uncertainty(
            lambda a, b, runs: function(a, b, replace(options, runs=runs), **kwargs), v, y, result,
            with_map=method != "semiparametric", runs=options.runs))
        result = replace(result, uncertainty=bounds)
    return result
