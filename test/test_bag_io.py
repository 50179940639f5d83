"""Field paths, msg_config files and reading bags (the committed sample bags are real MCAP
files, one written by mcap_ros2, one by rosbags): the samples come back exactly."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from make_sample_bags import G1, RESONANT, cubic_record, saturation_record
from make_sample_bags import main as make_sample_bags

from hammer_ros.errors import UsageError
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.methods import IdentifyOptions, identify
from hammer_ros.io.bags import (
    bag_files,
    engine_config_from_params,
    load_bag_record,
    load_msg_config,
    message_definition,
    stream_specs,
)
from hammer_ros.messages.field_path import FieldError, extract_samples, message_stamp, parse_field_path

REPO = Path(__file__).resolve().parents[1]
FLOAT64_BAG = REPO / "bags" / "float64_cubic_g1.mcap"
JOINT_BAG = REPO / "bags" / "joint_state_saturation"
CONFIGS = sorted((REPO / "msg_config").glob("*.yaml"))


def test_field_paths_on_dicts_and_rclpy_messages():
    from geometry_msgs.msg import TwistStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    joint = JointState(name=["a", "b", "c"], velocity=[0.5, -1.5, 2.5])
    joint.header.stamp.sec, joint.header.stamp.nanosec = 12, 250_000_000
    assert extract_samples(joint, parse_field_path("velocity[2]")).tolist() == [2.5]
    assert extract_samples(joint, parse_field_path("velocity[-1]")).tolist() == [2.5]
    assert extract_samples(joint, parse_field_path("velocity[:]")).tolist() == [0.5, -1.5, 2.5]
    assert extract_samples(joint, parse_field_path("header.stamp")).tolist() == [12.25]
    assert message_stamp(joint) == 12.25
    twist = TwistStamped()
    twist.twist.linear.x = 0.75
    assert extract_samples(twist, parse_field_path("twist.linear.x")).tolist() == [0.75]
    assert message_stamp(twist) == 0.0
    assert message_stamp(twist.twist) is None
    batch = Float64MultiArray(data=[1.0, 2.0, 3.0])
    assert parse_field_path("data[:]").is_batch
    assert extract_samples(batch, parse_field_path("data")).tolist() == [1.0, 2.0, 3.0]
    nested = {"twist": {"linear": {"x": 3.0}}, "flags": [True, False]}
    assert extract_samples(nested, parse_field_path("twist.linear.x")).tolist() == [3.0]
    assert extract_samples(nested, parse_field_path("flags[0]")).tolist() == [1.0]


@pytest.mark.parametrize(("path", "message"), [
    ("velocity[7]", "index 7 out of range, 'velocity' has 3 elements"),
    ("speed", "no field 'speed' in JointState"),
    ("name[0]", "not numeric"),
    ("header", "not numeric (Header)"),
    ("velocity[0].x", "no field 'x'"),
    ("position.x[0]", "no field 'x'"),
])
def test_field_errors_name_the_field(path, message):
    from sensor_msgs.msg import JointState

    joint = JointState(name=["a", "b", "c"], velocity=[0.5, -1.5, 2.5], position=[0.0, 0.0, 0.0])
    with pytest.raises(FieldError, match=f"^field {re.escape(repr(path))}: ") as err:
        extract_samples(joint, parse_field_path(path))
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("text", ["", "velocity[", "a..b", "data[]", "data[x][y]", "2x", "data[:][:]"])
def test_malformed_field_paths_are_usage_errors(text):
    with pytest.raises(UsageError, match="field path"):
        parse_field_path(text)


def test_float64_bag_written_by_mcap_ros2_gives_back_the_simulated_samples():
    """/cmd one Float64 per sample, /response Float64MultiArray batches of 10 stamped by the log
    time of their last sample: on the configured 100 Hz grid every sample comes back exactly."""
    record = load_bag_record(FLOAT64_BAG, config=REPO / "msg_config" / "float64_cubic_g1.yaml")
    v, y = cubic_record()
    np.testing.assert_array_equal(record.v, v)
    np.testing.assert_array_equal(record.y, y)
    np.testing.assert_allclose(np.diff(record.t), 0.01, atol=1e-6)
    result = identify("cls-markov", record.v, record.y, IdentifyOptions(order=3, delay=1))
    assert root_rss_error(G1.poles, result.poles) < 0.02


def test_joint_state_bag_written_by_rosbags_gives_back_the_simulated_samples():
    """Header stamps (not the jittered log times) place the JointState samples."""
    record = load_bag_record(JOINT_BAG, "/cmd:data", "/joint_states:velocity[0]")
    v, y = saturation_record()
    np.testing.assert_array_equal(record.v, v)
    np.testing.assert_array_equal(record.y, y)
    result = identify("cls-markov", record.v, record.y, IdentifyOptions(order=2, delay=1))
    assert root_rss_error(RESONANT.poles, result.poles) < 0.02
    effort = load_bag_record(JOINT_BAG, "/cmd:data", "/joint_states:effort[0]")
    np.testing.assert_array_equal(effort.y, np.clip(v, -0.6, 0.6))


@pytest.mark.parametrize(("bag", "specs"), [(FLOAT64_BAG, ("/cmd:data", "/response:data[:]")),
                                           (JOINT_BAG, ("/cmd:data", "/joint_states:velocity[0]")),
                                           (JOINT_BAG, ("/joint_states:position[:]", "/joint_states:effort[0]"))])
def test_the_fast_bag_read_equals_mcap_and_the_full_decode(monkeypatch, bag, specs):
    """The chunk parser gives mcap's records, and fields read from the CDR bytes with the bag's
    own schema (written by mcap_ros2 and by rosbags) give the samples and stamps of the full
    mcap_ros2 decode, message by message."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk

    from hammer_ros.io import bag_reader
    from hammer_ros.io import bags as bag_io

    chunks = 0
    for file in bag_files(bag):
        with open(file, "rb") as fh:
            for record in StreamReader(fh, emit_chunks=True).records:
                if isinstance(record, Chunk):
                    assert bag_io.chunk_records(record) == breakup_chunk(record, validate_crc=True)
                    chunks += 1
    assert chunks > 0
    excitation, response = (bag_io.parse_stream_spec(text, "spec") for text in specs)

    def samples() -> list:
        return [(s.stream, s.stamp, s.log_time, np.atleast_1d(s.values).tolist())
                for s in bag_io.iter_bag_samples(bag, excitation, response)]
    decoded = []
    full_decode = bag_reader._decode_message
    monkeypatch.setattr(bag_reader, "_decode_message", lambda *args: decoded.append(1) or full_decode(*args))
    fast = samples()
    assert not decoded  # every message read from its bytes
    monkeypatch.setattr(bag_reader, "_field_readers", lambda *args: None)
    assert fast == samples() and len(fast) > 1000 and len(decoded) > 500


