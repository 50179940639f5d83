"""The worker processes of a node (``solver_process``): ONE ``SolverProcess`` for the solves of
every channel, started with the channels (each channel is a lane of it: the worker keeps each
channel's published model and window apart, so the outcomes are those of in-process solves), and
ONE for the diagnoses of every channel, started by the first diagnosis (a node that never
diagnoses never pays for it). A node of N channels thus runs in at most 3 processes, whatever N.

The channels' solver threads take turns in the solver process (``SolverProcess.solve`` holds its
lock for a solve), their diagnosis threads in the diagnosis process. When a worker is lost (it
exited), every channel solves (diagnoses) in its own thread from then on, and /diagnostics says
why (``solver_state``, ``diagnosis_state``).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from ..streaming.engine import EngineSnapshot, SolveOutcome, solve_snapshot
from ..streaming.solver_process import SolverProcess, diagnose_window

WORKER_READY_SECONDS = 10.0  # longest wait for the solver process before subscribing (``wait_ready``)


class NodeWorkers:
    """The node's solver process (started here when ``in_process`` says so: some channel has
    ``solver_process`` on) and its diagnosis process (started by the first ``diagnose``)."""

    def __init__(self, in_process: bool) -> None:
        self.in_process = in_process
        self.solver: SolverProcess | None = SolverProcess() if in_process else None
        self.solver_lost = ""  # why the solver process is gone, when it went
        self.diagnoser: SolverProcess | None = None
        self.diagnoser_lost = ""  # why the diagnosis process is gone, when it went
        self._lock = threading.Lock()  # guards starting and losing the workers

    def wait_ready(self, logger) -> None:
        """Wait for the solver process (at most WORKER_READY_SECONDS): its start, about 0.7 s of CPU
        for imports, would otherwise compete with the first second of ingestion (2-core bench VM,
        a fresh node fed 20 000 - 32 000 100-sample messages/s per topic for 3 s as soon as it
        reported its subscriptions: lossy in 10 of 18 runs without the wait, 4 of 18 with it)."""
        if self.solver is not None and not self.solver.wait_ready(WORKER_READY_SECONDS):
            logger.warning(f"the solver process is not ready after {WORKER_READY_SECONDS:g} s; "
                           "subscribing anyway (solves wait for it)")

    def solve(self, snapshot: EngineSnapshot, lane: str, logger) -> SolveOutcome:
        """``solve_snapshot`` of channel ``lane`` in the solver process, or here when there is none
        (or it is gone)."""
        solver = self.solver
        if solver is not None:
            try:
                return solver.solve(snapshot, lane)
            except RuntimeError as exc:
                self._lose("solver", solver, exc, logger, "solving")
        return solve_snapshot(snapshot)

    def diagnose(self, v: np.ndarray, y: np.ndarray, order: int, reference: np.ndarray | None,
                 logger) -> dict[str, Any]:
        """``diagnose_window`` in the diagnosis process (started by the first call), or here when
        the node has no worker processes (or it is gone)."""
        if self.in_process and not self.diagnoser_lost:
            with self._lock:
                if self.diagnoser is None and not self.diagnoser_lost:
                    self.diagnoser = SolverProcess(role="diagnosis")
                diagnoser = self.diagnoser
            if diagnoser is not None:
                try:
                    return diagnoser.diagnose(v, y, order, reference)
                except RuntimeError as exc:
                    self._lose("diagnoser", diagnoser, exc, logger, "diagnosing")
        return diagnose_window(v, y, order, reference)

    def _lose(self, which: str, worker: SolverProcess, exc: RuntimeError, logger, doing: str) -> None:
        """Forget a worker that failed (once, whichever channel noticed it first) and close it."""
        with self._lock:
            if getattr(self, which) is not worker:  # another channel noticed first
                return
            setattr(self, which, None)
            setattr(self, f"{which}_lost", str(exc))
        logger.error(f"{which.replace('diagnoser', 'diagnosis')} process lost ({exc}); {doing} in the node's "
                     "thread from now on")
        worker.close()

    def solver_state(self) -> str:
        """What /diagnostics says of the solves of a channel with ``solver_process`` on."""
        solver = self.solver
        return f"process {solver.pid}" if solver is not None else f"thread ({self.solver_lost})"

    def diagnosis_state(self) -> str:
        """What /diagnostics says of the diagnoses of a channel with ``solver_process`` on."""
        diagnoser = self.diagnoser
        if diagnoser is not None:
            return f"process {diagnoser.pid}"
        return f"thread ({self.diagnoser_lost})" if self.diagnoser_lost else "process, from the first diagnosis"

    def close(self) -> None:
        """Stop both worker processes."""
        with self._lock:
            workers, self.solver, self.diagnoser = (self.solver, self.diagnoser), None, None
        for worker in workers:
            if worker is not None:
                worker.close()
