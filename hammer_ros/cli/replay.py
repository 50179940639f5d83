"""``hammer-ros replay``: a bag through the same streaming engine as the live node.

As fast as possible by default (messages are buffered and added to the engine in vectorised
batches between solves); ``--rate R`` paces the bag at R x real time and publishes the results
on the live ROS 2 graph under the node name ``hammer_ros`` (the node's topics, so the same
dashboard works); ``--out`` writes every result (``outputs``, ROS 2 messages only) into an MCAP
file, ``--dashboard-out`` their Foxglove dashboard channels (JSON) into another; ``--diagnose``
diagnoses the final window and adds it to both (``~/diagnosis``, the dashboard's diagnosis
channels) and to the JSON.

The loop itself is ``hammer_ros.io.replay.replay_bag`` (also each ``hammer-ros fleet`` task).
SIGINT/SIGTERM stop it at the next message: a final solve on what was read, ``--out`` finished
and closed, the final model printed, exit 128 + signal (``SignalStop``).

Solves happen every 1 / solve_rate seconds of bag time (``--solve-rate``, else the config's
``solve_rate``, else 2 Hz) and once at the end of the bag. When they are expected to take
OVERLAP_SECONDS or more and the bag is not paced, they run in a ``SolverProcess`` while the
reading goes on (the same output, in less wall time when the solves outweigh the worker's start).
Settings: command-line options, else the ``--config`` parameters, else the engine defaults
(tau_max: the method's batch default, so that a replay with a window holding the whole bag
equals ``identify`` on it).
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

from ..errors import UsageError
from ..identification.methods import REFERENCE_METHODS
from ..io.bag_config import (
    Channel,
    config_channels,
    engine_config_from_params,
    load_msg_config,
    stream_spec,
    stream_specs,
)
from ..io.bag_index import WarningLog, bag_duration, bag_message_counts
from ..io.bag_writer import check_output_path
from ..io.replay import NODE_NAME, SOLVE_BATCH, ChannelReplay, check_replay_input, replay_bag, replay_channels
from ..streaming.config import CLS_STRUCTURES, EngineConfig
from ..streaming.solver_process import SolverProcess
from .common import check_option_conflicts, format_model

DEFAULT_SOLVE_RATE = 2.0
# The periodic solves run in a SolverProcess beside the reading when they are expected to take at least
# OVERLAP_SECONDS in process: solves x the typical solve (2-core bench machine, W = 4000: CLS on the window's
# correlation sums 0.7 ms with the engine's flush and snapshot; the methods on the raw window 7 ms, growing
# with W). The worker is forked (~6 ms) and each solve's transfer costs ~0.1 ms on either side, so below that
# it does not pay: measured side by side, 39 solves 0.38-0.46 s in process against 0.41-0.47 s with the
# worker, 199 solves on a 100 000-message Float64 bag 1.72-1.96 against 1.61-1.79 s, 399 solves of
# 100-sample batches 0.31-0.33 against 0.24-0.26 s.
OVERLAP_SECONDS = 0.1
CLS_SOLVE_SECONDS, RAW_WINDOW_SOLVE_SECONDS = 0.0007, 0.007


def expected_solve_seconds(config: EngineConfig, solves: float) -> float:
    """In-process time of ``solves`` periodic solves of ``config``'s method (see OVERLAP_SECONDS)."""
    if config.method in CLS_STRUCTURES:
        return solves * CLS_SOLVE_SECONDS
    return solves * RAW_WINDOW_SOLVE_SECONDS * max(1.0, config.window / 4000)


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
    and prints the final model instead of dying with a half-written file. ``interrupt``: also
    raise KeyboardInterrupt (a caller blocked in a wait, e.g. the fleet's, stops at once). The
    handlers are installed even where the shell started the process with SIGINT ignored (a
    background job). Main thread only."""

    def __init__(self, interrupt: bool = False) -> None:
        self.signal: int | None = None
        self.interrupt = interrupt
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame) -> None:
        self.signal = signum
        if self.interrupt:
            raise KeyboardInterrupt

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
    params = load_msg_config(args.config) if args.config else {}
    source = str(args.config or "config")
    channels = config_channels(params, source)
    if len(channels) > 1:
        return run_channels(args, channels, params, source)
    if channels:  # one channel: exactly the single-channel replay of its parameters
        params = channels[0].params
    excitation, response = stream_specs(args.input, args.output, params, source)
    reference = stream_spec("--reference", "reference", args.reference, params, source, required=False)
    config, solve_rate = replay_settings(args, params, source)
    if reference is not None and config.method not in REFERENCE_METHODS:
        raise UsageError(f"--reference: not for {config.method} (instrumented methods: {', '.join(REFERENCE_METHODS)})")
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise UsageError(f"--rate: must be > 0 (got {args.rate})")
    # every user mistake before any output
    check_replay_input(args.bag, excitation, response, args.out, args.dashboard_out, reference)
    for option, path in (("--out", args.out), ("--dashboard-out", args.dashboard_out)):
        if path:
            check_output_path(path, option)
    progress = Progress(sum(bag_message_counts(args.bag).get(t, 0) for t in {excitation.topic, response.topic}))
    publisher = solver = None
    stop = SignalStop()
    try:
        if args.rate is None and expected_solve_seconds(config, solve_rate * bag_duration(args.bag)) >= OVERLAP_SECONDS:
            # Forked: no thread, no middleware yet, so the worker starts loaded. Documents only for files
            # (without them, only the last good model's is printed).
            written = args.out is not None or args.dashboard_out is not None
            solver = SolverProcess("fork", SOLVE_BATCH, documents=written)
        if args.rate is not None:
            from ..ros.live_publisher import LivePublisher  # rclpy only for --rate

            publisher = LivePublisher(NODE_NAME)
        stop.__enter__()  # after rclpy.init, which installs its own handlers
        result = replay_bag(args.bag, excitation, response, config, solve_rate,
                            frame_id=str(params.get("frame_id", "")), out=args.out, publisher=publisher,
                            rate=args.rate, stop=stop, solver=solver, dashboard_out=args.dashboard_out,
                            diagnose=args.diagnose, reference=reference,
                            progress=lambda done, samples, solves, force: progress.update(done, samples, solves, force))
    finally:
        progress.close()
        try:
            if publisher:
                publisher.close()
            if solver:
                solver.close()
        finally:
            stop.__exit__()
    WarningLog().warn(*result.read.warnings(args.bag))
    files = ", ".join(str(Path(p)) for p in (args.out, args.dashboard_out) if p)
    if stop.signal is not None:
        name = signal.Signals(stop.signal).name
        print(f"hammer-ros: replay stopped by {name} after {result.messages} of {result.total} messages; final model "
              f"solved on the {result.stats.aligned} samples read"
              + (f"; {result.written} messages in {files}" if files else ""), file=sys.stderr)
        if result.last_ok is None:
            reason = result.last.reason if result.last else "no messages"
            print(f"hammer-ros: no model identified ({reason})", file=sys.stderr)
            return 128 + stop.signal
    doc = result.document()
    if args.json:
        json.dump(doc, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        wall = result.wall_s
        rate = result.stats.aligned / wall if wall > 0 else float("inf")
        print(format_model(doc))
        print(f"replay   {doc['samples']} samples, {doc['solves']} solves in {wall:.2f} s ({rate:,.0f} samples/s)"
              + (f"; {result.written} messages -> {files}" if files else ""))
        if result.diagnosis is not None:
            print(f"diagnosis {result.diagnosis.get('cause', result.diagnosis.get('error'))}")
    return 0 if stop.signal is None else 128 + stop.signal


def channel_runs(args: argparse.Namespace, channels: list[Channel], source: str) -> list[ChannelReplay]:
    """Each channel's streams and settings (``replay_settings`` of its parameters: the command-line
    identify options apply to every channel); --input/--output/--reference are a UsageError (the
    channels' topics come from the config)."""
    for option in ("input", "output", "reference"):
        if getattr(args, option):
            raise UsageError(f"--{option}: {source} has {len(channels)} channels; their topics come from it")
    runs = []
    for channel in channels:
        config, solve_rate = replay_settings(args, channel.params, f"{source}: channel {channel.name!r}")
        runs.append(ChannelReplay(channel.name, channel.excitation, channel.response, config, solve_rate))
    return runs


def run_channels(args: argparse.Namespace, channels: list[Channel], params: dict, source: str) -> int:
    """``replay`` of a config with several channels (``replay_channels``): the command-line
    identify options apply to every channel, ``--dashboard-out`` and ``--diagnose`` per channel
    (under ``/hammer_ros/NAME/``); JSON ``{"channels": {NAME: <replay JSON, with its "diagnosis">},
    "samples", "solves", "wall_s"}`` (samples and solves summed over the channels)."""
    if args.rate is not None:
        raise UsageError(f"--rate: not with several channels ({source} has {len(channels)}); replay runs them "
                         "as fast as possible")
    runs = channel_runs(args, channels, source)
    for run in runs:
        check_replay_input(args.bag, run.excitation, run.response, args.out, args.dashboard_out)
    for option, path in (("--out", args.out), ("--dashboard-out", args.dashboard_out)):
        if path:
            check_output_path(path, option)
    topics = {spec.topic for c in channels for spec in (c.excitation, c.response)}
    progress = Progress(sum(bag_message_counts(args.bag).get(t, 0) for t in topics))
    try:
        results = replay_channels(args.bag, runs, frame_id=str(params.get("frame_id", "")), out=args.out,
                                  progress=progress.update, dashboard_out=args.dashboard_out, diagnose=args.diagnose)
    finally:
        progress.close()
    WarningLog().warn(*next(iter(results.values())).read.warnings(args.bag))  # the channels share one read
    docs = {name: result.document() for name, result in results.items()}
    wall = max(result.wall_s for result in results.values())
    doc = {"channels": docs, "samples": sum(d["samples"] for d in docs.values()),
           "solves": sum(d["solves"] for d in docs.values()), "wall_s": round(wall, 4)}
    if args.json:
        json.dump(doc, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
        return 0
    for name, channel_doc in docs.items():
        print(f"channel  {name}")
        print(format_model(channel_doc))
        if results[name].diagnosis is not None:
            print(f"diagnosis {results[name].diagnosis.get('cause', results[name].diagnosis.get('error'))}")
    files = ", ".join(str(Path(p)) for p in (args.out, args.dashboard_out) if p)
    print(f"replay   {len(docs)} channels, {doc['samples']} samples, {doc['solves']} solves in {wall:.2f} s"
          + (f"; {next(iter(results.values())).written} messages -> {files}" if files else ""))
    return 0