def _raw_messages(bag):
    from mcap.reader import make_reader

    out = []
    for file in bag_files(bag):
        with open(file, "rb") as fh:
            out += [(c.topic, m.log_time, m.data) for _, c, m in make_reader(fh).iter_messages(log_time_order=True)]
    return out


def test_sample_bags_are_reproducible_from_the_generator(tmp_path):
    make_sample_bags(str(tmp_path))
    for name in ("float64_cubic_g1.mcap", "joint_state_saturation", "servo_arm"):
        fresh, committed = tmp_path / name, REPO / "bags" / name
        assert sum(f.stat().st_size for f in bag_files(fresh)) < 2_000_000
        assert _raw_messages(fresh) == _raw_messages(committed)  # same CDR bytes, same times


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: p.name)
def test_every_msg_config_is_a_ros_params_file_with_valid_settings(config):
    doc = yaml.safe_load(config.read_text())
    assert list(doc) == ["hammer_ros"] and "ros__parameters" in doc["hammer_ros"]
    params = load_msg_config(config)
    engine = engine_config_from_params(params, str(config))
    excitation, response = stream_specs(None, None, params)
    assert engine.method == params["method"] and excitation.topic == params["excitation_topic"]
    assert response.type_name == params["response_type"]


def test_msg_config_errors_name_the_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("hammer_ros:\n  ros__parameters:\n    windw: 100\n")
    with pytest.raises(UsageError, match=r"bad.yaml: unknown parameter 'windw'"):
        engine_config_from_params(load_msg_config(bad), str(bad))
    bad.write_text("window: 100\n")
    with pytest.raises(UsageError, match=r"bad.yaml: expected a ROS 2 params file"):
        load_msg_config(bad)
    bad.write_text("hammer_ros: {ros__parameters: {window: [1, 2}\n")
    with pytest.raises(UsageError, match=r"bad.yaml: not valid YAML"):
        load_msg_config(bad)
    with pytest.raises(UsageError, match=r"^config: window: must be"):
        engine_config_from_params({"window": 5})
    with pytest.raises(UsageError, match=r"^--output: give /topic:field"):
        stream_specs("/cmd:data", None, {})


def test_bad_bags_are_usage_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(UsageError, match="not a rosbag2 directory"):
        bag_files(tmp_path / "empty")
    other = tmp_path / "other"
    other.mkdir()
    (other / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: leveldb\n  relative_file_paths: [a.ldb]\n")
    with pytest.raises(UsageError, match="storage 'leveldb' is not supported"):
        bag_files(other)
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"\x89MCAP0\r\n" + b"\0" * 40)
    with pytest.raises(UsageError, match=r"broken\.mcap: not a readable MCAP file"):
        load_bag_record(broken, "/cmd:data", "/y:data")


def test_message_definitions_include_every_nested_type():
    text = message_definition("diagnostic_msgs/msg/DiagnosticArray")
    assert [line for line in text.splitlines() if line.startswith("MSG: ")] == [
        "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time", "MSG: diagnostic_msgs/DiagnosticStatus",
        "MSG: diagnostic_msgs/KeyValue"]
    with pytest.raises(UsageError, match=r"no \.msg definition"):
        message_definition("nonexistent_msgs/msg/Thing")
