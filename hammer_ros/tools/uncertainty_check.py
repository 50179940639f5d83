"""Monte Carlo check of the reported confidence bounds (docs/methods.md, "Confidence bounds").

Three known Hammerstein systems (paper 000's G1 with F = v + 4 v^3; a second-order resonant
block with the saturation tanh(8 v)/8; two real poles with a dead zone), Gaussian white input of
std 1/(2 pi), 30 dB white output noise, N = 6000, ``runs`` realisations each. Per method:
``coverage``, the share of the 95 % intervals est +- 1.96 sd that hold the true poles' real and
imaginary parts (the imaginary part of a real pole, reported with sd 0, is left out), and
``sd_ratio``, the median reported sd over the Monte Carlo spread of the estimates (per pole part).
``cost`` measures the solve with and without the bounds (the node's ``solve_snapshot``).

    python -m hammer_ros.tools.uncertainty_check [--runs 30] [--methods cls-markov,plls-hammerstein] [--cost]
"""

from __future__ import annotations

import argparse
import functools
import json
import time
import timeit
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..identification.linear import LinearModel
from ..identification.methods import IdentifyOptions, identify
from ..identification.simulate import add_noise, simulate_hammerstein

SAMPLES = 6000
NOISE_TO_SIGNAL = 10 ** (-30 / 20)  # 30 dB
INPUT_STD = 1.0 / (2.0 * np.pi)
Z95 = 1.96


@dataclass(frozen=True)
class System:
    name: str
    linear: LinearModel
    nonlinearity: Callable[[np.ndarray], np.ndarray]


SYSTEMS = (
    System("G1, v + 4v^3", LinearModel.from_zeros_poles([1.25, 0.5], [0.95, 0.245 + 0.574j, 0.245 - 0.574j]),
           lambda v: v + 4.0 * v**3),
    System("resonant pair, tanh(8v)/8", LinearModel.from_zeros_poles([0.3], [0.8 + 0.3j, 0.8 - 0.3j]),
           lambda v: np.tanh(8.0 * v) / 8.0),
    System("real poles 0.9, 0.6, dead zone 0.05", LinearModel.from_zeros_poles([-0.5], [0.9, 0.6]),
           lambda v: np.sign(v) * np.maximum(np.abs(v) - 0.05, 0.0)),
)


def record(system: System, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One realisation: fresh input and output noise."""
    rng = np.random.default_rng([seed, 11])
    v = INPUT_STD * rng.standard_normal(SAMPLES)
    return v, add_noise(simulate_hammerstein(v, system.nonlinearity, system.linear), NOISE_TO_SIGNAL, seed=[seed, 12])


def _matched(truth: np.ndarray, doc_roots: list, doc_std: list) -> tuple[np.ndarray, np.ndarray]:
    """The estimated roots and their sds in the order of ``truth`` (one-to-one closest)."""
    roots = np.array([complex(*r) for r in doc_roots])
    _, cols = linear_sum_assignment(np.abs(truth[:, None] - roots[None, :]))
    return roots[cols], np.asarray(doc_std, dtype=float)[cols]


def monte_carlo(system: System, method: str, runs: int, seed: int = 0) -> dict:
    """coverage and sd_ratio (module docstring) of ``method`` on ``system`` over ``runs`` records."""
    truth = system.linear.poles
    estimates, sds = [], []
    for run in range(runs):
        v, y = record(system, seed + run)
        doc = identify(method, v, y, IdentifyOptions(order=system.linear.order, delay=1)).to_json()
        p, sd = _matched(truth, doc["poles"], doc["poles_std"])
        estimates.append(p)
        sds.append(sd)
    estimates, sds = np.array(estimates), np.array(sds)
    error = np.stack([estimates.real - truth.real, estimates.imag - truth.imag], axis=-1)
    checked = np.ones(error.shape[1:], dtype=bool)
    checked[:, 1] = truth.imag != 0.0
    covered = (np.abs(error) <= Z95 * sds)[:, checked]
    spread = np.stack([estimates.real.std(axis=0, ddof=1), estimates.imag.std(axis=0, ddof=1)], axis=-1)
    ratio = np.median(sds, axis=0)[checked] / spread[checked]
    return {"system": system.name, "method": method, "runs": runs, "coverage": float(covered.mean()),
            "sd_ratio": [round(float(r), 3) for r in ratio], "intervals": int(covered.size)}


def solve_cost(window: int = 4000, repeats: int = 200) -> dict:
    """p50 / p99 ms of the node's CLS mu-Markov solve (``solve_snapshot``, W = ``window``, tau_max 66) with
    the bounds and without them (the compiled solve without its bounds and ``cls_uncertainty`` replaced
    by None; wall time and the thread's CPU time, which a loaded machine inflates less), the reference's
    bounds alone, and the bench's goal row (in a ``SolverProcess`` beside ingestion at half its limit)
    with the bounds."""
    from ..identification import correlation_least_squares as cls
    from ..streaming.engine import solve_snapshot
    from .bench import SolveCase, feed_engine, hammerstein_record, loaded_solve_latencies

    case = SolveCase("cls-markov", 66, 30)
    v, y = hammerstein_record(window, seed=4)
    snap = feed_engine(case.config(window), v, y, chunk=1000).snapshot()
    with_bounds, compiled = cls.cls_uncertainty, cls.compiled_steps
    times: dict[str, list[float]] = {"with": [], "without": []}
    cpu: dict[str, list[float]] = {"with": [], "without": []}
    solve_snapshot(snap)
    try:
        for _ in range(repeats):  # alternately, so that both see the same load of the machine
            for label, bounds in (("with", True), ("without", False)):
                cls.cls_uncertainty = with_bounds if bounds else lambda *args: None
                cls.compiled_steps = functools.partial(compiled, bounds=bounds)
                started = time.thread_time()
                times[label].append(solve_snapshot(snap).solve_seconds * 1e3)
                cpu[label].append((time.thread_time() - started) * 1e3)
    finally:
        cls.cls_uncertainty, cls.compiled_steps = with_bounds, compiled
    out = {label: {"p50_ms": float(np.percentile(t, 50)), "p99_ms": float(np.percentile(t, 99)),
                   "cpu_p50_ms": float(np.percentile(cpu[label], 50)),
                   "cpu_p99_ms": float(np.percentile(cpu[label], 99))} for label, t in times.items()}
    arguments = (snap.phi_vv, snap.phi_yv, snap.v, snap.y, 3, 1, 30, *cls._step_two_map(snap.v, 3, None))
    out["bounds_alone_ms"] = 1e3 * min(timeit.repeat(lambda: with_bounds(*arguments), number=20, repeat=5)) / 20
    process = loaded_solve_latencies(case, window, repeats, in_process=True)  # the bench's goal row, with the bounds
    out["solver_process_loaded"] = {"p50_ms": process["solve_p50"], "p99_ms": process["solve_p99"]}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--methods", default="cls-markov,plls-hammerstein")
    parser.add_argument("--cost", action="store_true", help="also time the solve with and without the bounds")
    args = parser.parse_args(argv)
    rows = [monte_carlo(system, method, args.runs) for method in args.methods.split(",") for system in SYSTEMS]
    for row in rows:
        print(json.dumps(row))
    if args.cost:
        print(json.dumps({"solve_cost": solve_cost()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
