"""``hammer_ros_node --managed``: the lifecycle node driven through configure / activate /
deactivate / activate / shutdown with lifecycle_msgs service calls, next to a plant publishing
all along: models only while active, no sample counted while inactive."""

from __future__ import annotations

import signal
import time

import pytest
from ros_helpers import Listener, RosProcess

from hammer_ros.ros.environment import DomainLease, child_environment

pytestmark = pytest.mark.ros

RATE = 200.0
PLANT = {"rate": RATE, "seed": 3}
NODE = {"sample_rate": RATE, "order": 3, "delay": 2, "window": 100, "solve_rate": 5.0, "diagnosis_period": 0.0}
QUIET = 600  # plant messages (3 s) to watch an idle node for


class Lifecycle:
    """ChangeState / GetState clients of /hammer_ros."""

    def __init__(self, listener: Listener) -> None:
        from lifecycle_msgs.srv import ChangeState, GetState

        self.listener = listener
        self.change = listener.node.create_client(ChangeState, "/hammer_ros/change_state")
        self.get = listener.node.create_client(GetState, "/hammer_ros/get_state")
        listener.wait_for(lambda: self.change.service_is_ready() and self.get.service_is_ready(),
                          what="the lifecycle services")

    def state(self) -> str:
        from lifecycle_msgs.srv import GetState

        return self.listener.wait_future(lambda: self.get.call_async(GetState.Request())).current_state.label

    def transition(self, name: str) -> bool:
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        request = ChangeState.Request()
        request.transition.id = getattr(Transition, f"TRANSITION_{name.upper()}")
        return self.listener.wait_future(self.change.call_async(request), what=f"the {name} transition").success


def _set(listener: Listener, **values) -> list:
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(listener.node, "hammer_ros")
    listener.wait_for(client.services_are_ready, what="the node's parameter services")
    return listener.wait_future(client.set_parameters([Parameter(k, value=v) for k, v in values.items()])).results


def test_lifecycle_transitions_start_and_stop_identification(tmp_path):
    from std_msgs.msg import Float64

    with DomainLease() as lease:
        env = child_environment(lease.domain_id, log_dir=tmp_path / "ros_log")
        plant = RosProcess("hammer_ros.ros.plant_node", PLANT, env, tmp_path / "plant.log")
        node = RosProcess("hammer_ros.ros.node", NODE, env, tmp_path / "node.log", options=("--managed",))
        listener = Listener(env)
        try:
            commands = []
            listener.node.create_subscription(Float64, "/command", lambda m: commands.append(m.data), 1000)
            models = listener.subscribe_json("/hammer_ros/model", latched=False)
            diagnostics = listener.subscribe_diagnostics()
            lifecycle = Lifecycle(listener)

            def idle(what: str) -> None:
                seen = len(commands)
                listener.wait_for(lambda: len(commands) >= seen + QUIET, what=f"{QUIET} plant messages ({what})")

            assert lifecycle.state() == "unconfigured"
            idle("unconfigured")
            assert models == [] and diagnostics == []

            # window 100 < 2 tau_max + 2: configure fails with the reason, the node stays unconfigured
            assert not lifecycle.transition("configure")
            assert lifecycle.state() == "unconfigured"
            assert [r.successful for r in _set(listener, window=1000)] == [True]
            assert lifecycle.transition("configure") and lifecycle.state() == "inactive"
            idle("inactive")
            assert models == [] and diagnostics == []

            assert lifecycle.transition("activate") and lifecycle.state() == "active"
            listener.wait_for(lambda: [m for m in models if not m["stale"]], what="a model while active")

            assert lifecycle.transition("deactivate") and lifecycle.state() == "inactive"
            last = listener.wait_for(lambda: [d for d in diagnostics if d["ingesting"] == "False"],
                                     what="the counters at deactivation")[-1]
            counted, seen_models, seen_diagnostics = int(last["received_excitation"]), len(models), len(diagnostics)
            idle("deactivated")
            assert (len(models), len(diagnostics)) == (seen_models, seen_diagnostics)  # nothing while inactive

            asked = time.monotonic()
            assert lifecycle.transition("activate")
            first = listener.wait_for(lambda: diagnostics[seen_diagnostics:], what="diagnostics after reactivation")[0]
            elapsed = time.monotonic() - asked
            added = int(first["received_excitation"]) - counted
            # only what arrived since the activation: far fewer than the QUIET messages of the pause
            assert 0 <= added <= RATE * elapsed + 20, (added, elapsed)
            assert added < QUIET / 2
            listener.wait_for(lambda: len(models) > seen_models, what="models again once active")

            assert lifecycle.transition("active_shutdown")
            assert node.process.wait(timeout=30) == 0, node.output()[-3000:]
            assert "configure failed: window" in node.output()
        finally:
            listener.close()
            codes = (node.stop(signal.SIGINT), plant.stop(signal.SIGINT))
        assert codes == (0, 0), node.output()[-3000:]
