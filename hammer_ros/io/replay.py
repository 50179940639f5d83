"""A bag through the streaming engine: the loop of ``hammer-ros replay`` and of every
``hammer-ros fleet`` task (one function, so a fleet row is exactly what ``replay --json`` prints).

``replay_bag`` reads the two streams, adds them to a ``StreamingEngine`` in vectorised batches,
solves every 1 / solve_rate seconds of bag time and once at the end, and turns each solve into
the node's output messages, written into an MCAP (``out``) and/or handed to a live publisher.
It prints nothing; ``ReplayResult.document()`` is the ``replay --json`` document.

With a ``SolverProcess`` the solves run in a worker process while the loop reads on: a solve's
snapshot is submitted at its bag time (sent in batches of SOLVE_BATCH), and the outcomes that
have arrived are collected in order (their messages written) whenever a solve is due, and all at
the end. The messages, their stamps and counters are those of the in-process loop (the counters
and read statistics are taken at the snapshot, and the worker holds the published model), so
the output file is the same either way; only the wall time differs. When the worker is behind
(OWNER_ESTIMATES_FROM solves in flight), the loop estimates the next snapshot itself
(``estimate_snapshot``, CLS methods) and the worker only decides its outcome: both cores solve,
the outcomes unchanged. When nothing is written or published (``--json``, a fleet task), the
solves are not documented (``SolverProcess(documents=False)``, ``StreamingEngine.solve(document=False)``)
but the last good model, at the end: the same document without a ``to_json`` per solve.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from ..errors import IdentificationError, UsageError
from ..messages.outputs import (
    diagnosis_message,
    seconds_to_ns,
)
from ..streaming.config import EngineConfig, EngineStats
from ..streaming.engine import SolveOutcome, StreamingEngine, count_outcome, estimate_snapshot, portable_estimate
from ..streaming.solver_process import SolverProcess, diagnose_window, newest_window
from .bag_config import StreamSpec
from .bag_index import BagReadStats, bag_files, bag_message_counts
from .bag_reader import FLUSH_SAMPLES, check_fields, check_topics, iter_role_samples
from .bag_writer import JsonWriter, ResultWriter, record_results
from .outcome_messages import outcome_messages

NODE_NAME = "hammer_ros"
MAX_IN_FLIGHT = 64  # snapshots sent to a SolverProcess and not yet collected
SOLVE_BATCH = 8  # snapshots per transfer to a SolverProcess (one wake-up of the worker for several solves)
# Solves in flight from which the reading loop estimates the next snapshot itself (the worker behind:
# more than the batch it solves and the one being filled); the worker only decides those.
OWNER_ESTIMATES_FROM = 2 * SOLVE_BATCH
DIAGNOSIS_WINDOW = 10_000  # newest samples diagnosed (the node's ``diagnosis_window`` default)
STAMP_HISTORY = 4096  # excitation messages whose exact stamps a result can take (InputStamps)
STAMP_TOLERANCE = 1e-6  # s: a grid time this close to an input stamp is that stamp (float rounding)


class InputStamps:
    """The integer-ns stamps of the newest excitation messages, so that a result gets exactly
    the stamp of the input sample at its grid time. The engine works in float seconds, 238 ns
    apart at epoch times, so the grid time turned back into ns missed the input's stamp by up
    to ~120 ns (128 ns on the sample bags); the grid points are the excitation's stamps (or
    fall on them up to rounding), and a grid time within STAMP_TOLERANCE of one takes its
    integer stamp. Other grid times (a sample rate off the input's, the inner samples of a
    batch message) are rounded to the nearest ns."""

    def __init__(self) -> None:
        self._stamps: deque[tuple[float, int]] = deque(maxlen=STAMP_HISTORY)

    def add(self, stamp: float, stamp_ns: int) -> None:
        self._stamps.append((stamp, stamp_ns))

    def exact(self, stamp: float) -> int:
        for seconds, ns in reversed(self._stamps):
            if abs(seconds - stamp) <= STAMP_TOLERANCE:
                return ns
            if seconds < stamp - STAMP_TOLERANCE:
                break
        return seconds_to_ns(stamp)


class Publisher(Protocol):
    def publish(self, topic: str, type_name: str, message: dict) -> None: ...


class Stop(Protocol):
    """Set ``signal`` (a signal number) to stop at the next message; ``sleep`` wakes on it."""

    signal: int | None

    def sleep(self, seconds: float) -> None: ...


@dataclass
class ReplayResult:
    """What one replay did: the last good and the last solve, counters, time."""

    bag: str
    last_ok: SolveOutcome | None
    last: SolveOutcome | None
    stats: EngineStats
    read: BagReadStats
    messages: int  # messages read
    total: int  # messages of the two topics in the bag
    wall_s: float
    written: int  # messages written into ``out`` (and ``dashboard_out``)
    first_stamp: float  # bag time (s) of the first and last sample read (nan: none)
    last_stamp: float
    diagnosis: dict | None = None  # the final window's diagnosis (the ``~/diagnosis`` JSON), with diagnose

    def document(self) -> dict:
        """The ``replay --json`` document: the last good model's ``identify`` keys plus
        ``samples``, ``solves`` and ``wall_s``; an IdentificationError without a model."""
        if self.last_ok is None:
            reason = self.last.reason if self.last else "no messages"
            raise IdentificationError(f"{self.bag}: no model identified ({reason})")
        doc = dict(self.last_ok.doc)
        doc.update(samples=int(self.stats.aligned), solves=int(self.stats.solves), wall_s=round(self.wall_s, 4))
        if self.diagnosis is not None:
            doc["diagnosis"] = self.diagnosis
        return doc


def check_replay_input(bag: str | Path, excitation: StreamSpec, response: StreamSpec,
                       out: str | Path | None = None, dashboard_out: str | Path | None = None,
                       reference: StreamSpec | None = None) -> None:
    """Every user mistake about the bag before any output: its topics, their fields (of the
    ``reference`` too, named as --reference), and an ``out`` or ``dashboard_out`` that would
    overwrite the bag or each other (UsageError)."""
    check_topics(bag, (excitation, response))
    check_fields(bag, (excitation, response))
    if reference is not None:
        try:
            check_topics(bag, (reference,))
            check_fields(bag, (reference,))
        except UsageError as exc:
            raise UsageError(f"--reference: {exc}") from None
    for option, path in (("--out", out), ("--dashboard-out", dashboard_out)):
        if path and any(Path(path).resolve() == f.resolve() for f in bag_files(bag)):
            raise UsageError(f"{option}: {path} is the bag being replayed (it would be overwritten)")
    if out and dashboard_out and Path(out).resolve() == Path(dashboard_out).resolve():
        raise UsageError(f"--dashboard-out: {dashboard_out} is also --out (two files are needed)")


def replay_bag(bag: str | Path, excitation: StreamSpec, response: StreamSpec, config: EngineConfig,
               solve_rate: float, *, frame_id: str = "", out: str | Path | None = None,
               publisher: Publisher | None = None, rate: float | None = None, stop: Stop | None = None,
               progress: Callable[[int, int, int, bool], None] | None = None,
               node_name: str = NODE_NAME, atomic: bool = False,
               solver: SolverProcess | None = None, dashboard_out: str | Path | None = None,
               diagnose: bool = False, diagnosis_window: int = DIAGNOSIS_WINDOW,
               reference: StreamSpec | None = None) -> ReplayResult:
    """Replay ``bag`` (checked by ``check_replay_input``) through a new engine.

    ``out``: write every result message into this MCAP (with ``atomic``: under a temporary name,
    renamed when complete, so that a reader never sees half a file); ``dashboard_out``: their
    Foxglove dashboard channels (JSON) into this one; ``diagnose``: diagnose the final window
    (as the node's ``~/diagnosis``, stamped as the final result) and write it; ``publisher`` with ``rate``:
    pace at ``rate`` x real time and publish each result; ``stop``: polled between messages;
    ``progress(messages_done, aligned_samples, solves, force)``: called after every message;
    ``solver``: solve there, overlapping the reading (module docstring); ``reference``: a closed
    loop's reference (checked like the streams), the instrument of every solve (``add_reference``;
    a message of n > 1 samples is placed at the grid rate once it is known).
    """
    counts = bag_message_counts(bag)
    streams = [("excitation", excitation), ("response", response)] + ([("reference", reference)] if reference else [])
    total = sum(counts.get(topic, 0) for topic in {spec.topic for _, spec in streams})
    read = BagReadStats()
    engine = StreamingEngine(config, reference=reference is not None)
    last_ok: SolveOutcome | None = None
    last: SolveOutcome | None = None
    target = (Path(out).with_name(f".{Path(out).stem}.partial.mcap") if atomic else Path(out)) if out else None
    writer = ResultWriter(target) if target else None
    try:
        dashboard = JsonWriter(dashboard_out) if dashboard_out else None
    except UsageError:  # no half of the output either
        if writer:
            writer.close()
            target.unlink(missing_ok=True)
        raise
    input_stamps = InputStamps()
    last_stamp_ns = 0  # the stamp of the final results
    done = 0
    started = time.perf_counter()

    in_flight: deque = deque()  # (counters at the snapshot, read statistics then, its stamp) of solves in the solver
    quiet = writer is None and dashboard is None and publisher is None  # nobody reads the messages (--json, fleet)
    share = solver is not None and portable_estimate(config)  # the loop may estimate for a worker behind

    def stamp_of(grid_time: float) -> int:
        """The exact stamp of a solve at ``grid_time`` (taken when it is solved or submitted,
        while its input stamps are at hand); the last sample's before the first grid point."""
        return input_stamps.exact(grid_time) if math.isfinite(grid_time) else bag_time_ns

    def emit(outcome: SolveOutcome, stats: EngineStats, read_values: list[dict], stamp_ns: int) -> None:
        nonlocal last_ok, last, last_stamp_ns
        last = outcome
        last_ok = last if last.ok else last_ok
        last_stamp_ns = stamp_ns
        if quiet:
            return
        send(outcome_messages(last, last_ok, stats, last_stamp_ns, frame_id=frame_id, status_name=node_name,
                              complete_status=lambda status: status["values"].extend(read_values)), last_stamp_ns)

    def send(messages: list[tuple[str, str, dict]], stamp_ns: int) -> None:
        # first into the files: whatever is published is in them
        record_results(writer, messages, stamp_ns, node_name, dashboard_writer=dashboard)
        for topic, type_name, message in messages if publisher else ():
            publisher.publish(topic, type_name, message)

    def collect(wait: bool) -> None:
        """Emit the outcomes that have arrived (``wait``: every one in flight), in order."""
        while in_flight and (wait or solver.ready()):
            stats, read_values, stamp_ns = in_flight.popleft()
            outcome = solver.result()
            engine.record(outcome)
            count_outcome(stats, outcome)
            emit(outcome, stats, read_values, stamp_ns)

    def solve(final: bool = False) -> None:
        engine.flush()
        if solver is None:  # quiet: only the last good model's document is read (documented at the end)
            outcome = engine.solve(document=not quiet)
            emit(outcome, engine.stats, bag_values(read), stamp_of(outcome.stamp))
            return
        snapshot = engine.snapshot()
        help_worker = share and len(in_flight) >= OWNER_ESTIMATES_FROM
        solver.submit(snapshot, estimate_snapshot(snapshot, solver.documents) if help_worker else None)
        in_flight.append((snapshot.stats, bag_values(read), stamp_of(snapshot.stamp)))
        collect(wait=final or len(in_flight) > MAX_IN_FLIGHT)

    bag_start = next_solve = None
    bag_time, bag_time_ns = float("nan"), 0
    diagnosis = None
    complete = False
    try:
        check_topics(bag, tuple(spec for _, spec in streams))
        for sample in iter_role_samples(bag, streams, read):
            if sample.stream == "reference":
                add_reference(engine, sample.stamp, sample.values)
                continue
            if bag_start is None:
                bag_start, next_solve = sample.stamp, sample.stamp + 1.0 / solve_rate
            if publisher and rate:  # pace: bag time / rate = wall time since the start
                wait = (sample.stamp - bag_start) / rate - (time.perf_counter() - started)
                if wait > 0.005:
                    (stop.sleep if stop else time.sleep)(wait)
            if stop is not None and stop.signal is not None:
                break
            if sample.stamp >= next_solve:
                solve()
                next_solve += math.ceil((sample.stamp - next_solve) * solve_rate + 1e-9) / solve_rate
            engine.add_message(sample.stream, sample.stamp, sample.values, flush=False)
            if sample.stream == "excitation":
                input_stamps.add(sample.stamp, sample.stamp_ns)
            if engine.buffered >= FLUSH_SAMPLES:
                engine.flush()
            bag_time, bag_time_ns = sample.stamp, sample.stamp_ns
            done += 1
            if progress:
                progress(done, engine.stats.aligned, engine.stats.solves, False)
        solve(final=True)  # the final model, also after a signal
        if last_ok is not None and last_ok.doc is None:  # solved without documents
            documented = solver.document() if solver is not None else engine.documented(last_ok)
            last = documented if last is last_ok else last
            last_ok = documented
        if diagnose:
            diagnosis = diagnose_final(engine, config, diagnosis_window)
            send([diagnosis_message(diagnosis)], last_stamp_ns)
        if progress:
            progress(done, engine.stats.aligned, engine.stats.solves, True)
        complete = True
    finally:
        if dashboard:
            dashboard.close()
        if writer:
            writer.close()
            if atomic and complete:
                os.replace(target, out)
            elif atomic:
                target.unlink(missing_ok=True)
    first = float(bag_start) if bag_start is not None else float("nan")
    written = (writer.count if writer else 0) + (dashboard.count if dashboard else 0)
    return ReplayResult(str(bag), last_ok, last, engine.stats, read, done, total, time.perf_counter() - started,
                        written, first, bag_time, diagnosis)


