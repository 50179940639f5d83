"""Shared pieces of the bench: the plans (sizes of a run), the tables (``Section``), timing helpers, the
machine's description and the generated Hammerstein record with its batch FFT correlations."""

from __future__ import annotations

import datetime
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.fft

from ...identification.excitation import gaussian_white_noise
from ...identification.simulate import simulate_hammerstein
from ...reproduce.cls import G1, INPUT_STD, NONLINEARITIES
from ...streaming.config import EngineConfig
from ...streaming.engine import StreamingEngine

DATA_DIR = Path(__file__).resolve().parents[2] / "data"
SAMPLE_RATE = 1000.0  # Hz of the generated streams
SYSIDENTPY_VERSION = "0.9.0"  # requirements/bench.txt
F2 = NONLINEARITIES["F2"][1]  # tanh(8 v) / 8, paper 000


# ------------------------------------------------------------------------------------ plans
@dataclass(frozen=True)
class Plan:
    """Sizes of one bench run (``QUICK`` under 3 min, ``FULL`` under 15 min on 2 cores)."""

    name: str
    repeats: int  # repeats of each timed run (medians)
    ingest_samples: int
    ingest_taus: tuple[int, ...]
    ingest_windows: tuple[int, ...]
    ingest_forgetting: tuple[float, ...]
    ingest_chunk: int
    node_rates: dict[int, tuple[float, ...]]  # samples per message -> message rates (per topic) to try
    node_seconds: float
    replay_messages: dict[int, int]  # samples per message -> messages per topic
    replay_repeats: int
    solve_windows: tuple[int, ...]
    solve_repeats: int
    slow_solve_repeats: int  # PLLS and diagnose
    peer_frols: tuple[tuple[int, int, int], ...]  # (degree, lags, terms) of the FROLS runs
    memory_windows: tuple[int, ...]
    fleet_bags: int = 200  # small bags replayed serially and by `fleet --workers 2`
    # None: the node's ladders (``node_rates``); a step: the seeded search on rungs this far apart
    # (``_seeded_limits``, from the figures of the last run stored in NODE_LIMITS; ``node_rates``
    # are then only the start without a stored figure). Either run stores its figures there.
    node_step: float | None = None
    node_joint_rates: tuple[float, ...] = ()  # the six-joint row's ladder (full bench only: 70 s more in the quick one)
    node_budget: float | None = None  # s for the seeded searches (``node_section``); None: until they converge


QUICK = Plan(
    name="quick", repeats=3, ingest_samples=200_000, ingest_taus=(50, 200), ingest_windows=(10_000,),
    ingest_forgetting=(1.0, 0.999), ingest_chunk=1000,
    node_rates={1: (20000.0,), 100: (15000.0,)}, node_seconds=1.5, node_step=1.1, node_budget=70.0,
    replay_messages={1: 20_000, 100: 2_000}, replay_repeats=3, solve_windows=(4000,), solve_repeats=60,
    slow_solve_repeats=5,
    peer_frols=((3, 3, 15),), memory_windows=(10_000,), fleet_bags=100,
)
FULL = Plan(
    name="full", repeats=5, ingest_samples=1_000_000, ingest_taus=(50, 200), ingest_windows=(10_000, 100_000),
    ingest_forgetting=(1.0, 0.999), ingest_chunk=1000,
    node_rates={1: (1000.0, 2000.0, 5000.0, 7000.0, 10000.0, 12000.0, 14000.0, 20000.0),
                100: (500.0, 1000.0, 2000.0, 5000.0, 6000.0, 7000.0, 8500.0, 10000.0, 14000.0)},
    node_seconds=3.0, node_joint_rates=(4000.0, 8000.0, 16000.0, 24000.0),
    replay_messages={1: 100_000, 100: 10_000}, replay_repeats=3, solve_windows=(1000, 4000, 16000),
    solve_repeats=200, slow_solve_repeats=15, peer_frols=((3, 3, 15), (3, 4, 20), (3, 5, 30)),
    memory_windows=(10_000, 100_000, 1_000_000),
)


