"""One identification channel: an (excitation, response[, reference]) pair of inputs, its
``StreamingEngine``, its ``Ingest`` (inputs and stamper), its outcomes and its worker threads and
processes. A node identifies N >= 1 channels (``channels.ChannelSet``); the channel never touches
the rclpy node's internals: it publishes on the publishers the node made for it (``outputs``),
logs on its logger, stamps with the node's clock and asks the node's graph who publishes on its
input topics (public rclpy API). Threads and locks: ``node_core``'s module docstring.

A thin adapter over ``streaming.StreamingEngine``: the ingest thread moves the queued samples
into the engine every ``FLUSH_PERIOD`` s, the solver thread solves on a snapshot of the window
``solve_rate`` times a second and publishes the results built by ``outputs``. The solve runs in
the node's solver process (``workers.NodeWorkers``, one for every channel; parameter
``solver_process``, on by default), and so does the periodic diagnosis (in the node's diagnosis
process, started by the first diagnosis), so neither holds the interpreter lock against the
callbacks and the ingest thread. A slow solve skips solves, never samples; a solve
without a new model republishes the last good one marked stale.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.expand_topic_name import expand_topic_name  # noqa: E402

from ..diagnosis.closed_loop import TEST_NAME as CLOSED_LOOP_TEST  # noqa: E402
from ..diagnosis.closed_loop import WARNING as CLOSED_LOOP_WARNING  # noqa: E402
from ..identification.result import strict_json  # noqa: E402
from ..io.bag_writer import ResultWriter, record_results  # noqa: E402
from ..io.outcome_messages import outcome_messages  # noqa: E402
from ..messages.dashboard import dashboard_messages  # noqa: E402
from ..messages.outputs import (  # noqa: E402
    diagnosis_message,
    diagnostics_message,
    model_json,
)
from ..messages.types import normal_type  # noqa: E402
from ..streaming.config import EngineConfig  # noqa: E402
from ..streaming.engine import EngineSnapshot, SolveOutcome, StreamingEngine, solve_snapshot, window_problem  # noqa: E402
from ..streaming.solver_process import diagnose_window, newest_window  # noqa: E402
from .ingest import Ingest  # noqa: E402
from .message_types import to_ros_message  # noqa: E402
from .parameters import ENGINE_FIELDS, REFERENCE, STREAM_PARAMETERS, STREAMS, engine_config  # noqa: E402
from .workers import NodeWorkers  # noqa: E402

FLUSH_PERIOD = 0.05  # s between moves of the queued samples into the engine


class ErrorCount:
    """``loop_errors``: unexpected exceptions in the node's loops, services and callbacks (logged;
    they go on), counted from several threads under a lock."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._count = 0

    def add(self) -> None:
        with self._lock:
            self._count += 1

    @property
    def count(self) -> int:
        with self._lock:
            return self._count


class Recorder:
    """The node's output_mcap (``ResultWriter``, or none), shared by its channels under a lock."""

    def __init__(self, path: str) -> None:
        self._lock = threading.Lock()
        self._writer = ResultWriter(path, "output_mcap") if path else None

    def record(self, messages: list[tuple[str, str, dict]], stamp_ns: int, node_name: str) -> None:
        with self._lock:
            if self._writer is not None:
                record_results(self._writer, messages, stamp_ns, node_name)

    def close(self) -> None:
        """Finish the file, its message count (or why it failed) on stderr; later records are dropped."""
        with self._lock:
            writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.close()
            print(f"hammer_ros_node: {writer.count} messages in {writer.path}", file=sys.stderr)
        except OSError as exc:  # e.g. the disk is full
            print(f"hammer_ros_node: error: output_mcap {writer.path}: {exc.strerror or exc}", file=sys.stderr)


