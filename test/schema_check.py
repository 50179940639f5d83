"""A checker of JSON messages against the dashboard's JSON schemas (the subset of JSON Schema
that ``hammer_ros.messages.dashboard`` uses: type, properties, additionalProperties, items), and of
Foxglove message paths against a schema. Strict: a key that the schema does not declare is a
mismatch, so a new key in a message fails until its schema declares it. And the message paths
of a Foxglove layout."""

from __future__ import annotations

import re
from typing import Any

_TYPES = {"object": lambda v: isinstance(v, dict), "array": lambda v: isinstance(v, list),
          "string": lambda v: isinstance(v, str), "boolean": lambda v: isinstance(v, bool),
          "null": lambda v: v is None, "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
          "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)}


def mismatches(schema: dict[str, Any], value: Any, path: str = "") -> list[str]:
    """Where ``value`` does not follow ``schema``: undeclared keys and wrong types, as paths."""
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_TYPES[t](value) for t in types):
            return [f"{path or '.'}: {type(value).__name__} is not {'|'.join(types)}"]
    found: list[str] = []
    if isinstance(value, dict):
        properties, others = schema.get("properties", {}), schema.get("additionalProperties")
        for key, item in value.items():
            if key in properties:
                found += mismatches(properties[key], item, f"{path}.{key}")
            elif others is not None:
                found += mismatches(others, item, f"{path}.{key}")
            elif "properties" in schema or "type" in schema:
                found.append(f"{path}.{key}: not declared")
    elif isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            found += mismatches(schema["items"], item, f"{path}[{i}]")
    return found


def path_in_schema(schema: dict[str, Any], path: str) -> bool:
    """Whether a Foxglove message path (after the topic: '.a.b[0]', '.x[:]', '.items{key=="v"}.y')
    names fields the schema declares."""
    node = schema
    for name, index, key, _ in re.findall(r"\.(\w+)|\[(:|\d+)\]|\{(\w+)==\"([^\"]+)\"\}", path):
        if name:
            properties = node.get("properties", {})
            if name not in properties:
                return False
            node = properties[name]
        elif index:
            if "items" not in node:
                return False
            node = node["items"]
        elif key:
            item = node.get("items", {})
            if key not in item.get("properties", {}):
                return False
            node = item
    return True


def layout_paths(layout: dict) -> list[str]:
    """Every message path a Foxglove layout's panels read."""
    paths = []
    for config in layout["configById"].values():
        paths += [p["value"] for p in config.get("paths", [])] + [config.get("xAxisPath", {}).get("value")]
        paths += [config.get("topicPath"), config.get("topicToRender")]
    return [p for p in paths if p]


def layout_topic(path: str) -> str:
    """The topic of a Foxglove message path (``/a/b/model.poles[:].re`` -> ``/a/b/model``)."""
    return re.match(r"^/[\w/]+?(?=[.{\[]|$)", path).group(0)
