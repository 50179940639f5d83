"""What both node classes (``node.IdentificationNode``, ``managed_node.ManagedIdentificationNode``)
are made of: a ``NodeHost`` that owns, on the rclpy node, the parameters (declared with their
descriptors, checked on every change), the publishers and subscriptions its channels use, and
the Trigger services, and hands the messages to its ``channels.ChannelSet`` (N >= 1
``channel.IdentificationChannel``). The host only calls the node's public API.

Threads, locks and who owns which state:

- The executor thread (``node.main``'s EventsExecutor) runs the subscription callbacks: each only
  appends (receive time, message, reader) to its input's deque (``inputs._queueing_callback``; no
  lock, deque appends are atomic) and bumps that input's ``queue_dropped`` when full.
- Per channel, three threads (``channel.IdentificationChannel.start``): ingest (every
  ``FLUSH_PERIOD`` s drains the deques and adds the samples to the engine), solver (``solve_rate``
  a second: snapshot, solve in the solver process, publish) and diagnosis (every
  ``diagnosis_period`` s). The channel's ``_lock`` guards its engine and its ``Ingest`` (stamper,
  queues into the engine); ``_solve_lock`` makes one solve at a time (solver thread, ``~/solve``),
  ``_diagnose_lock`` one diagnosis (diagnosis thread, ``~/diagnose``). A ``SharedTopic``'s lock
  keeps its decoded chunks in message order.
- Processes (``workers.NodeWorkers``, one per ``ChannelSet``): ONE solver process for the solves
  of every channel (each channel a lane of it), ONE diagnosis process for their diagnoses, started
  by the first; the channels' threads take turns in each (``SolverProcess``'s lock around a solve
  or a diagnosis), ``NodeWorkers``' lock guards starting and losing them. A node of any number of
  channels is at most 3 processes.
- The services thread (``services.NodeServices``) answers ``~/reset``, ``~/solve``,
  ``~/diagnose``; the Foxglove server's threads call the same handlers and the parameter API.
- Parameters are changed from the executor thread (rclpy's parameter services) or the Foxglove
  server: ``NodeHost._on_set_parameters`` checks them and hands them to the channel under its lock.
- ``loop_errors`` (``channel.ErrorCount``) is counted by all of these under its own lock; the
  output_mcap writer (``channel.Recorder``) and the /diagnostics array (``DiagnosticsMerger``) are
  shared by the channels under their own locks.
"""

from __future__ import annotations

from typing import Any

from .environment import prepare_ros_environment

prepare_ros_environment()

from rcl_interfaces.msg import SetParametersResult  # noqa: E402
from rclpy.exceptions import (  # noqa: E402
    ParameterException,
    ParameterNotDeclaredException,
    ParameterUninitializedException,
)
from rclpy.parameter import Parameter  # noqa: E402

from ..errors import UsageError  # noqa: E402
from ..identification.methods import REFERENCE_METHODS  # noqa: E402
from .channel import ErrorCount  # noqa: E402
from .channels import ChannelSet  # noqa: E402
from .inputs import _drained, _Input, _queueing_callback  # noqa: E402
from .parameters import (  # noqa: E402
    NODE_NAME,
    NODE_WIDE,
    PARAMETERS,
    SOURCE,
    STREAMS,
    channel_values,
    check_field,
    check_stream,
    coerce,
    descriptor,
    engine_config,
    file_channels,
    parameter_overrides,
    proposed_values,
)
from .services import NodeServices  # noqa: E402

__all__ = ["NODE_NAME", "PARAMETERS", "NodeHost", "_Input", "_drained", "_queueing_callback", "check_field"]


