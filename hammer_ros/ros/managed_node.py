"""``hammer_ros_node --managed``: the identification node as an rclpy lifecycle (managed) node.

The same ``IdentificationCore`` as the unmanaged node, driven by the lifecycle transitions
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
from .channels import ChannelSupport  # noqa: E402
from .node_core import NODE_NAME, IdentificationCore  # noqa: E402


class ManagedIdentificationNode(ChannelSupport, IdentificationCore, LifecycleNode):
    """The identification node with the lifecycle states unconfigured / inactive / active / finalized."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self._setup()
        self.get_logger().info("managed node: waiting for the configure transition")

    def _create_output_publisher(self, cls, topic: str, qos):
        return self.create_lifecycle_publisher(cls, topic, qos)

    def _destroy_output_publisher(self, publisher) -> None:
        self.destroy_lifecycle_publisher(publisher)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.configure()
        except UsageError as exc:
            self.get_logger().error(f"configure failed: {exc}")
            self.cleanup()
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.activate()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.deactivate()  # (its /diagnostics goes out before the publishers are deactivated)
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.finish()
        self.cleanup()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.active:
            self.deactivate(publish=False)
        if self.engine is not None:
            self.finish()
            self.cleanup()
        self.finalized = True
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error("lifecycle transition failed; back to unconfigured")
        if self.active:
            self.deactivate(publish=False)
        if self.engine is not None:
            self.cleanup()
        return TransitionCallbackReturn.SUCCESS
