"""Identification results as ROS 2 messages (plain nested dicts), shared by the live node and
``replay --out``; pure Python (no rclpy).

| topic | type | content |
|---|---|---|
| ``~/model`` | std_msgs/msg/String | JSON of the ``identify --json`` keys (+ ``stamp``, ``samples``) |
| ``~/poles`` | sensor_msgs/msg/JointState | name ``p0_re, p0_im, p1_re, ...``, position = values |
| ``~/zeros`` | sensor_msgs/msg/JointState | name ``z0_re, z0_im, ...`` |
| ``~/markov`` | sensor_msgs/msg/JointState | name ``h0, h1, ...`` (Markov parameters) |
| ``~/nonlinearity`` | geometry_msgs/msg/PolygonStamped | points (x = input v, y = F(v), z = 0) |
| ``/diagnostics`` | diagnostic_msgs/msg/DiagnosticArray | engine counters, rates, condition number, fit |

JointState is used for the vector topics because Foxglove and PlotJuggler plot each named
entry of ``position`` as its own series. The dicts are what ``mcap_ros2`` writes directly;
``hammer_ros.ros.message_types.to_ros_message`` turns one into an rclpy message object (byte fields
become ``bytes``).
"""

from __future__ import annotations

import json
import math
import numbers
from typing import Any

from ..identification.result import strict_json
from ..streaming.config import EngineStats
from ..streaming.engine import SolveOutcome

OUTPUT_TOPICS: list[tuple[str, str]] = [
    ("~/model", "std_msgs/msg/String"),
    ("~/poles", "sensor_msgs/msg/JointState"),
    ("~/zeros", "sensor_msgs/msg/JointState"),
    ("~/markov", "sensor_msgs/msg/JointState"),
    ("~/nonlinearity", "geometry_msgs/msg/PolygonStamped"),
    ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
]
DIAGNOSTIC_OK, DIAGNOSTIC_WARN, DIAGNOSTIC_ERROR, DIAGNOSTIC_STALE = 0, 1, 2, 3


def seconds_to_ns(stamp_s: float) -> int:
    """Integer nanoseconds of a time in seconds (nan / negative -> 0). Only for times that are
    floats at their source (a clock, a computed grid point): an input's stamp stays in integer
    nanoseconds end to end, since float seconds of an epoch time are 238 ns apart."""
    return int(round(stamp_s * 1e9)) if math.isfinite(stamp_s) and stamp_s > 0 else 0


def checked_ns(stamp_ns: int) -> int:
    """``stamp_ns`` as a non-negative int; TypeError for a float (seconds passed where integer
    nanoseconds are expected would otherwise stamp 1.7e9 s as 1.7 s)."""
    if not isinstance(stamp_ns, numbers.Integral):
        raise TypeError(f"a stamp must be integer nanoseconds (got {type(stamp_ns).__name__} {stamp_ns!r})")
    return max(0, int(stamp_ns))


def stamp_dict(stamp_ns: int) -> dict:
    """builtin_interfaces/Time of a time in integer nanoseconds (negative -> 0)."""
    ns = checked_ns(stamp_ns)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _header(stamp_ns: int, frame_id: str) -> dict:
    return {"stamp": stamp_dict(stamp_ns), "frame_id": frame_id}


def _joint_state(header: dict, names: list[str], values) -> dict:
    return {"header": header, "name": names, "position": [float(x) for x in values], "velocity": [], "effort": []}


def _roots_state(header: dict, prefix: str, roots: list[list[float]]) -> dict:
    names = [f"{prefix}{i}_{part}" for i in range(len(roots)) for part in ("re", "im")]
    return _joint_state(header, names, [x for root in roots for x in root])


def model_json(outcome: SolveOutcome, stale_reason: str | None = None) -> str:
    """The ``~/model`` text: the identify JSON plus ``stamp`` (grid time, s), ``samples`` and
    ``stale`` (false for a fresh model; true, with ``stale_reason``, when the last solve gave no
    new model and this is the last good one, republished)."""
    doc = dict(outcome.doc or {})
    doc.update(stamp=outcome.stamp if math.isfinite(outcome.stamp) else None, samples=outcome.samples,
               stale=stale_reason is not None)
    if stale_reason is not None:
        doc["stale_reason"] = stale_reason
    return json.dumps(doc, allow_nan=False)


def stale_model_message(last_good: SolveOutcome, outcome: SolveOutcome) -> tuple[str, str, dict]:
    """The ``~/model`` message republishing ``last_good`` marked stale because ``outcome`` (the
    latest solve) gave no model; its ``stamp`` stays the grid time of the last good solve."""
    return "~/model", "std_msgs/msg/String", {"data": model_json(last_good, outcome.reason)}


