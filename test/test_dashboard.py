"""The Foxglove dashboard channels (``hammer_ros.ros.dashboard``): their JSON schemas declare every
key of every message the node and replay send (stale models, diagnoses, failed diagnoses), and
every path of the shipped Foxglove layout exists in the schemas."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from schema_check import mismatches, path_in_schema

from hammer_ros.identification.closed_loop import random_loop_pair
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.ros.dashboard import CHANNELS, dashboard_messages, dashboard_topic
from hammer_ros.ros.outputs import diagnosis_message, diagnostics_message, result_messages, stale_model_message
from hammer_ros.streaming.config import EngineConfig
from hammer_ros.streaming.engine import StreamingEngine
from hammer_ros.streaming.solver_process import diagnose_window

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "hammer_ros" / "dashboard" / "foxglove_layout.json"


def layout_paths() -> list[str]:
    layout = json.loads(LAYOUT.read_text())
    paths = []
    for config in layout["configById"].values():
        paths += [p["value"] for p in config.get("paths", [])] + [config.get("xAxisPath", {}).get("value")]
        paths += [config.get("topicPath"), config.get("topicToRender")]
    return [p for p in paths if p]


def test_every_layout_path_is_declared_by_its_channel_schema():
    paths = layout_paths()
    assert "/hammer_ros/dashboard/model.markov[:]" in paths and len(paths) > 20
    for path in paths:
        topic = re.match(r"^/[\w/]+?(?=[.{\[]|$)", path).group(0)
        name = topic.rsplit("/", 1)[1]
        assert topic == dashboard_topic(name) and name in CHANNELS, path
        assert path_in_schema(CHANNELS[name][1], path[len(topic):]), path


def test_the_checker_finds_an_undeclared_key_and_a_wrong_type():
    schema = CHANNELS["fit"][1]
    good = {"timestamp": {"sec": 1, "nsec": 2}, "fit_percent": None, "rms": 0.1, "stale": False,
            "window_fill_percent": 50.0, "samples": 10}
    assert mismatches(schema, good) == []
    assert mismatches(schema, {**good, "new_key": 1}) == [".new_key: not declared"]
    assert mismatches(schema, {**good, "samples": 1.5}) == [".samples: float is not integer"]
    assert not path_in_schema(schema, ".nope") and path_in_schema(schema, ".timestamp.sec")


def test_every_message_of_every_channel_is_declared_by_its_schema():
    """A solve (model, roots, map, fit, counters), a stale model after a failed solve, a diagnosis
    of a window with a cause (an output nonlinearity: extended model, gain, steps), one that
    cannot be diagnosed and a closed loop's with its reference (the evidence's notes)."""
    rng = np.random.default_rng(4)
    v = rng.uniform(-1, 1, 3000)
    linear = simulate_hammerstein(v, lambda x: x + 0.5 * x**3, _plant())
    y = np.tanh(2.0 * linear) + 0.002 * rng.standard_normal(v.size)  # a saturating sensor after the block
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=3000, order=2, delay=1, tau_max=40))
    t = 1.7e9 + np.arange(v.size) / 100.0
    engine.add_excitation(t, v)
    engine.add_response(t, y)
    outcome = engine.solve()
    assert outcome.ok, outcome.reason
    stamp = 1_700_000_029_990_000_000
    results = result_messages(outcome, stamp)
    results.append(("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray",
                    diagnostics_message(engine.stats, outcome, stamp)))
    failed = StreamingEngine(EngineConfig(sample_rate=100.0, window=3000, order=2)).solve()
    stale = [stale_model_message(outcome, failed),
             ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", diagnostics_message(engine.stats, failed, stamp))]
    diagnosis = {"samples": 3000, "stamp": 1.7e9 + 29.99, **diagnose_window(v, y, 2), "seconds": 1.0}
    assert diagnosis["cause"] != "none" and diagnosis["extended"] and diagnosis["gain"], diagnosis
    undiagnosable = {"samples": 10, "stamp": None, **diagnose_window(v[:10], y[:10], 2), "seconds": 0.0}
    assert "error" in undiagnosable
    closed, _ = random_loop_pair(104, samples=2000)  # a closed loop diagnosed with its reference: notes
    instrumented = {"samples": 2000, "stamp": None, **diagnose_window(closed.u, closed.y, 3, closed.r), "seconds": 1.0}
    assert instrumented["baseline"]["input"] == "reference_part"
    assert any(e.get("note") for e in instrumented["evidence"])
    sent: dict[str, int] = {}
    for messages in (results, stale, [diagnosis_message(diagnosis)], [diagnosis_message(undiagnosable)],
                     [diagnosis_message(instrumented)]):
        for channel, message in dashboard_messages(messages, stamp):
            assert mismatches(CHANNELS[channel][1], json.loads(json.dumps(message))) == [], channel
            sent[channel] = sent.get(channel, 0) + 1
    assert set(sent) == set(CHANNELS)


def _plant():
    from hammer_ros.identification.linear import LinearModel

    return LinearModel(b=[0.0, 1.0, 0.5], a=[1.0, -1.2, 0.5])
