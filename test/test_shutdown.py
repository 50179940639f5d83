"""Nothing is lost on SIGINT/SIGTERM: ``replay --out`` and the live node (``output_mcap``) finish
their MCAP so that ``rosbags`` reads it whole, with every result published before the signal
and the final model."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO
from ros_helpers import WAIT, Listener, RosProcess
from stamped_plant import NODE, WINDOW, Observer, StampedPlant, pole_error

from hammer_ros.ros.environment import DomainLease, child_environment

HAMMER_ROS = str(Path(sys.executable).parent / "hammer-ros")
JOINT_BAG = REPO / "bags" / "joint_state_saturation"
JOINT_CONFIG = REPO / "msg_config" / "joint_state_saturation.yaml"


def read_mcap(path: Path) -> dict[str, list]:
    """topic -> [(log time ns, message)] of every message, read by rosbags (independent reader):
    the ROS 2 messages deserialized, the Foxglove dashboard channels (JSON) parsed."""
    from rosbags.highlevel import AnyReader

    by_topic: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for connection, stamp, raw in reader.messages():
            message = (reader.deserialize(raw, connection.msgtype) if connection.ext.serialization_format == "cdr"
                       else json.loads(raw))
            by_topic.setdefault(connection.topic, []).append((stamp, message))
    return by_topic


def models_in(by_topic: dict[str, list]) -> list[dict]:
    return [json.loads(msg.data) for _, msg in by_topic.get("/hammer_ros/model", [])]


def wait_until(condition, timeout: float = WAIT, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def test_sigterm_mid_replay_leaves_a_complete_mcap_with_the_final_model(tmp_path):
    out, log = tmp_path / "results.mcap", tmp_path / "stderr.log"
    with open(log, "w") as err:
        proc = subprocess.Popen([HAMMER_ROS, "replay", str(JOINT_BAG), "--config", str(JOINT_CONFIG), "--solve-rate",
                                 "20", "--out", str(out), "--json"], stdout=subprocess.PIPE, stderr=err, text=True)

    def progress() -> float:
        done = re.findall(r"replay \[[# ]+\]\s+([\d.]+) %", log.read_text())
        return float(done[-1]) if done else 0.0

    wait_until(lambda: progress() >= 20.0, what="replay 20 % through the bag")
    proc.send_signal(signal.SIGTERM)
    stdout, _ = proc.communicate(timeout=WAIT)
    assert proc.returncode == 128 + signal.SIGTERM
    report = [line for line in log.read_text().split("\n") if line.startswith("hammer-ros: replay stopped")]
    match = re.fullmatch(r"hammer-ros: replay stopped by SIGTERM after (\d+) of 12000 messages; final model solved "
                         r"on the (\d+) samples read; (\d+) messages in .*results\.mcap", report[0])
    assert match, report
    final = json.loads(stdout)  # the final model, printed as for a whole run
    assert final["samples"] == int(match.group(2)) < 6000 and final["samples"] >= 1000
    by_topic = read_mcap(out)
    assert sum(len(messages) for messages in by_topic.values()) == int(match.group(3))
    models = models_in(by_topic)
    assert len(models) == final["solves"] + sum(m["stale"] for m in models)
    assert models[-1]["poles"] == final["poles"] and models[-1]["samples"] == min(final["samples"], 4000)


@pytest.mark.ros
def test_sigint_during_live_replay_keeps_every_published_result(ros_env, tmp_path):
    """replay --rate publishes on the graph and writes the file; everything a subscriber got
    before Ctrl-C is in the file, and the file ends with the final solve."""
    out = tmp_path / "live.mcap"
    listener = Listener(ros_env)
    try:
        observer = Observer(listener)
        with open(tmp_path / "replay.log", "w") as err:
            proc = subprocess.Popen([HAMMER_ROS, "replay", str(JOINT_BAG), "--config", str(JOINT_CONFIG), "--rate",
                                     "5", "--out", str(out), "--json"], env=ros_env, stdout=subprocess.PIPE,
                                    stderr=err, text=True)
        listener.wait_for(lambda: len(observer.models) >= 4, what="4 models published by replay --rate")
        proc.send_signal(signal.SIGINT)
        stdout, _ = proc.communicate(timeout=WAIT)
        received = list(observer.models)
    finally:
        listener.close()
    assert proc.returncode == 128 + signal.SIGINT
    written = models_in(read_mcap(out))
    assert all(model in written for model in received)
    assert len(written) > len(received) - 1 and written[-1]["poles"] == json.loads(stdout)["poles"]


@pytest.mark.ros
def test_sigterm_to_the_node_finishes_its_output_mcap_with_the_final_model(tmp_path):
    logs = tmp_path
    out = tmp_path / "node_results.mcap"
    with DomainLease() as lease:
        env = child_environment(lease.domain_id, log_dir=logs / "ros_log")
        node = RosProcess("hammer_ros.ros.node", {**NODE, "output_mcap": str(out)}, env, logs / "node.log")
        listener = Listener(env)
        try:
            observer = Observer(listener)
            plant = StampedPlant(listener)
            while not observer.count("received_response"):
                plant.send(100)
                observer.next_solve()
            model = observer.fresh_model(plant.send(WINDOW + 500)[-1])
            assert pole_error(model) < 0.05
            plant.send(300)  # samples the node has taken in but not yet solved on when the signal comes
            observer.settle(plant.last)
            received = list(observer.models)
        finally:
            listener.close()
            code = node.stop(signal.SIGTERM)
    assert code == 0, node.output()[-2000:]
    by_topic = read_mcap(out)
    written = models_in(by_topic)
    assert all(m in written for m in received)
    final_line = next(line for line in node.output().splitlines() if line.startswith("hammer_ros_node: final model: "))
    final = json.loads(final_line.split(": ", 2)[2])
    assert written[-1] == final and not final["stale"]
    assert final["stamp"] == pytest.approx(plant.last) and pole_error(final) < 0.05  # all samples sent, solved
    assert {"/hammer_ros/poles", "/hammer_ros/zeros", "/hammer_ros/markov", "/diagnostics"} <= set(by_topic)
    last_status = by_topic["/diagnostics"][-1][1].status[0]
    assert last_status.level == 0 and int({kv.key: kv.value for kv in last_status.values}["aligned"]) > WINDOW
    assert np.isfinite(final["fit_percent"])


def test_a_node_that_cannot_write_its_output_mcap_exits_2_at_startup(ros_env, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "-p",
                           f"output_mcap:={tmp_path}/missing/dir/out.mcap"], env=ros_env, capture_output=True,
                          text=True, timeout=WAIT)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "output_mcap: " in proc.stderr and "No such file or directory" in proc.stderr
