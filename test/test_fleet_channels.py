"""``hammer-ros fleet --config`` with several channels: rosbags-written rosbag2 bags of one robot
with two joints in one JointState (by name) and one command array, one bag a day; a row per
(bag, channel) with the joint's model against the generator's truth, the change test per channel
(joint2's gain drift flagged from its first day, joint1 never), the channel in fleet.parquet,
the JSON and fleet.html, a channel's row (and its diagnosis) equal to ``replay``'s of that channel, and bad channel
lists (exit 2, one line, before any work)."""

from __future__ import annotations

import datetime
import json
from pathlib import Path

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.fleet.sample_fleet import START, record, sample_joints
from hammer_ros.fleet.table import read_rows
from hammer_ros.identification.linear import root_rss_error

DAYS, SAMPLES, PERIOD_NS = 8, 2000, 10_000_000
JOINTS = sample_joints(robots=1, joints=2)  # robot_01/joint1 healthy, robot_01/joint2's gain drifts from day 4
CONFIG = """hammer_ros:
  ros__parameters:
    excitation_topic: /arm_cmd
    excitation_type: std_msgs/msg/Float64MultiArray
    response_topic: /joint_states
    response_type: sensor_msgs/msg/JointState
    sample_rate: 100.0
    window: 2000
    method: cls-markov
    order: 2
    delay: 1
    poly: 3
    solve_rate: 0.5
    channels: [joint1, joint2]
    joint1: {excitation_field: "data[0]", response_field: "velocity[joint1]"}
    joint2: {excitation_field: "data[1]", response_field: "velocity[joint2]"}
"""


