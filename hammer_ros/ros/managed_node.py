"""``hammer_ros_node --managed``: the identification node as an rclpy lifecycle (managed) node.

The same ``node_core.NodeHost`` as the unmanaged node, driven by the lifecycle transitions
(``lifecycle_msgs/srv/ChangeState`` on ``~/change_state``):

- configure: the parameters checked (a bad one fails the transition, with the reason logged),
  engine, publishers (lifecycle publishers: silent until activated), output_mcap, Foxglove server;
- activate: subscriptions and the ingest / solve / diagnosis threads;
- deactivate: unsubscribed and threads stopped (no sample is counted while inactive), the
  counters at that point published once on /diagnostics; the window and the last model stay;
- cleanup: final solve, output_mcap finished, everything ``configure`` built released;
- shutdown (from any state): as cleanup, and ``main`` returns (exit 0).
"""

from __future__ import annotations

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn  # noqa: E402

from ..errors import UsageError  # noqa: E402
from .node_core import NODE_NAME, NodeHost  # noqa: E402


class ManagedIdentificationNode(LifecycleNode):
    """The identification node with the lifecycle states unconfigured / inactive / active / finalized."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.host = NodeHost(self, self.create_lifecycle_publisher, self.destroy_lifecycle_publisher, managed=True)
        self.get_logger().info("managed node: waiting for the configure transition")

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.host.configure()
        except UsageError as exc:
            self.get_logger().error(f"configure failed: {exc}")
            self.host.cleanup()
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.host.activate()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.host.deactivate()  # (its /diagnostics goes out before the publishers are deactivated)
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.host.finish()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.host.finish()
        self.host.finalized = True
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error("lifecycle transition failed; back to unconfigured")
        if self.host.active:
            self.host.deactivate(publish=False)
        self.host.cleanup()
        return TransitionCallbackReturn.SUCCESS
