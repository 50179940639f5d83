"""`hammer-ros demo`: plant and node processes on a private graph; the table shows convergence."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO, VENV_BIN

pytestmark = pytest.mark.ros

ROW = re.compile(r"^\s*(\d+\.\d)\s+(\d+)\s+(\d\.\d{4})\s+(\d\.\d{4})\s+(\d+\.\d)\s+(-?\d+\.\d)\s*$")


def test_demo_shows_the_estimate_converging(ros_env):
    done = subprocess.run([str(VENV_BIN / "hammer-ros"), "demo", "--duration", "20"], cwd=REPO, env=ros_env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    rows = [tuple(float(x) for x in m.groups()) for m in map(ROW.match, done.stdout.splitlines()) if m]
    assert len(rows) >= 3, done.stdout  # several models over the run
    first_time, last = rows[0][0], rows[-1]
    assert last[0] == pytest.approx(20.0) and first_time < last[0]
    assert last[2] < 0.02 and last[3] < 0.1  # pole and zero RSS errors of the final model
    assert last[4] < 5.0  # % error of the piecewise-linear map against the dead zone
    assert last[5] > 90.0  # free-run fit % on the window
    assert "converged: pole RSS error" in done.stdout and "Traceback" not in done.stderr


def test_demo_is_a_cli_subcommand():
    done = subprocess.run([sys.executable, "-m", "hammer_ros.cli", "demo", "--help"], capture_output=True, text=True)
    assert done.returncode == 0 and "--duration" in done.stdout


def _resolve(message: dict, path: str):
    """Follow a Foxglove message path (after the topic) through a message dict: '.name',
    '[i]', '[:]' (all elements) and '{key=="x"}' (filter); fails on a field that is not there
    (an index past the end of an existing array is a series for a higher model order: None)."""
    value = message
    for name, index, key, wanted in re.findall(r"\.(\w+)|\[(:|\d+)\]|\{(\w+)==\"([^\"]+)\"\}", path):
        if name:
            value = (value[0] if isinstance(value, list) else value)[name]
        elif key:
            value = [item for item in value if item[key] == wanted]
            assert value, f"no element with {key} == {wanted!r}"
        elif index != ":":
            assert isinstance(value, list)
            if int(index) >= len(value):  # a series for higher orders than this model's
                return None
            value = value[int(index)]
    return value[0] if isinstance(value, list) else value


def test_dashboard_layout_plots_fields_the_node_publishes():
    """Every path of the Foxglove layout exists in the dashboard channels (``ros.dashboard``) the
    node serves and ``replay --dashboard-out`` records, and every channel is shown."""
    from hammer_ros.identification.simulate import simulate_hammerstein
    from hammer_ros.messages.dashboard import CHANNELS, dashboard_messages, dashboard_topic
    from hammer_ros.messages.outputs import diagnostics_message, result_messages
    from hammer_ros.ros.plant_node import DEMO_PLANT, static_map
    from hammer_ros.streaming.config import EngineConfig
    from hammer_ros.streaming.engine import StreamingEngine

    layout = json.loads((REPO / "hammer_ros" / "dashboard" / "foxglove_layout.json").read_text())
    v = 0.5 * np.random.default_rng(1).standard_normal(3000)
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=3000, order=3, delay=2))
    t = np.arange(v.size) / 100.0
    engine.add_excitation(t, v)
    engine.add_response(t, simulate_hammerstein(v, static_map("dead_zone", 0.2), DEMO_PLANT))
    outcome = engine.solve()
    assert outcome.ok, outcome.reason
    results = result_messages(outcome, 10**9)
    results.append(("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", diagnostics_message(engine.stats, outcome,
                                                                                               10**9)))
    results.append(("~/diagnosis", "std_msgs/msg/String", {"data": json.dumps({"cause": "none", "samples": 3000})}))
    messages = {dashboard_topic(channel): message for channel, message in dashboard_messages(results, 10**9)}
    assert set(messages) == {dashboard_topic(name) for name in CHANNELS}

    panels = json.dumps(layout["layout"])
    paths = []
    for panel_id, config in layout["configById"].items():
        assert panel_id in panels  # every configured panel is placed in the layout
        paths += [p["value"] for p in config.get("paths", [])] + [config.get("xAxisPath", {}).get("value")]
        paths += [config.get("topicPath"), config.get("topicToRender")]
    shown = set()
    for path in filter(None, paths):
        topic = re.match(r"^/[\w/]+?(?=[.{\[]|$)", path).group(0)
        assert topic in messages, path
        shown.add(topic)
        _resolve(messages[topic], path[len(topic):])  # KeyError/StopIteration: a field the node never publishes
    assert shown == set(messages)