def write_arm_day(path: Path, day: int) -> None:
    """/arm_cmd Float64MultiArray [u_1, u_2] and /joint_states JointState (velocity of joint1 and
    joint2, names in reverse order: read by name) at 100 Hz, each joint the sample fleet's plant
    on ``day`` (``sample_fleet.record``)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    signals = [record(spec, day, seed=1000 * g + 2 * day, samples=SAMPLES) for g, spec in enumerate(JOINTS)]
    start_ns = int((START + datetime.timedelta(days=day - 1)).timestamp()) * 1_000_000_000
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        cmd = writer.add_connection("/arm_cmd", "std_msgs/msg/Float64MultiArray", typestore=store)
        joints = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        layout = types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        names = [spec.joint for spec in reversed(JOINTS)]
        for k in range(SAMPLES):
            t = start_ns + k * PERIOD_NS
            writer.write(cmd, t, store.serialize_cdr(types["std_msgs/msg/Float64MultiArray"](
                layout=layout, data=np.array([v[k] for v, _ in signals])), "std_msgs/msg/Float64MultiArray"))
            stamp = types["builtin_interfaces/msg/Time"](sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
            velocity = np.array([y[k] for _, y in reversed(signals)])
            msg = types["sensor_msgs/msg/JointState"](
                header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=""), name=names, position=velocity,
                velocity=velocity, effort=np.array([], dtype=float))
            writer.write(joints, t + 500_000, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


@pytest.fixture(scope="module")
def arm_fleet(tmp_path_factory):
    """The bags, the config and ``fleet --workers 2 --json`` on them."""
    root = tmp_path_factory.mktemp("arm_fleet")
    bags = {}
    for day in range(1, DAYS + 1):
        path = root / "bags" / "robot_01" / (START + datetime.timedelta(days=day - 1)).date().isoformat()
        write_arm_day(path, day)
        bags[str(path.resolve())] = day
    config = root / "arm.yaml"
    config.write_text(CONFIG)
    out = root / "out"
    code, stdout = run_json(["fleet", str(root / "bags"), "--config", str(config), "--workers", "2", "--out",
                             str(out), "--json"])
    assert code == 0
    return bags, config, out, json.loads(stdout)


def run_json(argv: list[str]) -> tuple[int, str]:
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(argv)
    return code, buffer.getvalue()


def test_every_channel_of_every_bag_is_the_joints_model(arm_fleet):
    bags, _, out, doc = arm_fleet
    assert (doc["bags"], doc["ok"], doc["failed"], doc["channels"]) == (DAYS, 2 * DAYS, 0, ["joint1", "joint2"])
    assert {(r["path"], r["channel"]) for r in doc["rows"]} == {(p, s.joint) for p in bags for s in JOINTS}
    for row in doc["rows"]:
        spec = next(s for s in JOINTS if s.joint == row["channel"])
        day = bags[row["path"]]
        assert row["group"] == "robot_01" and row["samples"] == SAMPLES
        poles = np.array([complex(*p) for p in row["poles"]])
        assert root_rss_error(spec.linear(day).poles, poles) < 0.05, (row["channel"], day, poles)
        truth = spec.gain_on(day)  # F's slope over the central half is 1 (the saturation is at 2 sd)
        assert row["quantities"]["static_gain"] == pytest.approx(truth, rel=0.08), (row["channel"], day)
    table, _ = read_rows(out / "fleet.parquet")
    assert sorted((r["path"], r["channel"]) for r in table) == sorted((r["path"], r["channel"]) for r in doc["rows"])
    import pyarrow.parquet as pq

    assert pq.read_schema(out / "fleet.parquet").names[:3] == ["path", "group", "channel"]


def test_the_change_test_follows_each_channel_apart(arm_fleet):
    """joint2's drift is flagged from its first day in its channel's series; joint1 (the same bags)
    has no change."""
    _, _, out, doc = arm_fleet
    drifting = next(s for s in JOINTS if s.drift_day)
    changes = {(c["group"], c["channel"], c["quantity"]): c for c in doc["changes"]}
    assert all(c["channel"] == drifting.joint for c in doc["changes"]), list(changes)
    gain = changes[("robot_01", drifting.joint, "static_gain")]
    assert gain["first_date"] == (START + datetime.timedelta(days=drifting.drift_day - 1)).date().isoformat()
    assert gain["size"] < -0.15 and gain["bags"] == DAYS - drifting.drift_day + 1
    page = (out / "fleet.html").read_text()
    assert "robot_01 [joint1] (8 bags)" in page and "robot_01 [joint2] (8 bags)" in page


def test_a_channels_row_equals_replay_of_the_channels(arm_fleet):
    bags, config, _, doc = arm_fleet
    path = next(p for p, day in bags.items() if day == DAYS)
    code, stdout = run_json(["replay", path, "--config", str(config), "--json"])
    assert code == 0
    replayed = json.loads(stdout)["channels"]
    for row in (r for r in doc["rows"] if r["path"] == path):
        expected = dict(replayed[row["channel"]])
        expected.pop("wall_s")
        assert {k: row[k] for k in expected} == expected


def test_diagnose_gives_each_channel_the_diagnosis_of_replay_diagnose(arm_fleet, tmp_path):
    """``fleet --diagnose`` with channels: each (bag, channel) row's diagnosis is the one
    ``replay --diagnose`` gives that channel of the bag (cause, gain, confidence), in the JSON and
    in fleet.parquet."""
    from hammer_ros.fleet.tasks import row_diagnosis

    bags, config, _, _ = arm_fleet
    paths = sorted(bags)[-2:]
    out = tmp_path / "out"
    code, stdout = run_json(["fleet", *paths, "--config", str(config), "--workers", "1", "--diagnose",
                             "--out", str(out), "--json"])
    assert code == 0
    doc = json.loads(stdout)
    assert (doc["ok"], doc["failed"]) == (4, 0)
    stored = {(r["path"], r["channel"]): r["diagnosis"] for r in read_rows(out / "fleet.parquet")[0]}
    for path in paths:
        code, stdout = run_json(["replay", path, "--config", str(config), "--diagnose", "--json"])
        assert code == 0
        replayed = json.loads(stdout)["channels"]
        for row in (r for r in doc["rows"] if r["path"] == path):
            expected = row_diagnosis(replayed[row["channel"]]["diagnosis"])
            assert expected["cause"] is not None and "error" not in expected, expected
            assert row["diagnosis"] == expected == stored[(path, row["channel"])], (path, row["channel"])


def test_resume_keeps_the_finished_bags_channels_and_replays_the_rest(arm_fleet, tmp_path):
    """A fleet.parquet holding both channels of the first 3 bags: --resume replays the other 5
    bags (both channels each) and keeps the 6 rows as they were."""
    from hammer_ros.fleet.table import write_parquet

    bags, config, out, _ = arm_fleet
    rows, settings = read_rows(out / "fleet.parquet")
    kept = sorted(bags)[:3]
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    write_parquet([r for r in rows if r["path"] in kept], resumed / "fleet.parquet", settings, 100.0)
    code, stdout = run_json(["fleet", *bags, "--config", str(config), "--workers", "1", "--out", str(resumed),
                             "--resume"])
    assert code == 0 and "8 bags x 2 channels (joint1, joint2), 16 with a model, 0 failed (3 from the previous run)" \
        in stdout, stdout
    again, _ = read_rows(resumed / "fleet.parquet")
    assert sorted((r["path"], r["channel"]) for r in again) == sorted((r["path"], r["channel"]) for r in rows)
    before = {(r["path"], r["channel"]): r for r in rows}
    for row in again:
        if row["path"] in kept:
            assert row == before[(row["path"], row["channel"])]  # not replayed: the same row
        else:
            assert row["model"]["poles"] == before[(row["path"], row["channel"])]["model"]["poles"]


@pytest.mark.parametrize(("change", "reason"), [
    ("channels: [joint1, joint2, joint1]", "channels: duplicate channel 'joint1'"),
    ("channels: [joint1]", "joint2: parameters of a channel 'joint2' that is not in channels (joint1)"),
    ("channels: [joint1, joint2]\n    joint2.sample_rate: 50.0", "fleet needs one sample_rate for all channels"),
])
def test_bad_channel_lists_exit_2_naming_the_channel(arm_fleet, tmp_path, capsys, change, reason):
    bags, _, _, _ = arm_fleet
    config = tmp_path / "bad.yaml"
    config.write_text(CONFIG.replace("    channels: [joint1, joint2]\n", f"    {change}\n"))
    assert main(["fleet", *bags, "--config", str(config), "--workers", "1", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and "\n" not in err, err
    assert not (tmp_path / "out" / "fleet.parquet").exists()
