"""Joints by name (``position[elbow]``): the index is looked up in every message's ``name``
array, so a bag whose JointState names come in a different order in every message (written by
rosbags) gives exactly the samples, and the model, of the ordered bag; a message without the
name is counted and skipped (one warning), never read at another joint's index."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.errors import UsageError
from hammer_ros.identification.linear import LinearModel, root_rss_error
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.io.bags import load_bag_record
from hammer_ros.messages.field_path import MissingName, extract_samples, parse_field_path

JOINTS = ("shoulder_pan_joint", "elbow_joint", "wrist_1_joint")
PLANTS = {name: LinearModel.from_zeros_poles([-0.5], [pole, np.conj(pole)], dc_gain=1.0)
          for name, pole in zip(JOINTS, (0.9 + 0.2j, 0.8 + 0.4j, 0.7 + 0.1j), strict=True)}
SAMPLES, START_NS, PERIOD_NS = 3000, 1_700_000_000_000_000_000, 10_000_000
MISSING = (100, 1000, 2000)  # messages without elbow_joint


def write_arm_bag(path, shuffle: bool) -> dict[str, np.ndarray]:
    """/arm_cmd Float64MultiArray [u_0, u_1, u_2] and /joint_states JointState (velocity_j =
    G_j F(u_j), F = cubic) at 100 Hz, names in a random order per message when ``shuffle``;
    ``MISSING`` messages lack elbow_joint. Returns the commands by joint name."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    rng = np.random.default_rng(7)
    commands = {name: 0.5 * rng.standard_normal(SAMPLES) for name in JOINTS}
    velocity = {name: simulate_hammerstein(commands[name], lambda u: u + 0.5 * u**3, PLANTS[name])
                for name in JOINTS}
    order_rng = np.random.default_rng(8)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        cmd = writer.add_connection("/arm_cmd", "std_msgs/msg/Float64MultiArray", typestore=store)
        joints = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        layout = types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        for k in range(SAMPLES):
            t = START_NS + k * PERIOD_NS
            data = np.array([commands[name][k] for name in JOINTS])
            writer.write(cmd, t, store.serialize_cdr(types["std_msgs/msg/Float64MultiArray"](
                layout=layout, data=data), "std_msgs/msg/Float64MultiArray"))
            names = [n for n in JOINTS if not (k in MISSING and n == "elbow_joint")]
            if shuffle:
                names = [names[i] for i in order_rng.permutation(len(names))]
            stamp = types["builtin_interfaces/msg/Time"](sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
            msg = types["sensor_msgs/msg/JointState"](
                header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=""), name=names,
                position=np.array([commands[n][k] for n in names]),  # any numbers: not read here
                velocity=np.array([velocity[n][k] for n in names]), effort=np.array([], dtype=float))
            writer.write(joints, t + 500_000, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
    return commands


@pytest.fixture(scope="module")
def arm_bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("arm")
    commands = write_arm_bag(root / "ordered", shuffle=False)
    write_arm_bag(root / "shuffled", shuffle=True)
    return root / "ordered", root / "shuffled", commands


def test_a_named_element_is_looked_up_in_each_message():
    from sensor_msgs.msg import JointState

    path = parse_field_path("velocity[elbow_joint]")
    assert path.steps[0].element_name == "elbow_joint" and parse_field_path("velocity[2]").steps[0].indices == (2,)
    first = JointState(name=["elbow_joint", "wrist_1_joint"], velocity=[1.0, 2.0])
    second = JointState(name=["wrist_1_joint", "elbow_joint"], velocity=[2.0, 1.0])
    assert extract_samples(first, path).tolist() == extract_samples(second, path).tolist() == [1.0]
    with pytest.raises(MissingName, match=r"^field 'velocity\[elbow_joint\]': no 'elbow_joint' in this message's"):
        extract_samples(JointState(name=["wrist_1_joint"], velocity=[2.0]), path)


def test_a_reordered_bag_gives_the_samples_of_the_ordered_bag(arm_bags, capsys):
    ordered, shuffled, commands = arm_bags
    for joint, index in (("shoulder_pan_joint", 0), ("wrist_1_joint", 2)):
        specs = (f"/arm_cmd:data[{index}]", f"/joint_states:velocity[{joint}]")
        a, b = load_bag_record(ordered, *specs), load_bag_record(shuffled, *specs)
        np.testing.assert_array_equal(a.v, commands[joint])
        np.testing.assert_array_equal(b.y, a.y)
    capsys.readouterr()
    specs = ("/arm_cmd:data[1]", "/joint_states:velocity[elbow_joint]")
    record = load_bag_record(shuffled, *specs)  # the messages without elbow_joint: skipped, counted
    np.testing.assert_array_equal(record.y, load_bag_record(ordered, *specs).y)
    warning = capsys.readouterr().err.split("\n")[0]
    assert f"{len(MISSING)} message(s) on /joint_states skipped" in warning
    assert "no 'elbow_joint' in this message's name" in warning


def test_replay_of_a_reordered_bag_gives_the_model_of_the_ordered_bag(arm_bags, capsys):
    ordered, shuffled, _ = arm_bags
    models = []
    for bag in (ordered, shuffled):
        argv = ["replay", str(bag), "--input", "/arm_cmd:data[1]", "--output", "/joint_states:velocity[elbow_joint]",
                "--order", "2", "--window", "3000", "--json"]
        assert main(argv) == 0
        models.append(json.loads(capsys.readouterr().out))
    assert models[0]["poles"] == models[1]["poles"] and models[0]["b"] == models[1]["b"]
    found = np.array([complex(*p) for p in models[1]["poles"]])
    assert root_rss_error(PLANTS["elbow_joint"].poles, found) < 0.01


def test_the_node_reads_a_named_element_from_the_serialized_message():
    """The node's raw-CDR fast path reads the message's own ``name`` strings: the value of the
    named joint whatever the order, MissingName without it; a type without ``name`` is refused."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from hammer_ros.ros.message_types import raw_extractor
    from hammer_ros.ros.node_core import check_field

    path = parse_field_path("velocity[elbow_joint]")
    extract = raw_extractor(JointState, path)
    for names in (["elbow_joint", "wrist_1_joint"], ["wrist_1_joint", "shoulder_pan_joint", "elbow_joint"]):
        msg = JointState(name=names, velocity=[float(len(n)) for n in names])
        msg.header.stamp.sec = 5
        assert extract(serialize_message(msg)) == (float(len("elbow_joint")), 5.0)
    with pytest.raises(MissingName):
        extract(serialize_message(JointState(name=["wrist_1_joint"], velocity=[1.0])))
    check_field(JointState, path)
    with pytest.raises(UsageError, match=r"^field 'data\[elbow_joint\]': \[elbow_joint\] is looked up in a sibling"):
        check_field(Float64MultiArray, parse_field_path("data[elbow_joint]"))


ARM_CONFIG = """\
hammer_ros:
  ros__parameters:
    excitation_topic: /arm_cmd
    excitation_type: std_msgs/msg/Float64MultiArray
    response_topic: /joint_states
    response_type: sensor_msgs/msg/JointState
    order: 2
    window: 3000
    channels: [shoulder, elbow, wrist]
    shoulder: {excitation_field: "data[0]", response_field: "velocity[shoulder_pan_joint]"}
    elbow: {excitation_field: "data[1]", response_field: "velocity[elbow_joint]", method: plls-hammerstein}
    wrist: {excitation_field: "data[2]", response_field: "velocity[wrist_1_joint]"}
"""


def test_three_channels_over_one_joint_state_replay_to_each_joints_model(arm_bags, capsys, tmp_path):
    """One pass over the shuffled bag, the two topics shared by three channels: each channel's
    model is the single-channel replay's, and the right joint's."""
    _, shuffled, _ = arm_bags
    config = tmp_path / "arm.yaml"
    config.write_text(ARM_CONFIG)
    out = tmp_path / "arm.mcap"
    assert main(["replay", str(shuffled), "--config", str(config), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["channels"]) == {"shoulder", "elbow", "wrist"}
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as reader:
        topics = {c.topic for c in reader.connections}
    assert {f"/hammer_ros/{name}/{what}" for name in doc["channels"] for what in ("model", "poles")} <= topics
    assert doc["samples"] == sum(c["samples"] for c in doc["channels"].values()) and doc["wall_s"] > 0
    assert doc["channels"]["elbow"]["method"] == "plls-hammerstein"
    for channel, joint, index in (("shoulder", "shoulder_pan_joint", 0), ("elbow", "elbow_joint", 1),
                                  ("wrist", "wrist_1_joint", 2)):
        found = np.array([complex(*p) for p in doc["channels"][channel]["poles"]])
        assert root_rss_error(PLANTS[joint].poles, found) < 0.05, channel  # the pair 0.7 +- 0.1j: 0.04
        method = ["--method", "plls-hammerstein"] if channel == "elbow" else []
        assert main(["replay", str(shuffled), "--input", f"/arm_cmd:data[{index}]", "--output",
                     f"/joint_states:velocity[{joint}]", "--order", "2", "--window", "3000", *method, "--json"]) == 0
        single = json.loads(capsys.readouterr().out)
        assert single["poles"] == doc["channels"][channel]["poles"]


def test_several_channels_diagnose_and_write_dashboards_per_channel(arm_bags, capsys, tmp_path):
    """``--diagnose`` and ``--dashboard-out`` with three channels: each channel's final window
    diagnosed (its baseline's poles the joint's), in its JSON entry, in --out as
    /hammer_ros/NAME/diagnosis at the channel's final stamp, and in the dashboard file under
    /hammer_ros/NAME/dashboard/."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    from hammer_ros.diagnosis.causes import CAUSES
    from hammer_ros.messages.dashboard import dashboard_topic

    _, shuffled, _ = arm_bags
    config = tmp_path / "arm.yaml"
    config.write_text(ARM_CONFIG)
    out, dashboard_out = tmp_path / "arm.mcap", tmp_path / "dash.mcap"
    doc = run_json(capsys, "replay", str(shuffled), "--config", str(config), "--out", str(out), "--dashboard-out",
                   str(dashboard_out), "--diagnose", "--json")
    with AnyReader([out]) as reader:
        messages = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    with open(dashboard_out, "rb") as f:
        dashboard: dict[str, list[dict]] = {}
        for _, channel, message in make_reader(f).iter_messages():
            dashboard.setdefault(channel.topic, []).append(json.loads(message.data))
    for name, joint in (("shoulder", "shoulder_pan_joint"), ("elbow", "elbow_joint"), ("wrist", "wrist_1_joint")):
        diagnosis = doc["channels"][name]["diagnosis"]
        assert diagnosis["samples"] == 3000 and diagnosis["cause"] in CAUSES
        found = np.array([complex(*p) for p in diagnosis["baseline"]["poles"]])
        assert root_rss_error(PLANTS[joint].poles, found) < 0.05, name  # noise-free: the joint's plant
        written = [(t, json.loads(m.data)) for topic, t, m in messages if topic == f"/hammer_ros/{name}/diagnosis"]
        assert [d for _, d in written] == [diagnosis]
        assert written[0][0] == max(t for topic, t, _ in messages if topic.startswith(f"/hammer_ros/{name}/"))
        node = f"hammer_ros/{name}"
        shown = dashboard[dashboard_topic("diagnosis", node)]
        assert [{k: v for k, v in d.items() if k != "timestamp"} for d in shown] == [diagnosis]
        models = dashboard[dashboard_topic("model", node)]
        assert len(models) == doc["channels"][name]["solves"]  # every solve's model, on the channel's own topic
    assert not any(topic.startswith("/hammer_ros/dashboard/") for topic in dashboard)  # no channel-less topics


@pytest.mark.parametrize(("change", "reason"), [
    ("channels: [shoulder, elbow, shoulder]", "channels: duplicate channel 'shoulder'"),
    ("channels: [shoulder, 2nd]", "channels[1]: name '2nd' must be a name like"),
    ("channels: [shoulder, elbow]", "wrist: parameters of a channel 'wrist' that is not in channels (shoulder, elbow)"),
    ("channels: [shoulder, {name: elbow}]", "channels: expected a list of channel names"),
    ("channels: [shoulder, elbow, wrist]\n    wrist: {excitation_field: \"data[2]\", response_field: \"velocity[a]\", "
     "ordr: 2}", "channel 'wrist': unknown parameter 'ordr'"),
])
def test_bad_channel_lists_exit_2_naming_the_channel(arm_bags, capsys, tmp_path, change, reason):
    _, shuffled, _ = arm_bags
    text = ARM_CONFIG.replace("    channels: [shoulder, elbow, wrist]\n", f"    {change}\n")
    if "ordr" in change:
        text = text.replace('    wrist: {excitation_field: "data[2]", response_field: "velocity[wrist_1_joint]"}\n', "")
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    assert main(["replay", str(shuffled), "--config", str(config), "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and "\n" not in err, err


def test_identify_reads_one_channel(arm_bags, capsys, tmp_path):
    _, shuffled, _ = arm_bags
    config = tmp_path / "arm.yaml"
    config.write_text(ARM_CONFIG)
    assert main(["identify", str(shuffled), "--config", str(config)]) == 2
    assert "has 3 channels (shoulder, elbow, wrist); identify and diagnose read one pair" in capsys.readouterr().err
    others = ("    shoulder:", "    wrist:")
    lines = [line for line in ARM_CONFIG.splitlines(keepends=True) if not line.startswith(others)]
    config.write_text("".join(lines).replace("channels: [shoulder, elbow, wrist]", "channels: [elbow]"))
    one = run_json(capsys, "replay", str(shuffled), "--config", str(config), "--json")
    assert "channels" not in one and one["method"] == "plls-hammerstein"  # one channel: today's JSON
    assert run_json(capsys, "identify", str(shuffled), "--config", str(config), "--json")["method"] == "cls-markov"


def run_json(capsys, *argv) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.ros
def test_the_live_node_reads_joints_by_name_and_counts_a_missing_one(ros_env, tmp_path):
    """The demo plant's JointState (name ["joint"]): ``position[joint]`` is read in every
    message, ``position[elbow_joint]`` is in none of them: counted and named in /diagnostics,
    never read from another joint, and the node keeps running."""
    import signal

    from ros_helpers import Listener, RosProcess

    plant = RosProcess("hammer_ros.ros.plant_node", {"rate": 200.0, "message_type": "joint_state"}, ros_env,
                       tmp_path / "plant.log")
    node = RosProcess("hammer_ros.ros.node", {
        "excitation_type": "sensor_msgs/msg/JointState", "excitation_field": "position[joint]",
        "response_type": "sensor_msgs/msg/JointState", "response_field": "position[elbow_joint]", "solve_rate": 5.0},
        ros_env, tmp_path / "node.log")
    listener = Listener(ros_env)
    try:
        diagnostics = listener.subscribe_diagnostics()
        status = listener.wait_for(lambda: [d for d in diagnostics if int(d["response_field_errors"]) > 0],
                                   what="diagnostics counting the missing joint")[-1]
        assert status["level"] == 1 and "no 'elbow_joint' in this message's name (joint)" in status["message"]
        assert int(status["excitation_field_errors"]) == 0 and int(status["received_excitation"]) > 0
        assert int(status["received_response"]) == 0 and node.process.poll() is None
    finally:
        listener.close()
        codes = (node.stop(signal.SIGINT), plant.stop(signal.SIGINT))
    assert codes == (0, 0), node.output()[-2000:]
