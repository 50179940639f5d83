"""``hammer-ros replay``: a bag through the same streaming engine as the live node.

As fast as possible by default (messages are buffered and added to the engine in vectorised
batches between solves); ``--rate R`` paces the bag at R x real time and publishes the results
on the live ROS 2 graph under the node name ``hammer_ros`` (the node's topics, so the same
dashboard works); ``--out`` writes every result (``outputs``) into an MCAP file.

SIGINT/SIGTERM stop it at the next message: a final solve on what was read, ``--out`` finished
and closed, the final model printed, exit 128 + signal (``SignalStop``).

Solves happen every 1 / solve_rate seconds of bag time (``--solve-rate``, else the config's
``solve_rate``, else 2 Hz) and once at the end of the bag. Settings: command-line options, else
the ``--config`` parameters, else the engine defaults (tau_max: the method's batch default, so
that a replay with a window holding the whole bag equals ``identify`` on it).
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from pathlib import Path

from ..errors import IdentificationError, UsageError
from ..io.bags import (
    FLUSH_SAMPLES,
    BagReadStats,
    ResultWriter,
    bag_files,
    bag_message_counts,
    check_fields,
    check_topics,
    engine_config_from_params,
    forget_warnings,
    iter_bag_samples,
    load_msg_config,
    node_topic,
    stream_specs,
)
from ..ros.outputs import diagnostics_message, result_messages, stale_model_message
from ..streaming.config import CLS_STRUCTURES, EngineConfig
from ..streaming.engine import SolveOutcome, StreamingEngine
from .common import check_option_conflicts, format_model

DEFAULT_SOLVE_RATE = 2.0
NODE_NAME = "hammer_ros"


def replay_settings(args: argparse.Namespace, params: dict, source: str) -> tuple[EngineConfig, float]:
    """(engine config, solve rate) from the options, the config parameters and the defaults."""
    config = engine_config_from_params(params, source)
    cli = {"method": args.method, "order": args.order, "delay": args.delay, "mu": args.mu, "poly": args.poly,
           "partition": args.partition, "tau_max": args.tau_max, "window": args.window,
           "sample_rate": args.sample_rate, "forgetting": args.forgetting, "interpolation": args.interpolation}
    changes = {k: v for k, v in cli.items() if v is not None}
    if args.refine:
        changes["refine"] = True
    method = changes.get("method", config.method)
    check_option_conflicts(method, args, streaming=True)
    if "tau_max" not in changes and "tau_max" not in params and method in CLS_STRUCTURES:
        from ..identification.correlation_least_squares import DEFAULT_MU, default_tau_max

        mu = 1 if method == "cls-arx" else changes.get("mu", config.mu) or DEFAULT_MU
        changes["tau_max"] = default_tau_max(changes.get("order", config.order), mu)
    try:
        config = EngineConfig(**{**config.__dict__, **changes}).validated()
    except UsageError as exc:
        name, reason = str(exc).split(":", 1)
        raise UsageError(f"--{name.replace('_', '-')}:{reason}") from None
    solve_rate = args.solve_rate if args.solve_rate is not None else params.get("solve_rate", DEFAULT_SOLVE_RATE)
    option = "--solve-rate" if args.solve_rate is not None else f"{source}: solve_rate"
    if isinstance(solve_rate, bool) or not isinstance(solve_rate, (int, float)) or not 0 < solve_rate < math.inf:
        raise UsageError(f"{option}: must be > 0 (got {solve_rate!r})")
    return config, solve_rate


class Progress:
    """A one-line progress bar on stderr, redrawn at most 10 times per second."""

    def __init__(self, total: int, stream=None) -> None:
        self.total, self.stream, self.last = max(total, 1), stream or sys.stderr, 0.0

    def update(self, done: int, samples: int, solves: int, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last < 0.1:
            return
        self.last = now
        fraction = min(done / self.total, 1.0)
        bar = "#" * int(30 * fraction)
        self.stream.write(f"\rreplay [{bar:<30}] {100 * fraction:5.1f} %  {samples} samples  {solves} solves")
        self.stream.flush()

    def close(self) -> None:
        self.stream.write("\n")
        self.stream.flush()


class SignalStop:
    """While active, SIGINT and SIGTERM only set ``signal`` (the number), so that replay stops at
    a safe point between messages, solves once more on what it read, finishes the output MCAP
    and prints the final model instead of dying with a half-written file. Main thread only."""

    def __init__(self) -> None:
        self.signal: int | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame) -> None:
        self.signal = signum

    def __enter__(self) -> SignalStop:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)

    def sleep(self, seconds: float) -> None:
        """Sleep, waking up within 0.1 s of a signal."""
        deadline = time.perf_counter() + seconds
        while self.signal is None and (left := deadline - time.perf_counter()) > 0:
            time.sleep(min(left, 0.1))


def run(args: argparse.Namespace) -> int:
    forget_warnings()
    params = load_msg_config(args.config) if args.config else {}
    source = str(args.config or "config")
    excitation, response = stream_specs(args.input, args.output, params, source)
    config, solve_rate = replay_settings(args, params, source)
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise UsageError(f"--rate: must be > 0 (got {args.rate})")
    check_topics(args.bag, (excitation, response))
    check_fields(args.bag, (excitation, response))  # every user mistake before any output
    if args.out and any(Path(args.out).resolve() == f.resolve() for f in bag_files(args.bag)):
        raise UsageError(f"--out: {args.out} is the bag being replayed (it would be overwritten)")
    counts = bag_message_counts(args.bag)
    total = sum(counts.get(topic, 0) for topic in {excitation.topic, response.topic})
    read = BagReadStats()
    samples = iter_bag_samples(args.bag, excitation, response, read)
    engine = StreamingEngine(config)
    progress = Progress(total)
    last_ok: SolveOutcome | None = None
    last: SolveOutcome | None = None
    frame_id = str(params.get("frame_id", ""))
    writer = publisher = None
    done = 0
    stop = SignalStop()
    try:
        publisher = None
        if args.rate is not None:
            from ..ros.live_publisher import LivePublisher  # rclpy only for --rate

            publisher = LivePublisher(NODE_NAME)
        stop.__enter__()  # after rclpy.init, which installs its own handlers
        writer = ResultWriter(args.out) if args.out else None
        started = time.perf_counter()

        def solve(bag_time: float) -> None:
            nonlocal last_ok, last
            engine.flush()
            last = engine.solve()
            last_ok = last if last.ok else last_ok
            stamp = next((s for s in (last.stamp, bag_time) if math.isfinite(s)), 0.0)
            messages = result_messages(last, stamp, frame_id)
            if not last.ok and last_ok is not None:
                messages.append(stale_model_message(last_ok, last))
            diagnostics = diagnostics_message(engine.stats, last, stamp, NODE_NAME)
            diagnostics["status"][0]["values"].extend(_bag_values(read))
            messages.append(("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", diagnostics))
            for topic, type_name, message in messages:
                if writer:  # first into the file: whatever is published is already in it
                    writer.write(node_topic(topic, NODE_NAME), type_name, message, round(stamp * 1e9))
                if publisher:
                    publisher.publish(topic, type_name, message)

        bag_start = next_solve = None
        bag_time = float("nan")
        for sample in samples:
            if bag_start is None:
                bag_start, next_solve = sample.stamp, sample.stamp + 1.0 / solve_rate
            if publisher:  # pace: bag time / rate = wall time since the start
                wait = (sample.stamp - bag_start) / args.rate - (time.perf_counter() - started)
                if wait > 0.005:
                    stop.sleep(wait)
            if stop.signal is not None:
                break
            if sample.stamp >= next_solve:
                solve(sample.stamp)
                next_solve += math.ceil((sample.stamp - next_solve) * solve_rate + 1e-9) / solve_rate
            engine.add_message(sample.stream, sample.stamp, sample.values, flush=False)
            if engine.buffered >= FLUSH_SAMPLES:
                engine.flush()
            bag_time = sample.stamp
            done += 1
            progress.update(done, engine.stats.aligned, engine.stats.solves)
        solve(bag_time)  # the final model, also after a signal
        progress.update(done, engine.stats.aligned, engine.stats.solves, force=True)
    finally:
        progress.close()
        try:
            if writer:
                writer.close()
            if publisher:
                publisher.close()
        finally:
            stop.__exit__()
    read.report(args.bag)
    if stop.signal is not None:
        name = signal.Signals(stop.signal).name
        print(f"hammer-ros: replay stopped by {name} after {done} of {total} messages; final model solved on the "
              f"{engine.stats.aligned} samples read" + (f"; {writer.count} messages in {args.out}" if writer else ""),
              file=sys.stderr)
    wall = time.perf_counter() - started
    if last_ok is None:
        reason = last.reason if last else "no messages"
        if stop.signal is not None:
            print(f"hammer-ros: no model identified ({reason})", file=sys.stderr)
            return 128 + stop.signal
        raise IdentificationError(f"{args.bag}: no model identified ({reason})")
    doc = dict(last_ok.doc)
    doc.update(samples=int(engine.stats.aligned), solves=int(engine.stats.solves), wall_s=round(wall, 4))
    if args.json:
        json.dump(doc, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        rate = engine.stats.aligned / wall if wall > 0 else float("inf")
        print(format_model(doc))
        print(f"replay   {doc['samples']} samples, {doc['solves']} solves in {wall:.2f} s ({rate:,.0f} samples/s)"
              + (f"; {writer.count} messages -> {Path(args.out)}" if writer else ""))
    return 0 if stop.signal is None else 128 + stop.signal


def _bag_values(read: BagReadStats) -> list[dict]:
    """Diagnostics values of what reading the bag skipped so far."""
    values = {"bag_damage": len(read.damage), "bag_oversized_messages": read.oversized,
              "bag_undecodable_messages": read.undecodable, "bag_field_errors": sum(read.field_errors.values())}
    return [{"key": k, "value": str(v)} for k, v in values.items()]
