"""Reading a field straight from serialized messages (``cdr.raw_extractor``, the live node's
fast path) gives exactly what the message objects give, for rclpy's own serialization."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hammer_ros.messages.cdr import extract_batch
from hammer_ros.messages.field_path import FieldError, extract_samples, message_stamp, parse_field_path
from hammer_ros.ros.message_types import raw_extractor, topic_decoder


def messages():
    from geometry_msgs.msg import TwistStamped
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float32MultiArray, Float64, Float64MultiArray, Int32, MultiArrayDimension

    joint = JointState(name=["shoulder", "elbow_joint", "w"], position=[0.5, -1.5, 2.5], velocity=[0.25], effort=[])
    joint.header.stamp.sec, joint.header.stamp.nanosec = 1_700_000_123, 250_000_000
    joint.header.frame_id = "base_link_with_an_odd_length"
    twist = TwistStamped()
    twist.header.stamp.sec = 42
    twist.twist.linear.x, twist.twist.angular.z = 0.75, -0.125
    imu = Imu()
    imu.header.frame_id = "imu"
    imu.angular_velocity.z = 3.5
    imu.orientation_covariance = np.arange(9.0)
    labelled = Float64MultiArray(data=[1.0, 2.0, 3.0])
    labelled.layout.dim = [MultiArrayDimension(label="xyz", size=3, stride=3)]
    labelled.layout.data_offset = 7
    return [
        (Float64(data=2.5), ["data"]),
        (Float64MultiArray(data=list(np.linspace(-1, 1, 100))), ["data", "data[:]", "data[0]", "data[-1]"]),
        (Float64MultiArray(data=[]), ["data[:]"]),
        (labelled, ["data[:]", "data[1]"]),
        (Float32MultiArray(data=[1.5, -2.25]), ["data[:]", "data[1]"]),
        (Int32(data=-7), ["data"]),
        (joint, ["position[:]", "position[2]", "velocity[0]", "header.stamp"]),
        (twist, ["twist.linear.x", "twist.angular.z", "header.stamp"]),
        (imu, ["angular_velocity.z", "orientation_covariance[4]", "orientation_covariance[:]"]),
    ]


def test_raw_cdr_fields_equal_the_message_fields():
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64, Float64MultiArray

    checked = 0
    for msg, paths in messages():
        data = serialize_message(msg)
        for text in paths:
            path = parse_field_path(text)
            extract = raw_extractor(type(msg), path)
            assert extract is not None, text
            values, stamp = extract(data)
            assert np.atleast_1d(values).tolist() == extract_samples(msg, path).tolist(), text
            assert stamp == (message_stamp(msg) or 0.0), text
            assert isinstance(values, float) or values.dtype == np.float64
            checked += 1
    assert checked == 21
    batch = serialize_message(Float64MultiArray(data=[1.0, 2.0, 3.0]))
    view, _ = raw_extractor(Float64MultiArray, parse_field_path("data[:]"))(batch)
    assert not view.flags.owndata and view.tolist() == [1.0, 2.0, 3.0]  # no copy per message
    assert type(raw_extractor(Float64, parse_field_path("data"))(serialize_message(Float64(data=2.5)))[0]) is float


def test_big_endian_payloads_are_read_too():
    import struct

    from std_msgs.msg import Float64, Float64MultiArray

    assert raw_extractor(Float64, parse_field_path("data"))(b"\x00\x00\x00\x00" + struct.pack(">d", -3.25))[0] == -3.25
    data = b"\x00\x00\x00\x00" + struct.pack(">III", 0, 0, 2) + b"\0" * 4 + struct.pack(">dd", 1.5, 2.5)
    values, _ = raw_extractor(Float64MultiArray, parse_field_path("data[:]"))(data)
    assert values.tolist() == [1.5, 2.5]


def test_what_raw_cdr_cannot_read_falls_back_to_messages():
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool, String

    assert raw_extractor(JointState, parse_field_path("name[0]")) is None  # not numeric
    assert raw_extractor(JointState, parse_field_path("speed")) is None  # no such field
    assert raw_extractor(Bool, parse_field_path("data")) is None  # booleans: the message path decides
    assert raw_extractor(String, parse_field_path("data")) is None


def test_short_or_lying_payloads_are_field_errors():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    joint = JointState(name=["a", "b"], position=[1.0, 2.0])
    data = serialize_message(joint)
    extract = raw_extractor(JointState, parse_field_path("position[1]"))
    end = data.find(np.float64(2.0).tobytes()) + 8  # position[1] is whole from here on
    for cut in range(len(data)):
        if cut < end:
            with pytest.raises(FieldError, match="'position\\[1\\]'"):
                extract(data[:cut])
        else:
            assert extract(data[:cut])[0] == 2.0
    lying = bytearray(serialize_message(Float64MultiArray(data=[1.0, 2.0])))
    lying[12:16] = (10**6).to_bytes(4, "little")  # the data count claims a million doubles
    with pytest.raises(FieldError, match="ends inside it"):
        raw_extractor(Float64MultiArray, parse_field_path("data[:]"))(bytes(lying))
    huge = b"\x00\x01\x00\x00" + (2**32 - 1).to_bytes(4, "little") + bytes(16)  # 4e9 layout dims claimed
    with pytest.raises(FieldError, match="ends before it"):  # refused at once, not walked
        raw_extractor(Float64MultiArray, parse_field_path("data[:]"))(huge)
    rng = np.random.default_rng(4)
    for _ in range(300):  # random bytes: values or a FieldError, nothing else
        noise = rng.integers(0, 256, rng.integers(0, 64)).astype(np.uint8).tobytes()
        try:
            extract(noise)
        except FieldError:
            pass


def test_the_bag_schema_gives_the_layout_of_the_installed_types():
    """``schema_extractor`` reads the layout from the ros2msg text a bag stores (here the text
    ``ResultWriter`` writes, from the shipped .msg files): the same values and stamps as the
    installed types' introspection, and a message cut short is read only when mcap_ros2's full
    decoder (what replay falls back to) reads it too."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory
    from rclpy.serialization import serialize_message

    from hammer_ros.io.bags import message_definition
    from hammer_ros.messages.cdr import schema_extractor

    def decodes(decode, data: bytes) -> bool:
        try:
            decode(data)
            return True
        except Exception:
            return False

    checked = refused = 0
    for msg, paths in messages():
        data = serialize_message(msg)
        module, name = type(msg).__module__.split(".")[0], type(msg).__name__
        type_name = f"{module}/msg/{name}"
        for text in paths:
            path = parse_field_path(text)
            extract = schema_extractor(type_name, message_definition(type_name), path)
            assert extract is not None, text
            values, stamp = extract(data)
            expected, expected_stamp = raw_extractor(type(msg), path)(data)
            assert np.atleast_1d(values).tolist() == np.atleast_1d(expected).tolist(), text
            assert stamp == expected_stamp, text
            schema = Schema(id=1, name=type_name, encoding="ros2msg", data=message_definition(type_name).encode())
            decode = DecoderFactory().decoder_for("cdr", schema)
            for cut in range(1, len(data) - 3):
                if decodes(extract, data[:-cut]):
                    assert decodes(decode, data[:-cut]), (text, cut)
                    refused += not decodes(extract, data[: -cut - 1])
            checked += 1
    assert checked == 21 and refused > 0


