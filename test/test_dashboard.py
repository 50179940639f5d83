"""The Foxglove dashboard channels (``hammer_ros.messages.dashboard``): their JSON schemas declare every
key of every message the node and replay send (stale models, diagnoses, failed diagnoses), and
every path of the shipped Foxglove layout exists in the schemas."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from schema_check import layout_paths, layout_topic, mismatches, path_in_schema

from hammer_ros.identification.closed_loop import random_loop_pair
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.messages.dashboard import CHANNELS, dashboard_messages, dashboard_topic, foxglove_layout
from hammer_ros.messages.outputs import diagnosis_message, diagnostics_message, result_messages, stale_model_message
from hammer_ros.streaming.config import EngineConfig
from hammer_ros.streaming.engine import StreamingEngine
from hammer_ros.streaming.solver_process import diagnose_window
from hammer_ros.tools.foxglove_layout import main as foxglove_layout_tool

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "hammer_ros" / "dashboard" / "foxglove_layout.json"


def _declared(paths: list[str], node_name: str) -> None:
    for path in paths:
        topic = layout_topic(path)
        name = topic.rsplit("/", 1)[1]
        assert topic == dashboard_topic(name, node_name) and name in CHANNELS, path
        assert path_in_schema(CHANNELS[name][1], path[len(topic):]), path


def _leaves(tree) -> list[str]:
    return [tree] if isinstance(tree, str) else _leaves(tree["first"]) + _leaves(tree["second"])


def test_every_layout_path_is_declared_by_its_channel_schema():
    paths = layout_paths(json.loads(LAYOUT.read_text()))
    assert "/hammer_ros/dashboard/model.markov[:]" in paths and len(paths) > 20
    _declared(paths, "hammer_ros")
    assert foxglove_layout() == json.loads(LAYOUT.read_text())  # the shipped one, for a node named hammer_ros


def test_a_layout_of_several_channels_has_one_tab_of_every_panel_per_channel():
    shipped = json.loads(LAYOUT.read_text())
    one = foxglove_layout("arm", ["wrist"])  # one channel: the shipped layout on the node's topics
    assert one["layout"] == shipped["layout"] and len(layout_paths(one)) == len(layout_paths(shipped))
    _declared(layout_paths(one), "arm")
    layout = foxglove_layout("arm", ["shoulder", "elbow"])
    assert layout["layout"] == "Tab!channels"
    tabs = layout["configById"]["Tab!channels"]["tabs"]
    assert [tab["title"] for tab in tabs] == ["shoulder", "elbow"]
    for tab in tabs:
        panels = _leaves(tab["layout"])
        assert len(panels) == len(_leaves(shipped["layout"])) and all(p in layout["configById"] for p in panels)
        paths = layout_paths({"configById": {p: layout["configById"][p] for p in panels}})
        assert len(paths) == len(layout_paths(shipped))
        _declared(paths, f"arm/{tab['title']}")  # each tab reads its own channel's topics only
    assert len(layout["configById"]) == 2 * len(shipped["configById"]) + 1  # panel ids unique


def test_the_layout_tool_reads_a_params_file_and_refuses_a_bad_one(tmp_path, capsys):
    params = tmp_path / "arm.yaml"
    params.write_text("hammer_ros:\n  ros__parameters:\n    channels: [left, right]\n"
                      "    left: {excitation_topic: /cmd, excitation_field: 'data[0]', response_topic: /js,\n"
                      "           response_type: sensor_msgs/msg/JointState, response_field: 'velocity[l]'}\n"
                      "    right: {excitation_topic: /cmd, excitation_field: 'data[1]', response_topic: /js,\n"
                      "            response_type: sensor_msgs/msg/JointState, response_field: 'velocity[r]'}\n")
    out = tmp_path / "layout.json"
    assert foxglove_layout_tool(["--config", str(params), "--node", "arm", "-o", str(out)]) == 0
    assert json.loads(out.read_text()) == foxglove_layout("arm", ["left", "right"])
    params.write_text(params.read_text().replace("[left, right]", "[left, middle]"))
    assert foxglove_layout_tool(["--config", str(params)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "middle" in err[0] and str(params) in err[0], err


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
