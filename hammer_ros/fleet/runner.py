"""Running the fleet on Dask distributed: the client (a LocalCluster or an existing scheduler),
tasks of a few bags each, the progress bar, checkpoints of ``fleet.parquet``, resume and Ctrl-C.

Dask owns the scheduling and the faults of the cluster: a worker that dies (even by SIGKILL)
loses no bag, the scheduler reruns its tasks elsewhere (a task whose workers died
``distributed.scheduler.allowed-failures`` + 1 times becomes error rows). Tasks return only
their rows (one per bag, or per bag and channel); the bags are opened by path on the workers (on
a real cluster the paths, and the results directory, must be the same on every machine, e.g. a
shared filesystem).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..errors import UsageError
from .sources import BagSource
from .tasks import FleetSettings, bag_rows, empty_row

SCHEDULER_TIMEOUT_S = 5.0
# A LocalCluster shares the machine's cores with its scheduler (in this process) and its workers' own
# threads: the statistical profiler samples every task's stack 100 x/s and the monitors poll psutil
# every 0.5 s, for a dashboard that is off; profiler off, monitors every 5 s. Every server (the
# scheduler, each nanny and worker) also wakes 50 x/s to time its own event loop (the "unresponsive"
# warning), and the scheduler looks for work to steal 10 x/s, which tasks held back by the
# scheduler's queue and the shrinking tail of ``task_batches`` do not need: ticks every 1 s, no
# stealing (idle, this process used 3 % of a core and each worker 1.5 %, then under 1 %).
QUIET_CLUSTER = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "5s",
    "distributed.admin.tick.interval": "1s",
    "distributed.scheduler.work-stealing": False,
}
CHECKPOINT_S = 30.0  # fleet.parquet is rewritten at least this often while the fleet runs
MAX_BATCH = 8  # bags per task at most
BATCHES_PER_WORKER = 8  # tasks per worker at least, when the fleet is large enough to batch
TAIL_SHARE = 2  # a default task holds at most 1 / (TAIL_SHARE x workers) of the bags left (``task_batches``)


@dataclass
class FleetRun:
    """The rows of one run (the resumed ones first), its bags with rows, and whether Ctrl-C stopped it."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    bags: int = 0
    interrupted: bool = False
    missing: int = 0
    wall_s: float = 0.0
    workers: int = 0


class FleetProgress:
    """``fleet [#####     ] 12/24 bags  1 failed  ETA 0:00:14`` on stderr (redrawn at most 5 x/s)."""

    def __init__(self, total: int, stream=None, enabled: bool = True) -> None:
        self.total, self.stream, self.enabled = total, stream or sys.stderr, enabled
        self.started, self.last, self.done, self.failed = time.monotonic(), 0.0, 0, 0

    def update(self, done: int, failed: int, force: bool = False) -> None:
        self.done, self.failed = done, failed
        now = time.monotonic()
        if not self.enabled or (not force and now - self.last < 0.2):
            return
        self.last = now
        fraction = done / self.total if self.total else 1.0
        elapsed = now - self.started
        eta = elapsed * (self.total - done) / done if done else float("nan")
        eta_text = time.strftime("%H:%M:%S", time.gmtime(eta)) if eta == eta else "--:--:--"
        self.stream.write(f"\rfleet [{'#' * int(30 * fraction):<30}] {done}/{self.total} bags  {failed} failed  "
                          f"ETA {eta_text} ")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.update(self.done, self.failed, force=True)
            self.stream.write("\n")
            self.stream.flush()