class NodeHost:
    """The identification on an rclpy ``node`` (``create_output``/``destroy_output``: its
    publishers, lifecycle ones for a managed node): ``configure`` (parameters checked, the
    channels built), ``activate`` (subscriptions and worker threads), ``deactivate`` (ingestion
    stops, the last models stay), ``cleanup``, ``close`` (final solve, output_mcap finished,
    everything released)."""

    def __init__(self, node, create_output, destroy_output, managed: bool = False) -> None:
        self.node, self.create_output, self.destroy_output, self.managed = node, create_output, destroy_output, managed
        for name, spec in PARAMETERS.items():
            default = Parameter.Type.DOUBLE_ARRAY if spec.default is None else spec.default
            try:
                node.declare_parameter(name, default, descriptor(name, spec))
            except ParameterException as exc:  # an override outside the descriptor's range or type
                raise UsageError(f"{name}: {' '.join(str(exc).split())}") from None
        self.errors = ErrorCount()
        self.channels: ChannelSet | None = None
        self.several = False  # a params file of several channels: parameters fixed at startup
        self.finalized = False  # a managed node after its shutdown transition: main() returns
        node.add_on_set_parameters_callback(self._on_set_parameters)
        self.trigger_services = NodeServices(node, {"reset": self.reset_window, "solve": self.solve_now,
                                                    "diagnose": self.diagnose_now}, self.errors)

    @property
    def active(self) -> bool:
        return self.channels is not None and self.channels.active

    @property
    def configured(self) -> bool:
        return self.channels is not None

    def warn_throttled(self, text: str) -> None:
        self.node.get_logger().warning(text, throttle_duration_sec=5.0)

    def _declared_value(self, name: str) -> Any:
        try:
            return self.node.get_parameter(name).value
        except ParameterUninitializedException:  # a list parameter declared without a value
            return None

    def _checked(self, raw: dict[str, Any]) -> dict[str, Any]:
        """A channel's parameter values coerced and checked (UsageError naming the first bad one)."""
        values = {name: coerce(name, raw[name]) for name in PARAMETERS}
        engine_config(values)
        for stream in (*STREAMS, "reference") if values["reference_topic"] else STREAMS:
            check_stream(stream, values, self.node.get_name(), self.node.get_namespace())
        if values["reference_topic"] and values["method"] not in REFERENCE_METHODS:
            raise UsageError(f"reference_topic: the method {values['method']} has no instrumented form "
                             f"(use one of {', '.join(REFERENCE_METHODS)})")
        return values

    def configure(self) -> None:
        """Check every parameter and build the channels: the params file's ``channels`` (several:
        each its values; one: its values set as the node's parameters), else the node's own."""
        overrides = parameter_overrides(self.node)
        channels = file_channels(overrides)
        declared = {name: self._declared_value(name) for name in PARAMETERS}
        self.several = len(channels) > 1
        if self.several:
            if self.managed:
                raise UsageError(f"{SOURCE}: channels: several channels need the unmanaged node (without --managed)")
            values = {}
            for channel in channels:
                try:
                    values[channel.name] = {**declared, **channel_values(overrides, channel)}
                    self._check_node_wide(channel.name, values[channel.name], declared)
                    values[channel.name] = self._checked(values[channel.name])
                except UsageError as exc:
                    message = str(exc)
                    where = f"{SOURCE}: channel {channel.name!r}"
                    raise UsageError(message if message.startswith(where) else f"{where}: {message}") from None
        else:
            if channels:  # one channel: its parameters are the node's
                self._apply_parameters(channel_values(overrides, channels[0]))
                declared = {name: self._declared_value(name) for name in PARAMETERS}
            values = {"": self._checked(declared)}
        self.channels = ChannelSet(self, values, {name: declared[name] for name in NODE_WIDE})

    @staticmethod
    def _check_node_wide(name: str, values: dict[str, Any], declared: dict[str, Any]) -> None:
        for key in NODE_WIDE:
            if values[key] != declared[key]:
                raise UsageError(f"{SOURCE}: channel {name!r}: {key}: one for the node and every channel: "
                                 "set it at the top level")

    def _apply_parameters(self, params: dict[str, Any]) -> None:
        """Set the node parameters of ``params`` that differ from the declared ones (UsageError
        naming the first refused)."""
        changes = [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in params.items()
                   if v != self._declared_value(k)]
        for change in changes:
            result = self.node.set_parameters([change])[0]
            if not result.successful:
                raise UsageError(f"{change.name}: {result.reason}")

    def activate(self) -> None:
        self.channels.activate()

    def deactivate(self, publish: bool = True) -> None:
        self.channels.deactivate(publish)

    def cleanup(self) -> None:
        """Release what ``configure`` built (the last models are forgotten)."""
        if self.channels is not None:
            self.channels.cleanup()
            self.channels = None

    def finish(self) -> None:
        """Final solve of every channel, output_mcap finished, everything released (cleanup)."""
        if self.channels is not None:
            self.channels.close()
            self.channels = None

    def close(self) -> None:
        """On shutdown: stop ingesting, solve once more, finish output_mcap, release everything."""
        self.finish()
        self.trigger_services.close()

    # ------------------------------------------------------------------ services (NodeServices)
    def _service(self, name: str) -> tuple[bool, str]:
        channels = self.channels  # (the services thread: read once)
        if channels is None or not channels.active:
            return False, "the node is not active (managed node: configure and activate it first)"
        return channels.each(name)

    def reset_window(self) -> tuple[bool, str]:
        """~/reset: clear the window and the correlation sums (and the counters); parameters stay."""
        return self._service("reset_window")

    def solve_now(self) -> tuple[bool, str]:
        """~/solve: solve and publish now; the model JSON, or why there is none."""
        return self._service("solve_now")

    def diagnose_now(self) -> tuple[bool, str]:
        """~/diagnose: diagnose the window now and publish it; the diagnosis JSON, or why not."""
        return self._service("diagnose_now")

    # ------------------------------------------------------------------ parameters
    def parameter_values(self) -> dict[str, Any]:
        """The current value of every node parameter (None: unset), for the Foxglove server."""
        return {name: self._declared_value(name) for name in PARAMETERS}

    def set_parameter_value(self, name: str, value: Any) -> tuple[bool, str]:
        """Set one parameter as rclpy's SetParameters service does (``set_parameters_atomically``
        of it alone), so a change from Foxglove is validated exactly as one from ``ros2 param set``
        and refused with the same reason; (successful, reason)."""
        try:
            result = self.node.set_parameters_atomically([Parameter(name, value=value)])
        except (ParameterNotDeclaredException, TypeError, ValueError) as exc:  # TypeError: no parameter type
            return False, str(exc)
        return result.successful, result.reason

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        if self.several:
            return SetParametersResult(successful=False, reason="several channels: their parameters are read from "
                                       "the params file at startup")
        channels = self.channels
        try:
            current = dict(channels.channels[0].values) if channels is not None else {
                name: coerce(name, self._declared_value(name)) for name in PARAMETERS}
            proposed, config, changed = proposed_values(current, parameters, self.node.get_name(),
                                                        self.node.get_namespace())
        except UsageError as exc:
            self.node.get_logger().warning(f"parameter change rejected: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        if channels is None:  # unconfigured (managed node): configure reads the parameters
            return SetParametersResult(successful=True)
        channels.set_values(proposed, config, changed)
        return SetParametersResult(successful=True)
