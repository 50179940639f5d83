"""Several channels in one live node: a params file with three channels over one
sensor_msgs/JointState topic (joints by name) and one std_msgs/Float64MultiArray command topic,
fed in real time by this process from three known Hammerstein plants; each channel's
~/NAME/model converges to its own plant's poles, /diagnostics carries one status per channel
(a message without one joint counted by that joint's channel alone), and ~/solve answers for
every channel; the node's one Foxglove server serves every channel's dashboard under
/hammer_ros/NAME/dashboard/ (the per-channel layout reads only channels it advertises), and its
one output_mcap records every channel's results under /hammer_ros/NAME/ (read with rosbags). A
bad channels list exits 2 with one line."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from foxglove_client import FoxgloveClient
from ros_helpers import Listener, RosProcess, free_port
from schema_check import layout_paths, layout_topic, mismatches

from hammer_ros.identification.linear import LinearModel, root_rss_error
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.messages.dashboard import CHANNELS, dashboard_topic, foxglove_layout

pytestmark = pytest.mark.ros

RATE = 200.0
SECONDS = 20.0  # the longest feed; the test stops as soon as every channel converged
JOINTS = {"shoulder": "shoulder_pan_joint", "elbow": "elbow_joint", "wrist": "wrist_1_joint"}
PLANTS = {"shoulder": LinearModel.from_zeros_poles([-0.5], [0.9 + 0.2j, 0.9 - 0.2j], dc_gain=1.0),
          "elbow": LinearModel.from_zeros_poles([-0.5], [0.8 + 0.4j, 0.8 - 0.4j], dc_gain=1.0),
          "wrist": LinearModel.from_zeros_poles([], [0.7], dc_gain=1.0)}  # first order: its own `order: 1`
POLE_TOLERANCE = 0.02
MISSING = 5  # JointState messages without elbow_joint, sent last
WINDOW = 1000  # the window of PARAMS
PARAMS = """\
hammer_ros:
  ros__parameters:
    excitation_topic: /arm/cmd
    excitation_type: std_msgs/msg/Float64MultiArray
    response_topic: /arm/joint_states
    response_type: sensor_msgs/msg/JointState
    sample_rate: 200.0
    window: 1000
    order: 2
    delay: 1
    solve_rate: 5.0
    solver_process: false
    diagnosis_period: 0.0
    channels: [shoulder, elbow, wrist]
    shoulder: {excitation_field: "data[0]", response_field: "velocity[shoulder_pan_joint]"}
    elbow: {excitation_field: "data[1]", response_field: "velocity[elbow_joint]"}
    wrist: {excitation_field: "data[2]", response_field: "velocity[wrist_1_joint]", order: 1}
