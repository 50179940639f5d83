"""Section 7, fleet: serial replay vs ``fleet --workers 2`` (Dask) vs plain processes on small bags."""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

from ...identification.correlation_least_squares import DEFAULT_MU, default_tau_max
from ...streaming.config import EngineConfig
from .common import (
    Section,
    _median,
    _timed,
    children_cpu_seconds,
)

FLEET_WORKERS = 2
FLEET_ROUNDS = 3  # serial, fleet and plain processes back to back, this many times
BAG_SAMPLES, BAG_RATE = 3000, 100.0  # each bag: 30 s of a joint at 100 Hz (what the row has always measured)


def _replay_share(settings, sources, barrier, results) -> None:
    """One of ``fleet_section``'s plain processes: replay its share of the bags after the barrier
    (imports and a first bag done before it), and put its seconds on ``results``."""
    from ...fleet.tasks import run_bag

    run_bag(settings, sources[0])
    barrier.wait()
    seconds, _ = _timed(lambda: [run_bag(settings, s) for s in sources])
    results.put(seconds)


def plain_processes_wall(settings, sources, workers: int) -> float:
    """Wall seconds of ``workers`` plain processes replaying interleaved shares of ``sources`` at
    once (no scheduler, no transfer): the machine's own ceiling for running bags side by side."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(workers), context.Queue()
    processes = [context.Process(target=_replay_share, args=(settings, sources[i::workers], barrier, results))
                 for i in range(workers)]
    for process in processes:
        process.start()
    seconds = [results.get(timeout=600) for _ in processes]
    for process in processes:
        process.join()
    return max(seconds)


def fleet_section(bags: int, workers: int = FLEET_WORKERS, rounds: int = FLEET_ROUNDS) -> Section:
    """``bags`` small sample-fleet bags (BAG_SAMPLES samples): serial replay in this process (the fleet's
    own task, which is replay's loop) vs ``fleet --workers 2`` (a LocalCluster; its start-up
    reported apart) vs plain processes, in ``rounds`` rounds (each measuring the three back to
    back, in a rotated order: a burst of another job's load hits one round, not the verdict);
    speed-ups per round, their median decides; overhead = worker time per bag beyond the bag's
    own replay."""
    from ...fleet.runner import connect, run_fleet
    from ...fleet.sample_fleet import sample_joints, write_sample_fleet
    from ...fleet.sources import sources_from_paths
    from ...fleet.tasks import FleetSettings, run_bag
    from ...io.bags import load_msg_config, stream_specs

    section = Section("fleet", f"7. Fleet: serial replay vs `fleet --workers {workers}` (Dask LocalCluster)", [
        ("case", "case"), ("serial", "serial s"), ("fleet", "fleet s"), ("ratio", "speed-up"),
        ("ratios", "speed-up per round"), ("plain", f"{workers} plain processes: speed-up"),
        ("task", "replay s / bag"), ("cpu", "replay CPU s / bag-hour"), ("overhead", "Dask overhead s / bag"),
        ("startup", "cluster start s"),
        ("load", "load average (1 min) per round"), ("goal", "goal >= 1.7")])
    config_path = Path(__file__).resolve().parents[3] / "msg_config" / "sample_fleet.yaml"
    params = load_msg_config(config_path)
    config = EngineConfig(sample_rate=BAG_RATE, window=1000, tau_max=default_tau_max(2, DEFAULT_MU), order=2, delay=1)
    settings = FleetSettings(*stream_specs(None, None, params, str(config_path)), config, 0.5)
    # healthy joints: over 25 days the faulty ones' gain reaches 0 and their models are withheld as uncertain
    # (error rows, which the goal does not allow: 96 of 1200 rows before)
    joints = sample_joints(robots=4, joints=2, drift_day=None, dead_zone_day=None)
    serial, cpu, plain, runs, startups, loads, errors = [], [], [], [], [], [], []
    with tempfile.TemporaryDirectory(prefix="hammer_ros_bench_fleet_") as tmp:
        write_sample_fleet(tmp, joints, math.ceil(bags / len(joints)), samples=BAG_SAMPLES)
        sources = sources_from_paths([tmp])[:bags]
        run_bag(settings, sources[0])  # this process's first bag pays lazy imports, as a worker's warm-up does

        def measure_serial() -> None:
            started = time.process_time() + children_cpu_seconds()  # any solver process a replay forked too
            seconds, rows = _timed(lambda: [run_bag(settings, s) for s in sources])
            serial.append(seconds)
            used = time.process_time() + children_cpu_seconds() - started
            cpu.append(used / (len(sources) * BAG_SAMPLES / BAG_RATE / 3600.0))
            errors.extend(r["error"] for r in rows if r.get("error"))

        def measure_fleet() -> None:  # a cluster of its own: none idles beside the serial and plain runs
            startup, (client, cluster) = _timed(lambda: connect(None, workers))
            startups.append(startup)
            try:
                run_fleet(client, sources[:workers * 2], settings)  # warm the workers' imports
                runs.append(run_fleet(client, sources, settings))
            finally:
                client.close()
                cluster.close()

        steps = [measure_serial, measure_fleet, lambda: plain.append(plain_processes_wall(settings, sources, workers))]
        for i in range(rounds):
            loads.append(os.getloadavg()[0])
            for step in steps[i % 3:] + steps[:i % 3]:
                step()
    errors.extend(r["error"] for run in runs for r in run.rows if r.get("error"))
    ratios = [s / run.wall_s for s, run in zip(serial, runs, strict=True)]
    ratio = _median(ratios)
    overheads = [(run.wall_s * workers - sum(r["seconds"] for r in run.rows)) / len(sources) for run in runs]
    case = f"{len(sources)} bags x {BAG_SAMPLES} samples, {workers} workers, median of {rounds} rounds"
    section.rows.append({"case": case,
                         "serial": _median(serial), "fleet": _median([run.wall_s for run in runs]), "ratio": ratio,
                         "ratios": " ".join(f"{r:.2f}" for r in ratios),
                         "plain": _median([s / p for s, p in zip(serial, plain, strict=True)]),
                         "task": _median([r["seconds"] for run in runs for r in run.rows]), "cpu": _median(cpu),
                         "overhead": _median(overheads), "startup": _median(startups),
                         "load": " ".join(f"{x:.1f}" for x in loads), "goal": ratio >= 1.7 and not errors})
    if errors:
        section.notes.append(f"{len(errors)} bag(s) failed (the goal needs none), e.g. {errors[0]}")
    section.notes.append(f"serial: the fleet's task (replay's loop) on each bag in turn in this process (after one "
                         "bag apart); fleet: "
                         f"`run_fleet` on a LocalCluster of {workers} single-threaded worker processes, timed "
                         "from the first submit to the last row (cluster start-up and a warm-up of "
                         f"{workers * 2} bags apart); CPU per bag-hour: the serial replays' CPU seconds (this "
                         "process and any solver process it forked) per hour of recorded data "
                         f"({BAG_SAMPLES} samples at {BAG_RATE:g} Hz a bag); overhead = (fleet wall x workers - "
                         "sum of the tasks' own seconds) / bags: scheduling, transfer and idle time per bag; "
                         f"plain processes: {workers} processes (no Dask) replaying interleaved shares of the bags "
                         "at once, the machine's own ceiling for bags side by side (serial / their wall); "
                         f"{rounds} rounds of the three back to back (order rotated each round; each fleet on a "
                         "new cluster, closed before the next step), the speed-ups per round and their median "
                         "(the figures shown are medians)")
    return section


