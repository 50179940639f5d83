"""What every extension shares: the failure type and its reason, the extended model and its
maps, and the fitting context (data, baseline, tests, the L-N-L and Wiener fits used by two
causes)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ...errors import IdentificationError
from ...identification.linear import LinearModel
from ...identification.runs import Runs, per_run, several
from ..evidence import LineTest, WindowTest
from ..hammerstein import HammersteinModel, transient_samples
from ..split import Split
from ..wiener_hammerstein import WienerHammersteinFit, fit_nested_wiener, fit_wiener_hammerstein


class NotFitted(Exception):
    """An extension that cannot be fitted to this record; the message is the one-line reason
    the diagnosis JSON gives (``not_fitted``). ``suggests``: the cause whose model the attempt
    found to fit as well (the diagnosis then fits that one too)."""

    def __init__(self, reason: str, suggests: str | None = None):
        super().__init__(reason)
        self.suggests = suggests


# what an extension may raise on a record it cannot fit (too short, constant, non-finite, singular)
NUMERICAL_FAILURES = (NotFitted, IdentificationError, np.linalg.LinAlgError, ValueError, FloatingPointError)


def failure_reason(error: Exception) -> str:
    """The one-line reason of an extension that could not be fitted (``not_fitted``)."""
    text = " ".join(str(error).split()) or type(error).__name__
    return text if isinstance(error, (NotFitted, IdentificationError)) else f"{type(error).__name__}: {text}"


WIENER_RANDOM_FRONTS = 12  # random G1 of the Wiener model, screened by their start's error; the best is refined


@dataclass(frozen=True)
class MapPlot:
    """An identified static map for the report: f(x) on a grid."""

    title: str
    x: np.ndarray
    y: np.ndarray


@dataclass(frozen=True, eq=False)
class ExtendedModel:
    """The extension for ``cause``: its structure, its free-run validation output, the numbers
    that describe it (JSON-able), its identified maps and, where the model is one simulator of
    the input (not re-fitted along the record), ``simulate``: input -> output, on which a
    compound explanation (``chain``) builds its next step."""

    cause: str
    structure: str
    validation_output: np.ndarray
    details: dict = field(default_factory=dict)
    maps: tuple[MapPlot, ...] = ()
    simulate: Callable[[np.ndarray], np.ndarray] | None = None


@dataclass(frozen=True, eq=False)
class Context:
    """What every extension may use: the data, the baseline, the line and window tests. The
    estimation fits treat the estimation runs (``split.runs_est``) as separate experiments: every
    simulation, filter and regressor run by run, each run from rest at its first input
    (``per_run``, ``estimation_simulation``)."""

    split: Split
    baseline: HammersteinModel
    lines: LineTest
    windows: WindowTest

    @property
    def skip(self) -> int:
        return transient_samples(self.baseline.linear.poles, self.split.n_est)

    @property
    def runs(self) -> Runs | None:
        """The estimation part's runs when it holds several, else None (the one-record path)."""
        return several(self.split.runs_est)

    def estimation_simulation(self, simulate: Callable[[np.ndarray], np.ndarray],
                              v: np.ndarray | None = None) -> np.ndarray:
        """simulate on the estimation input (or ``v``, a signal over the estimation samples), every
        run on its own from rest at its first input: the output a fit's cost compares with y_est."""
        return per_run(simulate, self.split.v_est if v is None else v, self.runs)

    @property
    def map_segments(self) -> int:
        """Segments of the maps of the L-N-L family: one more than the baseline's."""
        return self.baseline.partition.size + 1

    @cached_property
    def wiener_hammerstein(self) -> WienerHammersteinFit | Exception:
        """The L-N-L model (``fit_wiener_hammerstein`` of the baseline's order, both relative
        degrees), fitted once for the extensions that use it, or why it could not be."""
        base, s = self.baseline, self.split
        try:
            return fit_wiener_hammerstein(s.v_est, s.y_est, base.order, base.delay, segments=self.map_segments,
                                          direct_term=True, runs=self.runs)
        except (IdentificationError, np.linalg.LinAlgError, ValueError) as error:
            return error

    @cached_property
    def nested_wiener(self) -> WienerHammersteinFit | Exception:
        """The Wiener model y = f(G1[v]) (``fit_nested_wiener``, the baseline's order and delay)
        from the BLA, from the L-N-L model's G1 (which finds an even map's dynamics where the
        BLA vanishes) and from the best of WIENER_RANDOM_FRONTS random G1 (``random_front``)
        by the error of its start (the map fitted, no iteration), when that beats the start
        error of the other two; the one with the smallest estimation error; or why not. The
        random fronts matter where both other starts stall, e.g. a rectified output of a
        relative-degree-3 plant under a PRBS (2 of 8 draws)."""
        base, s = self.baseline, self.split
        lnl = self.wiener_hammerstein
        fronts = [None] + ([] if isinstance(lnl, Exception) else [lnl.model.front])
        fits: list = []
        error_seen: Exception = IdentificationError("no start for the Wiener model")

        def fit(front: LinearModel | None, iterations: int = 200) -> WienerHammersteinFit:
            bla = fits[0].bla if fits else None  # computed once, by the first fit
            return fit_nested_wiener(s.v_est, s.y_est, base.order, base.delay, self.map_segments, iterations,
                                     front, bla, self.runs)

        given = np.inf  # the smallest start error of the BLA and L-N-L starts
        for front in fronts:
            try:
                fits.append(fit(front))
                given = min(given, fit(front, 0).rms)
            except (IdentificationError, np.linalg.LinAlgError, ValueError) as error:
                error_seen = error
        rng = np.random.default_rng(0)
        screened = []
        for front in (random_front(rng, base.order) for _ in range(WIENER_RANDOM_FRONTS)):
            try:
                screened.append((fit(front, 0).rms, front))
            except (IdentificationError, np.linalg.LinAlgError, ValueError):
                continue
        best = min(screened, key=lambda pair: pair[0], default=(np.inf, None))
        if best[0] < given:
            try:
                fits.append(fit(best[1]))
            except (IdentificationError, np.linalg.LinAlgError, ValueError) as error:
                error_seen = error
        return min(fits, key=lambda fit: fit.rms) if fits else error_seen


def random_front(rng: np.random.Generator, order: int) -> LinearModel:
    """A random stable G1 of ``order`` with unit gain: complex pole pairs of radius U(0.5, 0.95)
    at angles U(0.05, 1.5) rad, and a real pole U(0.3, 0.95) when the order is odd."""
    poles: list[complex] = []
    for _ in range(order // 2):
        pair = rng.uniform(0.5, 0.95) * np.exp(1j * rng.uniform(0.05, 1.5))
        poles += [pair, np.conj(pair)]
    if order % 2:
        poles.append(rng.uniform(0.3, 0.95))
    return LinearModel.from_zeros_poles([], poles, 1.0)


def map_plot(title: str, fn: Callable[[np.ndarray], np.ndarray], samples: np.ndarray) -> MapPlot:
    grid = np.linspace(float(np.min(samples)), float(np.max(samples)), 200)
    return MapPlot(title, grid, np.asarray(fn(grid), dtype=float))


def order_details(model: HammersteinModel) -> dict:
    return {"order": model.order, "delay": model.delay,
            "poles": [[float(p.real), float(p.imag)] for p in model.linear.poles]}
