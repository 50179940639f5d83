"""``hammer-ros bench``: speed and accuracy of hammer_ros beside a reference measured in the same run.

The machine is shared and noisy, so every figure stands beside a reference computed in the same
process (or the same minute) on the same data, and the comparison is a ratio of medians over
repeated runs (ingest: the median of the per-repeat ratios, engine and reference interleaved).
Sections (``--quick`` runs each on smaller sizes):

1. **ingest**: samples/s through ``StreamingEngine`` (alignment + correlation sums, fed in chunks
   as the node and replay do) for tau_max 50 / 200, several windows W, sliding window and
   forgetting; reference: the same three correlation functions (phi_vv, phi_yv, phi_yvv of
   paper 000 eq. 8, weighted for forgetting) of the whole record in one batch by real FFTs.
2. **node**: the highest publish rate at which the live node loses no sample (single-sample and
   100-sample messages) vs a bare rclpy subscriber (EventsExecutor running its own loop, as the node), both
   over DDS on a private ROS_DOMAIN_ID (``ros_rate_probe``).
3. **replay**: samples/s of ``hammer-ros replay`` on a generated bag vs a bare MCAP read + CDR
   decode (mcap_ros2) of the same bag and field.
4. **solve**: p50 / p99 latency of one solve on an engine snapshot (what the node does) per
   method, window, tau_max and mu; reference: batch ``identify`` on the same window.
5. **peers**: identification time and free-run validation NRMSE of hammer_ros's methods vs
   SysIdentPy FROLS (polynomial basis) on paper 000's G1 with tanh(8v)/8 and on real records.
6. **memory**: peak resident memory of the engine (a fresh process) for W = 1e4, 1e5, 1e6.
7. **fleet**: 200 small bags, serial replay in one process vs ``fleet --workers 2`` (Dask
   LocalCluster) vs plain processes, in 3 rounds (the median speed-up decides); the per-bag
   overhead of Dask beside the bag's own replay time.

NRMSE = ||y - y_sim|| / ||y - mean(y)|| on the validation record (= 1 - fit_percent / 100).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import csv
import datetime
import functools
import importlib.util
import io
import json
import math
import os
import platform
import pstats
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.fft

from ..errors import UsageError
from ..identification.correlation_least_squares import DEFAULT_MU, default_tau_max
from ..identification.excitation import gaussian_white_noise
from ..identification.methods import IdentifyOptions, identify
from ..identification.simulate import HammersteinStream, simulate_hammerstein
from ..process_status import process_status_kib
from ..reproduce.cls import G1, INPUT_STD, NONLINEARITIES
from ..streaming.config import EngineConfig
from ..streaming.engine import StreamingEngine, solve_snapshot
from ..streaming.solver_process import SolverProcess

DATA_DIR = Path(__file__).resolve().parents[1] / "data"
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


QUICK = Plan(
    name="quick", repeats=3, ingest_samples=200_000, ingest_taus=(50, 200), ingest_windows=(10_000,),
    ingest_forgetting=(1.0, 0.999), ingest_chunk=1000,
    node_rates={1: (20000.0,), 100: (15000.0,)}, node_seconds=1.5, node_step=1.1,
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


# ------------------------------------------------------------------------------------ 1 ingest
def ingest_section(samples: int, taus: Sequence[int], windows: Sequence[int], forgetting: Sequence[float],
                   chunk: int, repeats: int) -> Section:
    """Engine ingest rate vs the batch FFT correlations of the same record (paired repeats)."""
    section = Section("ingest", f"1. Engine ingest ({samples:,} samples, {chunk} per call)", [
        ("case", "tau_max, W, mode"), ("engine", "engine samples/s"), ("us_per_sample", "engine us/sample"),
        ("reference", "batch FFT samples/s"), ("ratio", "engine / FFT"), ("check", "max abs error vs FFT"),
        ("goal", "goal >= 0.5")])
    v, y = hammerstein_record(samples, seed=1)
    for tau_max in taus:
        for window in windows:
            for lam in forgetting:
                config = EngineConfig(sample_rate=SAMPLE_RATE, window=window, tau_max=tau_max, forgetting=lam,
                                      min_fill=1.0)
                engine_s, fft_s, ratios = [], [], []
                for _ in range(repeats):
                    te, engine = _timed(lambda config=config: feed_engine(config, v, y, chunk))
                    tf, _ = _timed(lambda tau_max=tau_max, lam=lam: batch_correlations_fft(v, y, tau_max, lam))
                    engine_s.append(te)
                    fft_s.append(tf)
                    ratios.append(tf / te)
                # the engine's sums at the end = the batch correlations of its window (sliding) or of
                # the whole record (forgetting: every centre since the start, weighted)
                tail = slice(-window, None) if lam == 1.0 else slice(None)
                error = float(np.max(np.abs(engine_correlations(engine)
                                            - batch_correlations_fft(v[tail], y[tail], tau_max, lam))))
                ratio = _median(ratios)
                mode = "sliding" if lam == 1.0 else f"forgetting {lam}"
                section.rows.append({
                    "case": f"{tau_max}, {window:,}, {mode}", "tau_max": tau_max, "window": window,
                    "forgetting": lam, "engine": samples / _median(engine_s),
                    "us_per_sample": 1e6 * _median(engine_s) / samples, "reference": samples / _median(fft_s),
                    "ratio": ratio, "check": error, "goal": ratio >= 0.5})
    section.notes += _growth_notes(section.rows)
    return section


def _growth_notes(rows: list[dict]) -> list[str]:
    """How the engine's cost per sample grows with tau_max and with W."""
    notes = []
    cost = {(r["tau_max"], r["window"], r["forgetting"]): r["us_per_sample"] for r in rows}
    taus = sorted({k[0] for k in cost})
    windows = sorted({k[1] for k in cost})
    for lam in sorted({k[2] for k in cost}, reverse=True):
        mode = "sliding" if lam == 1.0 else f"forgetting {lam}"
        if len(taus) > 1:
            growth = [cost[(taus[-1], w, lam)] / cost[(taus[0], w, lam)] for w in windows]
            notes.append(f"{mode}: cost per sample x{_median(growth):.2f} from tau_max {taus[0]} to {taus[-1]} "
                         f"(lag count x{(2 * taus[-1] + 1) / (2 * taus[0] + 1):.2f}); FFT ~flat in tau_max")
        if len(windows) > 1:
            growth = [cost[(t, windows[-1], lam)] / cost[(t, windows[0], lam)] for t in taus]
            notes.append(f"{mode}: cost per sample x{_median(growth):.2f} from W {windows[0]:,} to {windows[-1]:,}")
    return notes


# ------------------------------------------------------------------------------------ 2 node
LADDER_STEP = 1.5  # beyond the plan's ladder, each rate is this much above the one before
LADDER_CAP = 200_000.0  # msg/s; no publisher here gets near it
REFINE_STEPS = 2  # rates tried between a subscriber's last lossless rate and its first lossy one
REFINE_RATIO = 1.08  # ... while the two are further apart than this
STALL_RETRIES = 2  # reruns of a subscriber whose run the publisher spoiled (a stall, or short of the rate: ``_losses``)
CONFIRMATIONS = 1  # reruns of a subscriber that lost samples in a clean run, before the rate counts as lost
MAX_STALLS = 3  # more stalls in one run: the publisher cannot keep the rate (its average counts, stalls included)
SUBSCRIBER_KEYS = {"hammer_ros node": "node", "hammer_ros node + foxglove client": "foxglove"}  # else "bare"


def _past_the_bare_limit(ladder: Sequence[float], failed):
    """The plan's rates, then (while the bare subscriber has not lost a sample, i.e. is not in
    ``failed``) rates LADDER_STEP apart up to LADDER_CAP, so that the bare figure is a measured
    limit, not the ladder's top."""
    yield from ladder
    rate = float(ladder[-1]) if ladder else 1000.0
    while "bare" not in failed and rate * LADDER_STEP <= LADDER_CAP:
        rate = float(round(rate * LADDER_STEP, -2))
        yield rate