class IdentificationChannel:
    """One channel of the node. ``values``: its coerced parameter values; ``node``: the rclpy
    node (logger, clock, graph); ``outputs``: topic -> publisher (``~/model``, ..., /diagnostics);
    ``server``: where its dashboard channels go (or None); ``status_name``: its /diagnostics
    status name and the node part of its recorded topics; ``workers``: the node's worker
    processes (its solves there as lane ``name``). ``configure`` has checked ``values``."""

    def __init__(self, name: str, values: dict[str, Any], node, logger, outputs: dict[str, Any], server,
                 recorder: Recorder, errors: ErrorCount, status_name: str, workers: NodeWorkers) -> None:
        self.name, self.values, self.node, self.logger, self.workers = name, values, node, logger, workers
        self._outputs, self.server, self.recorder, self.errors = outputs, server, recorder, errors
        self.status_name = status_name
        self._lock = threading.Lock()  # guards the engine and the ingest (stamper, queues into the engine)
        self._solve_lock = threading.Lock()  # one solve at a time (the solver thread, ~/solve)
        self._diagnose_lock = threading.RLock()  # one diagnosis at a time (the diagnosis thread, ~/diagnose)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._workers: list[threading.Thread] = []
        self.active = False
        self.ingest = Ingest(values, logger)
        self.engine = self._new_engine(engine_config(values))
        self.last_outcome: SolveOutcome | None = None
        self.skipped_solves = 0
        self.closed_loop: bool | None = None  # the last diagnosis's ``closed_loop`` verdict (None: none yet)
        self._cpu_mark = (time.monotonic(), time.process_time())  # ``_cpu_percent``'s last reading

    def streams(self) -> tuple[str, ...]:
        """The input streams: excitation, response and, when ``reference_topic`` is set, reference."""
        return (*STREAMS, REFERENCE) if self.values["reference_topic"] else STREAMS

    def _new_engine(self, config: EngineConfig) -> StreamingEngine:
        """An empty engine of ``config`` (holding the reference when ``reference_topic`` is set)."""
        return StreamingEngine(config, reference=bool(self.values["reference_topic"]))

    def _now(self) -> int:
        """The node clock in integer nanoseconds (the stamp of what the node publishes)."""
        return self.node.get_clock().now().nanoseconds

    def start(self) -> None:
        """Start the ingest, solve and diagnosis threads (the node subscribes the inputs)."""
        self._stop = stop = threading.Event()  # per activation: a thread still finishing a solve sees its own
        self._workers = [threading.Thread(target=loop, args=(stop,), name=f"hammer_ros_{what}", daemon=True)
                         for loop, what in ((self._ingest_loop, "ingest"), (self._solve_loop, "solver"),
                                            (self._diagnosis_loop, "diagnosis"))]
        self.active = True
        for worker in self._workers:
            worker.start()

    def halt(self, publish: bool) -> None:
        """Stop ingesting (the node has unsubscribed): stop the threads (a running solve is waited
        for up to 1 s), move the queued samples in; with ``publish`` the counters on /diagnostics."""
        self.active = False
        self.stop()
        self._guarded(self._flush, "ingesting")
        if publish:
            with self._lock:
                stats = self.engine.stats.copy()
            diagnostics = diagnostics_message(stats, self.last_outcome, self._now(), self.status_name)
            self._add_node_diagnostics(diagnostics["status"][0])
            self._outputs["/diagnostics"].publish(to_ros_message("diagnostic_msgs/msg/DiagnosticArray", diagnostics))

    def apply(self, values: dict[str, Any], config: EngineConfig, changed: set[str]) -> set[str]:
        """Take checked parameter ``values`` live (``wake`` solves with them); a changed topic,
        type or field restarts the window. Returns the streams whose input changed (the node subscribes them anew)."""
        self.values = self.ingest.values = values
        streams = {STREAM_PARAMETERS[k] for k in changed & set(STREAM_PARAMETERS)}
        with self._lock:
            if streams:  # a new signal: the window restarts
                for source in self.ingest.inputs.values():
                    source.pending.clear()
                self.engine = self._new_engine(config)
                self.ingest.stamper.set_rate(config.sample_rate)
            else:
                self.engine.reconfigure(**{k: getattr(config, k) for k in changed & ENGINE_FIELDS})
                if "sample_rate" in changed:
                    self.ingest.stamper.set_rate(config.sample_rate)
        return streams

    def wake(self) -> None:
        """Solve now (after a parameter change)."""
        self._wake.set()

    def _flush(self) -> None:
        """Move the queued samples into the engine (``Ingest.flush``)."""
        with self._lock:
            self.ingest.flush(self.engine)

    def _guarded(self, step, what: str) -> None:
        """Run one loop step; an unexpected exception is logged and counted, the loop goes on."""
        try:
            step()
        except Exception as exc:  # the node never dies on a bug in one step
            self.errors.add()
            self.logger.error(f"{what} failed ({type(exc).__name__}: {exc}); continuing", throttle_duration_sec=5.0)

    def _solve_loop(self, stop: threading.Event) -> None:
        deadline = time.monotonic()
        while not stop.is_set():
            period = 1.0 / self.values["solve_rate"]
            deadline += period
            now = time.monotonic()
            if deadline < now:  # the last solve overran: skip the missed ticks
                self.skipped_solves += int((now - deadline) / period) + 1
                deadline = now + period
            self._wake.wait(deadline - now)
            if self._wake.is_set():
                self._wake.clear()
                deadline = time.monotonic()
            if stop.is_set():
                return
            self._guarded(self._solve_once, "solving")

    def _solve_once(self, publish: bool = True) -> SolveOutcome:
        with self._solve_lock:
            self._flush()
            if publish:  # (not on shutdown: the graph is gone)
                self._check_publisher_types()
            with self._lock:
                engine = self.engine
                snapshot = engine.snapshot()
            outcome = self._solve(snapshot)  # never raises: a failing method gives ok False, status "exception"
            if outcome.status == "exception":
                self.logger.error(f"solve failed: {outcome.reason}", throttle_duration_sec=5.0)
            with self._lock:
                if engine is self.engine:
                    engine.record(outcome)
                stats = engine.stats.copy()
            self._publish(outcome, stats, publish)
            return outcome

    def _diagnosis(self, v: np.ndarray, y: np.ndarray, reference: np.ndarray | None) -> dict[str, Any]:
        """``diagnose_window`` (instrumented by ``reference`` when the node has one over the window)
        in the node's diagnosis process (with ``solver_process``), else here. Called under
        ``_diagnose_lock``."""
        if self.values["solver_process"]:
            return self.workers.diagnose(v, y, self.values["order"], reference, self.logger)
        return diagnose_window(v, y, self.values["order"], reference)

    def _solve(self, snapshot: EngineSnapshot) -> SolveOutcome:
        """``solve_snapshot`` in the node's solver process (with ``solver_process``), else here."""
        if self.values["solver_process"]:
            return self.workers.solve(snapshot, self.name, self.logger)
        return solve_snapshot(snapshot)

    def _diagnosis_loop(self, stop: threading.Event) -> None:
        """Every ``diagnosis_period`` s: ``diagnose_record`` on the newest ``diagnosis_window``
        samples of the raw window (estimation on their first 70 %, validation on the rest; none
        while the window is empty), published as JSON on ~/diagnosis. The period is read every
        0.5 s, so a live change applies at once."""
        last = time.monotonic()
        while not stop.wait(0.5):
            period = self.values["diagnosis_period"]
            if period > 0 and time.monotonic() - last >= period:
                last = time.monotonic()
                with self._diagnose_lock:
                    self._guarded(self._diagnose_samples, "diagnosing")

    def _diagnose_samples(self) -> None:
        """The periodic diagnosis, of a window that has samples (an idle node diagnoses nothing, so
        it never starts its diagnosis process)."""
        with self._lock:
            snapshot = self.engine.snapshot()
        if snapshot.v.size:
            self._diagnose_once(snapshot)

    def _diagnose_once(self, snapshot: EngineSnapshot | None = None) -> dict[str, Any]:
        """Diagnose the newest ``diagnosis_window`` samples of the window (of ``snapshot``, else of
        a new one; with ``reference_topic``, instrumented by the reference over them), publish the
        JSON on ~/diagnosis and return it."""
        if snapshot is None:
            with self._lock:
                snapshot = self.engine.snapshot()
        v, y, r = newest_window(snapshot, self.values["diagnosis_window"])
        started = time.perf_counter()
        doc: dict[str, Any] = {"samples": int(v.size), "stamp": snapshot.stamp}
        doc |= self._diagnosis(v, y, r)
        doc["seconds"] = time.perf_counter() - started
        rows = [e for e in doc.get("evidence", ()) if e.get("test") == CLOSED_LOOP_TEST]
        self.closed_loop = (not rows[0]["passed"]) if rows else None
        self._send([diagnosis_message(doc)], self._now(), publish=self.active)
        return doc

    def _publish(self, outcome: SolveOutcome, stats, publish: bool = True) -> None:
        """Publish (and record in output_mcap, first) the results of a solve; after a solve without
        a model, the last good model again, marked stale."""
        stamp = self._now()
        messages = outcome_messages(outcome, self.last_outcome, stats, stamp, frame_id=self.values["frame_id"],
                                    status_name=self.status_name, complete_status=self._add_node_diagnostics)
        if outcome.ok:
            self.last_outcome = outcome
        self._send(messages, stamp, publish)

    def _send(self, messages: list[tuple[str, str, dict]], stamp_ns: int, publish: bool) -> None:
        """Record ``messages`` in output_mcap (ROS 2 messages only), hand their dashboard
        channels to the Foxglove server (never waits) and, with ``publish``, publish them."""
        server = self.server
        self.recorder.record(messages, stamp_ns, self.status_name)
        if not publish:
            return
        if server is not None:
            server.publish(dashboard_messages(messages, stamp_ns), stamp_ns)
        try:
            for topic, type_name, values in messages:
                self._outputs[topic].publish(to_ros_message(type_name, values))
        except Exception as exc:  # the context may be shutting down under us
            if self.active:
                self.logger.error(f"publishing failed: {exc}")

    def _check_publisher_types(self) -> None:
        """Note publishers of another message type on an input topic: DDS never delivers their
        messages, so without this a wrong type would look like silence."""
        for stream in self.streams():
            source = self.ingest.inputs[stream]
            topic = expand_topic_name(self.values[f"{stream}_topic"], self.node.get_name(), self.node.get_namespace())
            wanted = normal_type(self.values[f"{stream}_type"])
            others = sorted({info.topic_type for info in self.node.get_publishers_info_by_topic(topic)
                             if normal_type(info.topic_type) != wanted})
            expected = self.values[f"{stream}_type"]
            source.wrong_type = (f"{stream}_topic {topic} has publishers of {', '.join(others)}, expected "
                                 f"{expected}: their messages cannot be received") if others else ""

    def finish(self) -> SolveOutcome | None:
        """On shutdown: move the queued samples in, solve once more, record the final results in
        output_mcap (the ``ChannelSet`` finishes the file) and print the final model on stderr;
        returns the final outcome (None if it failed)."""
        outcome = None
        try:
            outcome = self._solve_once(publish=False)
        except Exception as exc:  # still close the file
            print(f"hammer_ros_node: final solve failed ({type(exc).__name__}: {exc})", file=sys.stderr)
        if self.last_outcome is not None:
            stale = None if outcome is not None and outcome.ok else getattr(outcome, "reason", "final solve failed")
            print(f"hammer_ros_node: final model: {model_json(self.last_outcome, stale)}", file=sys.stderr)
        return outcome

    def _add_node_diagnostics(self, status: dict) -> None:
        values: dict[str, Any] = {
            "ingesting": self.active,
            "excitation_field_errors": self.ingest.inputs["excitation"].field_errors,
            "response_field_errors": self.ingest.inputs["response"].field_errors,
            "unplaced_samples": self.ingest.unplaced,
            "clock_restarts": self.ingest.stamper.restarts,
            "excitation_zero_stamps": self.ingest.inputs["excitation"].zero_stamps,
            "response_zero_stamps": self.ingest.inputs["response"].zero_stamps,
            "skipped_solves": self.skipped_solves,
            "excitation_queue_dropped": self.ingest.inputs["excitation"].dropped(),
            "response_queue_dropped": self.ingest.inputs["response"].dropped(),
            "excitation_dds_lost": self.ingest.inputs["excitation"].dds_lost(),
            "response_dds_lost": self.ingest.inputs["response"].dds_lost(),
            "excitation_publishers": self.ingest.inputs["excitation"].publishers(),
            "response_publishers": self.ingest.inputs["response"].publishers(),
            "loop_errors": self.errors.count,
            "cpu_percent": self._cpu_percent(),
            "solver": self.workers.solver_state() if self.values["solver_process"] else "thread",
            "diagnosis": self.workers.diagnosis_state() if self.values["solver_process"] else "thread",
            "window": self.values["window"],
            "method": self.values["method"],
        }
        if self.server is not None:
            values.update(self.server.diagnostics(), foxglove_port=self.server.port)
        status["values"].extend({"key": k, "value": str(v)} for k, v in values.items())
        if self.closed_loop is not None:
            status["values"].append({"key": "closed_loop", "value": str(self.closed_loop).lower()})
        if self.closed_loop and not self.values["reference_topic"]:
            status["level"] = max(status["level"], 1)
            status["message"] = f"{status['message']}; {CLOSED_LOOP_WARNING}"
        errors = [s.last_error for s in self.ingest.inputs.values() if s.field_errors]
        errors += [s.wrong_type for s in self.ingest.inputs.values() if s.wrong_type]
        if errors and status["level"] < 2:
            status["level"] = 1
        if errors:
            status["message"] = f"{status['message']}; bad messages: {errors[0]}"

    def _cpu_percent(self) -> float:
        """CPU time of the node's process (all its threads; not its worker processes) since the
        last reading, in % of one core (100 = one core busy)."""
        (wall, cpu), self._cpu_mark = self._cpu_mark, (time.monotonic(), time.process_time())
        elapsed = self._cpu_mark[0] - wall
        return round(100.0 * (self._cpu_mark[1] - cpu) / elapsed, 1) if elapsed > 0 else 0.0

    def stop(self) -> None:
        """Stop the worker threads (waits for a running solve up to 1 s)."""
        self._stop.set()
        self._wake.set()
        for worker in self._workers:
            worker.join(timeout=1.0)
        self._workers = []

    def _refusal(self) -> str:
        return "" if self.active else "the node is not active (managed node: configure and activate it first)"

    def reset_window(self) -> tuple[bool, str]:
        """~/reset: clear the window and the correlation sums (and the counters); parameters stay."""
        if self._refusal():
            return False, self._refusal()
        with self._solve_lock, self._lock:
            self.ingest.distribute()
            dropped = self.engine.snapshot().v.size
            self.engine = self._new_engine(self.engine.config)
            self.ingest.restart()
            self.last_outcome = None
        self.logger.info(f"window reset by ~/reset ({dropped} samples dropped)")
        return True, f"window and correlation sums cleared ({dropped} samples dropped); parameters kept"

    def solve_now(self) -> tuple[bool, str]:
        """~/solve: solve and publish now; the model JSON, or why there is none."""
        if self._refusal():
            return False, self._refusal()
        outcome = self._solve_once()
        if not outcome.ok:
            return False, f"no model: {outcome.reason}"
        return True, model_json(outcome)

    def diagnose_now(self) -> tuple[bool, str]:
        """~/diagnose: diagnose the window now and publish it; the diagnosis JSON, or why not."""
        if self._refusal():
            return False, self._refusal()
        with self._diagnose_lock:
            self._flush()
            with self._lock:
                snapshot = self.engine.snapshot()
            status, reason, _, _ = window_problem(snapshot)
            if status:
                return False, f"cannot diagnose: {reason}"
            doc = self._diagnose_once(snapshot)
        if "error" in doc:
            return False, doc["error"]
        return True, json.dumps(strict_json(doc), allow_nan=False)

    def _ingest_loop(self, stop: threading.Event) -> None:
        while not stop.wait(FLUSH_PERIOD):
            self._guarded(self._flush, "ingesting")
