"""``hammer-ros fleet`` with real processes: a ``dask scheduler`` and two ``dask worker`` processes on
localhost over TCP, and a LocalCluster (``--workers``), on a generated fleet of 24 bags (one
damaged): the models against the generator's truth, the error row, the changes from the right
day, equality with ``replay --json``, a worker killed by SIGKILL mid-run, Ctrl-C and --resume, the
HTML page in headless Chromium, and bad input (exit 2, one line, before any work)."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from ros_helpers import free_port

from hammer_ros.fleet.sample_fleet import sample_joints, write_sample_fleet
from hammer_ros.fleet.table import QUANTITIES, read_rows
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.ros.environment import without_bootstrap

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
HAMMER_ROS, DASK = str(BIN / "hammer-ros"), str(BIN / "dask")
CONFIG = str(REPO / "msg_config" / "sample_fleet.yaml")
DAYS = 8
JOINTS = sample_joints(robots=2, joints=2)[:3]  # robot_01/joint1 healthy, /joint2 drifts; robot_02/joint1 dead zone


def child_env() -> dict[str, str]:
    env = without_bootstrap()
    env.update(OPENBLAS_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return env


def wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


class Cluster:
    """A ``dask scheduler`` and ``workers`` ``dask worker`` processes (no nanny: a SIGKILL kills
    the worker itself) on localhost; every process is killed on exit."""

    def __init__(self, tmp: Path, workers: int = 2) -> None:
        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.tmp, self.procs, self.workers, self.logs, self.files = tmp, [], [], [], []
        tmp.mkdir(parents=True, exist_ok=True)
        self.scheduler = self._spawn("scheduler", [DASK, "scheduler", "--host", "127.0.0.1", "--port",
                                                   str(self.port), "--no-dashboard"])
        wait_for(self._answers, 60, f"the scheduler on {self.address}")
        for i in range(workers):
            self.workers.append(self._spawn(f"worker{i}", [DASK, "worker", self.address, "--nthreads", "1",
                                                           "--no-nanny", "--no-dashboard", "--host", "127.0.0.1",
                                                           "--name", f"w{i}"]))
        for log in self.logs[1:]:
            wait_for(lambda log=log: "Registered to" in log.read_text(), 120, f"{log.name} to register")

    def _spawn(self, name: str, argv: list[str]) -> subprocess.Popen:
        log = self.tmp / f"{name}.log"
        self.logs.append(log)
        self.files.append(open(log, "w"))  # closed in close()
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=self.files[-1], env=child_env(), cwd=self.tmp)
        self.procs.append(proc)
        return proc

    def _answers(self) -> bool:
        try:
            socket.create_connection(("127.0.0.1", self.port), timeout=0.5).close()
            return True
        except OSError:
            return False

    def close(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=30)
        for f in self.files:
            f.close()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    bags = write_sample_fleet(root / "bags", JOINTS, DAYS, damaged=1, samples=3000)
    assert len(bags) == 24 and sum(b.damaged for b in bags) == 1
    return root, bags


@pytest.fixture(scope="module")
def scheduler_run(fleet):
    """The fleet on a scheduler and two worker processes over TCP (--out: results MCAPs too)."""
    root, _ = fleet
    cluster = Cluster(root / "cluster")
    try:
        out = root / "on_scheduler"
        done = run_cli("fleet", str(root / "bags"), "--config", CONFIG, "--scheduler", cluster.address,
                       "--out", str(out), "--json")
    finally:
        cluster.close()
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout), out


def run_cli(*argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([HAMMER_ROS, *argv], capture_output=True, text=True, timeout=timeout, env=child_env())


def by_path(rows) -> dict[str, dict]:
    return {r["path"]: r for r in rows}


def expected_onsets(bags) -> dict[tuple[str, str], str]:
    """(group, quantity) -> date of the first changed bag, from the generator's truth."""
    out = {}
    for spec in JOINTS:
        if spec.drift_day:
            out[(spec.group, "static_gain")] = next(b.date for b in bags if b.joint == spec and b.day == spec.drift_day)
        if spec.dead_zone_day:
            out[(spec.group, "small_signal_ratio")] = next(b.date for b in bags
                                                          if b.joint == spec and b.day == spec.dead_zone_day)
    return out


