"""The sample setups in msg_config/ as ROS 2 params files: ``hammer-ros node --ros-args
--params-file msg_config/FILE.yaml`` starts the node with exactly those parameters (a command-line
``-p`` after the file still wins), and ``replay --config`` reads the same files."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest
import yaml
from conftest import REPO
from ros_helpers import Listener, RosProcess, free_port

pytestmark = pytest.mark.ros

SETUPS = ("float64_example.yaml", "float64_cubic_g1.yaml", "joint_state_saturation.yaml")


@pytest.mark.parametrize("name", SETUPS)
def test_params_file_starts_the_node_with_its_parameters(ros_env, tmp_path, name):
    from rclpy.parameter import parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    path = REPO / "msg_config" / name
    params = yaml.safe_load(path.read_text())["hammer_ros"]["ros__parameters"]
    port = free_port()
    node = RosProcess("hammer_ros.ros.node", {"foxglove_port": port, "diagnosis_period": 0.0}, ros_env,
                      tmp_path / "node.log", params_file=path)
    listener = Listener(ros_env)
    try:
        client = AsyncParameterClient(listener.node, "hammer_ros")
        listener.wait_for(client.services_are_ready, what="the node's parameter services")
        values = listener.wait_future(lambda: client.get_parameters(list(params))).values
        assert dict(zip(params, [parameter_value_to_python(v) for v in values])) == {
            **params, "foxglove_port": port}
        diagnostics = listener.subscribe_diagnostics()
        status = listener.wait_for(lambda: diagnostics and diagnostics[-1], what="the node's diagnostics")
        assert int(status["foxglove_port"]) == port and status["window"] == str(params["window"])
    finally:
        listener.close()
        code = node.stop(signal.SIGINT, timeout=30)
    assert code == 0, node.output()


@pytest.mark.parametrize("name", ("float64_cubic_g1.yaml", "joint_state_saturation.yaml"))
def test_the_same_file_configures_replay(name):
    bag = {"float64_cubic_g1.yaml": "bags/float64_cubic_g1.mcap",
           "joint_state_saturation.yaml": "bags/joint_state_saturation"}[name]
    done = subprocess.run([sys.executable, "-m", "hammer_ros.cli", "replay", bag, "--config", f"msg_config/{name}",
                           "--json"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    params = yaml.safe_load((REPO / "msg_config" / name).read_text())["hammer_ros"]["ros__parameters"]
    assert json.loads(done.stdout)["order"] == params["order"]