def _losses(probe, rate: float, batch: int, seconds: float, subscribers: tuple[str, ...],
            tried: list[str], cpu: dict[tuple[str, float], dict[str, float]] | None = None,
            confirmations: int = CONFIRMATIONS, retries: int = STALL_RETRIES,
            runs: dict[str, int] | None = None) -> dict[str, Any]:
    """Samples lost by each of ``subscribers`` at ``rate`` (or why the rate is not a measurement);
    a line for the table goes to ``tried``, the CPU of each run to ``cpu[(who, rate)]``
    (``_cpu_use``). The rate the publisher kept leaves out the time of up to MAX_STALLS stalls
    (``ros_rate_probe._publish``: it fell more than MAX_LAG behind its schedule); with more, its
    plain average counts, and below 95 % of ``rate``, or with fewer than 95 % of the run's
    messages sent, the run is not a measurement of the subscriber. A subscriber whose publisher
    fell short so, or that lost samples in a run in which the publisher stalled, is run again, up
    to ``retries`` (STALL_RETRIES) times: the instrument failed. A loss in a clean run is confirmed by
    ``confirmations`` (CONFIRMATIONS) more runs, so that one hiccup of the shared machine does not
    end a subscriber's ladder (both subscribers alike; the seeded search confirms only the loss
    that decides a figure). The figure is the last run's. ``runs``: each subscriber's count of
    probe runs, reruns included, is added to it."""
    lost: dict[str, Any] = {}
    reruns: dict[str, int] = {}
    confirmed: dict[str, int] = {}
    running = tuple(subscribers)
    while running:
        with contextlib.redirect_stdout(sys.stderr):  # the probe logs its rows on stdout
            results = probe([rate], batch=batch, seconds=seconds, subscribers=running)
        again = []
        for row in results:
            who = SUBSCRIBER_KEYS.get(row["subscriber"], "bare")
            if runs is not None:
                runs[who] = runs.get(who, 0) + 1
            stalled = row.get("stalled_seconds", 0.0) if row.get("stalls", 0) <= MAX_STALLS else 0.0
            achieved = row["messages"] / max(row["publish_seconds"] - stalled, 1e-9)
            planned = int(rate * seconds)
            slow, short = achieved < 0.95 * rate, row["messages"] < 0.95 * planned
            behind = slow or short
            lost[who] = (f"publisher {achieved:.0f}/s" if slow else
                         f"publisher sent {row['messages']} of {planned}" if short else row["lost"])
            if "error" in row:  # the node did not run at this rate
                lost[who] = row["error"]
            if row.get("foxglove_messages", 1) == 0:  # the client never connected: not a measurement
                lost[who] = "no Foxglove message"
            if cpu is not None:
                cpu[(who, rate)] = _cpu_use(row)
            lossy = isinstance(lost[who], int) and lost[who] > 0
            instrument = behind or (stalled > 0 and lossy)
            if "error" in row:
                continue
            if instrument and reruns.get(who, 0) < retries:
                reruns[who] = reruns.get(who, 0) + 1
                again.append(who)
            elif lossy and not instrument and confirmed.get(who, 0) < confirmations:
                confirmed[who] = confirmed.get(who, 0) + 1
                reruns[who] = reruns.get(who, 0) + 1
                again.append(who)
        running = tuple(again)

    def cell(who: str) -> str:
        return "-" if who not in lost else f"{lost[who]}" + (f" ({reruns[who]} rerun)" if who in reruns else "")

    tried.append(f"{rate:g}: {cell('node')} / {cell('bare')} / {cell('foxglove')}")
    return lost


def _cpu_use(row: dict[str, Any]) -> dict[str, float]:
    """Of one probe run: the subscriber's CPU microseconds per message received (both topics'
    messages) and the cores it and the publisher kept busy on average (CPU seconds / publishing
    time); empty where the probe could not read them."""
    messages = 2 * row["messages"]
    subscriber, publisher = row.get("subscriber_cpu_seconds"), row.get("publisher_cpu_seconds")
    if subscriber is None or publisher is None or not messages or row["publish_seconds"] <= 0:
        return {}
    return {"us_per_message": 1e6 * subscriber / messages, "subscriber_cores": subscriber / row["publish_seconds"],
            "publisher_cores": publisher / row["publish_seconds"]}


def _cpu_cell(use: dict[str, float]) -> str:
    if not use:
        return "-"
    return f"{use['us_per_message']:.0f} us, {use['subscriber_cores']:.2f} + {use['publisher_cores']:.2f}"


def _zero_loss_limits(batch: int, ladder: Sequence[float], seconds: float, probe, cpu: dict | None = None,
                      subscribers: tuple[str, ...] = ("node", "bare", "foxglove")):
    """(highest lossless rate, first rate that was not lossless, rates tried, lower bounds) of the
    node, the bare subscriber and the node with a Foxglove client: the ladder
    (``_past_the_bare_limit``), then REFINE_STEPS geometric midpoints between each one's last
    lossless and first other rate. A figure is a lower bound (``lower[who]``) when no run of that
    subscriber lost samples: every rate above it was not a measurement (the publisher could not
    keep it, the node refused it) or the ladder reached its cap. ``cpu``: filled as by ``_losses``;
    ``subscribers``: those searched (the six-joint row has no Foxglove client)."""
    best = dict.fromkeys(subscribers, 0.0)
    first_loss: dict[str, float] = {}
    lossy: set[str] = set()  # subscribers that lost samples in a run (not only a failed instrument)
    tried: list[str] = []

    def measure(rate: float, running: tuple[str, ...]) -> None:
        for who, lost in _losses(probe, rate, batch, seconds, running, tried, cpu).items():
            if lost == 0:
                best[who] = rate
            else:
                first_loss[who] = min(rate, first_loss.get(who, math.inf))
                if isinstance(lost, int):
                    lossy.add(who)

    for rate in _past_the_bare_limit(ladder, first_loss):
        measure(rate, tuple(w for w in best if w not in first_loss))
        if len(first_loss) == len(best):
            break
    for who in best:
        for _ in range(REFINE_STEPS if best[who] and who in first_loss else 0):
            if first_loss[who] <= REFINE_RATIO * best[who]:
                break
            measure(float(round(math.sqrt(best[who] * first_loss[who]), -2)), (who,))
    return best, first_loss, tried, {who: who not in lossy for who in best}


JOINTS = 6  # the node section's JointState row: joints of one topic, each a channel of one node
NODE_LIMITS = DATA_DIR / "bench_node_limits.json"  # the last run's figures: where the quick search starts
SEARCH_RUNS = 9  # probe runs per subscriber at most in the seeded search, reruns included (a seed 2.3 x off takes 9)
SEARCH_RETRIES = 1  # its reruns of a run the publisher spoiled (the ladders': STALL_RETRIES)


@dataclass
class _Search:
    """One subscriber's search on rungs k (rate = anchor x step^k): from its seed's rung up while
    lossless, down while not, by 1, 2, 4 ... rungs, until a lossless rung lies below a lossy one;
    then bisection until they are adjacent. The lossy rung that decides the figure is run once
    more (the ladder's CONFIRMATIONS, for the one loss that matters): lossless then, the search
    climbs on from the next rung. Its figure is then known to within one step."""

    index: int
    lossless: int | None = None
    lossy: int | None = None
    confirmed: bool = False  # the run at ``lossy`` was confirmed (or was not a sample loss)
    stride: int = 1
    runs: int = 0  # probe runs, reruns included (``_seeded_limits`` counts them)

    def record(self, ok: bool, sample_loss: bool) -> None:
        if self.lossy is not None and self.index == self.lossy and self.lossless == self.index - 1:  # confirming
            self.confirmed = not ok
            if ok:  # its limit is near: climb one rung, then 2, 4 ...
                self.lossless, self.lossy, self.stride = self.index, None, 1
                self.index += 1
            return
        if ok:
            self.lossless = self.index if self.lossless is None else max(self.lossless, self.index)
        elif self.lossy is None or self.index < self.lossy:
            self.lossy, self.confirmed = self.index, not sample_loss
        if self.lossless is not None and self.lossy is not None:
            gap = self.lossy - self.lossless
            self.index = (self.lossless + self.lossy) // 2 if gap > 1 else self.lossy
        else:
            self.index += self.stride if ok else -self.stride
            self.stride *= 2

    @property
    def done(self) -> bool:
        return (self.lossless is not None and self.lossy is not None and self.lossy - self.lossless <= 1
                and self.confirmed)


