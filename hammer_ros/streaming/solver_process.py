"""Solves in a worker process of their own, so that a solve never holds the interpreter lock
against ingestion (the node's executor, replay's decoding).

``SolverProcess`` starts one process (by default ``spawn``: a fresh interpreter, safe beside the
threads of a ROS node and its middleware, started as a plain subprocess, so that no resource
tracker process comes with it; ``fork`` for an owner with no other thread, e.g. replay without ROS:
the worker then starts with the owner's modules loaded, in milliseconds instead of ~1 s) that runs
``engine.solve_snapshot`` on the snapshots it is sent, in order (and, asked, ``diagnose_window``: the
node diagnoses its windows in a second one, so that a diagnosis never holds the node's interpreter
lock either). One worker serves several engines (a node's channels): each snapshot comes with its
``lane`` (the channel), and the worker keeps the state below per lane. A snapshot (its correlation sums
and the raw window, about 70 kB at W = 4000; of a window that slid, only the samples new since the
last snapshot, the worker keeping the rest) crosses by a pipe; the outcome comes back without its
``result`` (a model holds its simulator, which stays in the worker) but with everything the outputs
are built from (``doc``, ``markov``; with ``documents=False`` the worker skips them, a tenth to a
sixth of a CLS solve, and documents the last good model on request). Several snapshots may be in
flight (replay sends the next one while the worker still solves), so the state a solve depends on
lives in the worker, per lane: the published model and the reference input std of the engine's ``epoch``,
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
sends and waits for the outcome; it, ``diagnose`` and ``document`` take a lock, so the threads of
several channels may share one worker (each waits for its turn). No thread is involved otherwise:
in the owner, a thread that serialises beside replay's reading loop took the interpreter lock from
it at every numpy call that released it; in the worker, a thread that sends the answers made the
pipeline stall (replay of the bench's 100-sample bag: 1.06 s without it, 1.75-1.88 s with it).

A worker sends READY once it has imported what a solve needs (``wait_ready``): the node
subscribes only then, so that a spawned worker's second of imports does not compete with the
first second of ingestion.

The worker ignores SIGINT and SIGTERM (sent to a whole process group, they are for the owner,
which handles them and then closes the worker); it exits when the owner closes the pipe or
dies, and is killed when it does not exit within CLOSE_TIMEOUT of ``close``.
"""

from __future__ import annotations

import multiprocessing
import select
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Hashable
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ..errors import UsageError
from .engine import EngineSnapshot, Estimate, SolveOutcome, decide_outcome, document_outcome, solve_snapshot

CLOSE_TIMEOUT = 2.0  # s the worker gets to exit before it is killed
# Batches sent and not yet answered, at most: the worker answers without waiting for the owner to read
# as long as their outcomes (~2 kB each, a doc and the Markov parameters) fit the socket's buffer (~200 kB).
MAX_SENT_BATCHES = 4
READY = "ready"  # the worker's first message: it has imported what a solve needs (``SolverProcess.wait_ready``)


@dataclass(frozen=True)
class Document:
    """The request for the documented outcome of a lane's published model (``SolverProcess.document``)."""

    lane: Hashable


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


class _Lane:
    """The worker's state of one lane (one engine): its epoch, the published model and the
    reference input std of that epoch, the last window received and the published model's
    outcome with its window (v, y)."""

    def __init__(self) -> None:
        self.epoch: int | None = None
        self.published = None
        self.reference = 0.0
        self.last: EngineSnapshot | None = None
        self.published_outcome: tuple[SolveOutcome, np.ndarray, np.ndarray] | None = None

    def solve(self, kept: int, sent: EngineSnapshot, estimate: Estimate | None, documents: bool) -> SolveOutcome:
        """The outcome of ``sent`` (its window's ``kept`` oldest samples: the newest of the last
        window) with this lane's state, which it updates as ``StreamingEngine.record`` does."""
        if sent.epoch != self.epoch:
            self.epoch, self.published, self.reference, self.published_outcome = sent.epoch, None, 0.0, None
        v, y = sent.v, sent.y
        if kept:  # the window's oldest samples are the newest of the last window (``SolverProcess._kept``)
            last = self.last
            tail = slice(last.v.size - kept, None)
            v, y = np.concatenate([last.v[tail], v]), np.concatenate([last.y[tail], y])
        self.last = snapshot = replace(sent, v=v, y=y, published=self.published, reference_std=self.reference)
        outcome = (solve_snapshot(snapshot, documents) if estimate is None
                   else decide_outcome(snapshot, estimate, documents))
        if outcome.ok:
            self.published, self.reference = outcome.result, max(self.reference, outcome.input_std)
            self.published_outcome = (outcome, v, y)
        return replace(outcome, result=None)


