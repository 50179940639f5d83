"""``hammer-ros replay``: the streaming engine on a bag equals ``identify`` on the same samples;
``--out`` is a valid MCAP that an independent reader (rosbags) reads back intact; bad input
exits 2 with one line; ``--rate`` publishes on a live (private) ROS 2 graph."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from make_sample_bags import G1, RESONANT

from hammer_ros.cli import main
from hammer_ros.diagnosis.causes import CAUSES
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.messages.dashboard import CHANNELS, dashboard_topic

REPO = Path(__file__).resolve().parents[1]
HAMMER_ROS = str(Path(sys.executable).parent / "hammer-ros")
FLOAT64_BAG = "bags/float64_cubic_g1.mcap"
JOINT_BAG = "bags/joint_state_saturation"  # written by rosbags (rosbag2 directory, MCAP storage)


def run_json(capsys, *argv) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def poles(doc) -> np.ndarray:
    return np.array([complex(re, im) for re, im in doc["poles"]])


@pytest.fixture(autouse=True)
def in_repo(monkeypatch):
    monkeypatch.chdir(REPO)


def test_replay_of_a_rosbags_bag_equals_identify_on_the_same_samples(capsys):
    common = ["--input", "/cmd:data", "--output", "/joint_states:velocity[0]", "--order", "2", "--tau-max", "80"]
    batch = run_json(capsys, "identify", JOINT_BAG, *common, "--json")
    streamed = run_json(capsys, "replay", JOINT_BAG, *common, "--window", "6000", "--json")
    assert streamed["samples"] == 6000 and streamed["solves"] >= 60 and streamed["wall_s"] > 0
    assert root_rss_error(poles(batch), poles(streamed)) < 1e-9
    np.testing.assert_allclose(streamed["a"], batch["a"], atol=1e-9)
    np.testing.assert_allclose(streamed["b"], batch["b"], atol=1e-9)
    assert root_rss_error(RESONANT.poles, poles(streamed)) < 0.02
    # a sliding window of 3000 samples: identify on the last 3000 aligned samples
    windowed = run_json(capsys, "replay", JOINT_BAG, *common, "--window", "3000", "--json")
    assert windowed["samples"] == 6000
    assert root_rss_error(poles(windowed), poles(batch)) > 1e-6  # not the whole record any more
    assert root_rss_error(RESONANT.poles, poles(windowed)) < 0.03


def test_replay_out_mcap_is_read_back_intact_by_rosbags(capsys, tmp_path):
    """Every message of --out deserialises in rosbags, stamped exactly as the input sample it was
    solved at; --dashboard-out holds the dashboard channels, each message declared by its schema."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader
    from schema_check import mismatches

    out, dashboard_out = tmp_path / "results.mcap", tmp_path / "dashboard.mcap"
    doc = run_json(capsys, "replay", FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml",
                   "--solve-rate", "1", "--out", str(out), "--dashboard-out", str(dashboard_out), "--json")
    with AnyReader([out]) as reader:
        assert {c.ext.serialization_format for c in reader.connections} == {"cdr"}  # nothing else for ROS readers
        types = {c.topic: c.msgtype for c in reader.connections}
        messages = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    with AnyReader([Path(FLOAT64_BAG)]) as reader:
        input_stamps = {t for c, t, _ in reader.messages() if c.topic == "/cmd"}
    assert all(t in input_stamps for _, t, _ in messages)  # integer ns, exactly the input's
    assert all(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == t
               for _, t, msg in messages if hasattr(msg, "header"))
    with open(dashboard_out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.topic: (c.message_encoding, summary.schemas[c.schema_id]) for c in summary.channels.values()}
        dashboard = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in reader.iter_messages()]
    solved = [name for name in CHANNELS if not name.startswith("diagnosis")]  # no --diagnose
    assert set(channels) == {dashboard_topic(name) for name in solved}
    for name in solved:
        schema_name, schema = CHANNELS[name]
        encoding, stored = channels[dashboard_topic(name)]
        assert (encoding, stored.name, stored.encoding, json.loads(stored.data)) == ("json", schema_name,
                                                                                     "jsonschema", schema)
    for topic, log_time, message in dashboard:
        assert mismatches(CHANNELS[topic.rsplit("/", 1)[1]][1], message) == [], topic
        assert log_time in input_stamps
        assert log_time == message["timestamp"]["sec"] * 10**9 + message["timestamp"]["nsec"]
    joint_state = "sensor_msgs/msg/JointState"
    assert types == {"/hammer_ros/model": "std_msgs/msg/String", "/hammer_ros/poles": joint_state,
                     "/hammer_ros/zeros": joint_state, "/hammer_ros/markov": joint_state,
                     "/hammer_ros/nonlinearity": "geometry_msgs/msg/PolygonStamped",
                     "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
    by_topic: dict[str, list] = {}
    for topic, stamp_ns, msg in messages:
        by_topic.setdefault(topic, []).append((stamp_ns, msg))
    solves = doc["solves"]
    assert all(len(by_topic[t]) == solves for t in types if t != "/diagnostics")
    assert len(by_topic["/diagnostics"]) >= solves  # one per attempt, the first ones before the window fills
    # content: each solve's messages agree with its model JSON and carry its stamp
    for (t_model, model), (t_poles, pole_msg), (_, markov_msg), (_, curve) in zip(
            by_topic["/hammer_ros/model"], by_topic["/hammer_ros/poles"], by_topic["/hammer_ros/markov"],
            by_topic["/hammer_ros/nonlinearity"]):
        model_doc = json.loads(model.data)
        assert t_model == t_poles == pytest.approx(model_doc["stamp"] * 1e9, abs=200)  # float s, ns exactly
        assert pole_msg.header.stamp.sec + 1e-9 * pole_msg.header.stamp.nanosec == pytest.approx(model_doc["stamp"])
        assert list(pole_msg.name) == [f"p{i}_{part}" for i in range(3) for part in ("re", "im")]
        np.testing.assert_array_equal(pole_msg.position, np.ravel(model_doc["poles"]))
        np.testing.assert_array_equal(markov_msg.position, model_doc["markov"])
        points = np.array([[p.x, p.y] for p in curve.polygon.points])
        np.testing.assert_allclose(points, model_doc["nonlinearity"]["points"], rtol=1e-6, atol=1e-6)  # float32
    last = json.loads(by_topic["/hammer_ros/model"][-1][1].data)
    assert {k: last[k] for k in doc if k not in ("samples", "solves", "wall_s")} == {
        k: doc[k] for k in doc if k not in ("samples", "solves", "wall_s")}
    assert root_rss_error(G1.poles, poles(last)) < 0.02
    status = by_topic["/diagnostics"][-1][1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == 0 and status.name == "hammer_ros: identification"
    assert int(values["aligned"]) == 6000 and int(values["nan_skipped"]) == 0
    first = by_topic["/diagnostics"][0][1].status[0]
    assert first.level == 1 and first.message.startswith("window")


def test_replay_diagnose_writes_the_final_diagnosis_into_both_files(capsys, tmp_path):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    out, dashboard_out = tmp_path / "results.mcap", tmp_path / "dashboard.mcap"
    doc = run_json(capsys, "replay", JOINT_BAG, "--config", "msg_config/joint_state_saturation.yaml", "--solve-rate",
                   "1", "--out", str(out), "--dashboard-out", str(dashboard_out), "--diagnose", "--json")
    assert doc["diagnosis"]["samples"] == 4000 and doc["diagnosis"]["cause"] in CAUSES  # the final window
    with AnyReader([out]) as reader:
        messages = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    diagnosis = [(t, json.loads(msg.data)) for topic, t, msg in messages if topic == "/hammer_ros/diagnosis"]
    assert [d for _, d in diagnosis] == [doc["diagnosis"]]
    assert diagnosis[0][0] == max(t for _, t, _ in messages)  # stamped as the final results
    with open(dashboard_out, "rb") as f:
        dashboard = {c.topic: json.loads(m.data) for _, c, m in make_reader(f).iter_messages()}
    assert {k: v for k, v in dashboard[dashboard_topic("diagnosis")].items() if k != "timestamp"} == doc["diagnosis"]
    assert dashboard[dashboard_topic("diagnosis_log")]["message"].startswith("diagnosis of 4000 samples")


def test_readme_example_runs_as_a_console_script():
    proc = subprocess.run([HAMMER_ROS, "replay", FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("method   cls-markov (order 3)")
    assert "replay   6000 samples" in proc.stdout
    assert "replay [" in proc.stderr and "100.0 %" in proc.stderr  # the progress bar


@pytest.mark.parametrize(("argv", "reason"), [
    (["bags/missing.mcap", "--input", "/cmd:data", "--output", "/response:data"], "no such bag"),
    ([FLOAT64_BAG, "--input", "/cmd:data", "--output", "/nope:data"], "no topic '/nope'"),
    ([FLOAT64_BAG, "--input", "/cmd:dta", "--output", "/response:data[:]"], "no field 'dta' in Float64"),
    ([JOINT_BAG, "--input", "/cmd:data", "--output", "/joint_states:velocity[4]"], "index 4 out of range"),
    ([JOINT_BAG, "--config", "msg_config/float64_cubic_g1.yaml"], "no topic '/response'"),
    ([JOINT_BAG, "--input", "/cmd", "--output", "/joint_states:velocity[0]"], "--input: expected /topic:field"),
    ([JOINT_BAG, "--config", "msg_config/missing.yaml"], "no such config file"),
    ([FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--window", "20"], "--window: must be >="),
    ([FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--solve-rate", "0"], "--solve-rate: must be > 0"),
    (["README.md", "--input", "/cmd:data", "--output", "/response:data"], "not a .mcap file"),
    ([FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--dashboard-out", "d.json"],
     "--dashboard-out: d.json: the file name must end in .mcap"),
    ([FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--dashboard-out", "/no/such/dir/d.mcap"],
     "--dashboard-out: /no/such/dir/d.mcap: No such file or directory"),
    ([FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--dashboard-out", FLOAT64_BAG],
     "--dashboard-out: bags/float64_cubic_g1.mcap is the bag being replayed"),
])
def test_bad_input_exits_2_with_one_line(capsys, tmp_path, argv, reason):
    assert main(["replay", *argv, "--out", str(tmp_path / "x.mcap")]) == 2
    assert not (tmp_path / "x.mcap").exists()  # no output at all
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and captured.err.startswith("hammer-ros: error: ")
    assert reason in captured.err


def test_bad_bag_exits_2_from_the_console_script(tmp_path):
    proc = subprocess.run([HAMMER_ROS, "identify", str(tmp_path / "nope.mcap"), "--input", "/a:data",
                           "--output", "/b:data", "--json"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().count("\n") == 0 and "nope.mcap: no such bag" in proc.stderr


SUBSCRIBER = """
import json, sys, rclpy
from rclpy.qos import QoSProfile, DurabilityPolicy, ReliabilityPolicy
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("model_listener")
qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
models = []
node.create_subscription(String, "/hammer_ros/model", lambda m: models.append(json.loads(m.data)), qos)
print("READY", flush=True)
while rclpy.ok() and len(models) < 2:
    rclpy.spin_once(node, timeout_sec=0.1)
print(json.dumps(models[-1]), flush=True)
node.destroy_node()
rclpy.shutdown()
"""


@pytest.mark.ros
def test_rate_publishes_models_on_the_live_graph(ros_env):
    listener = subprocess.Popen([sys.executable, "-c", SUBSCRIBER], env=ros_env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
    try:
        assert listener.stdout.readline().strip() == "READY"
        replay = subprocess.run([HAMMER_ROS, "replay", FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml",
                                 "--rate", "20", "--json"], cwd=REPO, env=ros_env, capture_output=True, text=True,
                                timeout=60)
        assert replay.returncode == 0, replay.stderr
        assert json.loads(replay.stdout)["wall_s"] >= 60 / 20 * 0.9  # paced: a 60 s bag at 20 x real time
        out, _ = listener.communicate(timeout=30)
        model = json.loads(out.strip().splitlines()[-1])
        assert model["method"] == "cls-markov" and root_rss_error(G1.poles, poles(model)) < 0.05
    finally:
        if listener.poll() is None:
            listener.terminate()
            listener.wait(timeout=10)


def test_replay_refine_refines_every_solve_and_fits_at_least_as_well(capsys):
    args = ("replay", FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--solve-rate", "0.2", "--json")
    plain = run_json(capsys, *args)
    refined = run_json(capsys, *args, "--refine")
    assert "refined" in refined and "refined" not in plain
    assert refined["refined"]["cost"] <= refined["refined"]["cost_start"]
    assert refined["rms"] <= plain["rms"] * 1.02
    assert refined["samples"] == plain["samples"]


def test_the_solver_process_is_started_only_when_the_solves_outweigh_its_start(capsys, monkeypatch):
    """The sample bag's 2 solves per second (over 20 CLS solves, well below OVERLAP_SECONDS) run
    in process; with the threshold at zero the same replay runs them in a SolverProcess, with
    the same model (documented at the end only: the worker skips the others' documents)."""
    import hammer_ros.cli.replay as replay_cli

    started = []
    real = replay_cli.SolverProcess
    monkeypatch.setattr(replay_cli, "SolverProcess",
                        lambda *args, **options: started.append((args, options)) or real(*args, **options))
    argv = ("replay", FLOAT64_BAG, "--config", "msg_config/float64_cubic_g1.yaml", "--solve-rate", "2", "--json")
    alone = run_json(capsys, *argv)
    assert not started and alone["solves"] > 20
    monkeypatch.setattr(replay_cli, "OVERLAP_SECONDS", 0.0)
    beside = run_json(capsys, *argv)
    # no thread, no middleware in replay: forked, loaded; 8 snapshots a transfer; no --out: no documents but the last
    assert started == [(("fork", 8), {"documents": False})]
    for doc in (alone, beside):
        doc.pop("wall_s")
    assert beside == alone
