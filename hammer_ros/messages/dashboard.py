"""The Foxglove dashboard channels (JSON messages with JSON schemas), built from the node's
result messages (``outputs`` dicts); pure Python, shared by the live Foxglove server
(``foxglove_server``) and ``replay --out``, so both carry the same channels.

Channels ``/<node>/dashboard/<name>`` (schema): ``model`` (hammer_ros.Model: the ``~/model``
JSON as an object); ``poles``, ``zeros`` (hammer_ros.Roots: ``real``, ``imag``, ``magnitude``
arrays and ``points`` {x: re, y: im} for a scatter; poles also ``unit_circle``; with the model's
bounds ``real_lower`` / ``real_upper``, ``imag_*`` and ``magnitude_*``, the 95 % intervals);
``nonlinearity`` (hammer_ros.Series: ``x`` = input v, ``y`` = F(v), ``points`` {x, y}; with bounds
``y_lower`` / ``y_upper``, the 95 % band);
``fit`` (hammer_ros.Fit, every solve: ``fit_percent``, ``rms``, ``stale`` of the published
model, ``window_fill_percent``, ``samples``); ``diagnosis`` (hammer_ros.Diagnosis: the
``~/diagnosis`` JSON as an object); ``diagnosis_log`` (foxglove.Log: one line per diagnosis,
WARNING with a cause, INFO without, ERROR when none was possible); ``diagnostics``
(hammer_ros.Counters: the node's ``/diagnostics`` status, ``level``, ``message`` and ``values``
as numbers). Every message has ``timestamp`` ({sec, nsec}, the publication time).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from importlib.resources import files
from typing import Any

from .outputs import checked_ns

# JSON schema building blocks. Every key a channel's messages can carry is declared (test_dashboard
# checks the messages of a replay and of a live node against them); an object whose keys depend on
# the method or the cause (``_OPEN``) declares its known keys and takes others as ``additionalProperties``.
_NUMBER, _INTEGER, _STRING, _BOOLEAN = ({"type": t} for t in ("number", "integer", "string", "boolean"))
_NUMBER_OR_NULL = {"type": ["number", "null"]}
_NUMBERS = {"type": "array", "items": _NUMBER}
_PAIRS = {"type": "array", "items": _NUMBERS}  # [[re, im], ...], [[u, F(u)], ...]
_ANY: dict[str, Any] = {}


def _object(properties: dict[str, Any], nullable: bool = False, others: dict[str, Any] | None = None) -> dict:
    schema: dict[str, Any] = {"type": ["object", "null"] if nullable else "object", "properties": properties}
    if others is not None:
        schema["additionalProperties"] = others
    return schema


def _list_of(properties: dict[str, Any]) -> dict:
    return {"type": "array", "items": _object(properties)}


_TIME = _object({"sec": _INTEGER, "nsec": _INTEGER})
_POINTS = _list_of({"x": _NUMBER, "y": _NUMBER})
_MAP = _object({"kind": _STRING, "coefficients": _NUMBERS, "breakpoints": _NUMBERS, "slopes": _NUMBERS,
                "points": _PAIRS, "points_std": _NUMBERS}, others=_ANY)  # a static map F (identify --json)
_LINEAR = _object({"a": _NUMBERS, "b": _NUMBERS, "poles": _PAIRS, "zeros": _PAIRS, "order": _INTEGER}, others=_ANY)
# the ``identify --json`` keys (+ the model's uncertainty keys) of a model
_MODEL = {"method": _STRING, "order": _INTEGER, "poles": _PAIRS, "zeros": _PAIRS, "gain": _NUMBER_OR_NULL,
          "stable": _BOOLEAN, "a": _NUMBERS, "b": _NUMBERS, "markov": _NUMBERS, "nonlinearity": _MAP,
          "feedback_nonlinearity": _MAP, "fit_percent": _NUMBER_OR_NULL, "rms": _NUMBER_OR_NULL,
          "poles_std": _PAIRS, "zeros_std": _PAIRS, "gain_std": _NUMBER_OR_NULL, "uncertainty": _STRING,
          "tau_max": _INTEGER, "mu": _INTEGER, "plls": _object({}, others=_ANY), "parallel_path": _LINEAR,
          "refined": _object({}, others=_ANY), "warnings": _list_of({"code": _STRING, "message": _STRING})}
_SCORE = {"structure": _STRING, "rms": _NUMBER, "fit_percent": _NUMBER}


def _schema(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": {"timestamp": _TIME, **properties}}


_ROOTS = _schema("hammer_ros.Roots", {"real": _NUMBERS, "imag": _NUMBERS, "magnitude": _NUMBERS, "points": _POINTS,
                                      "unit_circle": _POINTS, **{f"{part}_{bound}": _NUMBERS for part in
                                                                 ("real", "imag", "magnitude")
                                                                 for bound in ("lower", "upper")}})
# name -> (schema name, JSON schema); the schema name is what Foxglove shows (foxglove.Log is a
# well-known Foxglove schema, which its Log panel reads)
CHANNELS: dict[str, tuple[str, dict[str, Any]]] = {
    "model": ("hammer_ros.Model", _schema("hammer_ros.Model", {
        **_MODEL, "stamp": _NUMBER_OR_NULL, "samples": _INTEGER, "stale": _BOOLEAN, "stale_reason": _STRING})),
    "poles": ("hammer_ros.Roots", _ROOTS),
    "zeros": ("hammer_ros.Roots", _ROOTS),
    "nonlinearity": ("hammer_ros.Series", _schema("hammer_ros.Series", {"x": _NUMBERS, "y": _NUMBERS,
                                                                        "points": _POINTS, "y_lower": _NUMBERS,
                                                                        "y_upper": _NUMBERS})),
    "fit": ("hammer_ros.Fit", _schema("hammer_ros.Fit", {
        "fit_percent": _NUMBER_OR_NULL, "rms": _NUMBER_OR_NULL, "stale": {"type": ["boolean", "null"]},
        "window_fill_percent": _NUMBER, "samples": _INTEGER})),
    "diagnosis": ("hammer_ros.Diagnosis", _schema("hammer_ros.Diagnosis", {  # the diagnose --json keys
        "baseline": _object({**_SCORE, **_MODEL, "delay": _INTEGER, "dead_time": _INTEGER}, others=_ANY),
        "cause": {"type": ["string", "null"]}, "confidence": _NUMBER_OR_NULL,
        "evidence": _list_of({"test": _STRING, "value": _NUMBER_OR_NULL, "bound": _NUMBER_OR_NULL,
                              "passed": _BOOLEAN, "note": _STRING}),
        "extended": _object(_SCORE, nullable=True, others=_ANY),  # + the cause's model (its details)
        "gain": _object({"rms_ratio": _NUMBER}, nullable=True),
        "candidates": _list_of({"cause": _STRING, "rms_ratio": _NUMBER}),
        "steps": _list_of({"cause": _STRING, "structure": _STRING, "rms": _NUMBER, "gain": _NUMBER}),
        "chain_stopped": {"type": ["string", "null"]},
        "not_fitted": _list_of({"cause": _STRING, "reason": _STRING}),
        "input_coverage": _object({"estimation_range": _NUMBERS, "validation_range": _NUMBERS, "outside": _NUMBER,
                                   "bound": _NUMBER, "judged_samples": _INTEGER, "validation_samples": _INTEGER,
                                   "memory": _INTEGER, "judged_on": _STRING}),
        "split": _STRING,
        "samples": _INTEGER, "stamp": _NUMBER_OR_NULL, "seconds": _NUMBER, "error": _STRING})),
    "diagnosis_log": ("foxglove.Log", _schema("foxglove.Log", {
        "level": {"type": "integer", "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal"},
        "message": _STRING, "name": _STRING, "file": _STRING, "line": _INTEGER})),
    "diagnostics": ("hammer_ros.Counters", _schema("hammer_ros.Counters", {
        "level": _INTEGER, "message": _STRING, "values": _object({}, others={"type": ["number", "string"]})})),
}
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
_CIRCLE = [{"x": math.cos(2 * math.pi * k / 64), "y": math.sin(2 * math.pi * k / 64)} for k in range(65)]


def dashboard_topic(channel: str, node_name: str = "hammer_ros") -> str:
    """'model' -> '/hammer_ros/dashboard/model'."""
    return f"/{node_name}/dashboard/{channel}"


def channel_node(node_name: str, channel: str = "") -> str:
    """The node-name part of a channel's topics: ``NODE`` for a node of one channel, ``NODE/CHANNEL``
    for a channel of a node (or replay) with several: ``/NODE/CHANNEL/model``,
    ``/NODE/CHANNEL/dashboard/model``."""
    return f"{node_name}/{channel}" if channel else node_name


SHIPPED_NODE = "hammer_ros"  # the node name of the shipped layout's topics


def shipped_layout() -> dict[str, Any]:
    """The shipped Foxglove layout (``hammer_ros/dashboard/foxglove_layout.json``: one channel of
    a node named ``hammer_ros``)."""
    return json.loads(files("hammer_ros").joinpath("dashboard", "foxglove_layout.json").read_text())


def _renamed_tree(tree: Any, suffix: str) -> Any:
    """A mosaic tree (panel ids at its leaves) with every panel id suffixed."""
    if isinstance(tree, str):
        return tree + suffix
    return {k: _renamed_tree(v, suffix) if k in ("first", "second") else v for k, v in tree.items()}


def foxglove_layout(node_name: str = SHIPPED_NODE, channels: Sequence[str] = ()) -> dict[str, Any]:
    """The Foxglove layout of ``node_name``'s dashboard channels: the shipped layout with its
    topics ``/hammer_ros/dashboard/...`` moved to ``/<node>/dashboard/...``; with several
    ``channels``, a Tab panel with one tab per channel (titled by its name), each the shipped
    layout on ``/<node>/<channel>/dashboard/...`` (panel ids suffixed ``-<channel>``, unique)."""
    layout = shipped_layout()
    shipped = dashboard_topic("", SHIPPED_NODE)

    def moved(configs: dict[str, Any], channel: str, suffix: str) -> dict[str, Any]:
        text = json.dumps(configs).replace(json.dumps(shipped)[:-1], json.dumps(
            dashboard_topic("", channel_node(node_name, channel)))[:-1])
        return {panel + suffix: config for panel, config in json.loads(text).items()}

    if len(channels) <= 1:
        return {**layout, "configById": moved(layout["configById"], "", "")}
    configs: dict[str, Any] = {}
    tabs = []
    for channel in channels:
        configs |= moved(layout["configById"], channel, f"-{channel}")
        tabs.append({"title": channel, "layout": _renamed_tree(layout["layout"], f"-{channel}")})
    configs["Tab!channels"] = {"activeTabIdx": 0, "tabs": tabs}
    return {**layout, "configById": configs, "layout": "Tab!channels"}


def _time(stamp_ns: int) -> dict[str, int]:
    ns = checked_ns(stamp_ns)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _roots(message: dict) -> dict[str, Any]:
    values = message["position"]
    real, imag = [float(x) for x in values[0::2]], [float(x) for x in values[1::2]]
    return {"real": real, "imag": imag, "magnitude": [math.hypot(re, im) for re, im in zip(real, imag)],
            "points": [{"x": re, "y": im} for re, im in zip(real, imag)]}


def _number(text: str) -> float | str:
    try:
        value = float(text)
    except ValueError:
        return text
    return value if math.isfinite(value) else text


def _log_line(doc: dict) -> tuple[int, str]:
    if "error" in doc:
        return LOG_ERROR, doc["error"]
    cause = doc.get("cause")
    if cause in (None, "none"):
        return LOG_INFO, f"diagnosis of {doc.get('samples')} samples: the Hammerstein model misses nothing"
    gain = doc.get("gain")
    ratio = gain.get("rms_ratio") if isinstance(gain, dict) else gain
    return LOG_WARNING, (f"diagnosis of {doc.get('samples')} samples: {cause} (confidence {doc.get('confidence')})"
                         + (f", extended model: baseline rms / its rms = {ratio:.3g}" if ratio is not None else ""))


def _root_intervals(model: dict, roots: str) -> dict[str, list[float]]:
    """The 95 % intervals (est +- 1.96 sd) of the real and imaginary parts and of the modulus
    (sd(|p|) = sqrt((re sd_re)^2 + (im sd_im)^2) / |p|) of the model's ``roots`` from its ``<roots>_std``
    (docs/methods.md); none without bounds."""
    values, sds = model.get(roots) or [], model.get(f"{roots}_std") or []
    if not values or len(sds) != len(values):
        return {}
    out: dict[str, list[float]] = {f"{part}_{bound}": [] for part in ("real", "imag", "magnitude")
                                   for bound in ("lower", "upper")}
    for (re, im), (sd_re, sd_im) in zip(values, sds):
        radius = math.hypot(re, im)
        sd_radius = math.hypot(re * sd_re, im * sd_im) / radius if radius > 0 else math.hypot(sd_re, sd_im)
        for part, value, sd in (("real", re, sd_re), ("imag", im, sd_im), ("magnitude", radius, sd_radius)):
            out[f"{part}_lower"].append(value - 1.96 * sd)
            out[f"{part}_upper"].append(value + 1.96 * sd)
    return out


def _map_band(model: dict, count: int) -> dict[str, list[float]]:
    """F(v) -+ 1.96 sd at the map's points (``nonlinearity.points_std``), when they are the ``count``
    points drawn."""
    fmap = model.get("nonlinearity") or {}
    points, sds = fmap.get("points") or [], fmap.get("points_std") or []
    finite = [(f, sd) for (u, f), sd in zip(points, sds) if math.isfinite(u) and math.isfinite(f)]
    if not sds or len(sds) != len(points) or len(finite) != count:
        return {}
    return {"y_lower": [f - 1.96 * sd for f, sd in finite], "y_upper": [f + 1.96 * sd for f, sd in finite]}


def dashboard_messages(messages: list[tuple[str, str, dict]], stamp_ns: int) -> list[tuple[str, dict]]:
    """(channel, JSON message) of every dashboard channel that ``messages`` (the ``outputs``
    result messages of one solve, or the ``~/diagnosis`` message) update, stamped ``stamp_ns``."""
    by_topic = {topic: message for topic, _, message in messages}
    timestamp = _time(stamp_ns)
    out: list[tuple[str, dict]] = []
    model = json.loads(by_topic["~/model"]["data"]) if "~/model" in by_topic else None
    if model is not None:
        out.append(("model", {"timestamp": timestamp, **model}))
    for topic, channel in (("~/poles", "poles"), ("~/zeros", "zeros")):
        if topic in by_topic:
            out.append((channel, {"timestamp": timestamp, **_roots(by_topic[topic]),
                                  **({"unit_circle": _CIRCLE} if channel == "poles" else {}),
                                  **_root_intervals(model or {}, channel)}))
    if "~/nonlinearity" in by_topic:
        points = [{"x": p["x"], "y": p["y"]} for p in by_topic["~/nonlinearity"]["polygon"]["points"]]
        out.append(("nonlinearity", {"timestamp": timestamp, "x": [p["x"] for p in points],
                                     "y": [p["y"] for p in points], "points": points,
                                     **_map_band(model or {}, len(points))}))
    if "/diagnostics" in by_topic:
        status = by_topic["/diagnostics"]["status"][0]
        values = {kv["key"]: _number(kv["value"]) for kv in status["values"]}
        out.append(("fit", {"timestamp": timestamp,
                            "fit_percent": model.get("fit_percent") if model else None,
                            "rms": model.get("rms") if model else None,
                            "stale": model.get("stale") if model else None,
                            "window_fill_percent": values.get("window_fill_percent", 0.0),
                            "samples": int(model["samples"]) if model else 0}))
        out.append(("diagnostics", {"timestamp": timestamp, "level": int(status["level"]),
                                    "message": status["message"], "values": values}))
    if "~/diagnosis" in by_topic:
        doc = json.loads(by_topic["~/diagnosis"]["data"])
        level, line = _log_line(doc)
        out.append(("diagnosis", {"timestamp": timestamp, **doc}))
        out.append(("diagnosis_log", {"timestamp": timestamp, "level": level, "message": line,
                                      "name": "hammer_ros.diagnosis", "file": "", "line": 0}))
    return out
