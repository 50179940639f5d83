"""The ``msg_config`` YAML of a bag or a node (``load_msg_config``), the stream specs it and the
command line give (``/topic:field.path``, ``StreamSpec``), the engine settings in it
(``engine_config_from_params``) and its channels (``config_channels``: several (excitation,
response) pairs identified side by side)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..errors import UsageError
from ..messages.field_path import FieldPath, parse_field_path
from ..streaming.config import EngineConfig

# msg_config keys that are not engine settings
TOPIC_KEYS = ("excitation_topic", "excitation_type", "excitation_field", "response_topic", "response_type",
              "response_field", "reference_topic", "reference_type", "reference_field")
OTHER_KEYS = ("solve_rate", "frame_id", "use_sim_time", "qos_depth", "max_pending", "output_mcap", "foxglove_port",
              "foxglove_host", "channels")


@dataclass(frozen=True)
class StreamSpec:
    """Where one signal is: a topic, the field path in its messages, optionally the type."""

    topic: str
    field: FieldPath
    type_name: str | None = None

    def __str__(self) -> str:
        return f"{self.topic}:{self.field}"


def parse_stream_spec(text: str, option: str) -> StreamSpec:
    """``/topic:field.path`` (e.g. ``/joint_states:velocity[0]``) -> StreamSpec."""
    topic, sep, path = (text or "").partition(":")
    if not sep or not topic.startswith("/") or not path:
        raise UsageError(f"{option}: expected /topic:field.path (e.g. /cmd:data), got {text!r}")
    try:
        return StreamSpec(topic, parse_field_path(path))
    except UsageError as exc:
        raise UsageError(f"{option}: {exc}") from None


def load_msg_config(path: str | Path) -> dict[str, Any]:
    """The parameters of a msg_config YAML in ROS 2 params-file form
    (``<node name>: {ros__parameters: {...}}``, e.g. ``hammer_ros`` or ``/**``)."""
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"{path}: no such config file")
    try:
        doc = yaml.safe_load(path.read_text())  # safe_load: plain data only, no Python objects
    except UnicodeDecodeError:
        raise UsageError(f"{path}: not a text (UTF-8) file") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise UsageError(f"{path}: not valid YAML{where} ({problem})") from None
    if isinstance(doc, dict):
        for section in doc.values():
            if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
                return dict(section["ros__parameters"])
    raise UsageError(f"{path}: expected a ROS 2 params file 'hammer_ros: {{ros__parameters: {{...}}}}'")


def engine_config_from_params(params: dict[str, Any], source: str = "config",
                              base: EngineConfig | None = None) -> EngineConfig:
    """An EngineConfig from node-style parameters (unknown keys are an error naming them; ROS
    parameters cannot be null, so ``mu: 0`` and ``partition: []`` mean the method's default)."""
    fields = set(EngineConfig.__dataclass_fields__)
    changes = {}
    for key, value in params.items():
        if key in TOPIC_KEYS or key in OTHER_KEYS:
            continue
        if key not in fields:
            known = ", ".join(sorted(fields | set(TOPIC_KEYS) | set(OTHER_KEYS)))
            raise UsageError(f"{source}: unknown parameter {key!r} (known: {known})")
        if key == "mu" and value in (0, None):
            value = None
        elif key == "partition":
            if value is not None and not isinstance(value, (list, tuple)):
                raise UsageError(f"{source}: partition: must be a list of breakpoints, e.g. [-0.5, 0.5] "
                                 f"(got {value!r})")
            value = tuple(value) if value else None
        changes[key] = value
    try:
        config = EngineConfig(**{**(base or EngineConfig()).__dict__, **changes})
        return config.validated()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{source}: {exc}") from None


def stream_specs(input_spec: str | None, output_spec: str | None, params: dict[str, Any] | None,
                 source: str = "config") -> tuple[StreamSpec, StreamSpec]:
    """(excitation, response) from --input/--output, falling back to the config's topics/fields."""
    return (stream_spec("--input", "excitation", input_spec, params, source),
            stream_spec("--output", "response", output_spec, params, source))


def stream_spec(option: str, role: str, text: str | None, params: dict[str, Any] | None, source: str = "config",
                required: bool = True) -> StreamSpec | None:
    """One stream from its option (``/topic:field``), else the config's ``<role>_topic`` and
    ``<role>_field`` (``_type`` optional); without either: a UsageError, or None when not ``required``."""
    if text:
        return parse_stream_spec(text, option)
    params = params or {}
    topic, field = params.get(f"{role}_topic"), params.get(f"{role}_field")
    if not topic or not field:
        if required or topic or field:
            raise UsageError(f"{option}: give /topic:field or a --config with {role}_topic and {role}_field")
        return None
    try:
        return StreamSpec(str(topic), parse_field_path(str(field)), params.get(f"{role}_type"))
    except UsageError as exc:
        raise UsageError(f"{source}: {role}_field: {exc}") from None


@dataclass(frozen=True)
class Channel:
    """One (excitation, response) pair of a ``channels`` list: its name, streams and parameters
    (the file's top-level parameters with the channel's own overrides)."""

    name: str
    excitation: StreamSpec
    response: StreamSpec
    params: dict


_CHANNEL_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def config_channels(params: dict[str, Any], source: str = "config") -> list[Channel]:
    """The channels of a msg_config / params file, [] without a ``channels`` list. Two forms:
    ``channels: [shoulder, elbow]`` with each channel's parameters under its name
    (``shoulder: {response_field: "velocity[shoulder_joint]", order: 2}``: the form a ROS 2
    params file can hold, nested names becoming ``shoulder.response_field``), or a list of
    mappings each with a ``name``. The top-level parameters are every channel's defaults. A
    name that is not a ROS name token, a duplicate, or a bad parameter is a UsageError naming
    the file and the channel."""
    listed = params.get("channels")
    if listed is None or listed == []:
        return []
    if not isinstance(listed, list) or not (all(isinstance(c, str) for c in listed)
                                            or all(isinstance(c, dict) for c in listed)):
        raise UsageError(f"{source}: channels: expected a list of channel names (each with its parameters under "
                         "its name) or a list of mappings with a name")
    names = [c if isinstance(c, str) else c.get("name") for c in listed]
    for index, name in enumerate(names):
        if not isinstance(name, str) or not _CHANNEL_NAME.match(name):
            raise UsageError(f"{source}: channels[{index}]: name {name!r} must be a name like shoulder_pan "
                             "(letters, digits, _; a letter first)")
        if name in names[:index]:
            raise UsageError(f"{source}: channels: duplicate channel {name!r}")
    stray = next((k for k, v in params.items() if isinstance(v, dict) and k not in names), None)
    if stray is not None:
        raise UsageError(f"{source}: {stray}: parameters of a channel {stray!r} that is not in channels "
                         f"({', '.join(names)})")
    entries = [{"name": c, **_channel_section(params, c, source)} if isinstance(c, str) else c for c in listed]
    named = {c for c in listed if isinstance(c, str)}
    base = {k: v for k, v in params.items() if k != "channels" and str(k).split(".", 1)[0] not in named}
    channels: list[Channel] = []
    for entry in entries:
        name = entry["name"]
        merged = {**base, **{k: v for k, v in entry.items() if k != "name"}}
        where = f"{source}: channel {name!r}"
        engine_config_from_params(merged, where)  # unknown or bad parameters, named
        excitation, response = stream_specs(None, None, merged, where)
        channels.append(Channel(name, excitation, response, merged))
    return channels


def single_channel_params(params: dict[str, Any], source: str, why: str) -> dict[str, Any]:
    """``params`` of a file without channels, the parameters of its only channel, or a UsageError
    (naming the file, its channels and ``why``) for several."""
    channels = config_channels(params, source)
    if len(channels) > 1:
        raise UsageError(f"--config: {source} has {len(channels)} channels ({', '.join(c.name for c in channels)}); "
                         f"{why}")
    return channels[0].params if channels else params


def _channel_section(params: dict[str, Any], name: str, source: str) -> dict[str, Any]:
    """The parameters under a channel's name (nested, or ``name.key`` flattened); {} for none."""
    section = params.get(name, {})
    if not isinstance(section, dict):
        raise UsageError(f"{source}: {name}: the parameters of channel {name!r} must be a mapping")
    dotted = {k.split(".", 1)[1]: v for k, v in params.items() if isinstance(k, str) and k.startswith(f"{name}.")}
    return {**section, **dotted}

