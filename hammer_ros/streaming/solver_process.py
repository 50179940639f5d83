"""Solves in a worker process of their own, so that a solve never holds the interpreter lock
against ingestion (the node's executor, replay's decoding).

``SolverProcess`` starts one process (by default the ``spawn`` method, safe beside the threads of
a ROS node and its middleware; ``fork`` for an owner with no other thread, e.g. replay without
ROS: the worker then starts with the owner's modules loaded, in milliseconds instead of ~1 s) that
runs ``engine.solve_snapshot`` on the snapshots it is sent, in order. A snapshot (its
correlation sums and the raw window, about 70 kB at W = 4000; of a window that slid, only the
samples new since the last snapshot, the worker keeping the rest) crosses by a pipe; the outcome
comes back without its ``result`` (a model holds its simulator, which stays in the worker) but
with everything the outputs are built from (``doc``, ``markov``). Several snapshots may be in
flight (replay sends the next one while the worker still solves), so the state a solve depends
on lives in the worker: the published model and the reference input std of the engine's
``epoch``, updated from each outcome exactly as ``StreamingEngine.record`` updates the engine's.
A sequence of snapshots thus gives the outcomes of in-process ``solve_snapshot`` with the
engine's own state; a new epoch (new engine, new settings) starts without a published model,
as the engine does. Both ends use the pipe's socket buffers (about 200 kB each way) as queues:
``submit`` returns at once while the worker's side has room and waits for the worker otherwise
(the back-pressure of a worker that is behind); the owner reads the outcomes as it goes
(``ready``, ``result``), so the worker's side never fills. ``solve`` (the node's use: one
snapshot at a time) sends and waits for the outcome. No thread of the owner is involved: a
thread that pickles and unpickles beside replay's reading loop took the interpreter lock from
it at every numpy call that released it, costing the loop more than the transfers themselves.

The worker ignores SIGINT and SIGTERM (sent to a whole process group, they are for the owner,
which handles them and then closes the worker); it exits when the owner closes the pipe or
dies, and is killed when it does not exit within CLOSE_TIMEOUT of ``close``.
"""

from __future__ import annotations

import multiprocessing
import signal
from dataclasses import replace

import numpy as np

from .engine import EngineSnapshot, SolveOutcome, solve_snapshot

CLOSE_TIMEOUT = 2.0  # s the worker gets to exit before it is killed


def _serve(connection) -> None:
    """The worker: solve each snapshot received with the state of its epoch, answer in order."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    epoch, published, reference = None, None, 0.0
    last: EngineSnapshot | None = None
    while True:
        try:
            message = connection.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        kept, snapshot = message
        if kept:  # the window's oldest samples are the newest of the last window (``SolverProcess._kept``)
            snapshot = replace(snapshot, v=np.concatenate([last.v[last.v.size - kept:], snapshot.v]),
                               y=np.concatenate([last.y[last.y.size - kept:], snapshot.y]))
        last = snapshot
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

    def __init__(self, start_method: str = "spawn") -> None:
        context = multiprocessing.get_context(start_method)
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child,), name="hammer_ros_solver", daemon=True)
        self._process.start()
        child.close()
        self.in_flight = 0
        self._last: EngineSnapshot | None = None  # the last snapshot sent (its whole window)

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def _exited(self) -> str:
        self._process.join(CLOSE_TIMEOUT)
        return f"the solver process exited (exit code {self._process.exitcode})"

    def submit(self, snapshot: EngineSnapshot) -> None:
        """Send ``snapshot`` to the worker (its in-process ``published`` model stays here). Returns
        at once while the socket's buffer holds it, else when the worker has read enough."""
        kept = self._kept(snapshot)
        try:
            self._connection.send((kept, replace(snapshot, published=None, stats=None,  # the counters stay here
                                                 v=snapshot.v[kept:], y=snapshot.y[kept:])))
        except OSError as error:
            raise RuntimeError(self._exited()) from error
        self._last = snapshot
        self.in_flight += 1

    def _kept(self, snapshot: EngineSnapshot) -> int:
        """How many of the window's oldest samples the worker already holds as the newest ones of
        the last window sent (0: send the whole window). The window slid by the samples aligned
        since then; the overlap is compared, so a restarted window is sent whole."""
        last = self._last
        if last is None:
            return 0
        kept = snapshot.v.size - (snapshot.stats.aligned - last.stats.aligned)
        if not 0 < kept <= last.v.size:
            return 0
        tail = slice(last.v.size - kept, None)
        same = np.array_equal(snapshot.v[:kept], last.v[tail]) and np.array_equal(snapshot.y[:kept], last.y[tail])
        return kept if same else 0

    def ready(self) -> bool:
        """True when ``result`` would not wait."""
        return self.in_flight > 0 and self._connection.poll()

    def result(self) -> SolveOutcome:
        """The outcome of the oldest solve in flight (waits for it)."""
        if self.in_flight == 0:
            raise RuntimeError("no solve in flight")
        try:
            outcome = self._connection.recv()
        except (EOFError, OSError) as error:
            raise RuntimeError(self._exited()) from error
        self.in_flight -= 1
        return outcome

    def solve(self, snapshot: EngineSnapshot) -> SolveOutcome:
        """The outcome of ``snapshot`` (waits for it and for the solves submitted before it)."""
        self.submit(snapshot)
        while self.in_flight > 1:
            self.result()
        return self.result()

    def close(self) -> None:
        """Stop the worker (solves in flight are abandoned)."""
        try:
            self._connection.send(None)
        except OSError:
            pass
        self._process.join(CLOSE_TIMEOUT)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(CLOSE_TIMEOUT)
        self._connection.close()

    def __enter__(self) -> SolverProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
