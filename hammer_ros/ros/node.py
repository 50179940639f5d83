"""``hammer_ros_node`` / ``hammer-ros node``: the live ROS 2 identification node.

Unmanaged by default (configured and active from the start); with ``--managed`` an rclpy
lifecycle node (``managed_node``) that waits for configure/activate. The implementation shared
by both is a ``node_core.NodeHost`` (its module docstring: threads, locks, who owns what).
"""

from __future__ import annotations

import gc
import sys

from .environment import prepare_ros_environment

prepare_ros_environment()

import rclpy  # noqa: E402  (the environment must be prepared first)
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.experimental import EventsExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.task import Future  # noqa: E402
from rclpy.utilities import remove_ros_args  # noqa: E402

from ..errors import UsageError  # noqa: E402
from .managed_node import ManagedIdentificationNode  # noqa: E402
from .node_core import NODE_NAME, PARAMETERS, NodeHost  # noqa: E402

# The executor runs its own event loop (spin_until_future_complete on a future that never
# completes) and returns every CHECK_SECONDS for the checks of rclpy.ok() and a managed node's
# shutdown: a spin_once per event costs a Python round trip and a Context.ok() under a lock per
# message (15 % of the GIL's time at 20 000 x100 messages/s per topic; py-spy).
CHECK_SECONDS = 0.5


class IdentificationNode(Node):
    """The unmanaged node (the default): configured and active from construction."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.host = NodeHost(self, self.create_publisher, self.destroy_publisher)
        try:
            self.host.configure()
        except BaseException:
            self.host.close()
            self.destroy_node()
            raise
        self.host.activate()


def usage() -> str:
    """``--help``: how to start the node, and every parameter with its default."""
    lines = ["usage: hammer-ros node [--managed] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] "
             "[-r __node:=NAME]]",
             "", "Live Hammerstein identification: subscribes to excitation_topic and response_topic, publishes",
             "~/model (JSON, transient local), ~/poles, ~/zeros, ~/markov, ~/nonlinearity and /diagnostics;",
             "services ~/reset, ~/solve, ~/diagnose (std_srvs/srv/Trigger); with foxglove_port a Foxglove server.",
             "A params file with a channels list identifies every channel, its outputs under ~/NAME/ (docs/node.md).",
             "", "  --managed          run as a lifecycle (managed) node: idle until configured and activated",
             "", "parameters (default):"]
    for name, spec in PARAMETERS.items():
        default = "unset" if spec.default is None else repr(spec.default)
        lines.append(f"  {name:<18} {spec.description} ({default})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the node until SIGINT/SIGTERM (or, managed, its shutdown transition): exit 0; exit 2 on
    a bad startup configuration."""
    args = sys.argv if argv is None else ["hammer_ros_node", *argv]
    extra = remove_ros_args(args)[1:]
    if extra in (["-h"], ["--help"]):
        print(usage())
        return 0
    managed = "--managed" in extra
    extra = [a for a in extra if a != "--managed"]
    if extra:
        print(f"hammer_ros_node: error: unknown arguments {' '.join(extra)} (parameters go after --ros-args)",
              file=sys.stderr)
        return 2
    rclpy.init(args=args)
    node = None
    try:
        node = ManagedIdentificationNode() if managed else IdentificationNode()
        gc.freeze()  # what is alive now (modules, rclpy, the node) is never traversed by a full collection
        executor = EventsExecutor()
        never = Future()
        executor.add_node(node)
        while rclpy.ok() and not node.host.finalized:
            try:
                executor.spin_until_future_complete(never, timeout_sec=CHECK_SECONDS)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception as exc:  # a failing callback must not end the node
                if not rclpy.ok():
                    break
                node.host.errors.add()
                node.get_logger().error(f"callback failed ({type(exc).__name__}: {exc}); continuing",
                                        throttle_duration_sec=5.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except UsageError as exc:
        print(f"hammer_ros_node: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.host.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