def _seeded_limits(batch: int, seeds: dict[str, float], step: float, seconds: float, probe,
                   cpu: dict | None = None):
    """What ``_zero_loss_limits`` returns, by a search (``_Search``) of each subscriber from its
    seed (the last run's figure) on one grid of rungs ``step`` apart anchored at the bare
    subscriber's seed, so that node / bare is a power of ``step`` and each figure lies within one
    step of its limit. Each round runs the subscribers still searching (those at the same rate
    in one ``_losses`` call, with its reruns of a failed instrument). A subscriber that would go
    above LADDER_CAP stops there, below 100 msg/s at 0; one stops after SEARCH_RUNS probe runs
    (reruns of a spoiled run, at most SEARCH_RETRIES each, included; its
    figure a lower bound when nothing above it was lossy then, its bracket wider than a rung when
    a lossy rung lies further up)."""
    anchor = seeds["bare"]

    def rate(k: int) -> float:
        return float(round(anchor * step**k, -2))

    searches = {who: _Search(round(math.log(seeds[who] / anchor) / math.log(step))) for who in ("node", "bare",
                                                                                                "foxglove")}
    lossy: set[str] = set()
    tried: list[str] = []

    def searching(who: str) -> bool:
        search = searches[who]
        return not search.done and search.runs < SEARCH_RUNS and 100.0 <= rate(search.index) <= LADDER_CAP

    while running := [who for who in searches if searching(who)]:
        rungs = {who: searches[who].index for who in running}  # one run of each per round
        for k in sorted(set(rungs.values())):
            group = tuple(who for who in running if rungs[who] == k)
            runs: dict[str, int] = {}
            for who, lost in _losses(probe, rate(k), batch, seconds, group, tried, cpu, confirmations=0,
                                     retries=SEARCH_RETRIES, runs=runs).items():
                searches[who].runs += runs.get(who, 0)
                sample_loss = isinstance(lost, int) and lost > 0
                searches[who].record(lost == 0, sample_loss)
                if sample_loss:
                    lossy.add(who)
    best = {who: rate(s.lossless) if s.lossless is not None else 0.0 for who, s in searches.items()}
    first_loss = {who: rate(s.lossy) for who, s in searches.items() if s.lossy is not None}
    # a lower bound: no sample lost at all, or nothing lossy above the figure when the search stopped
    return best, first_loss, tried, {who: who not in lossy or s.lossy is None for who, s in searches.items()}


def stored_node_limits(path: Path = NODE_LIMITS) -> dict[str, Any]:
    """The figures the last run stored ({"date", "plan", "limits": {batch: {subscriber: msg/s}}}), or {}."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _store_node_limits(rows: list[dict], path: Path = NODE_LIMITS, plan: str = "full") -> str:
    """Write each message row's three figures to ``path`` for the quick search (not the JointState
    row's: the quick bench has none); a note saying so (or why not)."""
    limits = {str(r["batch"]): {"node": r["node_rate"], "bare": r["reference_rate"], "foxglove": r["foxglove_rate"]}
              for r in rows if r.get("reference_rate") and not r.get("joints")}  # the quick search's seeds
    doc = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "plan": plan,
           "limits": limits}
    try:
        path.write_text(json.dumps(doc, indent=1) + "\n")
    except OSError as exc:
        return f"figures not stored for the quick search ({path}: {exc.strerror or exc})"
    return f"figures stored in `{path.name}` (hammer_ros/data), where `bench --quick` starts its search"


def _range_cell(low: float | None, high: float | None) -> str:
    if low is None and high is None:
        return "-"
    if low is None:
        return f"<= {high:.2f}"
    return f">= {low:.2f}" if high is None else f"{low:.2f} - {high:.2f}"


def _node_row(batch: int, best: dict[str, float], first_loss: dict[str, float], tried: list[str],
              lower: dict[str, bool], cpu: dict, joints: int = 0) -> dict[str, Any]:
    """The node section's row of one message type from a search's figures (``_zero_loss_limits``);
    ``joints``: the row of one JointState topic read by that many channels (no Foxglove run)."""
    at_limit = {who: cpu.get((who, rate), {}) for who, rate in best.items() if who in ("node", "bare")}
    at_loss = {who: cpu.get((who, rate), {}) for who, rate in first_loss.items() if who in ("node", "bare")}
    node, bare, foxglove = best["node"], best["bare"], best.get("foxglove")
    ratio = node / bare if bare else None
    foxglove_ratio = foxglove / node if node and foxglove is not None else None
    # each true limit lies in [figure, first other rate); a lower bound's bracket is open above
    low = node / first_loss["bare"] if "bare" in first_loss and not lower["bare"] else None
    high = first_loss["node"] / bare if "node" in first_loss and not lower["node"] and bare else None
    label = (f"JointState of {joints} joints, {joints} channels (1 sample each)" if joints else
             "Float64 (1 sample)" if batch == 1 else f"Float64MultiArray ({batch} samples)")
    at_least = {who: ">= " if lower[who] else "" for who in best}
    return {"case": label, "batch": batch, "node": f"{at_least['node']}{node:g} ({node * batch:g})",
            "node_rate": node, "reference": f"{at_least['bare']}{bare:g}", "reference_rate": bare,
            "ratio": ratio, "ratio_range": [low, high], "range": _range_cell(low, high),
            "foxglove": "-" if foxglove is None else f"{foxglove:g} ({foxglove_ratio or 0:.2f})",
            "foxglove_rate": foxglove, "foxglove_ratio": foxglove_ratio,
            "tried": "; ".join(tried), "ladder_top": lower["bare"], "lower_bound": lower,
            "first_other_rate": first_loss,
            "cpu": "; ".join(f"{who} {_cpu_cell(use)}" for who, use in at_limit.items()),
            "cpu_at_limit": at_limit, "cpu_at_first_loss": at_loss,
            "joints": joints,
            "goal": None if ratio is None or (foxglove_ratio is None and not joints) else
            ratio >= 0.9 and (bool(joints) or foxglove_ratio >= 0.9)}


