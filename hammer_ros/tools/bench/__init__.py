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

The package holds one module per section (``ingest``, ``node``, ``replay``, ``solve``, ``peers``,
``memory``, ``fleet``), the shared plans, tables and data (``common``) and the goals (``goals``);
this module runs them (``run``: the CLI entry) and re-exports their names.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import math
import pstats
import sys
import time
import types
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...errors import UsageError
from . import common, fleet, goal_table, ingest, memory, node, peers, replay, solve
from .common import (
    DATA_DIR,
    F2,
    FULL,
    QUICK,
    SAMPLE_RATE,
    SYSIDENTPY_VERSION,
    Plan,
    Section,
    _timed,
    batch_correlations_fft,
    engine_correlations,
    feed_engine,
    hammerstein_record,
    machine,
)
from .fleet import FLEET_ROUNDS, FLEET_WORKERS, fleet_section, plain_processes_wall
from .goal_table import goals
from .ingest import ingest_section
from .memory import memory_child, memory_section
from .node import (
    CONFIRMATIONS,
    JOINTS,
    LADDER_CAP,
    LADDER_STEP,
    MAX_STALLS,
    NODE_LIMITS,
    REFINE_RATIO,
    REFINE_STEPS,
    SEARCH_RETRIES,
    SEARCH_RUNS,
    STALL_RETRIES,
    SUBSCRIBER_KEYS,
    _cpu_cell,
    _losses,
    _node_row,
    _seeded_limits,
    _store_node_limits,
    _zero_loss_limits,
    node_section,
    stored_node_limits,
)
from .peers import (
    PEER_METHODS,
    VALIDATION_SKIP,
    PeerCase,
    cascaded_tanks_case,
    frols_peer_row,
    g1_case,
    hammer_ros_peer_rows,
    nrmse,
    peer_section,
    sysidentpy_available,
)
from .replay import REPLAY_MODES, bare_decode, replay_section, run_replay, write_bench_bag
from .solve import (
    COMPILED_GOAL,
    LOADED_SHARE,
    SolveCase,
    compiled_solve_rows,
    diagnose_latencies,
    loaded_solve_latencies,
    solve_cases,
    solve_latencies,
    solve_section,
)

__all__ = [
    "COMPILED_GOAL",
    "CONFIRMATIONS",
    "DATA_DIR",
    "F2",
    "FLEET_ROUNDS",
    "FLEET_WORKERS",
    "FULL",
    "JOINTS",
    "LADDER_CAP",
    "LADDER_STEP",
    "LOADED_SHARE",
    "MAX_STALLS",
    "NODE_LIMITS",
    "PEER_METHODS",
    "QUICK",
    "REFINE_RATIO",
    "REFINE_STEPS",
    "REPLAY_MODES",
    "SAMPLE_RATE",
    "SEARCH_RETRIES",
    "SEARCH_RUNS",
    "SECTION_KEYS",
    "STALL_RETRIES",
    "SUBSCRIBER_KEYS",
    "SYSIDENTPY_VERSION",
    "VALIDATION_SKIP",
    "PeerCase",
    "Plan",
    "Section",
    "SolveCase",
    "_cpu_cell",
    "_json_safe",
    "_losses",
    "_node_row",
    "_seeded_limits",
    "_store_node_limits",
    "_timed",
    "_zero_loss_limits",
    "bare_decode",
    "batch_correlations_fft",
    "cascaded_tanks_case",
    "compiled_solve_rows",
    "diagnose_latencies",
    "engine_correlations",
    "feed_engine",
    "fleet_section",
    "frols_peer_row",
    "g1_case",
    "goals",
    "hammer_ros_peer_rows",
    "hammerstein_record",
    "ingest_section",
    "loaded_solve_latencies",
    "machine",
    "markdown",
    "memory_child",
    "memory_section",
    "node_section",
    "nrmse",
    "peer_section",
    "plain_processes_wall",
    "replay_section",
    "run",
    "run_replay",
    "run_sections",
    "solve_cases",
    "solve_latencies",
    "solve_section",
    "stored_node_limits",
    "sysidentpy_available",
    "write_bench_bag",
]

SECTIONS = (common, ingest, node, replay, solve, peers, memory, fleet, goal_table)


class _Facade(types.ModuleType):
    """Setting a re-exported constant here (a test's ``monkeypatch.setattr(bench, ...)``) sets it in
    the sections that read it."""

    def __setattr__(self, name: str, value: Any) -> None:
        if not isinstance(value, types.ModuleType):
            for module in SECTIONS:
                if hasattr(module, name):
                    setattr(module, name, value)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Facade

SECTION_KEYS = ("ingest", "node", "replay", "solve", "peers", "memory", "fleet")


def run_sections(plan: Plan, only: Sequence[str] = SECTION_KEYS, profile: bool = False,
                 log=sys.stderr) -> dict[str, Section]:
    """Run the sections named in ``only`` (in their order); with ``profile`` print each one's
    cProfile (top functions by own time) on ``log``: the evidence behind a missed goal."""
    builders: dict[str, Callable[[], Section]] = {
        "ingest": lambda: ingest_section(plan.ingest_samples, plan.ingest_taus, plan.ingest_windows,
                                         plan.ingest_forgetting, plan.ingest_chunk, plan.repeats),
        "node": lambda: node_section(plan.node_rates, plan.node_seconds, plan.node_step,
                                     joint_rates=plan.node_joint_rates, budget=plan.node_budget),
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
