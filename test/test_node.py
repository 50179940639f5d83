"""End-to-end tests of the live node: a plant process and the node process over DDS (own
ROS_DOMAIN_ID, loopback), observed from a listener node in the test process."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import REPO
from ros_helpers import Listener, RosProcess

from hammer_ros.identification.linear import root_rss_error
from hammer_ros.ros.environment import DomainLease, child_environment

pytestmark = pytest.mark.ros

RATE = 500.0
PLANT = {"rate": RATE, "nonlinearity": "dead_zone", "threshold": 0.2, "amplitude": 0.5, "noise": 0.002, "seed": 7}
NODE = {"sample_rate": RATE, "order": 3, "delay": 2, "window": 4000, "solve_rate": 4.0, "diagnosis_period": 5.0,
        "diagnosis_window": 3500}
POLE_TOLERANCE = 0.02  # RSS, the acceptance bound


def roots(pairs) -> np.ndarray:
    return np.array([complex(re, im) for re, im in pairs])


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """Plant + node on a private graph for the whole module, and a listener in this process."""
    logs = tmp_path_factory.mktemp("live")
    with DomainLease() as lease:
        env = child_environment(lease.domain_id, log_dir=logs / "ros_log")
        plant = RosProcess("hammer_ros.ros.plant_node", PLANT, env, logs / "plant.log")
        node = RosProcess("hammer_ros.ros.node", NODE, env, logs / "node.log")
        listener = Listener(env)
        listener.truth = listener.subscribe_json("/plant/truth")
        listener.models = listener.subscribe_json("/hammer_ros/model")
        listener.diagnostics = listener.subscribe_diagnostics()
        listener.diagnoses = listener.subscribe_json("/hammer_ros/diagnosis")
        listener.env = env
        try:
            yield listener
        finally:
            listener.close()
            codes = {"node": node.stop(signal.SIGINT), "plant": plant.stop(signal.SIGINT)}
            assert codes == {"node": 0, "plant": 0}, f"{codes}\n{node.output()[-2000:]}"


def _set(listener: Listener, **values):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(listener.node, "hammer_ros")
    listener.wait_for(lambda: client.services_are_ready(), what="the node's parameter services")
    future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
    return listener.wait_future(future).results


def _wait_quiet(listener: Listener, seconds: float) -> None:
    """Spin until no model has arrived for ``seconds``."""
    seen, since = len(listener.models), time.monotonic()

    def quiet() -> bool:
        nonlocal seen, since
        if len(listener.models) != seen:
            seen, since = len(listener.models), time.monotonic()
        return time.monotonic() - since >= seconds

    listener.wait_for(quiet, what=f"{seconds:g} s without a new model")


def _get(listener: Listener, *names):
    from rclpy.parameter import parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(listener.node, "hammer_ros")
    listener.wait_for(lambda: client.services_are_ready(), what="the node's parameter services")
    values = listener.wait_future(lambda: client.get_parameters(list(names))).values
    return [parameter_value_to_python(v) for v in values]


def test_model_poles_converge_to_the_plant(live):
    truth = live.wait_for(lambda: live.truth and live.truth[-1], what="the plant's truth")

    def converged():
        return any(root_rss_error(roots(truth["poles"]), roots(m["poles"])) < POLE_TOLERANCE for m in live.models)

    live.wait_for(converged, timeout=60, what=f"a model with pole RSS error < {POLE_TOLERANCE}")
    model = live.models[-1]
    assert model["method"] == "cls-markov" and model["order"] == 3
    assert set(model) >= {"poles", "zeros", "a", "b", "markov", "nonlinearity", "fit_percent", "rms"}
    assert model["warnings"] == []  # a Gaussian input, a good fit: nothing to warn about
    assert root_rss_error(roots(truth["zeros"]), roots(model["zeros"])) < 0.1
    diagnostics = live.wait_for(lambda: [d for d in live.diagnostics[-1:] if d["level"] == 0],
                                what="diagnostics of a successful solve")[0]
    assert diagnostics["message"] == "model identified"
    assert float(diagnostics["received_rate_excitation_hz"]) == pytest.approx(RATE, rel=0.05)
    assert int(diagnostics["excitation_field_errors"]) == 0 and int(diagnostics["response_field_errors"]) == 0


def test_diagnosis_of_the_window_is_published(live):
    """~/diagnosis: the plant is a clean Hammerstein system (dead zone, linear block, small
    noise), so once the window is full its diagnosis (of the newest diagnosis_window samples,
    clear of the start of the record) must find nothing missing."""
    live.wait_for(lambda: [m for m in live.models if m["samples"] == NODE["window"]], timeout=60,
                  what="a model on a full window")
    seen = len(live.diagnoses)  # a diagnosis started before the window was full may still arrive first (load)
    full = live.wait_for(lambda: [d for d in live.diagnoses[seen:] if d["samples"] == NODE["diagnosis_window"]],
                         timeout=4 * NODE["diagnosis_period"], what="a diagnosis of a full window")[-1]
    assert NODE["diagnosis_window"] < NODE["window"]
    assert max(d["samples"] for d in live.diagnoses) == NODE["diagnosis_window"]
    assert full["cause"] == "none", (full, live.diagnostics[-1])  # the counters: restarts, duplicates, gaps
    assert full["extended"] is None and full["gain"] is None
    assert full["baseline"]["fit_percent"] > 80, live.diagnostics[-1]  # the counters tell losses and restarts
    assert {"test", "value", "bound", "passed"} <= set(full["evidence"][0])


def test_window_change_applies_live(live):
    live.wait_for(lambda: live.models and live.models[-1]["samples"] > 2000, timeout=60,
                  what="a model on more than 2000 samples")
    assert [r.successful for r in _set(live, window=2000)] == [True]
    live.wait_for(lambda: live.models[-1]["samples"] == 2000, what="a model on the new 2000-sample window")
    live.wait_for(lambda: live.diagnostics[-1]["window"] == "2000", what="diagnostics of the new window")
    assert _get(live, "window") == [2000]


@pytest.mark.parametrize("name, value, needle", [
    ("window", 5, "window"),
    ("forgetting", 1.5, "forgetting"),
    ("delay", 7, "delay"),
    ("method", "nope", "method"),
    ("excitation_type", "nav_msgs/msg/Odometry", "nav_msgs"),
    ("response_field", "velocity[0]", "velocity"),
    ("response_topic", "bad topic", "response_topic"),
    ("order", "three", "order"),
])
def test_invalid_parameter_is_rejected_with_a_reason(live, name, value, needle):
    before = _get(live, name)
    [result] = _set(live, **{name: value})
    assert not result.successful
    assert needle in result.reason
    assert _get(live, name) == before


def test_late_joining_subscriber_gets_the_latest_model(live):
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    [info] = live.wait_for(lambda: live.node.get_publishers_info_by_topic("/hammer_ros/model"),
                           what="the model publisher")
    assert info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    live.wait_for(lambda: live.models, what="a model")
    count = len(live.models)  # counted before: the solve the change triggers may arrive with the reply
    assert [r.successful for r in _set(live, solve_rate=0.01)] == [True]  # one solve now, the next in 100 s
    live.wait_for(lambda: len(live.models) > count, what="the solve triggered by the change")
    _wait_quiet(live, 1.0)  # the triggered solve's model is the last one for 100 s
    late = live.subscribe_json("/hammer_ros/model")
    live.wait_for(lambda: late, what="the latched model on a late subscription")
    assert late[-1] == live.models[-1]
    assert [r.successful for r in _set(live, solve_rate=4.0)] == [True]


def test_bad_messages_are_counted_and_sigint_exits_cleanly(ros_env, tmp_path):
    """JointState without velocity: every response message fails its field path; the node
    reports it in /diagnostics, keeps running, and SIGINT stops it with exit code 0."""
    plant = RosProcess("hammer_ros.ros.plant_node", {"rate": 200.0, "message_type": "joint_state"}, ros_env,
                       tmp_path / "plant.log")
    node = RosProcess("hammer_ros.ros.node", {
        "excitation_type": "sensor_msgs/msg/JointState", "excitation_field": "position[0]",
        "response_type": "sensor_msgs/msg/JointState", "response_field": "velocity[0]", "solve_rate": 5.0},
        ros_env, tmp_path / "node.log")
    listener = Listener(ros_env)
    try:
        diagnostics = listener.subscribe_diagnostics()
        status = listener.wait_for(lambda: [d for d in diagnostics if int(d["response_field_errors"]) > 0],
                                   what="diagnostics counting bad response messages")[-1]
        assert status["level"] == 1 and "velocity" in status["message"]
        assert int(status["excitation_field_errors"]) == 0
        assert int(status["received_excitation"]) > 0
        assert node.process.poll() is None
    finally:
        listener.close()
        codes = (node.stop(signal.SIGINT), plant.stop(signal.SIGINT))
    assert codes == (0, 0), node.output()[-2000:]
    assert "velocity" in node.output()  # the throttled warning names the field


def test_params_file_configures_the_node_and_sigterm_exits_cleanly(ros_env, tmp_path):
    node = RosProcess("hammer_ros.ros.node", {"window": 3000}, ros_env, tmp_path / "node.log",
                      params_file=REPO / "msg_config" / "float64_example.yaml")
    listener = Listener(ros_env)
    try:
        assert _get(listener, "excitation_topic", "sample_rate", "window") == ["/cmd", 100.0, 3000]
    finally:
        listener.close()
        code = node.stop(signal.SIGTERM)
    assert code == 0, node.output()


@pytest.mark.parametrize("args, needle", [
    (["-p", "window:=5"], "window"),
    (["-p", "excitation_type:=foo/msg/Bar"], "foo"),
    (["-p", "response_field:=twist.linear.x"], "twist"),
])
def test_bad_startup_configuration_exits_2_with_one_line(ros_env, args, needle):
    done = subprocess.run([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", *args], env=ros_env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert needle in done.stderr and "Traceback" not in done.stderr