def diagnose_final(engine: StreamingEngine, config: EngineConfig, newest: int) -> dict:
    """The node's ``~/diagnosis`` JSON of the newest ``newest`` samples of the engine's window
    (``diagnose_window``: estimation on the first 70 %, validation on the rest; with the reference
    when the engine holds one at every one of those samples, ``newest_window``) with ``samples``,
    ``stamp`` (grid time, s) and ``seconds``."""
    snapshot = engine.snapshot()
    v, y, r = newest_window(snapshot, newest)
    started = time.perf_counter()
    doc = {"samples": int(v.size), "stamp": snapshot.stamp if math.isfinite(snapshot.stamp) else None}
    doc |= diagnose_window(v, y, config.order, r)
    doc["seconds"] = time.perf_counter() - started
    return doc


def add_reference(engine: StreamingEngine, stamp: float, values: np.ndarray | float) -> None:
    """One reference message's samples into ``engine`` (batch convention: the last at the stamp,
    spacing 1 / the grid rate; a batch before the rate is known is left out)."""
    values = np.atleast_1d(np.asarray(values, dtype=float))
    rate = engine.sample_rate
    if values.size == 1 or rate:
        engine.add_reference(stamp - np.arange(values.size - 1, -1, -1) / (rate or 1.0), values)