def result_messages(outcome: SolveOutcome, stamp_ns: int, frame_id: str = "") -> list[tuple[str, str, dict]]:
    """(topic, type, message dict) for every result topic of a successful solve ([] otherwise),
    stamped ``stamp_ns`` (integer nanoseconds)."""
    if not outcome.ok or outcome.doc is None:
        return []
    doc, header = outcome.doc, _header(stamp_ns, frame_id)
    markov = list(outcome.markov)
    messages = [
        ("~/model", "std_msgs/msg/String", {"data": model_json(outcome)}),
        ("~/poles", "sensor_msgs/msg/JointState", _roots_state(header, "p", doc["poles"])),
        ("~/zeros", "sensor_msgs/msg/JointState", _roots_state(header, "z", doc["zeros"])),
        ("~/markov", "sensor_msgs/msg/JointState",
         _joint_state(header, [f"h{i}" for i in range(len(markov))], markov)),
    ]
    nonlinearity = doc.get("nonlinearity")
    if nonlinearity and nonlinearity.get("points"):
        points = [{"x": float(u), "y": float(f), "z": 0.0} for u, f in nonlinearity["points"]
                  if math.isfinite(u) and math.isfinite(f)]
        messages.append(("~/nonlinearity", "geometry_msgs/msg/PolygonStamped",
                         {"header": header, "polygon": {"points": points}}))
    return messages


def diagnosis_message(doc: dict[str, Any]) -> tuple[str, str, dict]:
    """The ``~/diagnosis`` message (std_msgs/String) holding the diagnosis JSON ``doc``."""
    return "~/diagnosis", "std_msgs/msg/String", {"data": json.dumps(strict_json(doc), allow_nan=False)}


def _value_text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def diagnostics_message(stats: EngineStats, outcome: SolveOutcome | None, stamp_ns: int,
                        node_name: str = "hammer_ros") -> dict:
    """diagnostic_msgs/msg/DiagnosticArray with one status ``<node_name>: identification``.

    Level OK after a successful solve, WARN while the window fills, the input is not
    persistently exciting or the published model is kept, ERROR when the method failed.
    ``level`` is an int (what mcap_ros2 writes); ``ros.message_types.to_ros_message`` converts it to
    the ``bytes`` rclpy expects."""
    values: dict[str, Any] = {
        "received_rate_excitation_hz": stats.rate("excitation"),
        "received_rate_response_hz": stats.rate("response"),
        "aligned_rate_hz": stats.aligned_rate,
        "sample_rate_hz": stats.sample_rate,
        "received_excitation": stats.received_excitation,
        "received_response": stats.received_response,
        "aligned": stats.aligned,
        "nan_skipped": stats.nan_skipped,
        "late": stats.late,
        "duplicate": stats.duplicate,
        "last_stamp_excitation": f"{stats.last_stamp.get('excitation', float('nan')):.6f}",
        "last_stamp_response": f"{stats.last_stamp.get('response', float('nan')):.6f}",
        "missing_excitation": stats.missing("excitation"),
        "missing_response": stats.missing("response"),
        "excitation_held": stats.excitation_held,
        "dropped": stats.overflow + stats.unstamped,
        "overflow": stats.overflow,
        "unstamped": stats.unstamped,
        "gaps": stats.gaps,
        "clock_resets": stats.clock_resets,
        "window_fill_percent": 100.0 * stats.window_fill,
        "solves": stats.solves,
        "solve_errors": stats.solve_errors,
        "not_exciting": stats.not_exciting,
        "kept_published": stats.kept_published,
        "uncertain": stats.uncertain,
        "solve_failures": stats.solve_failures,
        "solve_exceptions": stats.solve_exceptions,
    }
    if outcome is None:
        level, message = DIAGNOSTIC_WARN, "no solve yet"
    else:
        values.update(condition_number=outcome.condition_number, solve_time_ms=1e3 * outcome.solve_seconds,
                      window_samples=outcome.samples)
        if outcome.ok:
            level, message = DIAGNOSTIC_OK, "model identified"
            values.update(fit_percent=outcome.doc.get("fit_percent"), rms=outcome.doc.get("rms"))
        elif outcome.status in ("filling", "not_exciting", "kept", "uncertain"):
            level, message = DIAGNOSTIC_WARN, outcome.reason
        else:
            level, message = DIAGNOSTIC_ERROR, outcome.reason
        if not outcome.ok and stats.solves:
            message += "; publishing the last good model as stale"
    status = {
        "level": level,
        "name": f"{node_name}: identification",
        "message": message,
        "hardware_id": node_name,
        "values": [{"key": k, "value": _value_text(v)} for k, v in values.items()],
    }
    return {"header": _header(stamp_ns, ""), "status": [status]}


def node_topic(topic: str, node_name: str = "hammer_ros") -> str:
    """'~/model' -> '/hammer_ros/model' (the private namespace of the node)."""
    return f"/{node_name}/{topic[2:]}" if topic.startswith("~/") else topic