def connect(scheduler: str | None, workers: int | None):
    """(client, cluster): a client of the scheduler at ``scheduler`` (a UsageError if none answers
    within SCHEDULER_TIMEOUT_S), else of a new LocalCluster of ``workers`` single-threaded processes."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise UsageError(f"--scheduler {scheduler}: no Dask scheduler answers ({reason})") from None
        return client, None
    with dask.config.set(QUIET_CLUSTER):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR)
    return Client(cluster), cluster


def worker_count(client) -> int:
    return len(client.scheduler_info(n_workers=-1).get("workers", {}))


def batch_size(bags: int, workers: int) -> int:
    """Bags per task: one while the fleet is small, then enough that each worker still gets at
    least BATCHES_PER_WORKER tasks (the last ones balance the load), at most MAX_BATCH (a lost
    worker reruns at most that many bags). Fewer, longer tasks take scheduler and worker event-loop
    work off the cores the bags need."""
    return int(max(1, min(MAX_BATCH, bags // (max(workers, 1) * BATCHES_PER_WORKER))))


def task_batches(sources: Sequence[BagSource], workers: int, size: int | None = None) -> list[list[BagSource]]:
    """The bags in tasks, in order: ``size`` bags each when given (``--batch``), else ``batch_size``
    bags while many are left and then fewer, each task at most ceil(left / (TAIL_SHARE x workers))
    (guided self-scheduling, Polychronopoulos & Kuck 1987), down to single bags at the end, so
    the workers finish together instead of one running its last full task while the others idle
    (200 bags on 2 workers: 22 tasks of 8, then 6, 5, 4, 3, 2 and four of 1)."""
    workers = max(workers, 1)
    largest = size or batch_size(len(sources), workers)
    batches, start = [], 0
    while start < len(sources):
        left = len(sources) - start
        take = largest if size else max(1, min(largest, math.ceil(left / (TAIL_SHARE * workers))))
        batches.append(list(sources[start : start + take]))
        start += take
    return batches


def run_batch(task: Callable[[FleetSettings, BagSource], list[dict]], settings: FleetSettings,
              batch: Sequence[BagSource]) -> list[dict]:
    """The rows of the bags of one task, in order (runs on a worker)."""
    return [row for source in batch for row in task(settings, source)]


def run_fleet(client, sources: Sequence[BagSource], settings: FleetSettings, done_rows: Sequence[dict] = (),
              checkpoint: Callable[[list[dict]], None] | None = None, progress: FleetProgress | None = None,
              task: Callable[[FleetSettings, BagSource], list[dict]] = bag_rows, batch: int | None = None) -> FleetRun:
    """Submit the bags in ``sources`` (minus those in ``done_rows``) in tasks of ``batch`` bags
    (default: ``task_batches``' shrinking tail), gather the rows as they finish; ``checkpoint(rows)`` every
    CHECKPOINT_S and at the end. Ctrl-C cancels what is left and returns what finished
    (``interrupted``)."""
    from distributed import as_completed

    done_paths = {row["path"] for row in done_rows}
    run = FleetRun(rows=list(done_rows), bags=len(done_paths), workers=worker_count(client))
    todo = [s for s in sources if s.path not in done_paths]
    batches = task_batches(todo, run.workers, batch)
    started = last_checkpoint = time.perf_counter()
    failed = sum(1 for row in done_rows if row.get("error"))
    progress = progress or FleetProgress(len(sources), enabled=False)
    progress.update(run.bags, failed, force=True)
    futures = {}
    try:
        for i, batch in enumerate(batches):
            future = client.submit(run_batch, task, settings, batch, key=f"hammer-ros-fleet-{i}-{batch[0].name}",
                                   pure=False)
            futures[future.key] = (future, batch)
        for future in as_completed([f for f, _ in futures.values()]):
            rows = _rows_of(future, futures[future.key][1], settings)
            future.release()
            run.rows.extend(rows)
            run.bags += len(futures[future.key][1])
            failed += sum(bool(row.get("error")) for row in rows)
            progress.update(run.bags, failed)
            if checkpoint and time.perf_counter() - last_checkpoint > CHECKPOINT_S:
                checkpoint(run.rows)
                last_checkpoint = time.perf_counter()
    except KeyboardInterrupt:
        run.interrupted = True
        client.cancel([f for f, _ in futures.values() if not f.done()])
    finally:
        progress.close()
    run.missing = len(sources) - run.bags
    run.wall_s = time.perf_counter() - started
    if checkpoint:
        checkpoint(run.rows)
    return run


def _rows_of(future, batch: Sequence[BagSource], settings: FleetSettings) -> list[dict]:
    """The task's rows, or an error row per bag (and channel) when Dask could not run it (e.g.
    KilledWorker)."""
    if future.status == "finished":
        return future.result()
    try:
        exc = future.exception()
    except Exception as raised:  # cancelled, lost
        exc = raised
    reason = str(exc).strip().splitlines()[0] if exc is not None and str(exc).strip() else future.status
    channels = [{"channel": c.name} for c in settings.channels] or [{}]
    return [{**empty_row(source), **channel, "seconds": None,
             "error": f"{source.path}: the task failed on the cluster ({type(exc).__name__}: {reason})"}
            for source in batch for channel in channels]
