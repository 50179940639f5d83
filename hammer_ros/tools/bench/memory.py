"""Section 6, memory: peak resident memory of the engine (a fresh process) per window."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from collections.abc import Sequence

import numpy as np

from ...identification.correlation_least_squares import DEFAULT_MU, default_tau_max
from ...identification.simulate import HammersteinStream
from ...process_status import process_status_kib
from ...reproduce.cls import G1, INPUT_STD
from ...ros.environment import without_bootstrap
from ...streaming.config import EngineConfig
from ...streaming.engine import StreamingEngine
from .common import (
    F2,
    SAMPLE_RATE,
    Section,
)


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


JOINT_CHANNELS = (1, 6)  # the idle node rows: a node of that many JointState channels


def memory_section(windows: Sequence[int], node: bool = True) -> Section:
    """Per W: the engine alone in a fresh process (``memory_child``) and, with ``node``, a fresh
    ``hammer-ros node`` fed over DDS (``ros_rate_probe.node_memory``); with ``node``, also a fresh
    idle node of 1 and of 6 JointState channels (``rate_probe_node.joints_node_memory``)."""
    section = Section("memory", "6. Peak memory of the engine and of the node (fresh processes; cls-markov, "
                      "mu 30, tau_max 66)", [
        ("case", "W"), ("ingest", "engine ingest peak MiB"), ("solve", "engine solve peak MiB"),
        ("reference", "raw window (v, y float64) MiB"), ("ratio", "engine ingest / raw window"),
        ("solve_seconds", "engine solve s"), ("node_idle", "node idle RSS MiB"), ("node_peak", "node peak RSS MiB"),
        ("node_added", "node peak - idle MiB"), ("workers_peak", "node's worker processes: peak RSS MiB (sum)"),
        ("processes", "node processes"), ("idle_pss", "node idle PSS MiB (sum)"), ("start", "node start s")])
    node_memory = None
    if node:
        try:
            from ..ros_rate_probe import node_memory
        except ImportError as exc:  # rclpy missing
            section.notes.append(f"node rows skipped: {exc}")
    for window in windows:
        code = ("import json; from hammer_ros.tools.bench.memory import memory_child; "
                f"print(json.dumps(memory_child({window})))")
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                              env=without_bootstrap())
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
    if node_memory is not None:
        section.rows += [_idle_node_row(joints) for joints in JOINT_CHANNELS]
    section.notes.append("engine: MiB above the process's resident size after the imports (VmHWM - VmRSS), while "
                         "it ingests 2 W samples and over one solve of the full window")
    if node_memory is not None:
        section.notes.append("node: VmRSS of a fresh `hammer-ros node` (window W, cls-markov, 1 solve/s, a diagnosis "
                             "every 2 s of its newest `diagnosis_window` = 10,000 samples) after startup, and its "
                             "VmHWM once 1.2 W samples of G1 / tanh data (Float64MultiArray of 1000 samples, 200 "
                             "messages/s per topic) filled the window and it solved twice and diagnosed once more; its "
                             "worker processes (the solver, the diagnosis): the "
                             "sum of their VmHWM at that point (each counts the shared library pages it maps, so the "
                             "sum overstates what they add)")
        section.notes.append("idle node of J channels: a fresh `hammer-ros node` of J JointState channels (one "
                             "topic, window 4000, cls-markov, 4 solves/s), no publisher: start = its launch until "
                             "/diagnostics has every channel's status; 3 s later the node and every process it "
                             "started (count), their VmRSS summed (node idle) and their Pss (shared pages counted "
                             "once) summed")
    return section


def _idle_node_row(joints: int) -> dict:
    """The idle node row of ``joints`` JointState channels (``joints_node_memory``)."""
    from ...ros.rate_probe_node import joints_node_memory

    case = f"node, {joints} JointState channel{'s' if joints > 1 else ''}, idle"
    try:
        with contextlib.redirect_stdout(sys.stderr):
            idle = joints_node_memory(joints)
    except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
        return {"case": case, "joints": joints, "node_idle": f"failed: {exc}"}
    return {"case": case, "joints": joints, "node_idle": idle["rss_kib"] / 1024, "idle_pss": idle["pss_kib"] / 1024,
            "processes": idle["processes"], "start": idle["start_seconds"]}


