"""The node's services ``~/reset``, ``~/solve`` and ``~/diagnose`` (std_srvs/srv/Trigger).

They are served by a small node of their own (``<name>_services``, without the global ROS
arguments, so ``-r __node:=`` renames only the identification node) and an executor in its
own thread: a diagnosis takes seconds, and the identification node's executor must keep taking
samples meanwhile (rclpy's EventsExecutor cannot answer a service later). The service names are
the identification node's private names (``/hammer_ros/reset``, ...).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from .environment import prepare_ros_environment

prepare_ros_environment()

import rclpy  # noqa: E402  (the environment must be prepared first)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

SERVICES = ("reset", "solve", "diagnose")  # -> NodeHost's reset_window, solve_now, diagnose_now


def trigger_handlers(methods: dict[str, Callable[[], tuple[bool, str]]], errors, logger
                     ) -> dict[str, Callable[[], tuple[bool, str]]]:
    """name -> the Trigger handler of ``methods[name]`` returning (success, message), guarded: a
    bug answers the call (counted in ``errors``, the node's ``loop_errors``), never ends the node.
    The ROS services and the Foxglove server's services call these."""

    def guarded(name: str, handler: Callable[[], tuple[bool, str]]) -> Callable[[], tuple[bool, str]]:
        def call() -> tuple[bool, str]:
            try:
                return handler()
            except Exception as exc:  # a bug answers the call, never ends the node
                errors.add()
                message = f"~/{name} failed: {type(exc).__name__}: {exc}"
                logger.error(message, throttle_duration_sec=5.0)
                return False, message

        return call

    return {name: guarded(name, methods[name]) for name in SERVICES}


class NodeServices:
    """Serves the Trigger services ``methods`` (name -> handler) of the rclpy ``node`` from a thread."""

    def __init__(self, node, methods: dict[str, Callable[[], tuple[bool, str]]], errors) -> None:
        self.node = rclpy.create_node(f"{node.get_name()}_services", namespace=node.get_namespace(),
                                      context=node.context, use_global_arguments=False,
                                      start_parameter_services=False)
        self.handlers = trigger_handlers(methods, errors, node.get_logger())
        base = node.get_fully_qualified_name()
        for name in SERVICES:
            self.node.create_service(Trigger, f"{base}/{name}", self._callback(self.handlers[name]))
        self._executor = SingleThreadedExecutor(context=node.context)
        self._executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="hammer_ros_services", daemon=True)
        self._thread.start()

    @staticmethod
    def _callback(handler: Callable[[], tuple[bool, str]]):
        def on_request(request, response):
            response.success, response.message = handler()
            return response

        return on_request

    def _spin(self) -> None:
        while not self._stop.is_set() and self._executor.context.ok():
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except (KeyboardInterrupt, ExternalShutdownException):
                return

    def close(self) -> None:
        """Stop serving (waits for a running call up to 5 s) and destroy the services' node."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