def _serve(connection: Connection, documents: bool) -> None:
    """The worker: solve each snapshot of each batch received with the state of its lane and
    answer with the batch's outcomes, in order; answer a ``Document`` with the lane's published
    model's outcome, documented, and a ``Diagnose`` with its window's diagnosis. Sends READY
    first, once the modules of a CLS solve are imported."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    from ..identification import correlation_least_squares  # noqa: F401  (what the first solve would import)

    connection.send(READY)
    lanes: dict[Hashable, _Lane] = {}
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
        if isinstance(batch, Document):
            published = lanes.get(batch.lane, _Lane()).published_outcome
            connection.send(None if published is None else replace(document_outcome(*published), result=None))
            continue
        outcomes = [lanes.setdefault(lane, _Lane()).solve(kept, sent, estimate, documents)
                    for lane, kept, sent, estimate in batch]
        try:
            connection.send(outcomes)
        except OSError:
            return


def _serve_descriptor(descriptor: int, documents: bool) -> None:
    """``_serve`` on the connection inherited as file ``descriptor`` (a worker started by ``_Spawned``)."""
    _serve(Connection(descriptor), documents)


class _Spawned:
    """A worker in a fresh interpreter started as a plain subprocess (multiprocessing's ``spawn``
    would start its resource tracker, a process more), with the owner's ``sys.path``, serving
    ``child`` (inherited as its descriptor); what the owner reads of a ``multiprocessing.Process``."""

    def __init__(self, child: Connection, documents: bool, name: str) -> None:
        code = (f"import sys; sys.path[:] = {sys.path!r}; from {__name__} import _serve_descriptor; "
                f" _serve_descriptor({child.fileno()}, {documents!r})")
        self._popen = subprocess.Popen([sys.executable, "-c", code], pass_fds=(child.fileno(),),
                                       stdin=subprocess.DEVNULL)
        self.name = name

    @property
    def pid(self) -> int:
        return self._popen.pid

    @property
    def exitcode(self) -> int | None:
        return self._popen.poll()

    def is_alive(self) -> bool:
        return self._popen.poll() is None

    def join(self, timeout: float) -> None:
        try:
            self._popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass

    def kill(self) -> None:
        self._popen.kill()


class SolverProcess:
    """``solve_snapshot`` in a worker process: ``submit`` snapshots and go on, collect their
    outcomes in order with ``result`` (``ready`` says whether one has arrived), or ``solve``.
    ``batch``: snapshots sent together (one transfer, one wake-up of the worker; ``result`` sends
    a partial batch before it waits). ``documents=False``: ok outcomes come without ``doc`` and
    ``markov`` (``solve_snapshot(..., document=False)``: for an owner that writes no outputs and
    reads the last model's document only, ``document``). ``diagnose``: a window's diagnosis there.
    ``lane`` (of ``submit``, ``solve``, ``document``): the engine a snapshot comes from, when
    several share the worker (a node's channels). ``role`` names the process and its exit in the
    errors."""

    def __init__(self, start_method: str = "spawn", batch: int = 1, documents: bool = True,
                 role: str = "solver") -> None:
        self._connection, child = multiprocessing.Pipe()
        name = f"hammer_ros_{role}"
        if start_method == "spawn":
            self._process = _Spawned(child, documents, name)
        else:
            context = multiprocessing.get_context(start_method)
            self._process = context.Process(target=_serve, args=(child, documents), name=name, daemon=True)
            self._process.start()
        child.close()
        self._poller = select.poll()  # ``ready``'s check of the pipe (Connection.poll builds a selector every call)
        self._poller.register(self._connection.fileno(), select.POLLIN)
        self._started = False  # READY received
        self._lock = threading.Lock()  # one owner's thread at a time in ``solve``, ``diagnose``, ``document``
        self.batch = batch
        self.max_sent = MAX_SENT_BATCHES * batch
        self._last: dict[Hashable, EngineSnapshot] = {}  # per lane, the last snapshot submitted (its whole window)
        self.documents = documents
        self._unsent: list[tuple[Hashable, int, EngineSnapshot, Estimate | None]] = []
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
        with self._lock:
            while not self._started and self._process.is_alive() and (left := deadline - time.monotonic()) > 0:
                try:
                    if self._connection.poll(min(left, 0.1)):
                        self._take_ready()
                except (EOFError, OSError):
                    return False
            return self._started

    def _take_ready(self) -> None:
        """Read the worker's READY (its first message), once."""
        if not self._started:
            if self._connection.recv() != READY:
                raise RuntimeError(f"the {self._role} process did not start as expected")
            self._started = True

    def _receive(self) -> Any:
        """The worker's next answer (after its READY)."""
        self._take_ready()
        return self._connection.recv()

    @property
    def _role(self) -> str:
        return self._process.name.removeprefix("hammer_ros_")

    def _exited(self) -> str:
        self._process.join(CLOSE_TIMEOUT)
        return f"the {self._role} process exited (exit code {self._process.exitcode})"

    def submit(self, snapshot: EngineSnapshot, estimate: Estimate | None = None, lane: Hashable = 0) -> None:
        """Queue ``snapshot`` for the worker (its in-process ``published`` model stays here); a full
        batch is sent, which returns at once while the socket's buffer holds it, else when the
        worker has read enough (the back-pressure of a worker that is behind). ``estimate``: the
        snapshot's ``estimate_snapshot(snapshot, self.documents)``, made by the owner (a CLS method's:
        picklable), so that the worker only decides its outcome (``decide_outcome``)."""
        kept = self._kept(snapshot, lane)
        self._unsent.append((lane, kept, replace(snapshot, published=None, stats=None,  # the counters stay here
                                                 v=snapshot.v[kept:], y=snapshot.y[kept:]), estimate))
        self._last[lane] = snapshot
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

    def _kept(self, snapshot: EngineSnapshot, lane: Hashable = 0) -> int:
        """How many of the window's oldest samples the worker already holds as the newest ones of
        the last window sent of ``lane`` (0: send the whole window). The window slid by the samples
        aligned since then; the overlap is compared, so a restarted window is sent whole."""
        last = self._last.get(lane)
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
        if self._outcomes:
            return True
        if self._sent == 0 or not self._poller.poll(0):  # readable, or closed (then ``result`` raises)
            return False
        if not self._started:  # READY came first
            self._take_ready()
            return bool(self._poller.poll(0))
        return True

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
            outcomes = self._receive()
        except (EOFError, OSError) as error:
            raise RuntimeError(self._exited()) from error
        self._sent -= len(outcomes)
        self._outcomes.extend(outcomes)

    def document(self, lane: Hashable = 0) -> SolveOutcome | None:
        """The last ok outcome of ``lane`` (of its newest epoch) with its ``doc`` and ``markov``; None
        before one. Every outcome submitted must have been taken by ``result``."""
        return self._ask(Document(lane))

    def diagnose(self, v: np.ndarray, y: np.ndarray, order: int,
                 reference: np.ndarray | None = None) -> dict[str, Any]:
        """``diagnose_window(v, y, order, reference)`` in the worker (waits for it). Every outcome
        submitted must have been taken by ``result``."""
        return self._ask(Diagnose(v, y, order, reference))

    def _ask(self, request: Any) -> Any:
        with self._lock:
            if self.in_flight:
                raise RuntimeError(f"{self.in_flight} solves in flight: take their outcomes first")
            try:
                self._connection.send(request)
                return self._receive()
            except (EOFError, OSError) as error:
                raise RuntimeError(self._exited()) from error

    def solve(self, snapshot: EngineSnapshot, lane: Hashable = 0) -> SolveOutcome:
        """The outcome of ``snapshot`` of ``lane`` (waits for it and for the solves submitted before it)."""
        with self._lock:
            self.submit(snapshot, lane=lane)
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
