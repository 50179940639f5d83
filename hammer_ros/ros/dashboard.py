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
from typing import Any

from ..io.bags import node_topic

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_NUMBERS = {"type": "array", "items": {"type": "number"}}
_POINTS = {"type": "array", "items": {"type": "object", "properties": {"x": {"type": "number"},
                                                                        "y": {"type": "number"}}}}
_NUMBER_OR_NULL = {"type": ["number", "null"]}


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
        "method": {"type": "string"}, "order": {"type": "integer"}, "poles": {"type": "array"},
        "zeros": {"type": "array"}, "fit_percent": _NUMBER_OR_NULL, "rms": _NUMBER_OR_NULL,
        "samples": {"type": "integer"}, "stale": {"type": "boolean"}})),
    "poles": ("hammer_ros.Roots", _ROOTS),
    "zeros": ("hammer_ros.Roots", _ROOTS),
    "nonlinearity": ("hammer_ros.Series", _schema("hammer_ros.Series", {"x": _NUMBERS, "y": _NUMBERS,
                                                                        "points": _POINTS, "y_lower": _NUMBERS,
                                                                        "y_upper": _NUMBERS})),
    "fit": ("hammer_ros.Fit", _schema("hammer_ros.Fit", {
        "fit_percent": _NUMBER_OR_NULL, "rms": _NUMBER_OR_NULL, "stale": {"type": ["boolean", "null"]},
        "window_fill_percent": {"type": "number"}, "samples": {"type": "integer"}})),
    "diagnosis": ("hammer_ros.Diagnosis", _schema("hammer_ros.Diagnosis", {
        "cause": {"type": ["string", "null"]}, "confidence": _NUMBER_OR_NULL, "samples": {"type": "integer"},
        "seconds": {"type": "number"}, "error": {"type": "string"}})),
    "diagnosis_log": ("foxglove.Log", _schema("foxglove.Log", {
        "level": {"type": "integer", "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal"},
        "message": {"type": "string"}, "name": {"type": "string"}, "file": {"type": "string"},
        "line": {"type": "integer"}})),
    "diagnostics": ("hammer_ros.Counters", _schema("hammer_ros.Counters", {
        "level": {"type": "integer"}, "message": {"type": "string"},
        "values": {"type": "object", "additionalProperties": {"type": ["number", "string"]}}})),
}
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
_CIRCLE = [{"x": math.cos(2 * math.pi * k / 64), "y": math.sin(2 * math.pi * k / 64)} for k in range(65)]


def dashboard_topic(channel: str, node_name: str = "hammer_ros") -> str:
    """'model' -> '/hammer_ros/dashboard/model'."""
    return f"/{node_name}/dashboard/{channel}"


def _time(stamp_s: float) -> dict[str, int]:
    ns = int(round(stamp_s * 1e9)) if math.isfinite(stamp_s) and stamp_s > 0 else 0
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
    return LOG_WARNING, (f"diagnosis of {doc.get('samples')} samples: {cause} (confidence {doc.get('confidence')})"
                         + (f", extended model gains {gain}" if gain is not None else ""))


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


def dashboard_messages(messages: list[tuple[str, str, dict]], stamp_s: float) -> list[tuple[str, dict]]:
    """(channel, JSON message) of every dashboard channel that ``messages`` (the ``outputs``
    result messages of one solve, or the ``~/diagnosis`` message) update."""
    by_topic = {topic: message for topic, _, message in messages}
    timestamp = _time(stamp_s)
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


def record_results(writer, messages: list[tuple[str, str, dict]], stamp_s: float, node_name: str,
                   dashboard: list[tuple[str, dict]] | None = None) -> None:
    """Write ``messages`` (as ROS 2 messages) and their dashboard channels (as JSON; ``dashboard``
    when already built) into a ``ResultWriter``."""
    log_time = round(stamp_s * 1e9)
    for topic, type_name, message in messages:
        writer.write(node_topic(topic, node_name), type_name, message, log_time)
    for channel, message in dashboard if dashboard is not None else dashboard_messages(messages, stamp_s):
        writer.write_json(dashboard_topic(channel, node_name), CHANNELS[channel][0], message, log_time)