def node_section(rates: dict[int, Sequence[float]], seconds: float, step: float | None = None,
                 limits_path: Path = NODE_LIMITS, joint_rates: Sequence[float] = ()) -> Section:
    """Highest zero-loss message rate of the node vs a bare rclpy subscriber (``ros_rate_probe``),
    climbing each ladder until both have lost samples (or the publisher cannot keep the rate),
    and storing the figures in ``limits_path``; with ``step``, by the seeded search from the
    figures stored there (``_seeded_limits``; ``rates[batch][-1]`` where there are none).
    ``joint_rates``: also the row of one JointState of JOINTS joints read by JOINTS channels of one
    node against a bare subscriber of that topic (``ProbeSession.joints_probe``), by the ladder."""
    section = Section("node", f"2. Live node: highest rate with zero lost samples ({seconds:g} s per rate)", [
        ("case", "message"), ("node", "node: max msg/s (samples/s)"), ("reference", "bare rclpy: max msg/s"),
        ("ratio", "node / bare"), ("range", "node / bare if each limit is anywhere in its bracket"),
        ("foxglove", "node + Foxglove client: max msg/s (/ node)"),
        ("tried", "msg/s per topic: samples lost by node / bare / node + Foxglove client"),
        ("cpu", "CPU at each one's max rate: us per message received; subscriber + publisher cores"),
        ("goal", "goal >= 0.9")])
    try:
        from .ros_rate_probe import ProbeSession
    except ImportError as exc:  # rclpy missing: an apt ROS install not sourced, or no [ros] extra
        section.notes.append(f"skipped: {exc}")
        return section
    stored = stored_node_limits(limits_path) if step else {}
    for batch, ladder in rates.items():
        cpu: dict[tuple[str, float], dict[str, float]] = {}
        with ProbeSession() as session:  # one per message type: DDS keeps a topic's first type in a participant
            if step:
                seeds = stored.get("limits", {}).get(str(batch), {})
                seeds = {who: float(seeds.get(who) or ladder[-1]) for who in ("node", "bare", "foxglove")}
                best, first_loss, tried, lower = _seeded_limits(batch, seeds, step, seconds, session.probe, cpu)
            else:
                best, first_loss, tried, lower = _zero_loss_limits(batch, ladder, seconds, session.probe, cpu)
        section.rows.append(_node_row(batch, best, first_loss, tried, lower, cpu))
    if joint_rates:
        cpu = {}
        who = ("node", "bare")
        with ProbeSession() as session:
            probe = functools.partial(session.joints_probe, joints=JOINTS)
            best, first_loss, tried, lower = _zero_loss_limits(1, joint_rates, seconds, probe, cpu, who)
        section.rows.append(_node_row(1, best, first_loss, tried, lower, cpu, joints=JOINTS))
    if step:
        origin = (f"the {stored.get('plan', 'full')} run of {stored['date']}" if stored.get("date") else
                  f"the plan's {', '.join(f'{r[-1]:g}' for r in rates.values())} msg/s (no figures stored)")
        section.notes.append(f"quick search: each subscriber starts at its figure of {origin} "
                             f"(`{limits_path.name}` in hammer_ros/data) on rungs x{step:g} apart (one grid per "
                             "message, anchored at the bare subscriber's figure), goes up while lossless and down "
                             "while not by 1, 2, 4 ... rungs, then bisects until its last lossless and first other "
                             f"rate are one rung apart (at most {SEARCH_RUNS} probe runs each, reruns of a run the "
                             f"publisher spoiled, at most {SEARCH_RETRIES} per rate, included): each figure is within "
                             f"x{step:g} of its limit (or its range says how far), and the range column is what "
                             "node / bare can be at that resolution")
    if section.rows:
        section.notes.append(_store_node_limits(section.rows, limits_path, "quick" if step else "full"))
    section.notes.append("`ros_rate_probe`: one publisher process per message type sends both topics (reliable, "
                         "depth 1000) for the stated time, from the moment both ends have matched both topics, to "
                         "the bare subscriber (EventsExecutor, counting) and to a `hammer-ros node` (window 4000, "
                         "cls-markov, 4 solves/s; its /diagnostics counters), and "
                         "to one more with its Foxglove server on (`foxglove_port`) and one WebSocket client "
                         "subscribed to every channel (goal: >= 0.9 of the node's rate, i.e. at most 10 % lower); "
                         "each subscriber has topics of its own, and the publisher and the subscribers are started "
                         "once per message type and kept for all its runs (before each run the node's sample_rate "
                         "is set and its window and counters reset by ~/reset, after it reset again: it idles on "
                         "an empty window while the others run); "
                         "a rate counts when the publisher kept >= 95 % of it, sent >= 95 % of the run's messages "
                         "and every sample arrived. The "
                         "publisher sends each message in its slot; when it falls more than 20 ms behind (descheduled) "
                         "it resumes on a new schedule instead of sending the backlog in one burst; the rate kept "
                         f"leaves out up to {MAX_STALLS} stalls (more: the publisher could not keep the rate). A "
                         "subscriber that lost samples in such a run, or whose publisher fell short so, is "
                         f"run again (up to {STALL_RETRIES} times; 'rerun' in the table); a loss in a clean run "
                         f"is confirmed by {CONFIRMATIONS} more run (the figure is the last run's). "
                         + ("" if step else
                            f"The ladder climbs past the plan's rates (x{LADDER_STEP:g} a step) until the bare "
                            "subscriber loses samples or the publisher cannot keep the rate (a subscriber is not run "
                            f"again above its first loss); then up to {REFINE_STEPS} rates between each subscriber's "
                            f"last lossless and first lossy rate (geometric midpoints, while more than "
                            f"x{REFINE_RATIO:g} apart) narrow its limit. ")
                         + "A figure marked '>=' (`lower_bound` in the JSON, `ladder_top` for the bare "
                         "subscriber) is a lower bound: that subscriber lost no sample at any rate it ran, the "
                         f"runs above its figure were not measurements (the publisher could not keep the rate) or "
                         f"the search reached {LADDER_CAP:g} msg/s; '-' = not run at that rate. CPU: "
                         "the subscriber's process (all its threads; not the node's worker processes) from the "
                         "publisher's start until every sample was counted, per message received on both topics, "
                         "and in cores (CPU seconds / publishing time) beside the publisher's; the JSON also has "
                         "them at each one's first lossy rate (`cpu_at_first_loss`)")
    if joint_rates:
        section.notes.append(f"JointState row: one topic of {JOINTS} named joints (one message = one sample of each), "
                             f"read by one node of {JOINTS} channels (`position[joint_k]` -> `velocity[joint_k]`, "
                             "the topic subscribed and decoded once; window 4000, cls-markov, 4 solves/s each; "
                             "received = the smallest count of any channel's inputs in /diagnostics) and by the "
                             "bare subscriber of that topic, which builds every JointState; no Foxglove run (a "
                             "node of several channels has no Foxglove server); the full bench only (a "
                             "six-channel node takes 10-25 s to start: the row would add about 70 s to the quick one)")
    return section


# ------------------------------------------------------------------------------------ 3 replay
def write_bench_bag(path: Path, messages: int, batch: int, seed: int = 3) -> int:
    """A bag of paper 000's G1 / F2 at SAMPLE_RATE: /cmd and /response, ``messages`` messages each,
    std_msgs/msg/Float64 (batch 1) or Float64MultiArray of ``batch`` samples (log time = time of
    the last sample). Returns the number of samples per topic."""
    from ..io.bags import ResultWriter

    samples = messages * batch
    v, y = hammerstein_record(samples, seed)
    start_ns = 1_700_000_000_000_000_000
    type_name = "std_msgs/msg/Float64" if batch == 1 else "std_msgs/msg/Float64MultiArray"
    with ResultWriter(path) as writer:
        for i in range(messages):
            last = (i + 1) * batch - 1
            stamp = start_ns + round(last * 1e9 / SAMPLE_RATE)
            for topic, x in (("/cmd", v), ("/response", y)):
                values = x[last + 1 - batch : last + 1]
                message = {"data": float(values[0])} if batch == 1 else {"data": values.tolist()}
                writer.write(topic, type_name, message, stamp)
    return samples


def bare_decode(path: Path, batch: int) -> int:
    """The reference: read the bag with mcap + mcap_ros2 (CDR decode) and pull the field out of
    every message of both topics into one float array per topic. Returns samples per topic."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    values: dict[str, list] = {"/cmd": [], "/response": []}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(topics=list(values)):
            if batch == 1:
                values[channel.topic].append(msg.data)
            else:
                values[channel.topic].extend(msg.data)
    arrays = [np.asarray(x, dtype=float) for x in values.values()]
    return int(min(a.size for a in arrays))


def run_replay(path: Path, batch: int, window: int, solve_rate: float | None = None) -> tuple[float, dict]:
    """(wall seconds, JSON document) of ``hammer-ros replay BAG --json`` run in this process
    (the whole command: bag checks, reading, engine, solves; its output discarded). The document
    gains ``cpu_s``: the CPU seconds of this process and of its solver process (a child, counted
    once it has been waited for), over the command."""
    from ..cli import build_parser
    from ..cli.replay import run as replay

    field_path = "data" if batch == 1 else "data[:]"
    argv = ["replay", str(path), "--input", f"/cmd:{field_path}", "--output", f"/response:{field_path}",
            "--sample-rate", f"{SAMPLE_RATE:g}", "--window", str(window), "--json"]
    if solve_rate is not None:
        argv += ["--solve-rate", f"{solve_rate:g}"]
    args = build_parser().parse_args(argv)
    out = io.StringIO()
    before, children = time.process_time(), _children_cpu_seconds()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        elapsed, _ = _timed(lambda: replay(args))
    doc = json.loads(out.getvalue())
    doc["cpu_s"] = {"reading": time.process_time() - before, "solver": _children_cpu_seconds() - children}
    return elapsed, doc


def _children_cpu_seconds() -> float:
    """User + system CPU seconds of this process's children that have been waited for."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


REPLAY_MODES = (("2 solves / bag s", None), ("final solve only", 1e-6))