# ------------------------------------------------------------------------------------ tables
@dataclass
class Section:
    """One table: ``columns`` are (key, header); rows are dicts keyed like the columns."""

    key: str
    title: str
    columns: list[tuple[str, str]]
    rows: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def to_json(self) -> dict:
        return {"key": self.key, "title": self.title, "columns": [k for k, _ in self.columns], "rows": self.rows,
                "notes": self.notes, "seconds": round(self.seconds, 2)}

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(h for _, h in self.columns) + " |",
                 "|" + "---|" * len(self.columns)]
        lines += ["| " + " | ".join(_cell(row.get(k)) for k, _ in self.columns) + " |" for row in self.rows]
        lines += [""] + [f"- {note}" for note in self.notes]
        return "\n".join(lines).rstrip() + "\n"


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "**no**"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:.3g}" if abs(value) < 1e5 else f"{value:,.0f}"
    return str(value)


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), q))


def _median(values: Sequence[float]) -> float:
    return float(np.median(np.asarray(values, dtype=float)))


def children_cpu_seconds() -> float:
    """User + system CPU seconds of this process's children that have been waited for."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    started = time.perf_counter()
    out = fn()
    return time.perf_counter() - started, out


def machine() -> dict[str, Any]:
    """nproc, CPU model, RAM, Python / numpy versions and the date of this run."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem_kb = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                      if line.startswith("MemTotal"))
    except (OSError, StopIteration):
        mem_kb = 0
    return {"date": datetime.date.today().isoformat(), "nproc": os.cpu_count(), "cpu": cpu,
            "ram_gib": round(mem_kb / 2**20, 1), "python": platform.python_version(), "numpy": np.__version__,
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS") or "default",
            "load_average": [round(x, 2) for x in os.getloadavg()]}


# ------------------------------------------------------------------------------------ data
def hammerstein_record(samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Paper 000's G1 after F2 = tanh(8 v) / 8, Gaussian white input of std 1/(2 pi) (noiseless)."""
    v = gaussian_white_noise(samples, INPUT_STD, seed=seed)
    return v, simulate_hammerstein(v, F2, G1)


def batch_correlations_fft(v: np.ndarray, y: np.ndarray, tau_max: int, forgetting: float = 1.0) -> np.ndarray:
    """phi_vv, phi_yv, phi_yvv (rows; tau = -tau_max..tau_max) of the whole record in one batch by
    real FFTs: the estimator of paper 000 eq. 8 / Remark 2 (``correlation.cross_correlation``), or
    its exponentially weighted form (``correlation.weighted_cross_correlation``) for lambda < 1."""
    products = v.size - 2 * tau_max
    size = scipy.fft.next_fast_len(v.size + products - 1, real=True)
    centre_v, centre_y = v[tau_max : tau_max + products], y[tau_max : tau_max + products]
    total = float(products)
    if forgetting < 1.0:
        weights = forgetting ** np.arange(products - 1, -1, -1)
        centre_v, centre_y, total = centre_v * weights, centre_y * weights, float(weights.sum())
    spectrum_v, spectrum_v2 = scipy.fft.rfft(v, size), scipy.fft.rfft(v * v, size)
    conj_v, conj_y = np.conj(scipy.fft.rfft(centre_v, size)), np.conj(scipy.fft.rfft(centre_y, size))
    lagged = [scipy.fft.irfft(a * b, size)[: 2 * tau_max + 1] for a, b in
              ((spectrum_v, conj_v), (spectrum_v, conj_y), (spectrum_v2, conj_y))]
    return np.vstack(lagged)[:, ::-1] / total


def feed_engine(config: EngineConfig, v: np.ndarray, y: np.ndarray, chunk: int) -> StreamingEngine:
    """A fresh engine fed (v, y) on the grid k / SAMPLE_RATE, ``chunk`` samples per call."""
    engine = StreamingEngine(config)
    t = np.arange(v.size) / SAMPLE_RATE
    for start in range(0, v.size, chunk):
        s = slice(start, start + chunk)
        engine.add_excitation(t[s], v[s])
        engine.add_response(t[s], y[s])
    return engine


def engine_correlations(engine: StreamingEngine) -> np.ndarray:
    snap = engine.snapshot()
    return np.vstack([snap.phi_vv, snap.phi_yv, snap.phi_yvv])