def bag_values(read: BagReadStats) -> list[dict]:
    """Diagnostics values of what reading the bag skipped so far."""
    values = {"bag_damage": len(read.damage), "bag_oversized_messages": read.oversized,
              "bag_undecodable_messages": read.undecodable, "bag_field_errors": sum(read.field_errors.values())}
    return [{"key": k, "value": str(v)} for k, v in values.items()]


@dataclass(frozen=True)
class ChannelReplay:
    """One channel of ``replay_channels``: its name, streams, engine config and solve rate."""

    name: str
    excitation: StreamSpec
    response: StreamSpec
    config: EngineConfig
    solve_rate: float


def replay_channels(bag: str | Path, channels: list[ChannelReplay], *, frame_id: str = "",
                    out: str | Path | None = None, node_name: str = NODE_NAME,
                    progress: Callable[[int, int, int, bool], None] | None = None,
                    dashboard_out: str | Path | None = None, diagnose: bool = False,
                    diagnosis_window: int = DIAGNOSIS_WINDOW) -> dict[str, ReplayResult]:
    """Several channels of one bag in one pass (every channel checked by ``check_replay_input``):
    each topic is read once per message and its samples go to the engine of every channel that
    uses them (``iter_role_samples``); each channel solves every 1 / its solve_rate seconds of
    bag time and at the end, in process. ``out``: the results of channel NAME under
    ``/<node_name>/NAME/...`` and its status in /diagnostics (hardware_id ``<node_name>/NAME``);
    ``dashboard_out``: their dashboard channels under ``/<node_name>/NAME/dashboard/...``;
    ``diagnose``: each channel's final window diagnosed (``diagnose_final``), written as
    ``/<node_name>/NAME/diagnosis`` at the channel's final stamp and kept in its result.
    Returns each channel's ReplayResult (``document()`` = its ``replay --json``)."""
    topics = {spec.topic for c in channels for spec in (c.excitation, c.response)}
    total = sum(bag_message_counts(bag).get(topic, 0) for topic in topics)
    read = BagReadStats()
    engines = [StreamingEngine(c.config) for c in channels]
    outcomes: list[list[SolveOutcome | None]] = [[None, None] for _ in channels]  # (last good, last)
    next_solve: list[float | None] = [None] * len(channels)
    writer = ResultWriter(out) if out else None
    try:
        dashboard = JsonWriter(dashboard_out) if dashboard_out else None
    except UsageError:
        if writer:
            writer.close()
        raise
    started = time.perf_counter()
    done, bag_start, bag_time, bag_time_ns = 0, None, float("nan"), 0
    input_stamps = [InputStamps() for _ in channels]  # each channel's results take its input's exact stamps
    final_stamps = [0] * len(channels)  # the stamp of each channel's last results
    diagnoses: list[dict | None] = [None] * len(channels)

    def send(index: int, messages: list[tuple[str, str, dict]], stamp: int) -> None:
        record_results(writer, messages, stamp, f"{node_name}/{channels[index].name}", dashboard_writer=dashboard)

    def solve(index: int, bag_time: float) -> None:
        engine = engines[index]
        engine.flush()
        outcome = engine.solve(document=writer is not None or dashboard is not None)  # else documented at the end
        last_ok = outcome if outcome.ok else outcomes[index][0]
        outcomes[index] = [last_ok, outcome]
        stamp = input_stamps[index].exact(outcome.stamp) if math.isfinite(outcome.stamp) else bag_time_ns
        final_stamps[index] = stamp
        if writer is None and dashboard is None:
            return
        send(index, outcome_messages(outcome, last_ok, engine.stats, stamp, frame_id=frame_id,
                                     status_name=f"{node_name}/{channels[index].name}",
                                     complete_status=lambda status: status["values"].extend(bag_values(read))), stamp)

    roles = [((i, stream), spec) for i, c in enumerate(channels)
             for stream, spec in (("excitation", c.excitation), ("response", c.response))]
    first_role: dict[str, tuple] = {}  # a message yields one sample per role on its topic: count its first
    for role, spec in roles:
        first_role.setdefault(spec.topic, role)
    firsts = set(first_role.values())
    try:
        for sample in iter_role_samples(bag, roles, read):
            index, stream = sample.stream
            if bag_start is None:
                bag_start = sample.stamp
                next_solve = [sample.stamp + 1.0 / c.solve_rate for c in channels]
            for i, due in enumerate(next_solve):
                if sample.stamp >= due:
                    solve(i, sample.stamp)
                    rate = channels[i].solve_rate
                    next_solve[i] = due + math.ceil((sample.stamp - due) * rate + 1e-9) / rate
            engine = engines[index]
            if stream == "excitation":
                input_stamps[index].add(sample.stamp, sample.stamp_ns)
            engine.add_message(stream, sample.stamp, sample.values, flush=False)
            if engine.buffered >= FLUSH_SAMPLES:
                engine.flush()
            bag_time, bag_time_ns = sample.stamp, sample.stamp_ns
            done += sample.stream in firsts
            if progress:
                progress(done, sum(e.stats.aligned for e in engines), sum(e.stats.solves for e in engines), False)
        for i in range(len(channels)):
            solve(i, bag_time)
            last_ok, last = outcomes[i]
            if last_ok is not None and last_ok.doc is None:  # solved without documents
                documented = engines[i].documented(last_ok)
                outcomes[i] = [documented, documented if last is last_ok else last]
        for i in range(len(channels) if diagnose else 0):
            diagnoses[i] = diagnose_final(engines[i], channels[i].config, diagnosis_window)
            send(i, [diagnosis_message(diagnoses[i])], final_stamps[i])
        if progress:
            progress(done, sum(e.stats.aligned for e in engines), sum(e.stats.solves for e in engines), True)
    finally:
        if dashboard:
            dashboard.close()
        if writer:
            writer.close()
    wall = time.perf_counter() - started
    first = float(bag_start) if bag_start is not None else float("nan")
    written = (writer.count if writer else 0) + (dashboard.count if dashboard else 0)
    return {c.name: ReplayResult(str(bag), outcomes[i][0], outcomes[i][1], engines[i].stats, read, done, total,
                                 wall, written, first, bag_time, diagnosis=diagnoses[i])
            for i, c in enumerate(channels)}