def replay_section(messages: dict[int, int], repeats: int) -> Section:
    section = Section("replay", "3. Replay vs bare MCAP read + CDR decode (same bag, same field, same process)", [
        ("case", "bag"), ("mode", "replay solves"), ("replay", "replay samples/s"),
        ("reference", "bare decode samples/s"), ("ratio", "replay / bare"),
        ("cpu", "CPU s: replay's reading + solver process (bare)"), ("goal", "goal >= 0.8")])
    with tempfile.TemporaryDirectory(prefix="hammer_ros_bench_") as tmp:
        for batch, count in messages.items():
            path = Path(tmp) / f"bench_{batch}.mcap"
            samples = write_bench_bag(path, count, batch)
            kind = "Float64" if batch == 1 else f"Float64MultiArray x{batch}"
            size = path.stat().st_size / 2**20
            for mode, solve_rate in REPLAY_MODES:
                replay_rates, bare_rates, ratios = [], [], []
                cpu: dict[str, list[float]] = {"reading": [], "solver": [], "bare": []}
                for _ in range(repeats):
                    elapsed, doc = run_replay(path, batch, min(4000, samples // 2), solve_rate)
                    bare_cpu = time.process_time()
                    tb, decoded = _timed(lambda path=path, batch=batch: bare_decode(path, batch))
                    cpu["bare"].append(time.process_time() - bare_cpu)
                    for part in ("reading", "solver"):
                        cpu[part].append(doc["cpu_s"][part])
                    replay_rates.append(doc["samples"] / elapsed)
                    bare_rates.append(decoded / tb)
                    ratios.append(replay_rates[-1] / bare_rates[-1])
                ratio = _median(ratios)
                cpu_s = {part: _median(seconds) for part, seconds in cpu.items()}
                section.rows.append({
                    "case": f"{kind}, 2 x {count:,} messages, {samples:,} samples/topic, {size:.1f} MiB",
                    "batch": batch, "mode": f"{mode} ({doc['solves']})", "replay": _median(replay_rates),
                    "reference": _median(bare_rates), "ratio": ratio, "cpu_s": cpu_s,
                    "cpu": f"{cpu_s['reading']:.3f} + {cpu_s['solver']:.3f} ({cpu_s['bare']:.3f})",
                    "goal": ratio >= 0.8})
    section.notes.append("replay: `hammer-ros replay BAG --input /cmd:F --output /response:F --sample-rate 1000 "
                         "--window 4000 --json` (default cls-markov), timed around the whole command in this "
                         "process; samples = aligned grid samples. bare: mcap reader + mcap_ros2 DecoderFactory, "
                         "the field of every message of both topics into a numpy array. Replay and bare alternate; "
                         "ratio = median of the pairs. CPU: medians of the replay process's CPU seconds and of its "
                         "solver process's (forked when the periodic solves are worth it; 0 without), and of the "
                         "bare decode's (one thread: about its wall time)")
    return section


def _child_env() -> dict[str, str]:
    """This environment without the ROS wheels' re-exec variables (a child re-bootstraps)."""
    return {k: v for k, v in os.environ.items() if k not in ("LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")}


# ------------------------------------------------------------------------------------ 4 solve
@dataclass(frozen=True)
class SolveCase:
    method: str
    tau_max: int | None = None  # None: the method's default (CLS), unused otherwise
    mu: int | None = None

    def config(self, window: int) -> EngineConfig:
        tau_max = self.tau_max or 60
        # max_relative_sd off: the bounds are computed (and timed) but do not withhold a model (plls-feedback's on
        # Hammerstein data has a pole 0.18 +- 0.26: uncertain, rightly, which is not what this row measures)
        return EngineConfig(sample_rate=SAMPLE_RATE, window=window, tau_max=tau_max, method=self.method,
                            mu=self.mu, min_fill=0.25, max_relative_sd=0.0)

    @property
    def label(self) -> str:
        parts = [self.method]
        if self.mu is not None:
            parts.append(f"mu {self.mu}")
        if self.method.startswith("cls"):
            parts.append(f"tau_max {self.tau_max}")
        return ", ".join(parts)


def solve_cases() -> list[SolveCase]:
    arx = default_tau_max(3, 1)
    cases = [SolveCase("cls-arx", arx), SolveCase("cls-arx", 50)]
    for mu in (10, DEFAULT_MU, 60):
        cases.append(SolveCase("cls-markov", default_tau_max(3, mu), mu))
    cases.append(SolveCase("cls-markov", 200, DEFAULT_MU))
    cases += [SolveCase("plls-hammerstein"), SolveCase("plls-feedback"), SolveCase("plls-hammerstein-feedback")]
    return cases


def solve_latencies(case: SolveCase, window: int, repeats: int) -> dict[str, Any]:
    """p50 / p99 of ``solve_snapshot`` on a full window of G1 / F2 data, and the batch
    ``identify`` reference on the same raw window."""
    v, y = hammerstein_record(window, seed=4)
    engine = feed_engine(case.config(window), v, y, chunk=1000)
    snap = engine.snapshot()
    first = solve_snapshot(snap)  # the warm-up: lazy imports and first-call caches, reported apart
    if not first.ok:
        return {"error": first.reason}
    times = [solve_snapshot(snap).solve_seconds for _ in range(repeats)]
    options = IdentifyOptions(order=3, delay=1, mu=case.mu, tau_max=case.tau_max if case.method.startswith("cls")
                              else None)

    def batch() -> None:
        result = identify(case.method, snap.v, snap.y, options)
        result.to_json(snap.v, snap.y)

    reference = [_timed(batch)[0] for _ in range(max(3, repeats // 4))]
    return {"p50": 1e3 * _percentile(times, 50), "p99": 1e3 * _percentile(times, 99),
            "first": 1e3 * first.solve_seconds, "reference": 1e3 * _median(reference), "n": repeats}


LOADED_SHARE = 0.5  # the ingest rate beside the loaded solves, a share of its measured limit


def _ingest_one_by_one(config: EngineConfig, rate: float | None, seconds: float, stop: threading.Event,
                       counted: list[float], started: threading.Event | None = None) -> None:
    """Feed a fresh engine one sample of each stream per call (a Float64 node's hand-off) at
    ``rate`` samples/s (None: as fast as it can) until ``stop`` or ``seconds``; the rate it
    reached goes to ``counted``; ``started`` is set once the first sample is in."""
    engine = StreamingEngine(config)
    v, y = hammerstein_record(20_000, seed=5)
    start, k = time.perf_counter(), 0
    while not stop.is_set() and (elapsed := time.perf_counter() - start) < seconds:
        due = k + 200 if rate is None else int(elapsed * rate)
        while k < due:
            i = k % v.size
            t = np.array([k / SAMPLE_RATE])
            engine.add_excitation(t, v[i : i + 1])
            engine.add_response(t, y[i : i + 1])
            k += 1
            if started is not None and k == 1:
                started.set()
        if rate is not None:
            time.sleep(0.001)
    counted.append(k / max(time.perf_counter() - start, 1e-9))


def loaded_solve_latencies(case: SolveCase, window: int, repeats: int, in_process: bool = False) -> dict[str, Any]:
    """p50 / p99 of ``solve_snapshot`` while a thread of this interpreter ingests one sample per
    call at LOADED_SHARE of its own limit (measured first, 1 s alone): the node's solve thread
    beside its ingestion, both under one GIL. ``in_process``: the solves run in a
    ``SolverProcess`` instead (what the node does with ``solver_process`` on), timed end to end
    here (snapshot out, outcome back: p50 / p99) and where they ran (solve_p50 / solve_p99)."""
    config = case.config(window)
    counted: list[float] = []
    _ingest_one_by_one(config, None, 1.0, threading.Event(), counted)
    limit = counted[0]
    v, y = hammerstein_record(window, seed=4)
    snap = feed_engine(config, v, y, chunk=1000).snapshot()
    solver = SolverProcess() if in_process else None

    def solve() -> tuple[float, bool, float]:
        """(end-to-end seconds, ok, seconds of the solve itself where it ran)."""
        started = time.perf_counter()
        outcome = solver.solve(snap) if solver else solve_snapshot(snap)
        return time.perf_counter() - started, outcome.ok, outcome.solve_seconds

    try:
        first, ok, _ = solve()  # the warm-up (the worker's imports), reported apart
        if not ok:
            return {"error": "the warm-up solve failed"}
        stop, counted, started = threading.Event(), [], threading.Event()
        feeder = threading.Thread(target=_ingest_one_by_one,
                                  args=(config, LOADED_SHARE * limit, 600.0, stop, counted, started), daemon=True)
        feeder.start()
        started.wait(5.0)  # the solves are timed beside an ingestion that runs
        try:
            timed = [solve() for _ in range(repeats)]
        finally:
            stop.set()
            feeder.join()
    finally:
        if solver is not None:
            solver.close()
    times, own = [t[0] for t in timed], [t[2] for t in timed]
    return {"p50": 1e3 * _percentile(times, 50), "p99": 1e3 * _percentile(times, 99), "n": repeats,
            "first": 1e3 * first, "ingest_limit": limit, "ingest_rate": counted[0],
            "solve_p50": 1e3 * _percentile(own, 50), "solve_p99": 1e3 * _percentile(own, 99)}


def _loaded_rows(case: SolveCase, window: int, repeats: int) -> list[dict]:
    """The solve beside ingestion: in a thread; in the solver process, timed there and end to end."""
    rows = []
    base = {"tau_max": case.tau_max, "mu": case.mu, "window": window}
    beside = f"beside ingestion at {LOADED_SHARE:.0%} of its limit"
    thread = loaded_solve_latencies(case, window, repeats, in_process=False)
    rows.append({"case": f"{case.label}, in a thread, {beside}", "method": f"{case.method} (thread)", **base,
                 **thread})
    process = loaded_solve_latencies(case, window, repeats, in_process=True)
    if "error" in process:
        return [*rows, {"case": f"{case.label}, in the solver process", "method": case.method, **process}]
    rows.append({"case": f"{case.label}, in the solver process, {beside}: the solve there",
                 "method": f"{case.method} (process)", **base, **process,
                 "p50": process["solve_p50"], "p99": process["solve_p99"]})
    rows.append({"case": f"{case.label}, in the solver process, {beside}: end to end", "method": "end to end",
                 **base, **process})
    for row in rows[:2]:
        if "p99" in row:
            row["goal"] = f"p99 < 5 ms: {'yes' if row['p99'] < 5.0 else 'NO'}"
    return rows


def diagnose_latencies(window: int, repeats: int) -> dict[str, Any]:
    """Latency of ``diagnose`` (baseline fit, residual tests, extended model) on ``window``
    samples (70 / 30 split), or the reason it could not run."""
    try:
        from ..diagnosis.diagnose import diagnose_record
    except ImportError as exc:
        return {"error": f"diagnose not available ({exc})"}
    v, y = hammerstein_record(window, seed=4)
    times = []
    for _ in range(repeats):
        elapsed, _ = _timed(lambda: diagnose_record(v, y, order=3))
        times.append(elapsed)
    return {"p50": 1e3 * _percentile(times, 50), "p99": 1e3 * _percentile(times, 99), "n": repeats}


COMPILED_GOAL = 4.0  # the compiled CLS solve with its bounds, x faster than the numpy reference (issue 52)


def compiled_solve_rows(window: int, repeats: int) -> list[dict[str, Any]]:
    """The CLS mu-Markov solve from an engine snapshot's correlation sums (order 3, mu 30, tau_max 66)
    with and without its bounds: the numba kernel (``cls_kernel``) beside the numpy reference, the four
    in turn on the same snapshot (the same load for each), p50 / p99 over ``repeats`` solves each; the
    poles of the two must agree to 1e-7."""
    from ..identification.correlation_least_squares import (
        cls_from_correlations,
        compiled_steps,
        correlation_least_squares_steps,
    )

    case = SolveCase("cls-markov", default_tau_max(3, DEFAULT_MU), DEFAULT_MU)
    v, y = hammerstein_record(window, seed=4)
    snap = feed_engine(case.config(window), v, y, chunk=1000).snapshot()
    options = case.config(window).identify_options()
    data, model = (snap.phi_vv, snap.phi_yv, snap.v, snap.y), (options.order, options.delay, DEFAULT_MU, options.poly)
    variants = {("with bounds", "compiled"): lambda: cls_from_correlations(*data, options, "markov"),
                ("with bounds", "reference"): lambda: cls_from_correlations(*data, options, "markov", compiled=False),
                ("without bounds", "compiled"): lambda: compiled_steps(*data, *model, bounds=False)[0],
                ("without bounds", "reference"): lambda: correlation_least_squares_steps(*data, *model)}
    found = {key: solve() for key, solve in variants.items()}  # the warm-up (numba's cache loaded)
    times: dict[tuple[str, str], list[float]] = {key: [] for key in variants}
    for _ in range(repeats):
        for key, solve in variants.items():
            times[key].append(_timed(solve)[0])
    rows = []
    for bounds in ("with bounds", "without bounds"):
        compiled, reference = found[bounds, "compiled"], found[bounds, "reference"]
        linear = (compiled.linear.linear, reference.linear.linear) if bounds == "without bounds" else (
            compiled.linear, reference.linear)
        same = bool(np.max(np.abs(linear[0].poles - linear[1].poles)) <= 1e-7)
        row = {"case": f"{case.label}, the solve from the sums {bounds}: compiled (reference: numpy)",
               "method": "cls-markov (compiled)", "tau_max": case.tau_max, "mu": DEFAULT_MU, "window": window,
               "p50": 1e3 * _percentile(times[bounds, "compiled"], 50),
               "p99": 1e3 * _percentile(times[bounds, "compiled"], 99), "n": repeats,
               "reference": 1e3 * _median(times[bounds, "reference"]), "poles_equal": same}
        row["ratio"] = row["reference"] / row["p50"]
        fast = f">= {COMPILED_GOAL:g} x: {'yes' if row['ratio'] >= COMPILED_GOAL else 'NO'}, "
        row["goal"] = f"{fast if bounds == 'with bounds' else ''}poles equal to 1e-7: {'yes' if same else 'NO'}"
        rows.append(row)
    return rows


def solve_section(windows: Sequence[int], repeats: int, slow_repeats: int) -> Section:
    section = Section("solve", "4. Solve latency on an engine snapshot (order 3, delay 1, G1 / tanh data)", [
        ("case", "method"), ("window", "W"), ("p50", "p50 ms"), ("p99", "p99 ms"), ("n", "solves"),
        ("first", "first solve ms (warm-up, not in p50/p99)"),
        ("reference", "reference p50 ms (batch identify; numpy for compiled)"), ("ratio", "reference / solve p50"),
        ("goal", "goal")])
    for window in windows:
        for case in solve_cases():
            slow = not case.method.startswith("cls")
            row = {"case": case.label, "method": case.method, "tau_max": case.tau_max, "mu": case.mu,
                   "window": window, **solve_latencies(case, window, slow_repeats if slow else repeats)}
            if "reference" in row:
                row["ratio"] = row["reference"] / row["p50"]
            if case.method == "cls-markov" and case.mu == DEFAULT_MU and "p99" in row:
                row["goal"] = f"p99 < 5 ms: {'yes' if row['p99'] < 5.0 else 'NO'}"
            section.rows.append(row)
            if case.method == "cls-markov" and case.mu == DEFAULT_MU and case.tau_max == default_tau_max(3, case.mu):
                section.rows += _loaded_rows(case, window, repeats)
        section.rows += compiled_solve_rows(window, 4 * repeats)
        row = {"case": "diagnose (70/30 split)", "method": "diagnose", "window": window,
               **diagnose_latencies(window, max(3, slow_repeats // 3))}
        section.rows.append(row)
    for row in section.rows:
        if "error" in row:
            row["goal"] = f"failed: {row['error']}"
    section.notes.append("solve = `streaming.solve_snapshot` (what the node's worker thread runs: CLS step 1 on the "
                         "window's correlation sums, step 2 and the JSON document with fit/rms on the raw window); "
                         "batch = `methods.identify` + `to_json` on the same raw window (correlations from scratch); "
                         "p50/p99 over the solves after a first one (lazy imports and first-call caches: a node pays "
                         "them once, at its first solve), which is reported apart; \"beside ingestion\": the same "
                         "solves while a thread of this process feeds another engine one sample per call at "
                         f"{LOADED_SHARE:.0%} of the rate it reached alone (the node's solve thread beside its "
                         "ingestion under one GIL with `solver_process` false; ingest_limit / ingest_rate in the "
                         "JSON); \"in the solver process\": the same solves in a `SolverProcess` (the node's default), "
                         "timed where they run (the solve time the node reports; counted in the goal) and end to end "
                         "in this process (snapshot out, outcome back: the wait for this interpreter's lock after "
                         "the answer arrives is part of it; not counted in the goal); \"compiled\": the CLS "
                         "solve (`cls_from_correlations`, with or without its bounds) by the numba kernel "
                         "`cls_kernel.cls_solve` (what the engine runs) beside the numpy reference (its "
                         "reference column: `compiled=False`), the four in turn on one snapshot")
    return section


# ------------------------------------------------------------------------------------ 5 peers
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


# ------------------------------------------------------------------------------------ 6 memory
def memory_child(window: int, method: str = "cls-markov") -> dict:
    """In a fresh process: resident memory after the imports, the peak while the engine ingests
    2 W samples (generated chunk by chunk), and the peak over one solve of the full window."""
    plant = HammersteinStream(F2, G1)
    chunk = 10_000
    config = EngineConfig(sample_rate=SAMPLE_RATE, window=window, tau_max=default_tau_max(3, DEFAULT_MU),
                          method=method)
    engine = StreamingEngine(config)
    rng = np.random.default_rng(5)
    baseline = process_status_kib("VmRSS")
    for start in range(0, 2 * window, chunk):
        v = INPUT_STD * rng.standard_normal(chunk)
        t = (start + np.arange(chunk)) / SAMPLE_RATE
        engine.add_excitation(t, v)
        engine.add_response(t, plant(v))
    ingest_peak = process_status_kib("VmHWM")
    outcome = engine.solve()
    return {"window": window, "baseline_kib": baseline, "ingest_peak_kib": ingest_peak,
            "solve_peak_kib": process_status_kib("VmHWM"), "solve_ok": outcome.ok,
            "solve_seconds": outcome.solve_seconds,
            "reason": outcome.reason}


def memory_section(windows: Sequence[int], node: bool = True) -> Section:
    """Per W: the engine alone in a fresh process (``memory_child``) and, with ``node``, a fresh
    ``hammer-ros node`` fed over DDS (``ros_rate_probe.node_memory``)."""
    section = Section("memory", "6. Peak memory of the engine and of the node (fresh processes; cls-markov, "
                      "mu 30, tau_max 66)", [
        ("case", "W"), ("ingest", "engine ingest peak MiB"), ("solve", "engine solve peak MiB"),
        ("reference", "raw window (v, y float64) MiB"), ("ratio", "engine ingest / raw window"),
        ("solve_seconds", "engine solve s"), ("node_idle", "node idle RSS MiB"), ("node_peak", "node peak RSS MiB"),
        ("node_added", "node peak - idle MiB"), ("workers_peak", "node's worker processes: peak RSS MiB (sum)")])
    node_memory = None
    if node:
        try:
            from .ros_rate_probe import node_memory
        except ImportError as exc:  # rclpy missing
            section.notes.append(f"node rows skipped: {exc}")
    for window in windows:
        code = ("import json; from hammer_ros.tools.bench import memory_child; "
                f"print(json.dumps(memory_child({window})))")
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                              env=_child_env())
        if done.returncode != 0:
            section.rows.append({"case": f"{window:,}", "ingest": f"failed: {done.stderr.strip()[-200:]}"})
            continue
        doc = json.loads(done.stdout.strip().splitlines()[-1])
        raw = 2 * 8 * window / 2**20
        ingest = (doc["ingest_peak_kib"] - doc["baseline_kib"]) / 1024
        solve = (doc["solve_peak_kib"] - doc["baseline_kib"]) / 1024
        row = {"case": f"{window:,}", "window": window, "ingest": ingest, "solve": solve,
               "reference": raw, "ratio": ingest / raw, "baseline_mib": doc["baseline_kib"] / 1024,
               "solve_seconds": doc["solve_seconds"] if doc["solve_ok"] else f"not ok: {doc['reason']}"}
        if node_memory is not None:
            try:
                with contextlib.redirect_stdout(sys.stderr):
                    live = node_memory(window)
            except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
                row["node_idle"] = f"failed: {exc}"
            else:
                row.update(node_idle=live["idle_kib"] / 1024, node_peak=live["peak_kib"] / 1024,
                           node_added=(live["peak_kib"] - live["idle_kib"]) / 1024,
                           workers_peak=live["workers_peak_kib"] / 1024,
                           node_complete=live["filled"] and live["solved"])
                if not row["node_complete"]:
                    row["node_added"] = f"{row['node_added']:.3g} (window not filled and solved)"
        section.rows.append(row)
    section.notes.append("engine: MiB above the process's resident size after the imports (VmHWM - VmRSS), while "
                         "it ingests 2 W samples and over one solve of the full window")
    if node_memory is not None:
        section.notes.append("node: VmRSS of a fresh `hammer-ros node` (window W, cls-markov, 1 solve/s, a diagnosis "
                             "every 2 s of its newest `diagnosis_window` = 10,000 samples) after startup, and its "
                             "VmHWM once 1.2 W samples of G1 / tanh data (Float64MultiArray of 1000 samples, 200 "
                             "messages/s per topic) filled the window and it solved twice and diagnosed once more; its "
                             "worker processes (the solver, the diagnosis, multiprocessing's resource tracker): the "
                             "sum of their VmHWM at that point (each counts the shared library pages it maps, so the "
                             "sum overstates what they add)")
    return section


# ------------------------------------------------------------------------------------ 7 fleet
FLEET_WORKERS = 2
FLEET_ROUNDS = 3  # serial, fleet and plain processes back to back, this many times


def _replay_share(settings, sources, barrier, results) -> None:
    """One of ``fleet_section``'s plain processes: replay its share of the bags after the barrier
    (imports and a first bag done before it), and put its seconds on ``results``."""
    from ..fleet.tasks import run_bag

    run_bag(settings, sources[0])
    barrier.wait()
    seconds, _ = _timed(lambda: [run_bag(settings, s) for s in sources])
    results.put(seconds)


def plain_processes_wall(settings, sources, workers: int) -> float:
    """Wall seconds of ``workers`` plain processes replaying interleaved shares of ``sources`` at
    once (no scheduler, no transfer): the machine's own ceiling for running bags side by side."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(workers), context.Queue()
    processes = [context.Process(target=_replay_share, args=(settings, sources[i::workers], barrier, results))
                 for i in range(workers)]
    for process in processes:
        process.start()
    seconds = [results.get(timeout=600) for _ in processes]
    for process in processes:
        process.join()
    return max(seconds)


def fleet_section(bags: int, workers: int = FLEET_WORKERS, rounds: int = FLEET_ROUNDS) -> Section:
    """``bags`` small sample-fleet bags (1000 samples): serial replay in this process (the fleet's
    own task, which is replay's loop) vs ``fleet --workers 2`` (a LocalCluster; its start-up
    reported apart) vs plain processes, in ``rounds`` rounds (each measuring the three back to
    back, in a rotated order: a burst of another job's load hits one round, not the verdict);
    speed-ups per round, their median decides; overhead = worker time per bag beyond the bag's
    own replay."""
    from ..fleet.runner import connect, run_fleet
    from ..fleet.sample_fleet import sample_joints, write_sample_fleet
    from ..fleet.sources import sources_from_paths
    from ..fleet.tasks import FleetSettings, run_bag
    from ..io.bags import load_msg_config, stream_specs

    section = Section("fleet", f"7. Fleet: serial replay vs `fleet --workers {workers}` (Dask LocalCluster)", [
        ("case", "case"), ("serial", "serial s"), ("fleet", "fleet s"), ("ratio", "speed-up"),
        ("ratios", "speed-up per round"), ("plain", f"{workers} plain processes: speed-up"),
        ("task", "replay s / bag"), ("overhead", "Dask overhead s / bag"), ("startup", "cluster start s"),
        ("load", "load average (1 min) per round"), ("goal", "goal >= 1.7")])
    config_path = Path(__file__).resolve().parents[2] / "msg_config" / "sample_fleet.yaml"
    params = load_msg_config(config_path)
    config = EngineConfig(sample_rate=100.0, window=1000, tau_max=default_tau_max(2, DEFAULT_MU), order=2, delay=1)
    settings = FleetSettings(*stream_specs(None, None, params, str(config_path)), config, 0.5)
    # healthy joints: over 25 days the faulty ones' gain reaches 0 and their models are withheld as uncertain
    # (error rows, which the goal does not allow: 96 of 1200 rows before)
    joints = sample_joints(robots=4, joints=2, drift_day=None, dead_zone_day=None)
    serial, plain, runs, startups, loads, errors = [], [], [], [], [], []
    with tempfile.TemporaryDirectory(prefix="hammer_ros_bench_fleet_") as tmp:
        write_sample_fleet(tmp, joints, math.ceil(bags / len(joints)), samples=1000)
        sources = sources_from_paths([tmp])[:bags]
        run_bag(settings, sources[0])  # this process's first bag pays lazy imports, as a worker's warm-up does

        def measure_serial() -> None:
            seconds, rows = _timed(lambda: [run_bag(settings, s) for s in sources])
            serial.append(seconds)
            errors.extend(r["error"] for r in rows if r.get("error"))

        def measure_fleet() -> None:  # a cluster of its own: none idles beside the serial and plain runs
            startup, (client, cluster) = _timed(lambda: connect(None, workers))
            startups.append(startup)
            try:
                run_fleet(client, sources[:workers * 2], settings)  # warm the workers' imports
                runs.append(run_fleet(client, sources, settings))
            finally:
                client.close()
                cluster.close()

        steps = [measure_serial, measure_fleet, lambda: plain.append(plain_processes_wall(settings, sources, workers))]
        for i in range(rounds):
            loads.append(os.getloadavg()[0])
            for step in steps[i % 3:] + steps[:i % 3]:
                step()
    errors.extend(r["error"] for run in runs for r in run.rows if r.get("error"))
    ratios = [s / run.wall_s for s, run in zip(serial, runs, strict=True)]
    ratio = _median(ratios)
    overheads = [(run.wall_s * workers - sum(r["seconds"] for r in run.rows)) / len(sources) for run in runs]
    section.rows.append({"case": f"{len(sources)} bags x 1000 samples, {workers} workers, median of {rounds} rounds",
                         "serial": _median(serial), "fleet": _median([run.wall_s for run in runs]), "ratio": ratio,
                         "ratios": " ".join(f"{r:.2f}" for r in ratios),
                         "plain": _median([s / p for s, p in zip(serial, plain, strict=True)]),
                         "task": _median([r["seconds"] for run in runs for r in run.rows]),
                         "overhead": _median(overheads), "startup": _median(startups),
                         "load": " ".join(f"{x:.1f}" for x in loads), "goal": ratio >= 1.7 and not errors})
    if errors:
        section.notes.append(f"{len(errors)} bag(s) failed (the goal needs none), e.g. {errors[0]}")
    section.notes.append(f"serial: the fleet's task (replay's loop) on each bag in turn in this process (after one "
                         "bag apart); fleet: "
                         f"`run_fleet` on a LocalCluster of {workers} single-threaded worker processes, timed "
                         "from the first submit to the last row (cluster start-up and a warm-up of "
                         f"{workers * 2} bags apart); overhead = (fleet wall x workers - sum of the tasks' own "
                         "seconds) / bags: scheduling, transfer and idle time per bag; plain processes: "
                         f"{workers} processes (no Dask) replaying interleaved shares of the bags at once, "
                         "the machine's own ceiling for bags side by side (serial / their wall); "
                         f"{rounds} rounds of the three back to back (order rotated each round; each fleet on a "
                         "new cluster, closed before the next step), the speed-ups per round and their median "
                         "(the figures shown are medians)")
    return section


# ------------------------------------------------------------------------------------ goals
def _measured(sections: dict[str, Section], key: str) -> list[dict]:
    """The rows of a section that hold a measurement (not a failure)."""
    section = sections.get(key)
    return [] if section is None else [r for r in section.rows if "error" not in r]


def _all_some_none(flags: Sequence[bool]) -> bool | str:
    return True if all(flags) else ("partly" if any(flags) else False)


def goals(sections: dict[str, Section]) -> Section:
    """The issue's goals, each with the figures that decide it ("partly": met in some cases)."""
    table = Section("goals", "Goals", [("goal", "goal"), ("measured", "measured"), ("met", "met")])

    def add(goal: str, measured: str, met: bool | str | None) -> None:
        table.rows.append({"goal": goal, "measured": measured, "met": met})

    rows = _measured(sections, "ingest")
    if rows:
        add("engine ingest >= 0.5 x batch FFT", "; ".join(f"{r['case']}: {r['ratio']:.2f}" for r in rows),
            _all_some_none([r["goal"] for r in rows]))
    rows = [r for r in _measured(sections, "node") if r.get("ratio") is not None]
    if rows:
        add("node zero loss up to >= 0.9 x bare rclpy",
            "; ".join(f"{r['case']}: {r['ratio']:.2f} ({r.get('range', '-')})" for r in rows),
            _all_some_none([r["goal"] for r in rows]))
    rows = _measured(sections, "replay")
    if rows:
        add("replay >= 0.8 x bare decode",
            "; ".join(f"{r['case'].split(',')[0]}, {r['mode'].split(' (')[0]}: {r['ratio']:.2f}" for r in rows),
            _all_some_none([r["goal"] for r in rows]))
    rows = [r for r in _measured(sections, "solve")
            if r.get("method") in ("cls-markov", "cls-markov (process)") and r.get("mu") == DEFAULT_MU and "p99" in r]
    if rows:
        add("CLS mu-Markov solve p99 < 5 ms at mu = 30 (alone; loaded = in the node's solver process beside "
            "ingestion at half its limit)",
            "; ".join(f"W {r['window']}, tau_max {r['tau_max']}{', loaded' if '(process)' in r['method'] else ''}: "
                      f"{r['p99']:.2f} ms" for r in rows),
            _all_some_none([r["p99"] < 5.0 for r in rows]))
    rows = [r for r in _measured(sections, "solve") if r.get("method") == "cls-markov (compiled)"
            and "with bounds" in r["case"] and "ratio" in r]
    if rows:
        add(f"compiled CLS mu-Markov solve with its bounds >= {COMPILED_GOAL:g} x the numpy reference, same poles",
            "; ".join(f"W {r['window']}: {r['ratio']:.1f} x ({r['p50']:.2f} vs {r['reference']:.2f} ms)" for r in rows),
            _all_some_none([r["ratio"] >= COMPILED_GOAL and r["poles_equal"] for r in rows]))
    peers = _measured(sections, "peers")
    rows = [r for r in peers if r.get("method") == "cls-markov" and "speedup" in r and r["case"].startswith("G1")]
    if rows:
        r = rows[0]
        best = min(p["nrmse"] for p in peers if p["method"] == "FROLS" and p["case"] == r["case"])
        add(">= 20 x faster than FROLS with a better validation NRMSE (G1, CLS mu-Markov)",
            f"{r['speedup']:.0f} x faster, NRMSE {r['nrmse']:.3f} vs best FROLS {best:.3f}",
            r["speedup"] >= 20 and r["better"])
    elif peers:
        add(">= 20 x faster than FROLS with a better validation NRMSE (G1, CLS mu-Markov)",
            "not measured: SysIdentPy is not installed (make bench-deps)", None)
    rows = _measured(sections, "fleet")
    if rows:
        add("fleet --workers 2 >= 1.7 x serial replay",
            "; ".join(f"{r['case']}: {r['ratio']:.2f} (plain processes {r['plain']:.2f}), overhead "
                      f"{r['overhead'] * 1e3:.1f} ms/bag" for r in rows),
            _all_some_none([r["goal"] for r in rows]))
    for key, section in sections.items():
        if not _measured(sections, key) and section.rows:
            add(f"section {key}", f"not measured: {section.rows[0].get('error')}", False)
    return table


# ------------------------------------------------------------------------------------ driver
SECTION_KEYS = ("ingest", "node", "replay", "solve", "peers", "memory", "fleet")


def run_sections(plan: Plan, only: Sequence[str] = SECTION_KEYS, profile: bool = False,
                 log=sys.stderr) -> dict[str, Section]:
    """Run the sections named in ``only`` (in their order); with ``profile`` print each one's
    cProfile (top functions by own time) on ``log``: the evidence behind a missed goal."""
    builders: dict[str, Callable[[], Section]] = {
        "ingest": lambda: ingest_section(plan.ingest_samples, plan.ingest_taus, plan.ingest_windows,
                                         plan.ingest_forgetting, plan.ingest_chunk, plan.repeats),
        "node": lambda: node_section(plan.node_rates, plan.node_seconds, plan.node_step,
                                     joint_rates=plan.node_joint_rates),
        "replay": lambda: replay_section(plan.replay_messages, plan.replay_repeats),
        "solve": lambda: solve_section(plan.solve_windows, plan.solve_repeats, plan.slow_solve_repeats),
        "peers": lambda: peer_section(plan.peer_frols, plan.repeats),
        "memory": lambda: memory_section(plan.memory_windows),
        "fleet": lambda: fleet_section(plan.fleet_bags),
    }
    sections = {}
    for key in only:
        print(f"bench: {key} ...", file=log, flush=True)
        profiler = cProfile.Profile() if profile else None
        try:
            if profiler:
                profiler.enable()
            elapsed, section = _timed(builders[key])
        except Exception as exc:  # one broken section must not hide the others
            print(f"bench: {key} failed: {exc!r}", file=log, flush=True)
            section, elapsed = Section(key, f"{key}: failed", [("error", "error")], [{"error": repr(exc)}]), 0.0
        finally:
            if profiler:
                profiler.disable()
        section.seconds = elapsed
        sections[key] = section
        print(f"bench: {key} done in {elapsed:.1f} s", file=log, flush=True)
        if profiler:
            pstats.Stats(profiler, stream=log).sort_stats("tottime").print_stats(15)
    return sections


def markdown(info: dict, sections: dict[str, Section], goal_table: Section, plan: Plan, wall: float) -> str:
    head = (f"hammer-ros bench ({plan.name}), {info['date']}: {info['nproc']} cores, {info['cpu']}, "
            f"{info['ram_gib']} GiB RAM, Python {info['python']}, numpy {info['numpy']} (BLAS threads "
            f"{info['blas_threads']}), load average at start "
            f"{', '.join(map(str, info['load_average']))}; {wall:.0f} s\n")
    return "\n".join([head, goal_table.markdown(), *(s.markdown() for s in sections.values())])


def run(args: argparse.Namespace) -> int:
    plan = QUICK if args.quick else FULL
    only = tuple(getattr(args, "only", None) or SECTION_KEYS)
    unknown = [key for key in only if key not in SECTION_KEYS]
    if unknown:
        raise UsageError(f"--only: unknown section {unknown[0]!r} (choose from {', '.join(SECTION_KEYS)})")
    info = machine()
    started = time.perf_counter()
    sections = run_sections(plan, only, profile=getattr(args, "profile", False))
    goal_table = goals(sections)
    wall = time.perf_counter() - started
    if args.json:
        doc = {"plan": plan.name, "machine": info, "wall_s": round(wall, 1), "goals": goal_table.rows,
               "sections": [s.to_json() for s in sections.values()]}
        json.dump(_json_safe(doc), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(markdown(info, sections, goal_table, plan, wall))
    return 0


def _json_safe(value: Any) -> Any:
    """numpy scalars as Python numbers, non-finite floats as strings ("inf", "nan")."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value