def test_scheduler_and_two_workers_give_23_models_one_error_and_the_changes(fleet, scheduler_run):
    _, bags = fleet
    doc, out = scheduler_run
    assert (doc["bags"], doc["ok"], doc["failed"]) == (24, 23, 1)
    rows = by_path(doc["rows"])
    damaged = next(b for b in bags if b.damaged)
    assert set(rows) == {str(b.path.resolve()) for b in bags}
    assert "error" in rows[str(damaged.path.resolve())] and "MCAP" in rows[str(damaged.path.resolve())]["error"]
    for b in bags:
        if b.damaged:
            continue
        row = rows[str(b.path.resolve())]
        assert row["group"] == b.joint.group and row["samples"] == 3000
        poles = np.array([complex(re, im) for re, im in row["poles"]])
        assert root_rss_error(b.joint.linear(b.day).poles, poles) < 0.05, (b.path, poles)
        assert Path(row["out"]).stat().st_size > 0  # its results MCAP, as replay --out writes it
    # what changed: the drift and the dead zone from the right day, no healthy joint
    changed = {(c["group"], c["quantity"]): c for c in doc["changes"]}
    healthy = {s.group for s in JOINTS if not s.drift_day and not s.dead_zone_day}
    assert not [c for c in changed if c[0] in healthy]
    for (group, quantity), date in expected_onsets(bags).items():
        assert (group, quantity) in changed, (group, quantity, list(changed))
        assert changed[(group, quantity)]["first_date"] == date
        earliest = min(c["first_date"] for c in doc["changes"] if c["group"] == group)
        assert earliest == date  # no quantity of the group is flagged before the fault began
    drift = changed[next((s.group, "static_gain") for s in JOINTS if s.drift_day)]
    assert drift["size"] < -0.15 and drift["bags"] == DAYS - next(s.drift_day for s in JOINTS if s.drift_day) + 1
    # fleet.parquet: one row per bag, the quantities as columns
    table, _ = read_rows(out / "fleet.parquet")
    assert len(table) == 24 and sum(1 for r in table if r["error"]) == 1
    import pyarrow.parquet as pq

    columns = pq.read_schema(out / "fleet.parquet").names
    assert {"path", "group", "start_time", "end_time", "samples", "poles_re", "zeros_re", "fit_percent",
            "diagnosis_cause", "diagnosis_gain", "error", *QUANTITIES} <= set(columns)


def test_local_cluster_in_batches_gives_the_same_table_and_prints_the_changes(fleet, scheduler_run):
    """A LocalCluster with 5 bags per task (the scheduler run had one per task; the damaged bag
    shares its task with healthy ones) gives the same rows."""
    root, bags = fleet
    out = scheduler_run[1]
    local = root / "local"
    done = run_cli("fleet", str(root / "bags"), "--config", CONFIG, "--workers", "2", "--batch", "5", "--out",
                   str(local))
    assert done.returncode == 0, done.stderr[-3000:]
    remote_rows = by_path(read_rows(out / "fleet.parquet")[0])
    local_rows = by_path(read_rows(local / "fleet.parquet")[0])
    assert set(remote_rows) == set(local_rows)
    for path, row in remote_rows.items():
        other = local_rows[path]
        assert other["error"] == row["error"]
        if row["model"]:
            a, b = dict(row["model"]), dict(other["model"])
            a.pop("wall_s"), b.pop("wall_s")
            assert a == b
    # the short table on stdout: "robot_01/joint2: static gain -24 % from 2026-11-04, 5 bags ..."
    for (group, quantity), date in expected_onsets(bags).items():
        start = f"{group}: {QUANTITIES[quantity][0]}"
        line = next(line for line in done.stdout.splitlines() if line.strip().startswith(start))
        assert re.search(rf"[-+]\d+ % from {date}, \d+ bags", line), line
    assert "fleet [" in done.stderr and "24/24 bags" in done.stderr and "1 failed" in done.stderr


