"""Section 5, peers: time and validation NRMSE of hammer_ros's methods vs SysIdentPy FROLS."""

from __future__ import annotations

import csv
import importlib.util
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...identification.correlation_least_squares import DEFAULT_MU, default_tau_max
from ...identification.methods import IdentifyOptions, identify
from .common import (
    DATA_DIR,
    SYSIDENTPY_VERSION,
    Section,
    _median,
    _timed,
    hammerstein_record,
)


@dataclass(frozen=True)
class PeerCase:
    """An estimation and a validation record and the model settings used on them."""

    name: str
    v_est: np.ndarray
    y_est: np.ndarray
    v_val: np.ndarray
    y_val: np.ndarray
    order: int
    description: str
    offset: tuple[float, float] = (0.0, 0.0)  # (v, y) subtracted before hammer_ros identifies


def g1_case() -> PeerCase:
    """Paper 000 Table 2's setting: G1, F2 = tanh(8 v)/8, Gaussian input std 1/(2 pi), 5001
    noiseless samples; validation on a fresh 5001-sample record (another seed)."""
    v_est, y_est = hammerstein_record(5001, seed=11)
    v_val, y_val = hammerstein_record(5001, seed=12)
    return PeerCase("G1, tanh(8v)/8", v_est, y_est, v_val, y_val, order=3,
                    description="paper 000 G1 + F2, Gaussian std 1/(2 pi), 5001 est + 5001 val samples, noiseless")


