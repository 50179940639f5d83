"""The live identification node's implementation (``IdentificationCore``), its parameters and
their checks; ``node`` runs it unmanaged, ``managed_node`` as a lifecycle node.

A thin adapter over ``streaming.StreamingEngine``: two subscriptions (sensor-data QoS) feed the
excitation and response samples into the engine, a worker thread solves on a snapshot of the
window ``solve_rate`` times a second and publishes the results built by ``outputs``. The solve
itself runs in a ``SolverProcess`` (parameter ``solver_process``, on by default), and so does
the periodic diagnosis (a second one, started by the first diagnosis), so neither ever holds the
interpreter lock against the callbacks and the ingest thread. Ingestion never waits
for a solve (a slow solve skips solves, never samples); parameters are validated and
applied live; a bad message is counted and reported in /diagnostics, never fatal. A solve
without a new model republishes the last good one marked stale. With ``output_mcap`` every
published result is also recorded (ROS 2 messages only); on SIGINT/SIGTERM the node solves once more, records the
final model and finishes the file.

Stamps: a message with a non-zero ``header.stamp`` is placed by its stamp (a batch of n samples
holds samples at stamp - (n-1)/fs .. stamp); any other message is placed by counting samples at
the sample rate, anchored on the least delayed receive times (``sample_clock.ArrivalStamper``),
except a message whose header stamp is zero (no stamp) on a stream that publishes far below the
grid rate (a setpoint: its median arrival interval over the last ``ARRIVALS`` messages longer than
``HOLD_PERIODS`` sample periods per sample): counting would put its samples a period apart, so it
is placed at its receive time, read on the other stream's time base (``_place_by_arrival``), and
the aligner holds it until the next one. The first zero stamp of a topic is logged once.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

from rcl_interfaces.msg import (  # noqa: E402
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.event_handler import QoSSubscriptionEventType, UnsupportedEventTypeError  # noqa: E402
from rclpy.exceptions import (  # noqa: E402
    InvalidHandle,
    ParameterException,
    ParameterNotDeclaredException,
    ParameterUninitializedException,
)
from rclpy.expand_topic_name import expand_topic_name  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from rclpy.validate_full_topic_name import validate_full_topic_name  # noqa: E402

from ..diagnosis.closed_loop import TEST_NAME as CLOSED_LOOP_TEST  # noqa: E402
from ..diagnosis.closed_loop import WARNING as CLOSED_LOOP_WARNING  # noqa: E402
from ..errors import UsageError  # noqa: E402
from ..identification.methods import METHODS, REFERENCE_METHODS  # noqa: E402
from ..identification.result import strict_json  # noqa: E402
from ..io.bag_writer import ResultWriter, record_results  # noqa: E402
from ..io.outcome_messages import outcome_messages  # noqa: E402
from ..messages.cdr import extract_batch  # noqa: E402
from ..messages.dashboard import dashboard_messages  # noqa: E402
from ..messages.field_path import NAME_FIELD, FieldError, FieldPath, extract_samples, message_stamp, parse_field_path  # noqa: E402
from ..messages.outputs import (  # noqa: E402
    OUTPUT_TOPICS,
    diagnosis_message,
    diagnostics_message,
    model_json,
)
from ..messages.types import INPUT_PACKAGES as MESSAGE_PACKAGES  # noqa: E402
from ..messages.types import normal_type as _normal_type  # noqa: E402
from ..streaming.config import HOLD_PERIODS, MAX_TAU_MAX, MAX_WINDOW, EngineConfig  # noqa: E402
from ..streaming.engine import EngineSnapshot, SolveOutcome, StreamingEngine, solve_snapshot, window_problem  # noqa: E402
from ..streaming.sample_clock import ArrivalStamper  # noqa: E402
from ..streaming.solver_process import SolverProcess, diagnose_window, newest_window  # noqa: E402
from .message_types import input_message_class as message_class  # noqa: E402
from .message_types import message_class as output_message_class  # noqa: E402
from .message_types import raw_extractor, to_ros_message  # noqa: E402
from .services import NodeServices  # noqa: E402

NODE_NAME = "hammer_ros"
FLUSH_PERIOD = 0.05  # s between moves of the queued samples into the engine
ARRIVALS = 6  # arrival times of zero-stamped messages kept per stream to tell a sparse stream (module docstring)
WORKER_READY_SECONDS = 10.0  # longest wait for the solver process before subscribing (``activate``)
STREAMS = ("excitation", "response")
REFERENCE = "reference"  # the optional third input: a closed loop's reference (``reference_topic``)
STREAMING_METHODS = tuple(m for m in METHODS if m != "semiparametric")


@dataclass(frozen=True)
class Spec:
    """One node parameter: default, kind (str/int/float/floats/bool), bounds and description."""

    default: Any
    kind: str
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False


PARAMETERS: dict[str, Spec] = {
    "excitation_topic": Spec("/command", "str", "topic of the excitation (actuator command) u"),
    "excitation_type": Spec("std_msgs/msg/Float64", "str",
                            f"message type of excitation_topic (package one of {', '.join(MESSAGE_PACKAGES)})"),
    "excitation_field": Spec("data", "str", "field path of u: data, data[0], velocity[2], twist.linear.x, data[:]"),
    "response_topic": Spec("/response", "str", "topic of the response (sensor) y"),
    "response_type": Spec("std_msgs/msg/Float64", "str", "message type of response_topic"),
    "response_field": Spec("data", "str", "field path of y"),
    "reference_topic": Spec("", "str", "topic of a closed loop's external reference r, the instrument of every "
                            f"solve ({', '.join(REFERENCE_METHODS)}); '' = none", read_only=True),
    "reference_type": Spec("std_msgs/msg/Float64", "str", "message type of reference_topic", read_only=True),
    "reference_field": Spec("data", "str", "field path of r", read_only=True),
    "sample_rate": Spec(0.0, "float", "Hz of the common sample grid; 0 = infer", 0.0, 1e8),
    "window": Spec(4000, "int", "W: samples in the sliding window", 16, MAX_WINDOW),
    "forgetting": Spec(1.0, "float", "1 = exact sliding window; < 1 = exponential forgetting factor", 0.0, 1.0),
    "method": Spec("cls-markov", "str", "identification method", choices=STREAMING_METHODS),
    "order": Spec(3, "int", "order n of the linear block", 1, 50),
    "delay": Spec(1, "int", "relative degree d (0..order)", 0, 50),
    "mu": Spec(0, "int", "Markov parameters of mu-Markov methods; 0 = method default", 0, 10_000),
    "tau_max": Spec(60, "int", "largest correlation lag (CLS)", 1, MAX_TAU_MAX),
    "poly": Spec(3, "int", "polynomial order p of the nonlinearity", 1, 50),
    "partition": Spec(None, "floats", "breakpoints c1 < c2 < ... of a piecewise-linear map (PLLS; cls-arx/"
                      "cls-markov: F piecewise linear instead of the polynomial); empty = method default"),
    "interpolation": Spec("zoh", "str", "resampling onto the grid", choices=("zoh", "linear")),
    "max_gap": Spec(0.0, "float", "seconds without samples that restart the window; 0 = 5 sample periods", 0.0, 1e6),
    "min_fill": Spec(0.25, "float", "fraction of the window needed before the first solve", 0.0, 1.0),
    "min_excitation": Spec(0.1, "float", "input std needed, relative to the windows behind the published "
                           "models (below: 'not persistently exciting', the last model stays, marked stale); 0 = off",
                           0.0, 1.0),
    "max_relative_sd": Spec(0.25, "float", "a new model whose pole interval crosses the unit circle or whose pole "
                            "(gain) sd exceeds this x max(|p|, 1 - |p|) (|gain|) is 'uncertain' (the last "
                            "confident model stays, marked stale); 0 = off", 0.0, 1e6),
    "refine": Spec(False, "bool", "refine each solve's estimate on the simulation error of the window "
                   "(identify --refine; slower solves, unbiased poles under output noise)"),
    "solve_rate": Spec(2.0, "float", "solves per second (a slow solve skips solves, never samples)", 0.01, 1000.0),
    "solver_process": Spec(True, "bool", "solve and diagnose in worker processes of the node's own, so that "
                           "neither holds the interpreter lock against ingestion; false = in the node's threads",
                           read_only=True),
    "diagnosis_period": Spec(30.0, "float", "seconds between diagnoses of the window published on ~/diagnosis "
                             "(hammer_ros.diagnosis, in the diagnosis process: see solver_process); 0 = off",
                             0.0, 86400.0),
    "diagnosis_window": Spec(10_000, "int", "the newest samples of the window that a diagnosis uses (its cost "
                             "grows faster than linearly: ~2 s for 10^4 samples)", 100, MAX_WINDOW),
    "frame_id": Spec("", "str", "frame_id of the stamped result messages"),
    "qos_depth": Spec(1000, "int", "history depth of the input subscriptions", 1, 1_000_000, read_only=True),
    "max_pending": Spec(1_000_000, "int", "samples queued per input between the callbacks and the engine; a "
                        "message that does not fit is dropped and counted (queue_dropped)", 1000, 100_000_000,
                        read_only=True),
    "output_mcap": Spec("", "str", "record every published result (ROS 2 messages) in this MCAP file, finished on "
                        "shutdown (SIGINT/SIGTERM) with the final model; '' = off", read_only=True),
    "foxglove_port": Spec(0, "int", "port of the in-process Foxglove WebSocket server of the dashboard channels; "
                          "0 = off", 0, 65535, read_only=True),
    "foxglove_host": Spec("127.0.0.1", "str", "address the Foxglove server listens on (loopback by default; "
                          "0.0.0.0 = every interface)", read_only=True),
}
ENGINE_FIELDS = {f.name for f in fields(EngineConfig)} & set(PARAMETERS)
STREAM_PARAMETERS = {f"{s}_{k}": s for s in STREAMS for k in ("topic", "type", "field")}
DIAGNOSIS_TYPE = "std_msgs/msg/String"


def check_field(cls, path: FieldPath) -> None:
    """Raise FieldError when ``path`` cannot exist in messages of ``cls``: checked on a default
    message down to the first index (array lengths are only known at run time); a path without
    an index must end at a number or a numeric array."""
    value = cls()
    for step in path.steps:
        names = value.get_fields_and_field_types() if hasattr(value, "get_fields_and_field_types") else {}
        if step.name not in names:
            known = f" (fields: {', '.join(names)})" if names else ""
            raise FieldError(f"field {path.text!r}: no field {step.name!r} in {type(value).__name__}{known}")
        if step.element_name is not None and NAME_FIELD not in names:
            raise FieldError(f"field {path.text!r}: [{step.element_name}] is looked up in a sibling "
                             f"{NAME_FIELD!r} array, and {type(value).__name__} has none")
        value = getattr(value, step.name)
        if step.indices:
            return
    extract_samples(cls(), path)


def _coerce(name: str, value: Any) -> Any:
    """A parameter value checked against its Spec (UsageError naming the parameter)."""
    spec = PARAMETERS[name]
    if spec.kind == "str":
        if not isinstance(value, str):
            raise UsageError(f"{name}: must be a string (got {value!r})")
        if spec.choices and value not in spec.choices:
            raise UsageError(f"{name}: {value!r} is not one of {', '.join(spec.choices)}")
        return value
    if spec.kind == "bool":
        if not isinstance(value, bool):
            raise UsageError(f"{name}: must be true or false (got {value!r})")
        return value
    if spec.kind == "floats":
        if type(value).__name__ == "array":  # rclpy hands DOUBLE_ARRAY values over as array.array('d')
            value = list(value)
        if value is None or (isinstance(value, (list, tuple)) and len(value) == 0):
            return None
        if not isinstance(value, (list, tuple)) or not all(isinstance(x, (int, float)) for x in value):
            raise UsageError(f"{name}: must be a list of numbers (got {value!r})")
        return tuple(float(x) for x in value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UsageError(f"{name}: must be a number (got {value!r})")
    if spec.kind == "int":
        if value != int(value):
            raise UsageError(f"{name}: must be an integer (got {value!r})")
        value = int(value)
    else:
        value = float(value)
    if (spec.low is not None and value < spec.low) or (spec.high is not None and value > spec.high):
        raise UsageError(f"{name}: must be in [{spec.low:g}, {spec.high:g}] (got {value!r})")
    return value


def engine_config(values: dict[str, Any]) -> EngineConfig:
    """The EngineConfig of a full set of coerced parameter values (validated)."""
    changes = {k: values[k] for k in ENGINE_FIELDS}
    changes["mu"] = changes["mu"] or None
    return replace(EngineConfig(), **changes).validated()


def _descriptor(name: str, spec: Spec) -> ParameterDescriptor:
    d = ParameterDescriptor(description=spec.description, read_only=spec.read_only,
                            dynamic_typing=spec.kind in ("int", "float"))
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if spec.kind == "int" and spec.low is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=0)]
    elif spec.kind == "float" and spec.low is not None:
        d.floating_point_range = [FloatingPointRange(from_value=spec.low, to_value=spec.high, step=0.0)]
    return d


class _Input:
    """One input stream: its subscription, message type and field path."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.subscription = None
        self.path: FieldPath | None = None
        self.raw = None  # cdr.raw_extractor(type, path): samples and stamp from serialized messages
        self.read = None  # message (serialized or built by rclpy) -> (samples, header stamp or 0.0)
        self.message_samples = 1  # samples of the last message read: what a queued message counts
        self.pending: deque = deque()  # (receive time, message, read) from the callback to the ingest thread
        self.pending_limit = 1  # messages the queue takes: max_pending / message_samples
        self.field_errors = 0
        self.last_error = ""
        self.queue_dropped = 0  # messages dropped because the queue to the engine was full (max_pending)
        self._lost_status = None  # the subscription's message-lost status, read by ``dds_lost``
        self._lost_before = 0  # messages lost by the subscriptions before this one
        self.wrong_type = ""  # publishers of another type on the topic (their messages never arrive)
        self.shared: _Input | None = None  # the subscription of a topic read by several channels (``channels``)
        self.feed = None  # channels.SharedTopic: its decoded chunks come into ``pending`` (``_decoded``)
        self.headed = False  # the message type has a std_msgs/Header: a zero stamp there is a missing stamp
        self.zero_stamps = 0  # messages with a header stamp of zero
        self.arrivals: deque = deque(maxlen=ARRIVALS)  # receive times of the last zero-stamped messages
        self.arrival_map = (np.empty(0), np.empty(0))  # (receive times, stamps of their last samples): last flush
        self.by_arrival: list[tuple[int, int, float]] = []  # (start, samples, receive time) placed at the flush's end

    def subscribe(self, node, cls, topic: str, callback: Callable, qos: QoSProfile, raw: bool) -> None:
        """(Re)subscribe. The middleware's message-lost status is read when asked (``dds_lost``),
        never taken as an event: the EventsExecutor takes each message-lost event in the thread
        that takes the messages, so once losses begin the messages wait behind them (at 60 000
        Float64 messages/s per topic, 3 of 6 runs lost 42-74 % of the samples with that thread
        found in the event handler's take; none of 6 with the status read here)."""
        self.unsubscribe(node)
        self.subscription = node.create_subscription(cls, topic, callback, qos, raw=raw)
        try:
            with self.subscription.handle:
                self._lost_status = _rclpy.EventHandle(self.subscription.handle,
                                                       QoSSubscriptionEventType.RCL_SUBSCRIPTION_MESSAGE_LOST)
        except UnsupportedEventTypeError:  # a middleware without the status: counted as 0
            self._lost_status = None

    def unsubscribe(self, node) -> None:
        if self.subscription is None:
            return
        self._lost_before = self.dds_lost()
        if self._lost_status is not None:
            self._lost_status.destroy_when_not_in_use()
            self._lost_status = None
        node.destroy_subscription(self.subscription)
        self.subscription = None

    def dds_lost(self) -> int:
        """Messages the middleware reports lost before the callback, over all subscriptions."""
        if self.shared is not None:
            return self.shared.dds_lost()
        status = self._lost_status
        if status is None:
            return self._lost_before
        try:
            with status:
                return self._lost_before + status.take_event().total_count
        except InvalidHandle:  # destroyed meanwhile (deactivate)
            return self._lost_before

    def dropped(self) -> int:
        """Messages dropped because a queue to the engine was full (its own, the shared topic's)."""
        return self.queue_dropped + (self.shared.queue_dropped if self.shared is not None else 0)

    def publishers(self) -> int:
        """Publishers matched with the subscription (0 when unsubscribed): the middleware delivers
        only their messages, so 0 while a publisher is still being discovered or has a QoS that
        cannot match."""
        if self.shared is not None:
            return self.shared.publishers()
        try:
            return self.subscription.get_publisher_count() if self.subscription is not None else 0
        except InvalidHandle:  # destroyed meanwhile (deactivate): none
            return 0


