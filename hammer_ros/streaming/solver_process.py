"""Solves in a worker process of their own, so that a solve never holds the interpreter lock
against ingestion (the node's executor, replay's decoding).

``SolverProcess`` starts one process (by default the ``spawn`` method, safe beside the threads of a
ROS node and its middleware; ``fork`` for an owner with no other thread, e.g. replay without ROS:
the worker then starts with the owner's modules loaded, in milliseconds instead of ~1 s) that runs
``engine.solve_snapshot`` on the snapshots it is sent, in order (and, asked, ``diagnose_window``: the
node diagnoses its window in a second one, so that a diagnosis never holds the node's interpreter
lock either). A snapshot (its correlation sums
and the raw window, about 70 kB at W = 4000; of a window that slid, only the samples new since the
last snapshot, the worker keeping the rest) crosses by a pipe; the outcome comes back without its
``result`` (a model holds its simulator, which stays in the worker) but with everything the outputs
are built from (``doc``, ``markov``; with ``documents=False`` the worker skips them, a tenth to a
sixth of a CLS solve, and documents the last good model on request). Several snapshots may be in
flight (replay sends the next one while the worker still solves), so the state a solve depends on
lives in the worker: the published model and the reference input std of the engine's ``epoch``,
updated from each outcome exactly as ``StreamingEngine.record`` updates the engine's. A sequence of
snapshots thus gives the outcomes of in-process ``solve_snapshot`` with the engine's own state; a
new epoch (new engine, new settings) starts without a published model, as the engine does. A
snapshot may come with its ``estimate_snapshot`` made by the owner (replay's reading loop helps a
worker that is behind, for the CLS methods, whose estimates can cross the pipe): the worker then
only decides its outcome (``decide_outcome``: the excitation check against its reference std,
the keep check against its published model), which gives the same outcome.
Snapshots travel in batches (``batch`` per transfer: one serialisation, one system call and one
wake-up of the worker for several solves; replay sends 8) and their outcomes come back the same
way. The pipe's socket buffers (about 200 kB each way) are the queues: sending returns at once
while the worker's side has room and waits for the worker otherwise (the back-pressure of a worker
that is behind). The owner never has more than MAX_SENT_BATCHES batches unanswered (it reads
outcomes before sending more), so their answers fit the buffer and the worker never waits for the
owner to read: neither side can block the other. ``solve`` (the node's use: one snapshot at a time)
sends and waits for the outcome. No thread is involved: in the owner, a thread that serialises
beside replay's reading loop took the interpreter lock from it at every numpy call that released
it; in the worker, a thread that sends the answers made the pipeline stall (replay of the bench's
100-sample bag: 1.06 s without it, 1.75-1.88 s with it).

A worker sets an event once it has imported what a solve needs (``wait_ready``): the node
subscribes only then, so that a spawned worker's second of imports does not compete with the
first second of ingestion.

The worker ignores SIGINT and SIGTERM (sent to a whole process group, they are for the owner,
which handles them and then closes the worker); it exits when the owner closes the pipe or
dies, and is killed when it does not exit within CLOSE_TIMEOUT of ``close``.
"""

from __future__ import annotations

import multiprocessing
import signal
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import UsageError
from .engine import EngineSnapshot, Estimate, SolveOutcome, decide_outcome, document_outcome, solve_snapshot

CLOSE_TIMEOUT = 2.0  # s the worker gets to exit before it is killed
# Batches sent and not yet answered, at most: the worker answers without waiting for the owner to read
# as long as their outcomes (~2 kB each, a doc and the Markov parameters) fit the socket's buffer (~200 kB).
MAX_SENT_BATCHES = 4
DOCUMENT = "document"  # the request for the published model's documented outcome (``SolverProcess.document``)


@dataclass(frozen=True, eq=False)
class Diagnose:
    """The request for ``diagnose_window(v, y, order, reference)`` (``SolverProcess.diagnose``)."""

    v: np.ndarray
    y: np.ndarray
    order: int
    reference: np.ndarray | None = None


