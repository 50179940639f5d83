"""Section 3, replay: samples/s of ``hammer-ros replay`` on a generated bag vs a bare MCAP read + CDR decode."""

from __future__ import annotations

import contextlib
import gc
import io
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import (
    SAMPLE_RATE,
    Section,
    _median,
    _timed,
    children_cpu_seconds,
    hammerstein_record,
)


def write_bench_bag(path: Path, messages: int, batch: int, seed: int = 3) -> int:
    """A bag of paper 000's G1 / F2 at SAMPLE_RATE: /cmd and /response, ``messages`` messages each,
    std_msgs/msg/Float64 (batch 1) or Float64MultiArray of ``batch`` samples (log time = time of
    the last sample). Returns the number of samples per topic."""
    from ...io.bags import ResultWriter

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
    from ...cli import build_parser
    from ...cli.replay import run as replay

    field_path = "data" if batch == 1 else "data[:]"
    argv = ["replay", str(path), "--input", f"/cmd:{field_path}", "--output", f"/response:{field_path}",
            "--sample-rate", f"{SAMPLE_RATE:g}", "--window", str(window), "--json"]
    if solve_rate is not None:
        argv += ["--solve-rate", f"{solve_rate:g}"]
    args = build_parser().parse_args(argv)
    out = io.StringIO()
    before, children = time.process_time(), children_cpu_seconds()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        elapsed, _ = _timed(lambda: replay(args))
    doc = json.loads(out.getvalue())
    doc["cpu_s"] = {"reading": time.process_time() - before, "solver": children_cpu_seconds() - children}
    return elapsed, doc


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
                    gc.collect()  # each timed part from a collected heap (below)
                    elapsed, doc = run_replay(path, batch, min(4000, samples // 2), solve_rate)
                    gc.collect()
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
                         "the field of every message of both topics into a numpy array. Replay and bare alternate, "
                         "each after a full garbage collection (else the objects one leaves can trigger a full "
                         "collection inside the next: measured 0.09 s of a 0.28 s bare decode); "
                         "ratio = median of the pairs. CPU: medians of the replay process's CPU seconds and of its "
                         "solver process's (forked when the periodic solves are worth it; 0 without), and of the "
                         "bare decode's (one thread: about its wall time)")
    return section