def _queueing_callback(source: _Input) -> Callable[[Any], None]:
    """The subscription callback of ``source``: queue the message with its arrival time and the
    subscription's ``read``, nothing more. The executor thread is what limits the node's message
    rate, so the samples are read from the message (raw CDR or rclpy's message) in the ingest
    thread, and the callback is one closure over a deque (thread-safe appends, no lock; 0.14 us a
    message here against 0.36 us for a method behind a lambda taking a lock). The queue is bounded
    at max_pending samples, a message counted at the size of its stream's last one."""
    queue, read, now = source.pending, source.read, time.time

    def on_message(msg) -> None:
        if len(queue) < source.pending_limit:
            queue.append((now(), msg, read))
        else:  # a flood is dropped
            source.queue_dropped += 1

    return on_message


def built_reader(path: FieldPath) -> Callable[[Any], tuple]:
    """``read`` of messages built by rclpy: (samples at ``path``, header stamp or 0.0)."""
    return lambda msg: (extract_samples(msg, path), message_stamp(msg) or 0.0)


def _drained(queue: deque) -> list:
    """What ``queue`` holds now, taken out (the callback may append meanwhile)."""
    return [queue.popleft() for _ in range(len(queue))]


def close_output_mcap(writer: ResultWriter | None) -> None:
    """Finish an output_mcap file, its message count (or why it failed) on stderr."""
    if writer is None:
        return
    try:
        writer.close()
        print(f"hammer_ros_node: {writer.count} messages in {writer.path}", file=sys.stderr)
    except OSError as exc:  # e.g. the disk is full
        print(f"hammer_ros_node: error: output_mcap {writer.path}: {exc.strerror or exc}", file=sys.stderr)