def test_a_schema_definition_in_msg_form():
    from hammer_ros.messages.cdr import schema_extractor
    from hammer_ros.messages.types import definition_fields

    text = ("# comment\nuint8 OK=0\nstring NAME = \"a=b\"\nHeader header\nfloat64[] a  # trailing\n"
            "float32[<=3] b\nint16[4] c\nstring<=8 d\ngeometry_msgs/Vector3 e\nPoint f\nbool g true\n")
    assert definition_fields(text, "my_msgs") == {
        "header": "std_msgs/Header", "a": "sequence<double>", "b": "sequence<float, 3>", "c": "int16[4]",
        "d": "string<8>", "e": "geometry_msgs/Vector3", "f": "my_msgs/Point", "g": "boolean"}
    assert schema_extractor("my_msgs/msg/Odd", "float64 x\n", parse_field_path("y")) is None  # no such field
    assert schema_extractor("my_msgs/msg/Odd", "Unknown u\nfloat64 x\n", parse_field_path("x")) is None


def test_many_messages_of_one_layout_are_read_at_once_with_the_same_values():
    """``extract_batch`` (the node's ingest of a flush) equals reading each message, and gives up
    (None: one by one) when the messages differ in layout or carry a header stamp."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray, Float64, Float64MultiArray, MultiArrayDimension

    rng = np.random.default_rng(4)
    cases = [
        ([Float64MultiArray(data=list(rng.standard_normal(100))) for _ in range(50)], "data[:]"),
        ([Float64(data=float(x)) for x in rng.standard_normal(50)], "data"),
        ([Float32MultiArray(data=list(rng.standard_normal(7))) for _ in range(9)], "data[:]"),
    ]
    for msgs, text in cases:
        extract = raw_extractor(type(msgs[0]), parse_field_path(text))
        data = [serialize_message(m) for m in msgs]
        block = extract_batch(extract, data)
        assert block is not None and block.dtype == np.float64, text
        assert block.tolist() == [np.atleast_1d(extract(d)[0]).tolist() for d in data], text

    path = parse_field_path("data[:]")
    extract = raw_extractor(Float64MultiArray, path)
    plain = Float64MultiArray(data=[1.0, 2.0, 3.0])
    labelled = Float64MultiArray(data=[1.0, 2.0, 3.0])  # same length, another layout before the data
    labelled.layout.data_offset = 5
    assert len(serialize_message(plain)) == len(serialize_message(labelled))
    assert extract_batch(extract, [serialize_message(plain), serialize_message(labelled)]) is None
    dims = Float64MultiArray(data=[1.0])
    dims.layout.dim = [MultiArrayDimension(label="x", size=1, stride=1)]
    assert extract_batch(extract, [serialize_message(plain), serialize_message(dims)]) is None  # lengths differ
    one = Float64MultiArray(data=[4.0, 5.0])  # 2 samples after one dimension: the length of 4 without any
    one.layout.dim = [MultiArrayDimension(label="x", size=2, stride=2)]
    four = Float64MultiArray(data=[6.0, 7.0, 8.0, 9.0])
    both = [serialize_message(one), serialize_message(four)]
    assert len(both[0]) == len(both[1]) and extract_batch(extract, both) is None
    assert extract_batch(raw_extractor(Float64MultiArray, parse_field_path("data[1]")),
                         [serialize_message(plain)]) is None  # one element: read one by one
    joint = JointState(position=[0.5])
    assert extract_batch(raw_extractor(JointState, parse_field_path("position[:]")),
                         [serialize_message(joint)]) is None  # a header: its stamp is read per message


def test_a_bag_extractor_reads_every_message_of_a_stream_as_if_it_were_the_first():
    """Replay's extractor reads a message with the last one's length and bytes up to a field that
    ends the message without walking it: over a stream whose layout changes and comes back
    (counts, labels, offsets, byte order, cut messages), every value and error is the one of a
    fresh extractor; a field with something after it is walked every time."""
    import struct

    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension

    from hammer_ros.io.bags import message_definition
    from hammer_ros.messages.cdr import schema_extractor

    def multi(data, label="", offset=0):
        msg = Float64MultiArray(data=data)
        msg.layout.data_offset = offset
        if label:
            msg.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=1)]
        return serialize_message(msg)

    big = b"\x00\x00\x00\x00" + struct.pack(">III", 0, 0, 3) + b"\0" * 4 + struct.pack(">ddd", 1.5, 2.5, -4.0)
    stream = [multi([1.0, 2.0, 3.0]), multi([4.0, 5.0, 6.0]), multi([7.0, 8.0]), multi([1.0, 2.0, 9.0], offset=3),
              multi([7.0, 7.5, 8.0], "abc"), multi([7.0, 7.5, 8.5], "abd"), big, multi([0.5, 0.25, 0.125]),
              multi([0.5, 0.25, 0.125])[:-1], multi([1.0, 1.0, 1.0])]
    name = "std_msgs/msg/Float64MultiArray"
    for text in ("data[:]", "data[2]"):
        reused = schema_extractor(name, message_definition(name), parse_field_path(text))
        for data in stream:
            fresh = schema_extractor(name, message_definition(name), parse_field_path(text))
            try:
                expected = np.atleast_1d(fresh(data)[0]).tolist()
            except FieldError as error:
                with pytest.raises(FieldError, match=re.escape(str(error))):
                    reused(data)
                continue
            assert np.atleast_1d(reused(data)[0]).tolist() == expected, (text, data)
    trailing = schema_extractor("my_msgs/msg/Tail", "float64[] x\nstring s\n", parse_field_path("x"))

    def tail(x, s):
        return b"\x00\x01\x00\x00" + struct.pack("<I", len(x)) + b"\0" * 4 + struct.pack(f"<{len(x)}d", *x) + \
            struct.pack("<I", len(s) + 1) + s.encode() + b"\0"
    assert trailing(tail([1.0, 2.0], "ab"))[0].tolist() == [1.0, 2.0]
    assert trailing(tail([3.0, 4.0], "cd"))[0].tolist() == [3.0, 4.0]
    lying = tail([3.0, 4.0], "cd")
    lying = lying[:-7] + struct.pack("<I", 10) + lying[-3:]  # the same bytes up to x, a string past the end
    with pytest.raises(FieldError, match="ends before it"):  # walked, not taken from the last message
        trailing(lying)


def test_several_fields_of_a_topic_are_read_in_one_pass_as_one_by_one():
    """``topic_decoder`` (a topic shared by channels): the names of every message are looked
    up, so reordered names read the right joint, a missing one is bad in that message only, a
    message that ends early is bad for every field; each value and stamp is the one-message
    reader's (``raw_extractor``) and the ground truth's, one layout walked once."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    joints = [f"joint_{k}" for k in range(6)]
    texts = [f"{field}[{name}]" for name in joints for field in ("position", "velocity")]
    paths = [parse_field_path(t) for t in texts]
    decoder = topic_decoder(JointState, paths)
    rng = np.random.default_rng(5)
    messages, truth = [], []
    for i in range(400):
        names = list(joints)
        if i % 50 == 3:
            names = [names[j] for j in rng.permutation(6)]
        if i == 200:
            names.remove("joint_4")
        msg = JointState(name=names, position=[int(n[-1]) + 0.001 * i for n in names],
                         velocity=[-int(n[-1]) - 0.001 * i for n in names])
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000 + i, 1000 * i
        msg.header.frame_id = "base" if i != 300 else "a_longer_frame"
        messages.append(serialize_message(msg))
        truth.append([s * (k + 0.001 * i) for k in range(6) for s in (1, -1)])
    messages.append(messages[0][:60])  # ends inside the names
    decoded = decoder.decode(messages)
    assert len(decoder._plans) <= 12  # the permutations, the missing joint, the long frame_id
    for i, data in enumerate(messages):
        for j, path in enumerate(paths):
            try:
                value, stamp = raw_extractor(JointState, path)(data)
            except FieldError:
                assert decoded.bad[i, j], (i, texts[j])
                continue
            assert not decoded.bad[i, j] and decoded.values[i, j] == value == truth[i][j], (i, texts[j])
            assert decoded.stamps[i] == stamp == 1_700_000_000 + i + 1e-6 * i
    assert decoded.bad[200].tolist() == [t.startswith(("position[joint_4]", "velocity[joint_4]")) for t in texts]
    assert decoded.bad[-1].all() and np.count_nonzero(decoded.bad) == 2 + len(paths)
    assert decoded.errors[8] == "field 'position[joint_4]': the message ends before its last field"  # the last
    again = decoder.decode(messages[200:201])  # a kept plan: the same answers
    assert again.errors[8].startswith("field 'position[joint_4]': no 'joint_4' in this message's name")
    assert again.errors[0] == "" and not again.bad[0, 0] and again.values[0, 0] == 0.2
    commands = topic_decoder(Float64MultiArray, [parse_field_path("data[0]"), parse_field_path("data[-1]")])
    block = commands.decode([serialize_message(Float64MultiArray(data=[1.0 * i, 0.0, 3.0 * i])) for i in range(5)])
    assert block.values.tolist() == [[i, 3.0 * i] for i in range(5)] and not block.bad.any()
    for text in ("position", "position[:]", "name[0]", "header.stamp", "speed"):  # not one number each
        assert topic_decoder(JointState, [paths[0], parse_field_path(text)]) is None, text
    noise = [rng.integers(0, 256, 40).astype(np.uint8).tobytes() for _ in range(50)]
    assert topic_decoder(JointState, paths).decode(noise).values.shape == (50, 12)  # bad or numbers


def test_the_alignment_padding_does_not_make_a_new_layout():
    """A serializer need not zero CDR's alignment padding (rclpy's leaves what its buffer held): two
    messages that differ in padding bytes only share one plan and read the same numbers."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import JointState

    msg = JointState(name=["a", "b"], position=[1.5, 2.5])
    msg.header.frame_id = "base"  # 4 + 4 + 4 + 5 bytes: the names' count is aligned after 3 bytes of padding
    data = serialize_message(msg)
    smudged = bytearray(data)
    smudged[4 + 17 : 4 + 20] = b"\xab\xcd\xef"
    back = deserialize_message(bytes(smudged), JointState)
    assert back.header.frame_id == "base" and list(back.name) == ["a", "b"]  # they were padding
    decoder = topic_decoder(JointState, [parse_field_path("position[b]")])
    decoded = decoder.decode([data, bytes(smudged)])
    assert len(decoder._plans) == 1
    assert decoded.values[:, 0].tolist() == [2.5, 2.5] and not decoded.bad.any()