def cascaded_tanks_case() -> PeerCase:
    """The cascaded-tanks benchmark (hammer_ros/data/cascaded_tanks): estimation record uEst/yEst,
    validation uVal/yVal, 1024 samples each, Ts = 4 s. hammer_ros's models start from rest, so
    they run on the data minus the estimation means (both records, same offset)."""
    with open(DATA_DIR / "cascaded_tanks" / "dataBenchmark.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    col = {k: np.array([float(r[k]) for r in rows]) for k in ("uEst", "yEst", "uVal", "yVal")}
    return PeerCase("cascaded tanks (real)", col["uEst"], col["yEst"], col["uVal"], col["yVal"], order=2,
                    description="Schoukens et al. 2016, 1024 est + 1024 val samples, Ts 4 s",
                    offset=(float(col["uEst"].mean()), float(col["yEst"].mean())))


PEER_METHODS = ("cls-markov", "cls-arx", "nls-arx", "plls-hammerstein", "bf-hammerstein")
VALIDATION_SKIP = 5  # samples at the start of the validation record left out of every NRMSE (FROLS's seed)


def nrmse(y: np.ndarray, y_sim: np.ndarray, skip: int = VALIDATION_SKIP) -> float:
    """||y - y_sim|| / ||y - mean(y)|| over samples ``skip``.. (1 - fit_percent / 100); inf for a
    diverged simulation."""
    y, y_sim = np.asarray(y, float)[skip:], np.asarray(y_sim, float)[skip:]
    with np.errstate(all="ignore"):
        error = float(np.linalg.norm(y - y_sim) / np.linalg.norm(y - np.mean(y)))
    return error if math.isfinite(error) else float("inf")


def _divergence_note(error: float) -> str | None:
    return "free run diverges (unstable or wrong-sign model)" if error > 10 else None


def hammer_ros_peer_rows(case: PeerCase, repeats: int) -> list[dict]:
    rows = []
    dv, dy = case.offset
    options = IdentifyOptions(order=case.order, delay=1, poly=3)
    for method in PEER_METHODS:
        times, result = [], None
        try:
            for _ in range(repeats):
                elapsed, result = _timed(lambda method=method: identify(method, case.v_est - dv, case.y_est - dy,
                                                                        options))
                times.append(elapsed)
            with np.errstate(all="ignore"):
                error = nrmse(case.y_val, result.simulate(case.v_val - dv) + dy)
        except Exception as exc:  # a failing method is a row of the table, not a crash
            rows.append({"case": case.name, "tool": "hammer_ros", "method": method, "note": f"failed: {exc}"})
            continue
        settings = f"order {case.order}, delay 1" + (", poly 3" if method.split("-")[0] in ("cls", "nls") else "")
        if method == "cls-markov":
            settings += f", mu {DEFAULT_MU}, tau_max {default_tau_max(case.order, DEFAULT_MU)}"
        rows.append({"case": case.name, "tool": "hammer_ros", "method": method, "settings": settings,
                     "seconds": _median(times), "nrmse": error, "note": _divergence_note(error)})
    return rows


def sysidentpy_available() -> bool:
    return importlib.util.find_spec("sysidentpy") is not None


def frols_peer_row(case: PeerCase, degree: int, lags: int, terms: int) -> dict:
    """SysIdentPy FROLS (polynomial basis of ``degree``, ylag = xlag = ``lags``, AIC order
    selection among up to ``terms`` terms, least squares); free run (``predict`` with
    steps_ahead=None) on the validation input from its first ``lags`` measured outputs."""
    from sysidentpy.basis_function import Polynomial
    from sysidentpy.model_structure_selection import FROLS
    from sysidentpy.parameter_estimation import LeastSquares

    model = FROLS(order_selection=True, n_info_values=terms, ylag=lags, xlag=lags, info_criteria="aic",
                  estimator=LeastSquares(), basis_function=Polynomial(degree=degree), model_type="NARMAX")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        elapsed, _ = _timed(lambda: model.fit(X=case.v_est.reshape(-1, 1), y=case.y_est.reshape(-1, 1)))
        with np.errstate(all="ignore"):
            y_sim = model.predict(X=case.v_val.reshape(-1, 1), y=case.y_val[:lags].reshape(-1, 1)).ravel()
    return {"case": case.name, "tool": f"SysIdentPy {SYSIDENTPY_VERSION}", "method": "FROLS",
            "settings": f"Polynomial degree {degree}, ylag = xlag = {lags}, AIC over <= {terms} terms, "
                        f"LeastSquares ({len(model.final_model)} terms chosen)",
            "seconds": elapsed, "nrmse": nrmse(case.y_val, y_sim, max(lags, VALIDATION_SKIP))}


def peer_section(frols: Sequence[tuple[int, int, int]], repeats: int) -> Section:
    section = Section("peers", "5. Peers: identification time and free-run validation NRMSE", [
        ("case", "data"), ("tool", "tool"), ("method", "method"), ("settings", "settings"),
        ("seconds", "identify s"), ("nrmse", "val NRMSE"), ("speedup", "FROLS time / this"),
        ("better", "NRMSE below best FROLS"), ("note", "note")])
    have_peer = sysidentpy_available()
    if not have_peer:
        section.notes.append("SysIdentPy rows skipped: sysidentpy is not installed (run `make bench-deps`, which "
                             f"installs sysidentpy=={SYSIDENTPY_VERSION} from requirements/bench.txt)")
    for case in (g1_case(), cascaded_tanks_case()):
        ours = hammer_ros_peer_rows(case, repeats)
        peers = [frols_peer_row(case, *config) for config in frols] if have_peer else []
        if peers:
            fastest = min(p["seconds"] for p in peers)
            best = min(p["nrmse"] for p in peers)
            for row in ours:
                if "seconds" in row:
                    row["speedup"] = fastest / row["seconds"]
                    row["better"] = row["nrmse"] < best
        section.rows += ours + peers
    section.notes.append(f"NRMSE = ||y_val - y_sim|| / ||y_val - mean(y_val)|| of the free-run simulation on the "
                         f"validation record from sample {VALIDATION_SKIP} on (hammer_ros models start from rest; "
                         f"FROLS is seeded with the first `lags` measured outputs); hammer_ros times are medians of "
                         f"repeated runs, FROLS one fit each")
    section.notes.append("speedup: the fastest FROLS fit on the same data over this method's time")
    return section