class IdentificationCore:
    """The identification node's implementation, shared by the unmanaged ``IdentificationNode``
    and the lifecycle ``managed_node.ManagedIdentificationNode`` (a mixin of an rclpy Node):
    ``configure`` (parameters checked, engine, publishers, output_mcap, Foxglove server),
    ``activate`` (subscriptions and worker threads), ``deactivate`` (ingestion stops, the last
    model stays), ``close`` (final solve, output_mcap finished, everything released)."""

    def _setup(self) -> None:
        """Declare the parameters, the services and the state of an unconfigured node."""
        for name, spec in PARAMETERS.items():
            default = Parameter.Type.DOUBLE_ARRAY if spec.default is None else spec.default
            try:
                self.declare_parameter(name, default, _descriptor(name, spec))
            except ParameterException as exc:  # an override outside the descriptor's range or type
                raise UsageError(f"{name}: {' '.join(str(exc).split())}") from None
        self._init_state()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.trigger_services = NodeServices(self)

    def _init_state(self) -> None:
        """The state of an unconfigured node (or of one channel of ``channels.ChannelSet``)."""
        self._lock = threading.Lock()  # guards the engine and the stamper
        self._solve_lock = threading.Lock()  # one solve at a time (the solver thread, ~/solve)
        self._diagnose_lock = threading.RLock()  # one diagnosis at a time (the diagnosis thread, ~/diagnose)
        self._writer_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._workers: list[threading.Thread] = []
        self.engine: StreamingEngine | None = None
        self.active = False
        self.finalized = False  # a managed node after its shutdown transition: main() returns
        self.server = None  # foxglove_server.DashboardServer when foxglove_port > 0
        self.solver: SolverProcess | None = None  # when solver_process is true
        self.solver_lost = ""  # why the solver process is gone, when it went
        self.diagnoser: SolverProcess | None = None  # the diagnoses' process, started by the first diagnosis
        self.diagnoser_lost = ""  # why it is gone, when it went
        self._writer: ResultWriter | None = None
        self._outputs: dict[str, Any] = {}
        self.inputs = {s: _Input(s) for s in (*STREAMS, REFERENCE)}
        self.last_outcome: SolveOutcome | None = None
        self.skipped_solves = 0
        self.closed_loop: bool | None = None  # the last diagnosis's ``closed_loop`` verdict (None: none yet)
        self.loop_errors = 0  # unexpected exceptions in the ingest/solve loops (logged; the loops go on)
        self._cpu_mark = (time.monotonic(), time.process_time())  # ``_cpu_percent``'s last reading
        self.channel_set = None  # channels.ChannelSet when the params file has several channels

    def _create_output_publisher(self, cls, topic: str, qos):
        return self.create_publisher(cls, topic, qos)

    def _destroy_output_publisher(self, publisher) -> None:
        self.destroy_publisher(publisher)

    def configure(self) -> None:
        """Check every parameter (UsageError naming the first bad one) and build the engine, the
        publishers, the output_mcap writer and the Foxglove server; with several ``channels`` in
        the params file, a ``channels.ChannelSet`` of one such core per channel instead."""
        channels = self._file_channels()
        if len(channels) > 1:
            self.channel_set = self._channel_set(channels)
            return
        if channels:  # one channel: its parameters are the node's
            self._apply_parameters(self._channel_values(channels[0]))
        self.values = {name: _coerce(name, self._declared_value(name)) for name in PARAMETERS}
        config = engine_config(self.values)
        for stream in self._streams():  # fail fast on a bad configuration
            self._check_stream(stream, self.values)
        if self.values["reference_topic"] and self.values["method"] not in REFERENCE_METHODS:
            raise UsageError(f"reference_topic: the method {self.values['method']} has no instrumented form "
                             f"(use one of {', '.join(REFERENCE_METHODS)})")
        if self.values["foxglove_port"]:
            from .foxglove_server import DashboardServer  # the SDK only when asked for

            self.server = DashboardServer(self.values["foxglove_host"], self.values["foxglove_port"], self.get_name(),
                                          self._warn_throttled, parameters=self,
                                          services=self.trigger_services.handlers)
        self.engine = self._new_engine(config)
        self.stamper = ArrivalStamper(self.values["sample_rate"])
        self.unplaced = 0  # samples seen while the stamper still infers the rate
        if self.values["solver_process"]:
            self.solver = SolverProcess()
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for topic, type_name in [*OUTPUT_TOPICS, ("~/diagnosis", DIAGNOSIS_TYPE)]:
            qos = latched if topic in ("~/model", "~/diagnosis") else 10
            self._outputs[topic] = self._create_output_publisher(output_message_class(type_name), topic, qos)
        self._writer = ResultWriter(self.values["output_mcap"], "output_mcap") if self.values["output_mcap"] else None
        serving = f"; Foxglove on ws://{self.values['foxglove_host']}:{self.server.port}" if self.server else ""
        self.get_logger().info(
            f"identifying {self.values['excitation_topic']}:{self.values['excitation_field']} -> "
            f"{self.values['response_topic']}:{self.values['response_field']} with {self.values['method']} "
            f"(order {self.values['order']}, delay {self.values['delay']}, window {self.values['window']}){serving}")

    # the channels of the params file: ``channels.ChannelSupport`` (a mixin of the node classes, so that this
    # module, which ``channels`` builds on, does not import it)
    def _file_channels(self) -> list:
        raise NotImplementedError("a node class mixes in channels.ChannelSupport")

    def _channel_set(self, channels: list):
        raise NotImplementedError("a node class mixes in channels.ChannelSupport")

    def _channel_values(self, channel) -> dict[str, Any]:
        raise NotImplementedError("a node class mixes in channels.ChannelSupport")

    def _apply_parameters(self, params: dict[str, Any]) -> None:
        """Set the node parameters of ``params`` that differ from the declared ones (UsageError
        naming the first refused)."""
        changes = [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in params.items()
                   if v != self._declared_value(k)]
        for change in changes:
            result = self.set_parameters([change])[0]
            if not result.successful:
                raise UsageError(f"{change.name}: {result.reason}")

    def activate(self) -> None:
        """Subscribe to the inputs and start the ingest, solve and diagnosis threads; with a solver
        process, once it is ready (at most WORKER_READY_SECONDS): its start, about 0.7 s of CPU
        for imports, would otherwise compete with the first second of ingestion (2-core bench VM,
        a fresh node fed 20 000 - 32 000 100-sample messages/s per topic for 3 s as soon as it
        reported its subscriptions: lossy in 10 of 18 runs without the wait, 4 of 18 with it)."""
        if self.channel_set is not None:
            return self.channel_set.activate()
        if self.solver is not None and not self.solver.wait_ready(WORKER_READY_SECONDS):
            self.get_logger().warning(f"the solver process is not ready after {WORKER_READY_SECONDS:g} s; "
                                      "subscribing anyway (solves wait for it)")
        for stream in self._streams():
            self._subscribe(stream)
        self._stop = stop = threading.Event()  # per activation: a thread still finishing a solve sees its own
        self._workers = [threading.Thread(target=loop, args=(stop,), name=f"hammer_ros_{what}", daemon=True)
                         for loop, what in ((self._ingest_loop, "ingest"), (self._solve_loop, "solver"),
                                            (self._diagnosis_loop, "diagnosis"))]
        self.active = True
        for worker in self._workers:
            worker.start()

    def deactivate(self, publish: bool = True) -> None:
        """Stop ingesting: unsubscribe, stop the threads (a running solve is waited for up to 1 s),
        move the queued samples in; with ``publish`` the counters at this point on /diagnostics."""
        if self.channel_set is not None:
            return self.channel_set.deactivate(publish)
        self.active = False
        for source in self.inputs.values():
            source.unsubscribe(self)
        self.stop()
        self._guarded(self._flush, "ingesting")
        if publish:
            with self._lock:
                stats = self.engine.stats.copy()
            diagnostics = diagnostics_message(stats, self.last_outcome, self._now(), self._status_name())
            self._add_node_diagnostics(diagnostics["status"][0])
            self._outputs["/diagnostics"].publish(to_ros_message("diagnostic_msgs/msg/DiagnosticArray", diagnostics))

    def cleanup(self) -> None:
        """Release what ``configure`` built (the last model is forgotten)."""
        if self.channel_set is not None:
            self.channel_set.cleanup()
            self.channel_set = None
            return
        if self.server is not None:
            self.server.stop()
            self.server = None
        for worker in (self.solver, self.diagnoser):
            if worker is not None:
                worker.close()
        self.solver = self.diagnoser = None
        for publisher in self._outputs.values():
            self._destroy_output_publisher(publisher)
        self._outputs = {}
        self.engine = None
        self.last_outcome = None

    def close(self) -> SolveOutcome | None:
        """On shutdown: stop ingesting, solve once more, finish output_mcap, release everything;
        returns the final outcome (None if there was none; with several channels, always None)."""
        if self.channel_set is not None:
            self.channel_set.close()
            self.channel_set = None
        if self.active:
            self.deactivate(publish=False)
        outcome = None
        if self.engine is not None:
            outcome = self.finish()
            self.cleanup()
        self.trigger_services.close()
        return outcome

    def _status_name(self) -> str:
        """The name of the node's status on /diagnostics (before ': identification'), and the
        node-name part of the topics output_mcap records (``/NAME/model``, ...)."""
        return self.get_name()

    def _now(self) -> int:
        """The node clock in integer nanoseconds (the stamp of what the node publishes)."""
        return self.get_clock().now().nanoseconds

    def _warn_throttled(self, text: str) -> None:
        self.get_logger().warning(text, throttle_duration_sec=5.0)

    def _declared_value(self, name: str) -> Any:
        try:
            return self.get_parameter(name).value
        except ParameterUninitializedException:  # a list parameter declared without a value
            return None

    # ------------------------------------------------------------------ inputs
    def _subscribe(self, stream: str) -> None:
        source, cls, qos = self._prepare_input(stream)
        source.subscribe(self, cls, self.values[f"{stream}_topic"], _queueing_callback(source), qos,
                         raw=source.raw is not None)

    def _prepare_input(self, stream: str) -> tuple[_Input, Any, QoSProfile]:
        """The input of ``stream`` made ready to read its messages: (input, message class, QoS)."""
        source = self.inputs[stream]
        cls = message_class(self.values[f"{stream}_type"])
        source.headed = cls.get_fields_and_field_types().get("header") == "std_msgs/Header"
        source.path = parse_field_path(self.values[f"{stream}_field"])
        source.raw = raw_extractor(cls, source.path)  # None: rclpy builds the messages
        source.read = source.raw or built_reader(source.path)
        qos = QoSProfile(depth=self.values["qos_depth"], reliability=qos_profile_sensor_data.reliability,
                         durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)
        source.pending_limit = max(1, self.values["max_pending"] // source.message_samples)
        return source, cls, qos

    def _new_engine(self, config: EngineConfig) -> StreamingEngine:
        """An empty engine of ``config`` (holding the reference when ``reference_topic`` is set)."""
        return StreamingEngine(config, reference=bool(self.values["reference_topic"]))

    def _streams(self) -> tuple[str, ...]:
        """The input streams: excitation, response and, when ``reference_topic`` is set, reference."""
        return (*STREAMS, REFERENCE) if self.values["reference_topic"] else STREAMS

    def _bad_message(self, stream: str, exc: Exception) -> None:
        self._bad_messages(stream, 1, str(exc) if isinstance(exc, FieldError) else f"{type(exc).__name__}: {exc}")

    def _bad_messages(self, stream: str, count: int, why: str) -> None:
        """``count`` messages of ``stream`` skipped, the last for ``why``: counted, warned (throttled)."""
        source = self.inputs[stream]
        source.field_errors += count
        source.last_error = why
        self.get_logger().warning(f"{stream} {self.values[f'{stream}_topic']}: {why}", throttle_duration_sec=5.0)

    def _distribute(self) -> None:
        """Decode the shared topics' queued messages for every channel reading them (``channels``)."""
        for source in self.inputs.values():
            if source.feed is not None:
                source.feed.distribute()

    def _flush(self) -> None:
        """Move the queued samples into the engine: one vectorised add of both streams,
        interleaved in time (``StreamingEngine.add_streams``)."""
        with self._lock:
            self._distribute()
            pending = {stream: _drained(source.pending) for stream, source in self.inputs.items()}
            batches = {stream: (self._decoded if self.inputs[stream].feed else self._stamped)(stream, items)
                       for stream, items in pending.items() if items}
            reference = batches.pop(REFERENCE, None)
            if reference is not None:
                self.engine.add_reference(*reference)
            self._place_by_arrival(batches)
            self.engine.add_streams({k: v for k, v in batches.items() if v is not None})
            for source in self.inputs.values():
                source.pending_limit = max(1, self.values["max_pending"] // source.message_samples)

    def _stamped(self, stream: str, items: list[tuple[float, Any, Callable]]) -> tuple | None:
        """(stamps, values) of one stream's queued messages (None when none could be placed): each
        message's samples read (a bad one counted and skipped), then per message only its first
        stamp found; the stamps of all samples are made at once, ``first + k / fs`` for the k-th
        sample of each message. Messages of one layout without a header stamp: ``_counted``."""
        receives, messages, reads = zip(*items)
        read = reads[0]  # serialized messages of one layout, all from one subscription: read at once
        block = extract_batch(read, list(messages)) if reads.count(read) == len(reads) else None
        if block is not None:
            return self._counted(stream, receives, block)
        firsts: list[float] = []
        sizes: list[int] = []
        values: list = []
        arrived: list[float] = []
        explicit: list[tuple[int, np.ndarray]] = []  # stamped batches placed by the engine's rule
        total = 0
        source = self.inputs[stream]
        for receive, msg, read in items:
            try:
                x, stamp = read(msg)
            except Exception as exc:  # FieldError, or anything odd in a message: counted, never fatal
                self._bad_message(stream, exc)
                continue
            n = source.message_samples = 1 if type(x) is float else x.size
            if n == 0:
                continue
            if stamp and n == 1:
                first = stamp
            elif stamp:  # a stamped batch: the last sample at the stamp
                t = (self.engine.message_stamps(stream, stamp, n) if stream != REFERENCE else
                     stamp - np.arange(n - 1, -1, -1) / self.stamper.rate if self.stamper.rate else None)
                if t is None:
                    self.engine.stats.unstamped += 1
                    continue
                explicit.append((total, t))
                first = t[0]
            elif source.headed and self._sparse(stream, receive, n):
                source.by_arrival.append((total, n, receive))
                first = math.nan  # placed at the end of the flush (``_place_by_arrival``)
            else:
                first = self.stamper.first_stamp(stream, receive, n)
                if first is None:
                    self.unplaced += n
                    continue
            firsts.append(first)
            sizes.append(n)
            values.append(x)
            arrived.append(receive)
            total += n
        if not values:
            return None
        floats = [type(x) is float for x in values]
        counts = np.array(sizes)
        if all(floats):  # single samples
            stamps, joined = np.array(firsts), np.array(values)
        else:
            offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)  # k within its message
            # (fs is known whenever a batch was placed by counting; explicit stamps overwrite theirs)
            stamps = np.repeat(np.array(firsts), counts) + offsets / (self.stamper.rate or 1.0)
            for start, t in explicit:
                stamps[start:start + t.size] = t
            joined = np.concatenate([np.atleast_1d(x) for x in values] if any(floats) else values)
        ends = stamps[np.cumsum(counts) - 1]
        placed = np.isfinite(ends)
        if placed.any():
            source.arrival_map = (np.array(arrived)[placed], ends[placed])
        return stamps, joined

    def _sparse(self, stream: str, receive: float, samples: int) -> bool:
        """Whether ``stream``, whose message received at ``receive`` has a zero header stamp,
        publishes far below the grid rate (module docstring), or is not yet known not to (its first
        message); counts and logs the zero stamp."""
        source = self.inputs[stream]
        if not source.zero_stamps:
            self.get_logger().warning(f"{stream} {self.values[f'{stream}_topic']}: header.stamp is zero (no stamp): "
                                      "its samples are placed by their receive times")
        source.zero_stamps += 1
        source.arrivals.append(receive)
        if stream == REFERENCE or (not self.stamper.rate and samples > 1):
            return False
        if len(source.arrivals) < 2 or not self.stamper.rate:  # not yet known: never counted on a wrong clock
            return True
        interval = float(np.median(np.diff(source.arrivals)))
        return interval > HOLD_PERIODS * samples / self.stamper.rate

    def _place_by_arrival(self, batches: dict[str, tuple | None]) -> None:
        """Stamp the samples left for it by ``_stamped`` (zero-stamped messages of a sparse
        stream): the message's receive time r read on the other stream's stamps, s_j + (r - r_j)
        for the other stream's message j received nearest to r (its receive time r_j, its last
        sample's stamp s_j): whatever that stream's time base (a robot's clock, a bag's recording
        time played at any rate, or receive times) the message lands where the other stream was
        when it arrived. Before the other stream's first message it cannot be placed (unplaced)."""
        for stream, other in (STREAMS, STREAMS[::-1]):
            source = self.inputs[stream]
            if not source.by_arrival or batches.get(stream) is None:
                source.by_arrival.clear()
                continue
            stamps, values = batches[stream]
            receives, ends = self.inputs[other].arrival_map
            for start, n, receive in source.by_arrival:
                if receives.size:
                    j = int(np.argmin(np.abs(receives - receive)))
                    last = ends[j] + receive - receives[j]
                    stamps[start:start + n] = last - np.arange(n - 1, -1, -1) / (self.stamper.rate or 1.0)
                else:
                    self.unplaced += n
            source.by_arrival.clear()
            placed = np.isfinite(stamps)
            if not placed.all():
                batches[stream] = (stamps[placed], values[placed]) if placed.any() else None

    def _decoded(self, stream: str, chunks: list[tuple]) -> tuple | None:
        """``_stamped`` for the chunks of a shared topic (``SharedTopic.distribute``: receive
        times, values, bad, header stamps, why bad), one number per message: a bad one counted
        and skipped, a message with a stamp at its stamp, the others stamped by the stamper."""
        receives, values, bad, stamps = (np.concatenate(column) for column in list(zip(*chunks))[:4])
        if bad.any():
            self._bad_messages(stream, int(np.count_nonzero(bad)), next(c[4] for c in reversed(chunks) if c[2].any()))
            good = ~bad
            receives, values, stamps = receives[good], values[good], stamps[good]
        self.inputs[stream].message_samples = 1
        unstamped = stamps == 0.0
        if unstamped.any():
            stamps[unstamped] = self.stamper.first_stamps(stream, receives[unstamped], 1)
        placed = np.isfinite(stamps)
        self.unplaced += placed.size - int(np.count_nonzero(placed))
        return (stamps[placed], values[placed]) if placed.any() else None

    def _counted(self, stream: str, receives: tuple[float, ...], block: np.ndarray) -> tuple | None:
        """``_stamped`` for messages of one layout without a header stamp (``extract_batch``'s
        block, a row per message): the stamper counts the first samples of all of them at once."""
        n = self.inputs[stream].message_samples = block.shape[1]
        if n == 0:
            return None
        firsts = self.stamper.first_stamps(stream, np.array(receives), n)
        placed = np.isfinite(firsts)
        self.unplaced += n * (placed.size - int(np.count_nonzero(placed)))
        if not placed.any():
            return None
        self.inputs[stream].arrival_map = (np.array(receives)[placed], firsts[placed] + (n - 1) / self.stamper.rate)
        return (firsts[placed, None] + np.arange(n) / self.stamper.rate).ravel(), block[placed].ravel()

    def _ingest_loop(self, stop: threading.Event) -> None:
        while not stop.wait(FLUSH_PERIOD):
            self._guarded(self._flush, "ingesting")

    def _guarded(self, step, what: str) -> None:
        """Run one loop step; an unexpected exception is logged and counted, the loop goes on."""
        try:
            step()
        except Exception as exc:  # the node never dies on a bug in one step
            self.loop_errors += 1
            self.get_logger().error(f"{what} failed ({type(exc).__name__}: {exc}); continuing",
                                    throttle_duration_sec=5.0)

    # ------------------------------------------------------------------ parameters
    def parameter_values(self) -> dict[str, Any]:
        """The current value of every node parameter (None: unset), for the Foxglove server."""
        return {name: self._declared_value(name) for name in PARAMETERS}

    def set_parameter_value(self, name: str, value: Any) -> tuple[bool, str]:
        """Set one parameter as rclpy's SetParameters service does (``set_parameters_atomically``
        of it alone), so a change from Foxglove is validated exactly as one from ``ros2 param set``
        and refused with the same reason; (successful, reason)."""
        try:
            result = self.set_parameters_atomically([Parameter(name, value=value)])
        except (ParameterNotDeclaredException, TypeError, ValueError) as exc:  # TypeError: no parameter type
            return False, str(exc)
        return result.successful, result.reason

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        if self.channel_set is not None:
            return SetParametersResult(successful=False, reason="several channels: their parameters are read from "
                                       "the params file at startup")
        try:
            current = dict(self.values) if self.engine is not None else {
                name: _coerce(name, self._declared_value(name)) for name in PARAMETERS}
            proposed = dict(current)
            for p in parameters:
                if p.name not in PARAMETERS:
                    continue
                if PARAMETERS[p.name].read_only:
                    raise UsageError(f"{p.name}: read-only (set it at startup)")
                proposed[p.name] = _coerce(p.name, p.value)
            config = engine_config(proposed)
            changed = {k for k in PARAMETERS if proposed[k] != current[k]}
            for stream in {STREAM_PARAMETERS[k] for k in changed & set(STREAM_PARAMETERS)}:
                self._check_stream(stream, proposed)
        except UsageError as exc:
            self.get_logger().warning(f"parameter change rejected: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        if self.engine is None:  # unconfigured (managed node): configure reads the parameters
            return SetParametersResult(successful=True)
        self.values = proposed
        streams = {STREAM_PARAMETERS[k] for k in changed & set(STREAM_PARAMETERS)}
        with self._lock:
            if streams:  # a new signal: the window restarts
                for source in self.inputs.values():
                    source.pending.clear()
                self.engine = self._new_engine(config)
                self.stamper.set_rate(config.sample_rate)
                for stream in streams if self.active else ():
                    self._subscribe(stream)
            else:
                self.engine.reconfigure(**{k: getattr(config, k) for k in changed & ENGINE_FIELDS})
                if "sample_rate" in changed:
                    self.stamper.set_rate(config.sample_rate)
        if changed:
            self.get_logger().info("parameters applied: " + ", ".join(f"{k}={proposed[k]}" for k in sorted(changed)))
            if self.server is not None:
                self.server.parameters_changed({k: proposed[k] for k in changed})
        self._wake.set()
        return SetParametersResult(successful=True)

    def _check_stream(self, stream: str, values: dict[str, Any]) -> None:
        topic = values[f"{stream}_topic"]
        try:
            validate_full_topic_name(expand_topic_name(topic, self.get_name(), self.get_namespace()))
        except Exception as exc:  # rclpy raises several exception types for bad names
            raise UsageError(f"{stream}_topic: invalid topic name {topic!r} ({str(exc).split(',')[0]})") from None
        try:
            cls = message_class(values[f"{stream}_type"])
        except UsageError as exc:
            raise UsageError(f"{stream}_type: {exc}") from None
        try:
            check_field(cls, parse_field_path(values[f"{stream}_field"]))
        except UsageError as exc:
            raise UsageError(f"{stream}_field: {exc}") from None

    # ------------------------------------------------------------------ solving
    def _solve_loop(self, stop: threading.Event) -> None:
        deadline = time.monotonic()
        while not stop.is_set():
            period = 1.0 / self.values["solve_rate"]
            deadline += period
            now = time.monotonic()
            if deadline < now:  # the last solve overran: skip the missed ticks
                self.skipped_solves += int((now - deadline) / period) + 1
                deadline = now + period
            self._wake.wait(deadline - now)
            if self._wake.is_set():
                self._wake.clear()
                deadline = time.monotonic()
            if stop.is_set():
                return
            self._guarded(self._solve_once, "solving")

    def _solve_once(self, publish: bool = True) -> SolveOutcome:
        with self._solve_lock:
            self._flush()
            if publish:  # (not on shutdown: the graph is gone)
                self._check_publisher_types()
            with self._lock:
                engine = self.engine
                snapshot = engine.snapshot()
            outcome = self._solve(snapshot)  # never raises: a failing method gives ok False, status "exception"
            if outcome.status == "exception":
                self.get_logger().error(f"solve failed: {outcome.reason}", throttle_duration_sec=5.0)
            with self._lock:
                if engine is self.engine:
                    engine.record(outcome)
                stats = engine.stats.copy()
            self._publish(outcome, stats, publish)
            return outcome

    def _diagnosis(self, v: np.ndarray, y: np.ndarray, reference: np.ndarray | None) -> dict[str, Any]:
        """``diagnose_window`` (instrumented by ``reference`` when the node has one over the window)
        in the diagnosis process (with ``solver_process``; started by the first diagnosis, so a node
        that never diagnoses never pays for it), or here when there is none (or it is gone). Called
        under ``_diagnose_lock``."""
        order = self.values["order"]
        if self.values["solver_process"] and not self.diagnoser_lost:
            try:
                if self.diagnoser is None:
                    self.diagnoser = SolverProcess(role="diagnosis")
                return self.diagnoser.diagnose(v, y, order, reference)
            except RuntimeError as exc:
                self.get_logger().error(f"diagnosis process lost ({exc}); diagnosing in the node's thread from now on")
                self.diagnoser.close()
                self.diagnoser, self.diagnoser_lost = None, str(exc)
        return diagnose_window(v, y, order, reference)

    def _solve(self, snapshot: EngineSnapshot) -> SolveOutcome:
        """``solve_snapshot`` in the solver process, or here when there is none (or it is gone)."""
        if self.solver is not None:
            try:
                return self.solver.solve(snapshot)
            except RuntimeError as exc:
                self.get_logger().error(f"solver process lost ({exc}); solving in the node's thread from now on")
                self.solver.close()
                self.solver, self.solver_lost = None, str(exc)
        return solve_snapshot(snapshot)

    def _diagnosis_loop(self, stop: threading.Event) -> None:
        """Every ``diagnosis_period`` s: ``diagnose_record`` on the newest ``diagnosis_window``
        samples of the raw window (estimation on their first 70 %, validation on the rest),
        published as JSON on ~/diagnosis. The period is read every 0.5 s, so a live change
        applies at once."""
        last = time.monotonic()
        while not stop.wait(0.5):
            period = self.values["diagnosis_period"]
            if period > 0 and time.monotonic() - last >= period:
                last = time.monotonic()
                with self._diagnose_lock:
                    self._guarded(self._diagnose_once, "diagnosing")

    def _diagnose_once(self, snapshot: EngineSnapshot | None = None) -> dict[str, Any]:
        """Diagnose the newest ``diagnosis_window`` samples of the window (of ``snapshot``, else of
        a new one; with ``reference_topic``, instrumented by the reference over them), publish the
        JSON on ~/diagnosis and return it."""
        if snapshot is None:
            with self._lock:
                snapshot = self.engine.snapshot()
        v, y, r = newest_window(snapshot, self.values["diagnosis_window"])
        started = time.perf_counter()
        doc: dict[str, Any] = {"samples": int(v.size), "stamp": snapshot.stamp}
        doc |= self._diagnosis(v, y, r)
        doc["seconds"] = time.perf_counter() - started
        rows = [e for e in doc.get("evidence", ()) if e.get("test") == CLOSED_LOOP_TEST]
        self.closed_loop = (not rows[0]["passed"]) if rows else None
        self._send([diagnosis_message(doc)], self._now(), publish=self.active)
        return doc

    def _publish(self, outcome: SolveOutcome, stats, publish: bool = True) -> None:
        """Publish (and record in output_mcap, first) the results of a solve; after a solve without
        a model, the last good model again, marked stale."""
        stamp = self._now()
        messages = outcome_messages(outcome, self.last_outcome, stats, stamp, frame_id=self.values["frame_id"],
                                    status_name=self._status_name(), complete_status=self._add_node_diagnostics)
        if outcome.ok:
            self.last_outcome = outcome
        self._send(messages, stamp, publish)

    def _send(self, messages: list[tuple[str, str, dict]], stamp_ns: int, publish: bool) -> None:
        """Record ``messages`` in output_mcap (ROS 2 messages only), hand their dashboard
        channels to the Foxglove server (never waits) and, with ``publish``, publish them."""
        server = self.server
        with self._writer_lock:
            if self._writer is not None:
                record_results(self._writer, messages, stamp_ns, self._status_name())
        if not publish:
            return
        if server is not None:
            server.publish(dashboard_messages(messages, stamp_ns), stamp_ns)
        try:
            for topic, type_name, values in messages:
                self._outputs[topic].publish(to_ros_message(type_name, values))
        except Exception as exc:  # the context may be shutting down under us
            if self.active:
                self.get_logger().error(f"publishing failed: {exc}")

    def _check_publisher_types(self) -> None:
        """Note publishers of another message type on an input topic: DDS never delivers their
        messages, so without this a wrong type would look like silence."""
        for stream in self._streams():
            source = self.inputs[stream]
            topic = expand_topic_name(self.values[f"{stream}_topic"], self.get_name(), self.get_namespace())
            wanted = _normal_type(self.values[f"{stream}_type"])
            others = sorted({info.topic_type for info in self.get_publishers_info_by_topic(topic)
                             if _normal_type(info.topic_type) != wanted})
            expected = self.values[f"{stream}_type"]
            source.wrong_type = (f"{stream}_topic {topic} has publishers of {', '.join(others)}, expected "
                                 f"{expected}: their messages cannot be received") if others else ""

    def finish(self) -> SolveOutcome | None:
        """On shutdown: move the queued samples in, solve once more, record the final results in
        output_mcap and finish that file; returns the final outcome (None if it failed)."""
        outcome = None
        try:
            outcome = self._solve_once(publish=False)
        except Exception as exc:  # still close the file
            print(f"hammer_ros_node: final solve failed ({type(exc).__name__}: {exc})", file=sys.stderr)
        with self._writer_lock:
            self._close_writer()
        if self.last_outcome is not None:
            stale = None if outcome is not None and outcome.ok else getattr(outcome, "reason", "final solve failed")
            print(f"hammer_ros_node: final model: {model_json(self.last_outcome, stale)}", file=sys.stderr)
        return outcome

    def _close_writer(self) -> None:
        """Finish output_mcap (its count on stderr) and forget it."""
        close_output_mcap(self._writer)
        self._writer = None

    def _add_node_diagnostics(self, status: dict) -> None:
        values: dict[str, Any] = {
            "ingesting": self.active,
            "excitation_field_errors": self.inputs["excitation"].field_errors,
            "response_field_errors": self.inputs["response"].field_errors,
            "unplaced_samples": self.unplaced,
            "clock_restarts": self.stamper.restarts,
            "excitation_zero_stamps": self.inputs["excitation"].zero_stamps,
            "response_zero_stamps": self.inputs["response"].zero_stamps,
            "skipped_solves": self.skipped_solves,
            "excitation_queue_dropped": self.inputs["excitation"].dropped(),
            "response_queue_dropped": self.inputs["response"].dropped(),
            "excitation_dds_lost": self.inputs["excitation"].dds_lost(),
            "response_dds_lost": self.inputs["response"].dds_lost(),
            "excitation_publishers": self.inputs["excitation"].publishers(),
            "response_publishers": self.inputs["response"].publishers(),
            "loop_errors": self.loop_errors,
            "cpu_percent": self._cpu_percent(),
            "solver": (f"process {self.solver.pid}" if self.solver is not None
                       else "thread" + (f" ({self.solver_lost})" if self.solver_lost else "")),
            "diagnosis": (f"process {self.diagnoser.pid}" if self.diagnoser is not None
                          else f"thread ({self.diagnoser_lost})" if self.diagnoser_lost
                          else "process, from the first diagnosis" if self.values["solver_process"] else "thread"),
            "window": self.values["window"],
            "method": self.values["method"],
        }
        if self.server is not None:
            values.update(self.server.diagnostics(), foxglove_port=self.server.port)
        status["values"].extend({"key": k, "value": str(v)} for k, v in values.items())
        if self.closed_loop is not None:
            status["values"].append({"key": "closed_loop", "value": str(self.closed_loop).lower()})
        if self.closed_loop and not self.values["reference_topic"]:
            status["level"] = max(status["level"], 1)
            status["message"] = f"{status['message']}; {CLOSED_LOOP_WARNING}"
        errors = [s.last_error for s in self.inputs.values() if s.field_errors]
        errors += [s.wrong_type for s in self.inputs.values() if s.wrong_type]
        if errors and status["level"] < 2:
            status["level"] = 1
        if errors:
            status["message"] = f"{status['message']}; bad messages: {errors[0]}"

    def _cpu_percent(self) -> float:
        """CPU time of the node's process (all its threads; not its worker processes) since the
        last reading, in % of one core (100 = one core busy)."""
        (wall, cpu), self._cpu_mark = self._cpu_mark, (time.monotonic(), time.process_time())
        elapsed = self._cpu_mark[0] - wall
        return round(100.0 * (self._cpu_mark[1] - cpu) / elapsed, 1) if elapsed > 0 else 0.0

    def stop(self) -> None:
        """Stop the worker threads (waits for a running solve up to 1 s)."""
        self._stop.set()
        self._wake.set()
        for worker in self._workers:
            worker.join(timeout=1.0)
        self._workers = []

    # ------------------------------------------------------------------ services (NodeServices)
    def _refusal(self) -> str:
        return "" if self.active else "the node is not active (managed node: configure and activate it first)"

    def reset_window(self) -> tuple[bool, str]:
        """~/reset: clear the window and the correlation sums (and the counters); parameters stay."""
        if self.channel_set is not None:
            return self.channel_set.each("reset_window")
        if self._refusal():
            return False, self._refusal()
        with self._solve_lock, self._lock:
            self._distribute()
            for source in self.inputs.values():
                source.pending.clear()
            dropped = self.engine.snapshot().v.size
            self.engine = self._new_engine(self.engine.config)
            self.stamper = ArrivalStamper(self.values["sample_rate"])
            self.last_outcome = None
        self.get_logger().info(f"window reset by ~/reset ({dropped} samples dropped)")
        return True, f"window and correlation sums cleared ({dropped} samples dropped); parameters kept"

    def solve_now(self) -> tuple[bool, str]:
        """~/solve: solve and publish now; the model JSON, or why there is none."""
        if self.channel_set is not None:
            return self.channel_set.each("solve_now")
        if self._refusal():
            return False, self._refusal()
        outcome = self._solve_once()
        if not outcome.ok:
            return False, f"no model: {outcome.reason}"
        return True, model_json(outcome)

    def diagnose_now(self) -> tuple[bool, str]:
        """~/diagnose: diagnose the window now and publish it; the diagnosis JSON, or why not."""
        if self.channel_set is not None:
            return self.channel_set.each("diagnose_now")
        if self._refusal():
            return False, self._refusal()
        with self._diagnose_lock:
            self._flush()
            with self._lock:
                snapshot = self.engine.snapshot()
            status, reason, _, _ = window_problem(snapshot)
            if status:
                return False, f"cannot diagnose: {reason}"
            doc = self._diagnose_once(snapshot)
        if "error" in doc:
            return False, doc["error"]
        return True, json.dumps(strict_json(doc), allow_nan=False)
