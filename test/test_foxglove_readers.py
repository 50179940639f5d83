"""``replay --out`` and ``--dashboard-out`` of each sample bag read by Foxglove's own TypeScript
readers (``test/js``: @mcap/core, @foxglove/rosmsg + @foxglove/rosmsg2-serialization, pinned by
its lockfile; installed by ``.ci/run``): every ROS 2 message decodes from its ``ros2msg`` schema,
every JSON message follows its JSON schema, and the results file holds nothing but ROS 2
messages. Skipped, saying why, without Node.js or the installed packages."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from foxglove_js import run_checker

from hammer_ros.cli import main
from hammer_ros.messages.dashboard import CHANNELS, dashboard_topic

REPO = Path(__file__).resolve().parents[1]
BAGS = [("bags/float64_cubic_g1.mcap", "msg_config/float64_cubic_g1.yaml", []),
        ("bags/joint_state_saturation", "msg_config/joint_state_saturation.yaml", ["--diagnose"])]


@pytest.mark.parametrize(("bag", "config", "options"), BAGS, ids=["float64", "joint_state"])
def test_foxglove_readers_decode_every_message_of_both_files(capsys, tmp_path, bag, config, options):
    out, dashboard_out = tmp_path / "results.mcap", tmp_path / "dashboard.mcap"
    assert main(["replay", str(REPO / bag), "--config", str(REPO / config), "--solve-rate", "1", "--out", str(out),
                 "--dashboard-out", str(dashboard_out), *options, "--json"]) == 0
    solves = json.loads(capsys.readouterr().out)["solves"]
    code, report = run_checker("check_mcap.mjs", str(out), str(dashboard_out))
    assert code == 0, {f: {t: v["errors"] for t, v in topics.items() if v["errors"]} for f, topics in report.items()}
    results, dashboard = report[str(out)], report[str(dashboard_out)]
    assert {v["encoding"] for v in results.values()} == {"cdr/ros2msg"}
    assert results["/hammer_ros/model"]["messages"] == solves
    assert ("/hammer_ros/diagnosis" in results) == bool(options)
    channels = [name for name in CHANNELS if options or not name.startswith("diagnosis")]
    assert set(dashboard) == {dashboard_topic(name) for name in channels}
    assert {v["encoding"] for v in dashboard.values()} == {"json/jsonschema"}
    assert dashboard[dashboard_topic("model")]["messages"] == solves