def newest_window(snapshot: EngineSnapshot, newest: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The newest ``newest`` samples of the snapshot's raw window, (v, y), and the reference over
    them: None without one, or when it is missing (NaN) at one of them (what the node's and the
    replay's diagnoses read)."""
    v, y = snapshot.v[-newest:], snapshot.y[-newest:]
    r = None if snapshot.reference_window is None else snapshot.reference_window[-newest:]
    return v, y, r if r is not None and np.all(np.isfinite(r)) else None


def diagnose_window(v: np.ndarray, y: np.ndarray, order: int, reference: np.ndarray | None = None) -> dict[str, Any]:
    """The ``hammer_ros.diagnosis.diagnose_record`` JSON of the window (v, y) (estimation on its
    first 70 %, validation on the rest; with a closed loop's ``reference`` over the window, the
    instrumented diagnosis), or {"error": why} when the window cannot be diagnosed."""
    from ..diagnosis.diagnose import diagnose_record  # imported on first use: matplotlib-free, but heavy

    try:
        with np.errstate(all="ignore"):
            return diagnose_record(v, y, order=order, reference=reference).to_json()
    except (UsageError, ValueError, np.linalg.LinAlgError) as exc:
        return {"error": f"window not diagnosable: {exc}"}


def _serve(connection, documents: bool, ready) -> None:
    """The worker: solve each snapshot of each batch received with the state of its epoch and
    answer with the batch's outcomes, in order; answer DOCUMENT with the published model's
    outcome, documented, and a ``Diagnose`` with its window's diagnosis. ``ready`` (an Event) is
    set once the modules of a CLS solve are imported."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    from ..identification import correlation_least_squares  # noqa: F401  (what the first solve would import)

    ready.set()
    epoch, published, reference = None, None, 0.0
    last: EngineSnapshot | None = None
    published_outcome: tuple[SolveOutcome, np.ndarray, np.ndarray] | None = None  # with its window (v, y)
    while True:
        try:
            batch = connection.recv()
        except (EOFError, OSError):
            return
        if batch is None:
            return
        if isinstance(batch, Diagnose):
            connection.send(diagnose_window(batch.v, batch.y, batch.order, batch.reference))
            continue
        if batch == DOCUMENT:
            answer = None if published_outcome is None else replace(document_outcome(*published_outcome), result=None)
            connection.send(answer)
            continue
        outcomes = []
        for kept, sent, estimate in batch:
            if sent.epoch != epoch:
                epoch, published, reference, published_outcome = sent.epoch, None, 0.0, None
            v, y = sent.v, sent.y
            if kept:  # the window's oldest samples are the newest of the last window (``SolverProcess._kept``)
                tail = slice(last.v.size - kept, None)
                v, y = np.concatenate([last.v[tail], v]), np.concatenate([last.y[tail], y])
            last = snapshot = replace(sent, v=v, y=y, published=published, reference_std=reference)
            outcome = (solve_snapshot(snapshot, documents) if estimate is None
                       else decide_outcome(snapshot, estimate, documents))
            if outcome.ok:
                published, reference = outcome.result, max(reference, outcome.input_std)
                published_outcome = (outcome, v, y)
            outcomes.append(replace(outcome, result=None))
        try:
            connection.send(outcomes)
        except OSError:
            return


class SolverProcess:
    """``solve_snapshot`` in a worker process: ``submit`` snapshots and go on, collect their
    outcomes in order with ``result`` (``ready`` says whether one has arrived), or ``solve``.
    ``batch``: snapshots sent together (one transfer, one wake-up of the worker; ``result`` sends
    a partial batch before it waits). ``documents=False``: ok outcomes come without ``doc`` and
    ``markov`` (``solve_snapshot(..., document=False)``: for an owner that writes no outputs and
    reads the last model's document only, ``document``). ``diagnose``: a window's diagnosis there.
    ``role`` names the process (``hammer_ros_<role>``) and its exit in the errors."""

    def __init__(self, start_method: str = "spawn", batch: int = 1, documents: bool = True,
                 role: str = "solver") -> None:
        context = multiprocessing.get_context(start_method)
        self._connection, child = context.Pipe()
        self._ready = context.Event()
        self._process = context.Process(target=_serve, args=(child, documents, self._ready),
                                        name=f"hammer_ros_{role}", daemon=True)
        self._process.start()
        child.close()
        self.batch = batch
        self.max_sent = MAX_SENT_BATCHES * batch
        self._last: EngineSnapshot | None = None  # the last snapshot submitted (its whole window)
        self.documents = documents
        self._unsent: list[tuple[int, EngineSnapshot, Estimate | None]] = []
        self._sent = 0  # solves sent whose outcomes have not been read
        self._outcomes: deque[SolveOutcome] = deque()  # read, not yet taken by ``result``

    @property
    def in_flight(self) -> int:
        """Solves submitted whose outcomes ``result`` has not returned yet."""
        return len(self._unsent) + self._sent + len(self._outcomes)

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def wait_ready(self, timeout: float) -> bool:
        """Wait until the worker has started and imported what a solve needs (a spawned worker
        imports for about a second, on a core that ingestion would otherwise have); False when
        it has not within ``timeout`` s or has exited. Solves may be submitted before: they wait
        in the pipe."""
        deadline = time.monotonic() + timeout
        while self._process.is_alive() and (left := deadline - time.monotonic()) > 0:
            if self._ready.wait(min(left, 0.1)):
                return True
        return self._ready.is_set()

    def _exited(self) -> str:
        self._process.join(CLOSE_TIMEOUT)
        role = self._process.name.removeprefix("hammer_ros_")
        return f"the {role} process exited (exit code {self._process.exitcode})"

    def submit(self, snapshot: EngineSnapshot, estimate: Estimate | None = None) -> None:
        """Queue ``snapshot`` for the worker (its in-process ``published`` model stays here); a full
        batch is sent, which returns at once while the socket's buffer holds it, else when the
        worker has read enough (the back-pressure of a worker that is behind). ``estimate``: the
        snapshot's ``estimate_snapshot(snapshot, self.documents)``, made by the owner (a CLS method's:
        picklable), so that the worker only decides its outcome (``decide_outcome``)."""
        kept = self._kept(snapshot)
        self._unsent.append((kept, replace(snapshot, published=None, stats=None,  # the counters stay here
                                           v=snapshot.v[kept:], y=snapshot.y[kept:]), estimate))
        self._last = snapshot
        if len(self._unsent) >= self.batch:
            self._send()

    def _send(self) -> None:
        batch, self._unsent = self._unsent, []
        while self._sent and self._sent + len(batch) > self.max_sent:
            self._read()
        try:
            self._connection.send(batch)
        except OSError as error:
            raise RuntimeError(self._exited()) from error
        self._sent += len(batch)

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
        return bool(self._outcomes) or (self._sent > 0 and self._connection.poll())

    def result(self) -> SolveOutcome:
        """The outcome of the oldest solve in flight (waits for it)."""
        if self.in_flight == 0:
            raise RuntimeError("no solve in flight")
        if not self._outcomes:
            if self._sent == 0:
                self._send()
            self._read()
        return self._outcomes.popleft()

    def _read(self) -> None:
        """Wait for the outcomes of the oldest batch sent."""
        try:
            outcomes = self._connection.recv()
        except (EOFError, OSError) as error:
            raise RuntimeError(self._exited()) from error
        self._sent -= len(outcomes)
        self._outcomes.extend(outcomes)

    def document(self) -> SolveOutcome | None:
        """The last ok outcome (of the newest epoch) with its ``doc`` and ``markov``; None before one.
        Every outcome submitted must have been taken by ``result``."""
        return self._ask(DOCUMENT)

    def diagnose(self, v: np.ndarray, y: np.ndarray, order: int,
                 reference: np.ndarray | None = None) -> dict[str, Any]:
        """``diagnose_window(v, y, order, reference)`` in the worker (waits for it). Every outcome
        submitted must have been taken by ``result``."""
        return self._ask(Diagnose(v, y, order, reference))

    def _ask(self, request: Any) -> Any:
        if self.in_flight:
            raise RuntimeError(f"{self.in_flight} solves in flight: take their outcomes first")
        try:
            self._connection.send(request)
            return self._connection.recv()
        except (EOFError, OSError) as error:
            raise RuntimeError(self._exited()) from error

    def solve(self, snapshot: EngineSnapshot) -> SolveOutcome:
        """The outcome of ``snapshot`` (waits for it and for the solves submitted before it)."""
        self.submit(snapshot)
        if self._unsent:
            self._send()
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
