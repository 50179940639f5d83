"""Solves in a worker process of their own, so that a solve never holds the interpreter lock
against ingestion (the node's executor, replay's decoding).

``SolverProcess`` starts one process (the ``spawn`` method: safe beside the threads of a ROS node)
that runs ``engine.solve_snapshot`` on the snapshots it is sent, in order. A snapshot (its
correlation sums and the raw window, about 70 kB at W = 4000) crosses by a pipe; the outcome
comes back without its ``result`` (a model holds its simulator, which stays in the worker) but
with everything the outputs are built from (``doc``, ``markov``). Several snapshots may be in
flight (replay sends the next one while the worker still solves), so the state a solve depends
on lives in the worker: the published model and the reference input std of the engine's
``epoch``, updated from each outcome exactly as ``StreamingEngine.record`` updates the engine's.
A sequence of snapshots thus gives the outcomes of in-process ``solve_snapshot`` with the
engine's own state; a new epoch (new engine, new settings) starts without a published model,
as the engine does. ``solve`` (the node's use: one snapshot at a time) sends and receives in
the calling thread; the first ``submit`` (replay's pipeline) starts two threads of the owner
that move the data from then on: one sends the snapshots (so that ``submit`` returns at once
while the worker still solves or starts up; a send waits for the worker to read), one reads
the outcomes as they come (so that the pipe never fills).

The worker ignores SIGINT and SIGTERM (sent to a whole process group, they are for the owner,
which handles them and then closes the worker); it exits when the owner closes the pipe or
dies, and is killed when it does not exit within CLOSE_TIMEOUT of ``close``.
"""

from __future__ import annotations

import multiprocessing
import queue
import signal
import threading
from dataclasses import replace

from .engine import EngineSnapshot, SolveOutcome, solve_snapshot

CLOSE_TIMEOUT = 2.0  # s the worker gets to exit before it is killed


def _serve(connection) -> None:
    """The worker: solve each snapshot received with the state of its epoch, answer in order."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    epoch, published, reference = None, None, 0.0
    while True:
        try:
            snapshot = connection.recv()
        except (EOFError, OSError):
            return
        if snapshot is None:
            return
        if snapshot.epoch != epoch:
            epoch, published, reference = snapshot.epoch, None, 0.0
        outcome = solve_snapshot(replace(snapshot, published=published, reference_std=reference))
        if outcome.ok:
            published, reference = outcome.result, max(reference, outcome.input_std)
        try:
            connection.send(replace(outcome, result=None))
        except OSError:
            return


class SolverProcess:
    """``solve_snapshot`` in a worker process: ``submit`` snapshots and go on, collect their
    outcomes in order with ``result`` (``ready`` says whether one has arrived), or ``solve``."""

    def __init__(self) -> None:
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child,), name="hammer_ros_solver", daemon=True)
        self._process.start()
        child.close()
        self._requests: queue.Queue = queue.Queue()
        self._outcomes: queue.Queue = queue.Queue()
        self._threads: list[threading.Thread] = []  # started by the first ``submit``
        self.in_flight = 0

    def _send(self) -> None:
        while True:
            snapshot = self._requests.get()
            try:
                self._connection.send(snapshot)
            except OSError:  # the worker is gone: the reader reports it
                return
            if snapshot is None:
                return

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def _read(self) -> None:
        while True:
            try:
                outcome = self._connection.recv()
            except (EOFError, OSError):
                self._outcomes.put(None)  # the worker is gone
                return
            self._outcomes.put(outcome)

    def _exited(self) -> str:
        self._process.join(CLOSE_TIMEOUT)
        return f"the solver process exited (exit code {self._process.exitcode})"

    def submit(self, snapshot: EngineSnapshot) -> None:
        """Queue ``snapshot`` for the worker (its in-process ``published`` model stays here)."""
        if not self._process.is_alive():
            raise RuntimeError(self._exited())
        if not self._threads:
            self._threads = [threading.Thread(target=target, name=f"hammer_ros_solver_{what}", daemon=True)
                             for target, what in ((self._send, "sender"), (self._read, "reader"))]
            for thread in self._threads:
                thread.start()
        self._requests.put(replace(snapshot, published=None))
        self.in_flight += 1

    def ready(self) -> bool:
        """True when ``result`` would not wait."""
        return self.in_flight > 0 and not self._outcomes.empty()

    def result(self) -> SolveOutcome:
        """The outcome of the oldest solve in flight (waits for it)."""
        if self.in_flight == 0:
            raise RuntimeError("no solve in flight")
        outcome = self._outcomes.get()
        if outcome is None:
            self._outcomes.put(None)  # every later call fails the same way
            raise RuntimeError(self._exited())
        self.in_flight -= 1
        return outcome

    def solve(self, snapshot: EngineSnapshot) -> SolveOutcome:
        """The outcome of ``snapshot`` (waits for it; in this thread until the first ``submit``)."""
        if self._threads:
            self.submit(snapshot)
            return self.result()
        try:
            self._connection.send(replace(snapshot, published=None))
            return self._connection.recv()
        except (EOFError, OSError) as error:
            raise RuntimeError(self._exited()) from error

    def close(self) -> None:
        """Stop the worker (solves in flight are abandoned)."""
        if self._threads:
            self._requests.put(None)
        else:
            try:
                self._connection.send(None)
            except OSError:
                pass
        self._process.join(CLOSE_TIMEOUT)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(CLOSE_TIMEOUT)
        self._connection.close()  # wakes a sender still waiting for the killed worker to read
        for thread in self._threads:
            thread.join(CLOSE_TIMEOUT)

    def __enter__(self) -> SolverProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