def test_a_fleet_row_equals_replay_json_on_the_same_bag(fleet, scheduler_run):
    _, bags = fleet
    doc, _ = scheduler_run
    bag = next(b for b in bags if not b.damaged and b.day == DAYS)
    done = run_cli("replay", str(bag.path), "--config", CONFIG, "--json")
    assert done.returncode == 0, done.stderr
    replayed = json.loads(done.stdout)
    row = by_path(doc["rows"])[str(bag.path.resolve())]
    assert replayed.pop("wall_s") > 0
    assert {k: row[k] for k in replayed} == replayed


def read_progress(proc: subprocess.Popen, state: dict) -> None:
    """Follow the progress bar on proc's stderr: state['done'] = bags done so far."""
    text = ""
    while chunk := proc.stderr.read(64):
        text += chunk
        found = re.findall(r"(\d+)/(\d+) bags", text[-400:])
        if found:
            state["done"] = int(found[-1][0])
    state["stderr"] = text


def start_fleet(*argv: str) -> tuple[subprocess.Popen, dict, threading.Thread]:
    proc = subprocess.Popen([HAMMER_ROS, "fleet", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=child_env())
    state = {"done": 0}
    reader = threading.Thread(target=read_progress, args=(proc, state), daemon=True)
    reader.start()
    return proc, state, reader


def test_sigkill_of_a_worker_mid_run_loses_no_bag(fleet, tmp_path):
    root, _ = fleet
    cluster = Cluster(tmp_path / "cluster")
    try:  # 10 solves per bag second: bags of ~0.2 s each, so that the kill meets tasks in flight
        proc, state, reader = start_fleet(str(root / "bags"), "--config", CONFIG, "--scheduler", cluster.address,
                                          "--out", str(tmp_path / "out"), "--solve-rate", "10", "--json")
        wait_for(lambda: state["done"] >= 3 or proc.poll() is not None, 240, "3 bags done")
        done_at_kill = state["done"]
        os.kill(cluster.workers[0].pid, signal.SIGKILL)
        stdout = proc.stdout.read()
        assert proc.wait(timeout=300) == 0, state.get("stderr", "")[-3000:]
        reader.join(10)
        proc.stdout.close(), proc.stderr.close()
        assert cluster.workers[0].wait(timeout=10) == -signal.SIGKILL
    finally:
        cluster.close()
    assert 3 <= done_at_kill < 23  # killed while tasks were in flight
    doc = json.loads(stdout)
    assert (doc["bags"], doc["ok"], doc["failed"]) == (24, 23, 1)
    assert len({r["path"] for r in doc["rows"]}) == 24


def test_ctrl_c_keeps_the_finished_bags_and_resume_finishes_the_rest(fleet, scheduler_run, tmp_path):
    root, _ = fleet
    out = tmp_path / "out"
    argv = (str(root / "bags"), "--config", CONFIG, "--workers", "1", "--batch", "1", "--out", str(out))
    proc, state, reader = start_fleet(*argv)
    wait_for(lambda: state["done"] >= 3 or proc.poll() is not None, 240, "3 bags done")
    proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=120)
    reader.join(10)
    assert code == 130, state.get("stderr", "")[-3000:]
    proc.stdout.close(), proc.stderr.close()
    kept, _ = read_rows(out / "fleet.parquet")
    assert 3 <= len(kept) < 24
    missing = re.search(r"(\d+) of 24 bags in .*fleet.parquet, (\d+) missing", state["stderr"])
    assert missing and int(missing[1]) == len(kept) and int(missing[2]) == 24 - len(kept)
    done = run_cli("fleet", *argv, "--resume", "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(done.stdout)
    assert (doc["bags"], doc["ok"], doc["failed"]) == (24, 23, 1)
    finished = by_path(read_rows(out / "fleet.parquet")[0])
    for row in kept:  # the kept rows were not run again
        assert finished[row["path"]]["seconds"] == row["seconds"]
    assert [(c["group"], c["quantity"], c["first_date"]) for c in doc["changes"]] == [
        (c["group"], c["quantity"], c["first_date"]) for c in scheduler_run[0]["changes"]]


def test_diagnose_adds_the_cause_and_gain_of_the_bag(fleet):
    from hammer_ros.cli import build_parser
    from hammer_ros.cli.replay import replay_settings
    from hammer_ros.fleet.sources import sources_from_paths
    from hammer_ros.fleet.tasks import FleetSettings, run_bag
    from hammer_ros.io.bags import load_msg_config, stream_specs

    _, bags = fleet
    args = build_parser().parse_args(["fleet", "x", "--config", CONFIG])
    params = load_msg_config(CONFIG)
    config, solve_rate = replay_settings(args, params, CONFIG)
    settings = FleetSettings(*stream_specs(None, None, params, CONFIG), config, solve_rate, diagnose=True)
    bag = next(b for b in bags if b.joint.dead_zone_day and b.day == DAYS)
    row = run_bag(settings, sources_from_paths([str(bag.path)])[0])
    assert row["error"] is None and row["model"]["samples"] == 3000
    # the plant is a Hammerstein system (a dead zone before linear dynamics): nothing to extend
    assert row["diagnosis"]["cause"] == "none" and row["diagnosis"]["gain"] is None, row["diagnosis"]
    assert row["diagnosis"]["confidence"] >= 0.5


def test_the_html_page_is_self_contained(scheduler_run):
    page = (scheduler_run[1] / "fleet.html").read_text()
    targets = re.findall(r"""(?:src|href)\s*=\s*["']?([^"'\s>]*)""", page, re.IGNORECASE)
    assert targets and all(t.startswith("data:") for t in targets), "external resource"
    assert "<link" not in page and "@import" not in page and "url(" not in page
    assert len(re.findall(r"src='data:image/png;base64,[A-Za-z0-9+/=]{1000,}'", page)) == len(JOINTS)
    assert "robot_01/joint2" in page and "Failed bags" in page


@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium (Debian package) not installed")
def test_the_html_page_renders_in_headless_chromium(scheduler_run, tmp_path):
    shot = tmp_path / "shot.png"
    subprocess.run(["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={shot}", "--window-size=1200,1600", (scheduler_run[1] / "fleet.html").as_uri()],
                   capture_output=True, timeout=120, check=False)
    import matplotlib.image

    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (1600, 1200)
    rows_with_ink = np.mean(np.std(pixels[..., :3], axis=1).max(axis=1) > 0.05)
    assert rows_with_ink > 0.5  # text and plots all the way down, not a blank or error page


@pytest.mark.parametrize("case, fragment", [
    ("no path column", "'path' column"),
    ("missing bag", "no such bag: robot_09/nope.mcap"),
    ("no topic", "'/nope'"),
    ("no bags", "no bags in this directory"),
    ("both cluster options", "--scheduler and --workers"),
    ("batch of zero bags", "--batch: must be >= 1"),
])
def test_bad_input_is_one_line_and_exit_2(fleet, tmp_path, capsys, case, fragment):
    from hammer_ros.cli import main

    root, _ = fleet
    manifest = tmp_path / "manifest.csv"
    argv = [str(root / "bags"), "--config", CONFIG]
    if case == "no path column":
        manifest.write_text("bag,robot\nx.mcap,robot_01\n")
        argv = ["--manifest", str(manifest), "--config", CONFIG]
    elif case == "missing bag":
        lines = (root / "bags" / "manifest.csv").read_text().splitlines()
        manifest.write_text("\n".join([*lines, "robot_09/nope.mcap,robot_09,joint1,2026-11-01"]) + "\n")
        argv = ["--manifest", str(manifest), "--config", CONFIG]
        shutil.copytree(root / "bags" / "robot_01", tmp_path / "robot_01")  # the other rows resolve
        shutil.copytree(root / "bags" / "robot_02", tmp_path / "robot_02")
    elif case == "no topic":
        argv = [str(root / "bags"), "--input", "/nope:data[:]", "--output", "/response:data[:]"]
    elif case == "no bags":
        (tmp_path / "empty").mkdir()
        argv = [str(tmp_path / "empty"), "--config", CONFIG]
    elif case == "batch of zero bags":
        argv += ["--batch", "0"]
    else:
        argv += ["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"]
    assert main(["fleet", *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and fragment in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "out" / "fleet.parquet").exists()  # found before any work


def test_a_scheduler_that_does_not_answer_is_exit_2_before_any_work(fleet, tmp_path):
    root, _ = fleet
    address = f"tcp://127.0.0.1:{free_port()}"
    started = time.monotonic()
    done = run_cli("fleet", str(root / "bags"), "--config", CONFIG, "--scheduler", address, "--out", str(tmp_path))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and address in lines[0] and "Traceback" not in done.stderr, done.stderr
    assert time.monotonic() - started < 60
    assert not (tmp_path / "fleet.parquet").exists()


def test_batch_size_keeps_small_fleets_one_bag_per_task_and_caps_large_ones():
    from hammer_ros.fleet.runner import MAX_BATCH, batch_size

    assert batch_size(24, 2) == 1  # the fleets of these tests: one bag per task
    assert batch_size(200, 2) == MAX_BATCH  # the bench: 25 tasks of 8 bags
    assert batch_size(40, 2) == 2  # each worker still gets >= 8 tasks
    assert batch_size(10_000, 32) == MAX_BATCH
    assert batch_size(0, 0) == 1


def test_default_tasks_shrink_to_single_bags_at_the_end():
    """``task_batches``: every bag once, in order; the bench's 200 bags on 2 workers in tasks of 8
    and then fewer, the last ones single bags (the workers finish together); ``--batch N`` keeps
    N bags per task."""
    from hammer_ros.fleet.runner import MAX_BATCH, TAIL_SHARE, task_batches

    bags = list(range(200))
    batches = task_batches(bags, 2)
    assert [b for batch in batches for b in batch] == bags
    sizes = [len(batch) for batch in batches]
    assert sizes[0] == MAX_BATCH and sizes == sorted(sizes, reverse=True) and sizes[-4:] == [1, 1, 1, 1]
    left = len(bags)
    for size in sizes:  # each task at most its share of what is left
        assert size <= max(1, math.ceil(left / (TAIL_SHARE * 2)))
        left -= size
    assert [len(b) for b in task_batches(bags, 2, 5)] == [5] * 40
    assert [len(b) for b in task_batches(list(range(24)), 2)] == [1] * 24


def test_sample_fleet_bags_hold_the_samples_asked_for(tmp_path):
    """``write_sample_fleet(samples=N)``: N samples per topic (the bench's fleet row sizes its bags so;
    the argument was once ignored and every bag held the default)."""
    from hammer_ros.fleet.sample_fleet import BATCH, SAMPLES
    from hammer_ros.io.bag_index import bag_message_counts

    joints = sample_joints(robots=1, joints=1, drift_day=None, dead_zone_day=None)
    for samples in (1000, SAMPLES):
        bag = write_sample_fleet(tmp_path / str(samples), joints, 1, samples=samples)[0]
        assert bag_message_counts(bag.path) == {"/cmd": samples // BATCH, "/response": samples // BATCH}
