"""When not to trust a model: the ``warnings`` of every model JSON (identify, replay, ``~/model``,
diagnose).

Pure checks on arrays, each returning a tuple of ``ModelWarning(code, message)``:

- ``poor_fit``: the free-run fit on the model's own data, 100 (1 - ||y - y_sim|| / ||y - mean y||),
  is below ``POOR_FIT_PERCENT`` (0 %: the model explains less than the mean does).
- ``not_exciting``: an output whose spread is within its quantisation (std(y) < ``QUANTISATION_STEPS``
  times the smallest step between its distinct values, e.g. an encoder that toggles between
  two counts: the input did not move it), an input whose std is below ``STILL_INPUT`` of its
  level (a held command and its noise), or an input with fewer distinct levels than the input
  map has parameters (two levels determine an affine map, a gain, and nothing more:
  ``affine.degraded_to_gain``). A two-level input on its own is no reason: a step is one.
- ``input_not_white``: a correlation method on an input that breaks its assumption. CLS (paper 000,
  sec. 3.1) needs a separable input (Gaussian, a sine), Billings-Fakhouri (paper 003) a white
  Gaussian one. Steps, ramps and trajectories are slowly varying (lag-1 autocorrelation
  rho(1) > ``SLOW_RHO``) and either far from Gaussian (|skewness| > ``MAX_SKEW`` or |excess
  kurtosis| > ``MAX_EXCESS_KURTOSIS``: a step has two values, a ramp is uniform, excess kurtosis
  -1.2) or held (more than ``MAX_HELD`` of the samples equal to the one before: setpoints).
- ``closed_loop``: the diagnosis' feedback test (``diagnosis.closed_loop``: the residual against
  the input's future innovations) fails on an input that is a random process (not a trajectory);
  the test is run above this layer (``identify``'s ``cli._closed_loop``, the diagnosis), which
  makes the warning with ``closed_loop_warning``.
- ``irregular_sampling`` is made where the time stamps are read (``io.resample``).

``UNTRUSTED`` codes make the streaming engine hold a model back as ``uncertain``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .compiled_loops import distinct_values, spread_figures

POOR_FIT_PERCENT = 0.0
QUANTISATION_STEPS = 2.0  # a spread of fewer quantisation steps than this is within the quantisation
STILL_INPUT = 1e-3  # an input whose std is below this fraction of its level barely varies
SLOW_RHO = 0.9  # lag-1 autocorrelation above which an input varies slowly (steps, ramps, trajectories)
WHITE_RHO = 0.3  # |lag-1 autocorrelation| above which an input is not white (Billings-Fakhouri)
MAX_SKEW = 0.5
MAX_EXCESS_KURTOSIS = 1.0
MAX_HELD = 0.5  # an input held at its previous value on more samples than this is a staircase of setpoints
UNTRUSTED = ("poor_fit", "not_exciting")  # models with these are not published as confident ones
SEPARABLE_INPUT_METHODS = ("cls-arx", "cls-markov")  # paper 000: a separable (e.g. Gaussian) input
WHITE_GAUSSIAN_METHODS = ("bf-hammerstein", "bf-feedforward")  # paper 003: a white Gaussian input
FOR_STEPS = "use --refine or plls-hammerstein (docs/methods.md, 'Step and ramp inputs')"


@dataclass(frozen=True)
class ModelWarning:
    """One reason not to trust a model: a fixed ``code`` and a one-line ``message``. ``holds_back``:
    whether an ``UNTRUSTED`` code keeps the model from being published as a confident one (False
    for a map reduced to the gain that two input levels do determine: the model then claims no
    more than the data show)."""

    code: str
    message: str
    holds_back: bool = True

    def to_json(self) -> dict[str, str]:
        return {"code": self.code, "message": self.message}


def warnings_json(warnings: Iterable[ModelWarning]) -> list[dict[str, str]]:
    return [w.to_json() for w in warnings]


def untrusted(warnings: Iterable[ModelWarning]) -> ModelWarning | None:
    """The first warning whose code is ``UNTRUSTED``, None when there is none."""
    return next((w for w in warnings if w.code in UNTRUSTED and w.holds_back), None)


def fit_warnings(fit: float | None, data: str = "its own data") -> tuple[ModelWarning, ...]:
    """``poor_fit`` when the fit on ``data`` (the model's own) is below POOR_FIT_PERCENT (or not finite)."""
    if fit is not None and math.isfinite(fit) and fit >= POOR_FIT_PERCENT:
        return ()
    figure = "not finite" if fit is None or not math.isfinite(fit) else f"{fit:.1f} %"
    return (ModelWarning("poor_fit", f"the model's fit on {data} is {figure}: it explains less of the "
                                     "output than its mean does"),)


def quantisation_step(x: np.ndarray) -> float:
    """The smallest step between distinct values of x (inf for a constant)."""
    levels = np.unique(np.asarray(x, dtype=float))
    return float(np.diff(levels).min()) if levels.size > 1 else math.inf


def _distinct_values(x: np.ndarray, enough: int) -> int:
    """The number of distinct values of x, or some number >= ``enough`` when it has that many (the
    first samples usually show it: a random input differs at every sample)."""
    if enough <= 2:
        return enough
    head = distinct_values(x[:64])
    return head if head >= enough else distinct_values(x)


def map_levels_needed(nonlinearity: Any) -> int:
    """Distinct input levels that determine the input map: p + 1 for a polynomial of degree p, one
    per knot plus one for a piecewise-linear map (0: no map, or a map known only at points)."""
    from .static_maps import PiecewiseLinearMap, PolynomialMap

    if isinstance(nonlinearity, PolynomialMap):
        coefficients = nonlinearity.coefficients.tolist()
        while coefficients and coefficients[-1] == 0.0:  # the degree + 1 (trailing zeros dropped)
            coefficients.pop()
        return len(coefficients) if nonlinearity.coefficients.size > 2 else 0
    if isinstance(nonlinearity, PiecewiseLinearMap):
        return int(nonlinearity.breakpoints.size) + 1
    return 0


def excitation_warnings(v: np.ndarray, y: np.ndarray, nonlinearity: Any = None,
                        nonlinear_method: bool = False) -> tuple[ModelWarning, ...]:
    """``not_exciting`` (module docstring): the output's spread within its quantisation, the input's
    spread within its noise floor (below ``STILL_INPUT`` of its level), or fewer input levels than
    the map needs (``nonlinear_method``: the method fits a nonlinear map, so two levels are too few
    whatever map it returned)."""
    v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
    if v.size == 0 or y.size == 0:
        return ()
    out = []
    # a non-zero change of at most std / QUANTISATION_STEPS bounds the quantisation step (at most any non-zero
    # difference of two values: rounding is monotone): the spread is then not within it, decided without the sort
    spread, _, _, moves = spread_figures(y, 1.0 / QUANTISATION_STEPS)
    if spread == 0.0 or not moves:
        step = quantisation_step(y)
        if spread < QUANTISATION_STEPS * step or spread == 0.0:
            out.append(ModelWarning("not_exciting", f"the output varies within its quantisation (std {spread:.3g}, "
                                                    f"{np.unique(y).size} distinct values {step:.3g} apart): the "
                                                    "input did not move it"))
    spread, high, low, _ = spread_figures(v)
    level = max(high, -low)
    if spread <= STILL_INPUT * level:
        out.append(ModelWarning("not_exciting", f"the input barely varies (std {spread:.3g} at a level of "
                                                f"{level:.3g}): what it excites is within noise"))
    needed = max(map_levels_needed(nonlinearity), 3 if nonlinear_method else 0)
    levels = _distinct_values(v, needed)
    if 1 < levels < needed:
        determined = "a gain (an affine map)" if levels == 2 else "a coarse map"
        reduced = map_levels_needed(nonlinearity) <= levels  # the map returned is what the levels determine
        out.append(ModelWarning("not_exciting", f"the input takes {levels} distinct values, too few for the input "
                                                f"map ({needed} needed): only {determined} is determined"
                                + (", and the model's map is that" if reduced else ""), holds_back=not reduced))
    return tuple(out)


def input_shape(v: np.ndarray) -> tuple[float, float, float, float]:
    """(lag-1 autocorrelation, skewness, excess kurtosis, fraction of samples held at the previous
    value) of the input (zeros for a constant)."""
    x = np.asarray(v, dtype=float)
    if x.size < 3:
        return 0.0, 0.0, 0.0, 0.0
    held = float(np.mean(x[1:] == x[:-1]))
    x = x - x.mean()
    variance = float(x @ x) / x.size
    if variance <= 0.0:
        return 0.0, 0.0, 0.0, held
    rho = float(x[1:] @ x[:-1]) / (variance * x.size)
    square = x * x  # products, not x**3 and x**4: numpy's power is ~10 x slower (a solve calls this)
    return rho, float(square @ x) / x.size / variance**1.5, float(square @ square) / x.size / variance**2 - 3.0, held


def is_trajectory(v: np.ndarray, shape: tuple[float, float, float, float] | None = None) -> bool:
    """Whether the input is a step, ramp or trajectory rather than a random process (module docstring);
    ``shape``: ``input_shape(v)`` when the caller has it."""
    rho, skew, kurtosis, held = input_shape(v) if shape is None else shape
    gaussian = abs(skew) <= MAX_SKEW and abs(kurtosis) <= MAX_EXCESS_KURTOSIS
    return rho > SLOW_RHO and not (gaussian and held <= MAX_HELD)


def whiteness_warnings(method: str, v: np.ndarray) -> tuple[ModelWarning, ...]:
    """``input_not_white`` for a correlation method whose input assumption ``v`` breaks (module docstring)."""
    if method not in SEPARABLE_INPUT_METHODS and method not in WHITE_GAUSSIAN_METHODS:
        return ()
    rho, skew, kurtosis, held = measured = input_shape(v)
    gaussian = abs(skew) <= MAX_SKEW and abs(kurtosis) <= MAX_EXCESS_KURTOSIS
    shape = (f"lag-1 autocorrelation {rho:.2f}, skewness {skew:.2f}, excess kurtosis {kurtosis:.2f}, "
             f"{100 * held:.0f} % of samples held")
    if method in SEPARABLE_INPUT_METHODS and is_trajectory(v, measured):
        return (ModelWarning("input_not_white", f"{method} assumes a separable (e.g. Gaussian) input; this one "
                                                f"varies slowly and is not Gaussian ({shape}: steps, ramps or a "
                                                f"trajectory): {FOR_STEPS}"),)
    if method in WHITE_GAUSSIAN_METHODS and (abs(rho) > WHITE_RHO or not gaussian or held > MAX_HELD):
        return (ModelWarning("input_not_white", f"{method} assumes a white Gaussian input; this one is not "
                                                f"({shape}): {FOR_STEPS}"),)
    return ()


def closed_loop_warning(value: float, bound: float) -> ModelWarning:
    return ModelWarning("closed_loop", f"the input depends on past residuals (feedback test {value:.3g} > "
                                       f"{bound:.3g}): a closed loop biases the estimate; give the external "
                                       "reference with --reference")


def model_warnings(result: Any, v: np.ndarray, y: np.ndarray, fit: float | None,
                   input_assumptions: bool = True) -> tuple[ModelWarning, ...]:
    """The warnings of an ``IdentificationResult`` on its data (v, y) with its fit there (a refined
    one, ``refinement``, is an output-error estimate: no ``input_not_white``; nor without
    ``input_assumptions``)."""
    nonlinear = not result.method.startswith("ls-")
    refined = "refined" in result.extra  # an output-error estimate: no assumption on the input's shape
    return (*fit_warnings(fit), *excitation_warnings(v, y, result.nonlinearity, nonlinear),
            *(() if refined or not input_assumptions else whiteness_warnings(result.method, v)))