"""


def _pole_error(name: str, model: dict) -> float:
    return root_rss_error(PLANTS[name].poles, np.array([complex(re, im) for re, im in model["poles"]]))


def test_three_channels_converge_each_to_its_own_joint(ros_env, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray
    from std_srvs.srv import Trigger

    rng = np.random.default_rng(3)
    n = int(SECONDS * RATE)
    commands = {name: 0.5 * rng.standard_normal(n) for name in JOINTS}
    velocity = {name: simulate_hammerstein(commands[name], lambda u: u + 0.5 * u**3, PLANTS[name])
                + 0.002 * rng.standard_normal(n) for name in JOINTS}
    params, recorded, port = tmp_path / "arm.yaml", tmp_path / "results.mcap", free_port()
    params.write_text(PARAMS + f"    foxglove_port: {port}\n    output_mcap: {recorded}\n")
    node = RosProcess("hammer_ros.ros.node", {}, ros_env, tmp_path / "node.log", params_file=params)
    listener = Listener(ros_env)
    fox = None
    try:
        models = {name: listener.subscribe_json(f"/hammer_ros/{name}/model") for name in JOINTS}
        served = {name: dashboard_topic("model", f"hammer_ros/{name}") for name in JOINTS}
        arrays: list[dict[str, dict[str, str]]] = []  # per /diagnostics: status name -> values
        listener.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: arrays.append(
            {s.name: {kv.key: kv.value for kv in s.values} for s in m.status}), 10)
        cmd = listener.node.create_publisher(Float64MultiArray, "/arm/cmd", 100)
        joints = listener.node.create_publisher(JointState, "/arm/joint_states", 100)
        listener.wait_for(lambda: cmd.get_subscription_count() and joints.get_subscription_count(),
                          what="the node's subscriptions")
        assert joints.get_subscription_count() == 1  # one subscription for the three channels
        fox = FoxgloveClient(port, tuple(served.values()))  # (the server is up before the subscriptions)
        names = list(JOINTS.values())[::-1]  # not the channels' order: looked up by name
        joint_channel = {joint: name for name, joint in JOINTS.items()}
        start = time.monotonic()

        def converged() -> bool:
            return all(m and m[-1]["samples"] == WINDOW and _pole_error(name, m[-1]) < POLE_TOLERANCE
                       for name, m in models.items())

        for k in range(n):
            cmd.publish(Float64MultiArray(data=[float(commands[c][k]) for c in JOINTS]))
            joints.publish(JointState(name=names, velocity=[float(velocity[joint_channel[j]][k]) for j in names]))
            if k % 20 == 0 and converged():
                break
            deadline = start + (k + 1) / RATE
            while (left := deadline - time.monotonic()) > 0:
                listener.executor.spin_once(timeout_sec=left)
        listener.wait_for(converged, timeout=10, what=f"every channel's pole RSS error < {POLE_TOLERANCE}")
        assert models["wrist"][-1]["order"] == 1 and models["shoulder"][-1]["order"] == 2
        for name in JOINTS:
            print(f"{name}: pole RSS error {_pole_error(name, models[name][-1]):.4f} after "
                  f"{models[name][-1]['samples']} samples")
        assert fox.error is None and set(fox.channels) == {
            dashboard_topic(what, f"hammer_ros/{name}") for name in JOINTS for what in CHANNELS}
        for name, topic in served.items():  # the channel's own dashboard model: its ~/NAME/model of the same solve
            def same_solve(name=name, topic=topic):
                ros = {m["stamp"]: m for m in models[name]}
                return [(m, ros[m["stamp"]]) for m in fox.messages[topic] if m["stamp"] in ros]

            dashboard_model, ros_model = listener.wait_for(same_solve, what=f"{topic} of a ~/{name}/model solve")[-1]
            assert {k: v for k, v in dashboard_model.items() if k != "timestamp"} == ros_model
            assert mismatches(CHANNELS["model"][1], dashboard_model) == []
        layout = foxglove_layout("hammer_ros", list(JOINTS))
        assert [tab["title"] for tab in layout["configById"]["Tab!channels"]["tabs"]] == list(JOINTS)
        layout_topics = {layout_topic(path) for path in layout_paths(layout)}
        assert layout_topics <= set(fox.channels) and len(layout_topics) == len(JOINTS) * len(CHANNELS)
        expected = [f"hammer_ros/{name}: identification" for name in JOINTS]
        listener.wait_for(lambda: arrays and list(arrays[-1]) == expected, what="one /diagnostics status per channel")
        client = listener.node.create_client(Trigger, "/hammer_ros/solve")
        listener.wait_for(client.service_is_ready, what="~/solve")
        answer = listener.wait_future(lambda: client.call_async(Trigger.Request()))
        assert answer.success, answer.message
        solved = json.loads(answer.message)
        assert set(solved) == set(JOINTS)
        assert all(_pole_error(name, solved[name]) < POLE_TOLERANCE for name in JOINTS)
        others = [j for j in names if j != "elbow_joint"]
        for _ in range(MISSING):  # without elbow_joint: counted by the elbow channel alone
            joints.publish(JointState(name=others, velocity=[0.0] * len(others)))

        def field_errors() -> dict[str, int]:
            return {name.split("/")[1].split(":")[0]: int(values["response_field_errors"])
                    for name, values in (arrays[-1] if arrays else {}).items()}

        listener.wait_for(lambda: field_errors() == {"shoulder": 0, "elbow": MISSING, "wrist": 0},
                          what=f"{MISSING} field errors of the elbow channel alone")
        assert node.process.poll() is None
    finally:
        if fox is not None:
            fox.close()
        listener.close()
        code = node.stop(signal.SIGINT, timeout=20)
    log = (tmp_path / "node.log").read_text()
    assert code == 0, log[-3000:]
    from rosbags.highlevel import AnyReader

    with AnyReader([recorded]) as reader:  # an independent reader: every channel's results under its name
        written = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    for name in JOINTS:
        final = [json.loads(m.data) for topic, m in written if topic == f"/hammer_ros/{name}/model"]
        assert len(final) >= 2 and _pole_error(name, final[-1]) < POLE_TOLERANCE, name
        assert any(topic == f"/hammer_ros/{name}/poles" for topic, _ in written)
    statuses = {s.name for topic, m in written if topic == "/diagnostics" for s in m.status}
    assert statuses == {f"hammer_ros/{name}: identification" for name in JOINTS}
    assert not any(topic.startswith("/hammer_ros/model") for topic, _ in written)  # nothing channel-less


@pytest.mark.parametrize("change, needle", [
    ("channels: [shoulder, elbow, shoulder]", "channels: duplicate channel 'shoulder'"),
    ("channels: [shoulder, 2nd]", "channels[1]: name '2nd' must be a name like"),
    ("order: 1, foxglove_port: 8765}", "channel 'wrist': foxglove_port: one for the node and every channel"),
])
def test_bad_channels_exit_2_with_one_line(ros_env, tmp_path, change, needle):
    params = tmp_path / "bad.yaml"
    if change.startswith("order"):  # the node's Foxglove server set for one channel
        text = PARAMS.replace("order: 1}", change)
    else:
        text = PARAMS.replace("    channels: [shoulder, elbow, wrist]\n", f"    {change}\n")
    params.write_text(text)
    done = subprocess.run([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "--params-file", str(params)],
                          env=ros_env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if "error" in line]
    assert len(lines) == 1 and needle in lines[0], done.stderr


def test_one_channel_is_the_single_channel_node_of_its_parameters(ros_env, tmp_path):
    from rclpy.parameter import parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    params = tmp_path / "one.yaml"
    params.write_text(PARAMS.replace("channels: [shoulder, elbow, wrist]", "channels: [wrist]")
                      .replace("    shoulder: {", "    # shoulder: {").replace("    elbow: {", "    # elbow: {"))
    node = RosProcess("hammer_ros.ros.node", {}, ros_env, tmp_path / "node.log", params_file=params)
    listener = Listener(ros_env)
    try:
        client = AsyncParameterClient(listener.node, "hammer_ros")
        listener.wait_for(client.services_are_ready, what="the node's parameter services")
        names = ["excitation_field", "response_field", "order"]
        values = listener.wait_future(lambda: client.get_parameters(names)).values
        assert [parameter_value_to_python(v) for v in values] == ["data[2]", "velocity[wrist_1_joint]", 1]
        topics = listener.wait_for(lambda: {t for t, _ in listener.node.get_topic_names_and_types()} >=
                                   {"/hammer_ros/model", "/hammer_ros/poles"} and
                                   {t for t, _ in listener.node.get_topic_names_and_types()},
                                   what="the node's output topics")
        assert not any(t.startswith("/hammer_ros/wrist") for t in topics)
    finally:
        listener.close()
        code = node.stop(signal.SIGINT, timeout=20)
    assert code == 0, (tmp_path / "node.log").read_text()[-3000:]
