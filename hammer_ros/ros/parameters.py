"""The live node's parameters: their specs (``PARAMETERS``), checks and descriptors, the message
types and field paths of its inputs, and the channels of its params file.

The params file's overrides are read through rclpy's public node handle (``parameter_overrides``),
never a private attribute: a ``channels`` list there makes several channels (``file_channels``),
each with the node parameters its section sets (``channel_values``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from .environment import prepare_ros_environment

prepare_ros_environment()

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor  # noqa: E402
from rclpy.expand_topic_name import expand_topic_name  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.validate_full_topic_name import validate_full_topic_name  # noqa: E402

from ..errors import UsageError  # noqa: E402
from ..identification.methods import METHODS, REFERENCE_METHODS  # noqa: E402
from ..io.bag_config import OTHER_KEYS, TOPIC_KEYS, Channel, config_channels  # noqa: E402
from ..messages.field_path import NAME_FIELD, FieldError, FieldPath, extract_samples, parse_field_path  # noqa: E402
from ..messages.types import INPUT_PACKAGES as MESSAGE_PACKAGES  # noqa: E402
from ..streaming.config import MAX_TAU_MAX, MAX_WINDOW, EngineConfig  # noqa: E402
from .message_types import input_message_class as message_class  # noqa: E402

NODE_NAME = "hammer_ros"
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


def coerce(name: str, value: Any) -> Any:
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


def descriptor(name: str, spec: Spec) -> ParameterDescriptor:
    d = ParameterDescriptor(description=spec.description, read_only=spec.read_only,
                            dynamic_typing=spec.kind in ("int", "float"))
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if spec.kind == "int" and spec.low is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=0)]
    elif spec.kind == "float" and spec.low is not None:
        d.floating_point_range = [FloatingPointRange(from_value=spec.low, to_value=spec.high, step=0.0)]
    return d


REPLAY_KEYS = {f.name for f in fields(EngineConfig)} | set(TOPIC_KEYS) | set(OTHER_KEYS)
SOURCE = "params file"
NODE_WIDE = ("foxglove_port", "foxglove_host", "output_mcap")  # one for the node, never per channel



def check_stream(stream: str, values: dict[str, Any], node_name: str, namespace: str) -> None:
    """UsageError naming the parameter when ``stream``'s topic, type or field cannot work."""
    topic = values[f"{stream}_topic"]
    try:
        validate_full_topic_name(expand_topic_name(topic, node_name, namespace))
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


def proposed_values(current: dict[str, Any], parameters: list[Parameter], node_name: str,
                    namespace: str) -> tuple[dict[str, Any], EngineConfig, set[str]]:
    """``current`` with the changes of ``parameters`` (those of other names ignored), checked:
    (values, their EngineConfig, the names that changed); UsageError for a refused change."""
    proposed = dict(current)
    for p in parameters:
        if p.name not in PARAMETERS:
            continue
        if PARAMETERS[p.name].read_only:
            raise UsageError(f"{p.name}: read-only (set it at startup)")
        proposed[p.name] = coerce(p.name, p.value)
    config = engine_config(proposed)
    changed = {k for k in PARAMETERS if proposed[k] != current[k]}
    for stream in {STREAM_PARAMETERS[k] for k in changed & set(STREAM_PARAMETERS)}:
        check_stream(stream, proposed, node_name, namespace)
    return proposed, config, changed


def parameter_overrides(node) -> dict[str, Any]:
    """The parameter overrides of ``node``'s arguments (params files, ``-p``) by name, read from
    the public node handle (``Node.handle``), as rclpy itself reads them at construction."""
    with node.handle:
        overrides = node.handle.get_parameters(Parameter)
    return {name: list(p.value) if type(p.value).__name__ == "array" else p.value for name, p in overrides.items()}


def file_channels(overrides: dict[str, Any]) -> list[Channel]:
    """The channels of the node's params file ([] without a ``channels`` parameter): its
    overrides as ``config_channels`` reads them (``NAME.key`` per channel); a node-only key
    (solver_process, diagnosis_period, ...) is left to ``channel_values``."""
    if not overrides.get("channels"):
        return []
    params = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if head == "qos_overrides" or ((rest or key) not in REPLAY_KEYS and (rest or key) in PARAMETERS):
            continue
        params[key] = value
    return config_channels(params, SOURCE)


def channel_values(overrides: dict[str, Any], channel: Channel) -> dict[str, Any]:
    """The node parameters ``channel`` sets: its ``params`` (the file's top level with its own
    overrides) and its node-only keys (``NAME.solver_process``, ...) from the node's overrides."""
    section = {k.split(".", 1)[1]: v for k, v in overrides.items() if k.startswith(f"{channel.name}.")}
    return {k: v for k, v in {**channel.params, **section}.items() if k in PARAMETERS}
