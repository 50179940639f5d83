"""Bad input to the command line: damaged bags, CSV/NPZ, configs and contradictory options.

A user mistake exits 2 with one line on stderr naming the file, field or option (never a
traceback); a damaged recording is read up to where it broke, with a warning saying where."""

from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from conftest import G1, REPO

from hammer_ros.cli import main
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.io import bag_reader
from hammer_ros.io.bags import message_definition

HAMMER_ROS = str(Path(sys.executable).parent / "hammer-ros")
JOINT_BAG = REPO / "bags" / "joint_state_saturation"
FLOAT64_BAG = REPO / "bags" / "float64_cubic_g1.mcap"
FLOAT64_CONFIG = REPO / "msg_config" / "float64_cubic_g1.yaml"
CDR_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header, little endian


def float64_cdr(x: float) -> bytes:
    return CDR_LE + struct.pack("<d", x)


def multiarray_cdr(values: np.ndarray, claimed: int | None = None) -> bytes:
    """std_msgs/Float64MultiArray: empty layout, then float64[] (length, pad to 8, doubles)."""
    n = values.size if claimed is None else claimed
    return CDR_LE + struct.pack("<III", 0, 0, n) + b"\0" * 4 + np.asarray(values, "<f8").tobytes()


class Bag:
    """An MCAP file written record by record with mcap's own writer (raw CDR), so tests can put
    exactly what they want in it: small chunks, unknown schemas, huge or lying messages."""

    def __init__(self, path: Path, chunk_size: int = 4096) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = path
        self._file = open(path, "wb")
        self.writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self.writer.start(profile="ros2", library="test")
        self.channels: dict[str, int] = {}

    def channel(self, topic: str, type_name: str, encoding: str = "ros2msg", schema: bytes | None = None,
                message_encoding: str = "cdr") -> int:
        if topic not in self.channels:
            data = schema if schema is not None else message_definition(type_name).encode()
            schema_id = self.writer.register_schema(type_name, encoding, data)
            self.channels[topic] = self.writer.register_channel(topic, message_encoding, schema_id)
        return self.channels[topic]

    def write(self, topic: str, type_name: str, stamp: float, data: bytes) -> None:
        ns = int(round(stamp * 1e9))
        self.writer.add_message(self.channel(topic, type_name), log_time=ns, data=data, publish_time=ns)

    def close(self) -> Path:
        self.writer.finish()
        self._file.close()
        return self.path


def g1_bag(path: Path, n: int = 6000, chunk_size: int = 4096) -> Path:
    """/cmd and /y (std_msgs/Float64) at 100 Hz: paper 000's G1 after F(v) = v + 4 v^3."""
    rng = np.random.default_rng(5)
    v = rng.normal(0.0, 0.3, n)
    y = simulate_hammerstein(v, lambda x: x + 4 * x**3, G1) + 0.01 * rng.standard_normal(n)
    bag = Bag(path, chunk_size)
    for k in range(n):
        bag.write("/cmd", "std_msgs/msg/Float64", 1.0 + k / 100.0, float64_cdr(v[k]))
        bag.write("/y", "std_msgs/msg/Float64", 1.0 + k / 100.0 + 1e-4, float64_cdr(y[k]))
    return bag.close()


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_usage_error(capsys, argv, *needles) -> str:
    code, out, err = run(capsys, *argv)
    assert code == 2, err
    assert out == "" and "Traceback" not in err
    err = "".join(line + "\n" for line in err.split("\n")[:-1] if not line.startswith("\r"))  # replay's progress
    assert err.count("\n") == 1 and err.startswith("hammer-ros: error: "), err
    for needle in needles:
        assert needle in err, err
    return err


def warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("hammer-ros: warning: ")]


def replay_json(capsys, bag, *extra) -> tuple[dict, str]:
    code, out, err = run(capsys, "replay", bag, "--input", "/cmd:data", "--output", "/y:data", "--json", *extra)
    assert code == 0, err
    return json.loads(out), err


def pole_error(doc) -> float:
    return root_rss_error(G1.poles, np.array([complex(re_, im) for re_, im in doc["poles"]]))


# ------------------------------------------------------------------------------------ bags
def test_a_truncated_recording_is_read_up_to_where_it_broke(capsys, tmp_path):
    whole = g1_bag(tmp_path / "whole.mcap")
    cut = tmp_path / "cut.mcap"
    data = whole.read_bytes()
    cut.write_bytes(data[: int(0.6 * len(data))])  # e.g. the recorder lost power
    doc, err = replay_json(capsys, cut)
    [warning] = warnings(err)
    match = re.search(r"cut\.mcap: truncated: the file ends inside the record at byte ([\d,]+) of ([\d,]+); "
                      r"read the (\d+) messages before it", warning)
    assert match, warning
    messages = int(match.group(3))
    assert doc["samples"] == messages // 2 > 3000  # every complete (/cmd, /y) pair before the break
    assert pole_error(doc) < 0.05
    code, out, err = run(capsys, "identify", cut, "--input", "/cmd:data", "--output", "/y:data", "--json")
    assert code == 0 and len(warnings(err)) == 1 and pole_error(json.loads(out)) < 0.05


def test_a_corrupt_chunk_is_skipped_and_the_rest_is_read(capsys, tmp_path):
    from mcap.reader import make_reader

    whole = g1_bag(tmp_path / "whole.mcap")
    with open(whole, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    middle = chunks[len(chunks) // 2].chunk_start_offset + 100  # inside a chunk's compressed data
    data = bytearray(whole.read_bytes())
    data[middle : middle + 64] = bytes(b ^ 0x5A for b in data[middle : middle + 64])
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    doc, err = replay_json(capsys, broken)
    [warning] = warnings(err)
    assert re.search(r"broken\.mcap: chunk at byte [\d,]+ is corrupt \(.+\); skipped", warning), warning
    assert 5000 < doc["samples"] < 6000  # one chunk of ~300 samples lost, the segments after it read
    assert pole_error(doc) < 0.05


def damaged(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    """One random damage of a file: flipped bits, a zeroed run, a cut, or a spliced-out stretch."""
    b = bytearray(data)
    kind = ("flips", "zeroed", "cut", "splice")[rng.integers(4)]
    if kind == "flips":
        for at in rng.integers(len(b), size=rng.integers(1, 20)):
            b[at] ^= 1 << int(rng.integers(8))
    elif kind == "zeroed":
        at = int(rng.integers(len(b)))
        b[at:at + int(rng.integers(1, 4000))] = b"\0" * len(b[at:at + 4000])
    elif kind == "cut":
        del b[int(rng.integers(len(b))):]
    else:
        at, to = sorted(int(i) for i in rng.integers(len(b), size=2))
        del b[at:to]
    return kind, bytes(b)


def test_randomly_damaged_bags_give_a_model_or_one_line_never_a_traceback(capsys, tmp_path):
    """A fuzz of the sample bag: 40 random damages (seeded). Each run either identifies (exit 0,
    a model) or exits 2 with one error line naming the file - never exit 1 or a traceback."""
    rng = np.random.default_rng(11)
    data = FLOAT64_BAG.read_bytes()
    outcomes = {0: 0, 2: 0}
    for trial in range(40):
        kind, damage = damaged(data, rng)
        path = tmp_path / f"damaged_{trial}.mcap"
        path.write_bytes(damage)
        code, out, err = run(capsys, "identify", path, "--config", FLOAT64_CONFIG, "--method", "cls-arx", "--json")
        assert code in outcomes and "Traceback" not in err, (kind, trial, code, err)
        if code == 0:
            assert len(json.loads(out)["poles"]) == 3, (kind, trial)
        else:
            [line] = [x for x in err.splitlines() if x.startswith("hammer-ros: error: ")]
            assert path.name in line, (kind, trial, line)
        outcomes[code] += 1
    assert min(outcomes.values()) >= 5, outcomes  # both outcomes were exercised


def test_a_bag_broken_inside_its_first_chunk_is_a_one_line_error(capsys, tmp_path):
    whole = g1_bag(tmp_path / "one_chunk.mcap", chunk_size=10_000_000)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[:40_000])
    assert_usage_error(capsys, ["identify", cut, "--input", "/cmd:data", "--output", "/y:data"],
                       "cut.mcap: no topic '/cmd'", "truncated", "read the 0 messages")


@pytest.mark.parametrize("content, needle", [
    (b"", "not a readable MCAP file (empty file)"),
    (b"u,y\n1,2\n", "not an MCAP file (wrong magic bytes)"),
    (b"\x89MCAP0\r\n" + b"\0" * 40, "not a readable MCAP file"),
])
def test_files_that_are_not_mcap_are_one_line_errors(capsys, tmp_path, content, needle):
    bag = tmp_path / "bad.mcap"
    bag.write_bytes(content)
    assert_usage_error(capsys, ["replay", bag, "--input", "/cmd:data", "--output", "/y:data"], f"bad.mcap: {needle}")


def test_a_rosbag2_directory_without_metadata_is_read_with_a_warning(capsys, tmp_path):
    bare = tmp_path / "bare"
    bare.mkdir()
    for file in JOINT_BAG.glob("*.mcap"):
        shutil.copy(file, bare)
    spec = ["--input", "/cmd:data", "--output", "/joint_states:velocity[0]", "--order", "2", "--json"]
    code, out, err = run(capsys, "identify", bare, *spec)
    assert code == 0 and warnings(err) == [f"hammer-ros: warning: {bare}: no metadata.yaml; reading its 1 bag "
                                           "file(s) in name order"]
    code, reference, _ = run(capsys, "identify", JOINT_BAG, *spec)
    assert json.loads(out)["poles"] == json.loads(reference)["poles"]
    (tmp_path / "empty").mkdir()
    assert_usage_error(capsys, ["identify", tmp_path / "empty", *spec[:4]],
                       "not a rosbag2 directory (no metadata.yaml and no .mcap or .db3 files)")


def test_each_read_of_a_process_warns_for_itself(capsys, tmp_path):
    """The warnings belong to the read that finds them (no state shared between the reads of one process):
    ``hammer_ros.read`` twice in one process warns twice; one read that takes the bag twice (its reference)
    warns once; two reads in two threads at once warn once each."""
    import hammer_ros

    bare = tmp_path / "bare"
    bare.mkdir()
    for file in JOINT_BAG.glob("*.mcap"):
        shutil.copy(file, bare)
    note = f"hammer-ros: warning: {bare}: no metadata.yaml; reading its 1 bag file(s) in name order"
    spec = {"input": "/cmd:data", "output": "/joint_states:velocity[0]"}
    for _ in range(2):
        hammer_ros.read(bare, **spec)
        assert warnings(capsys.readouterr().err) == [note]
    hammer_ros.read(bare, **spec, reference="/cmd:data")
    assert warnings(capsys.readouterr().err) == [note]
    with ThreadPoolExecutor(2) as pool:
        records = list(pool.map(lambda _: hammer_ros.read(bare, **spec), range(2)))
    assert warnings(capsys.readouterr().err) == [note, note]
    np.testing.assert_array_equal(records[0].y, records[1].y)


def test_unknown_schemas_in_a_bag_are_skipped_unless_asked_for(capsys, tmp_path):
    bag = Bag(tmp_path / "mixed.mcap")
    rng = np.random.default_rng(1)
    v = rng.normal(0, 0.3, 3000)
    y = simulate_hammerstein(v, lambda x: x + 4 * x**3, G1)
    bag.channel("/log", "foxglove.Log", encoding="jsonschema", schema=b"{}", message_encoding="json")
    bag.channel("/odd", "odd_msgs/msg/Odd", schema=b"this is not a msg definition ]]]")
    for k in range(3000):
        bag.write("/cmd", "std_msgs/msg/Float64", 1 + k / 100, float64_cdr(v[k]))
        bag.write("/y", "std_msgs/msg/Float64", 1 + k / 100, float64_cdr(y[k]))
        bag.write("/log", "foxglove.Log", 1 + k / 100, b'{"message": "hello"}')
        bag.write("/odd", "odd_msgs/msg/Odd", 1 + k / 100, b"\x00\x01\x00\x00garbage")
    path = bag.close()
    doc, err = replay_json(capsys, path)
    assert doc["samples"] == 3000 and warnings(err) == [] and pole_error(doc) < 0.02
    assert_usage_error(capsys, ["replay", path, "--input", "/log:message", "--output", "/y:data"],
                       "topic /log: 'json' messages with a 'jsonschema' schema are not ROS 2 CDR/ros2msg")
    assert_usage_error(capsys, ["replay", path, "--input", "/odd:data", "--output", "/y:data"],
                       "topic /odd: cannot parse its schema 'odd_msgs/msg/Odd'")


def test_a_decoder_is_reused_for_the_same_schema_text_only(tmp_path):
    """Decoders are kept across files by their schema's text (``bag_reader._Decoders``): a second
    bag of the same type gets the first one's, and a bag with another definition under the same
    type name gets its own, which reads its own layout (an int32 before the double)."""
    plain, padded = Bag(tmp_path / "plain.mcap"), Bag(tmp_path / "padded.mcap")
    plain.channel("/x", "my_msgs/msg/Sample", schema=b"float64 data")
    padded.channel("/x", "my_msgs/msg/Sample", schema=b"int32 count\nfloat64 data")
    for k in range(3):
        plain.write("/x", "my_msgs/msg/Sample", 1 + k, float64_cdr(0.5 + k))
        padded.write("/x", "my_msgs/msg/Sample", 1 + k, CDR_LE + struct.pack("<i4xd", 7 + k, -0.25 * k))
    paths = [plain.close(), padded.close()]
    shutil.copy(paths[0], tmp_path / "again.mcap")

    def read(path: Path) -> list:
        return [msg for _, _, msg in bag_reader.iter_bag_messages(path, ["/x"])]

    first, second, again = read(paths[0]), read(paths[1]), read(tmp_path / "again.mcap")
    assert [m.data for m in first] == [0.5, 1.5, 2.5] == [m.data for m in again]
    assert [(m.count, m.data) for m in second] == [(7, -0.0), (8, -0.25), (9, -0.5)]
    assert type(again[0]) is type(first[0]) and type(second[0]) is not type(first[0])  # the same decoder, another


def test_the_read_after_the_checks_parses_each_chunk_once_and_a_rewritten_bag_again(capsys, tmp_path, monkeypatch):
    """``RecordScan`` keeps the chunk it parsed last: ``replay`` checks the fields (its first chunk)
    and then reads every chunk, each parsed once; the same path rewritten with other samples is
    parsed again and gives its own model."""
    from hammer_ros.io import bag_index

    parsed = []
    parse = bag_index.chunk_records
    monkeypatch.setattr(bag_index, "chunk_records", lambda chunk: parsed.append(chunk) or parse(chunk))
    path = g1_bag(tmp_path / "g1.mcap", chunk_size=16_384)
    chunks = sum(1 for group in bag_index.RecordScan(path).groups() if len(group) > 1)
    parsed.clear()
    doc, _ = replay_json(capsys, path)
    assert chunks > 3 and len(parsed) == chunks and pole_error(doc) < 0.02
    other = g1_bag(tmp_path / "other.mcap", n=4000, chunk_size=16_384)
    shutil.copy(other, path)  # another bag under the same name
    parsed.clear()
    again, _ = replay_json(capsys, path)
    assert len(parsed) == sum(1 for group in bag_index.RecordScan(other).groups() if len(group) > 1)
    assert again["samples"] < doc["samples"]


def test_the_scan_steps_over_message_indexes_and_reads_every_message(tmp_path):
    """``RecordScan`` skips the message index records unparsed (mcap's reader yields one per
    channel and chunk) and still gives every message, byte for byte, as mcap's own reader does."""
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader

    from hammer_ros.io import bag_index

    path = g1_bag(tmp_path / "g1.mcap", n=2000, chunk_size=16_384)
    with open(path, "rb") as f:
        plain = {type(r).__name__ for r in StreamReader(f).records}
        f.seek(0)
        expected = sorted((m.channel_id, m.log_time, bytes(m.data)) for _, _, m in make_reader(f).iter_messages())
    records = [r for group in bag_index.RecordScan(path).groups() for r in group]
    kinds = {type(r).__name__ for r in records}
    assert "MessageIndex" in plain and "MessageIndex" not in kinds and {"Header", "Schema", "Channel"} <= kinds
    messages = [r for r in records if type(r).__name__ == "Message"]
    assert sorted((r.channel_id, r.log_time, bytes(r.data)) for r in messages) == expected


def test_a_hostile_bag_cannot_exhaust_memory(capsys, tmp_path, monkeypatch):
    """One 10^6-sample message per topic (read and aligned in full), a 24 MB message (over the
    16 MiB limit: skipped unread), and a message claiming 10^8 elements (does not decode)."""
    n = 1_000_000
    rng = np.random.default_rng(3)
    v = rng.normal(0, 0.3, n)
    y = simulate_hammerstein(v, lambda x: x + 4 * x**3, G1)
    bag = Bag(tmp_path / "hostile.mcap", chunk_size=1 << 20)
    kind = "std_msgs/msg/Float64MultiArray"
    end = 1.0 + (n - 1) / 100.0
    bag.write("/cmd", kind, end, multiarray_cdr(v))
    bag.write("/y", kind, end, multiarray_cdr(y))
    bag.write("/y", kind, end + 1, multiarray_cdr(np.zeros(3_000_000)))
    bag.write("/cmd", kind, end + 2, multiarray_cdr(np.zeros(1), claimed=100_000_000))
    path = bag.close()
    spec = ["--input", "/cmd:data[:]", "--output", "/y:data[:]", "--sample-rate", "100", "--json"]
    code, out, err = run(capsys, "replay", path, *spec)
    assert code == 0, err
    assert json.loads(out)["samples"] == n and pole_error(json.loads(out)) < 0.02
    oversized, undecodable = sorted(warnings(err))
    assert oversized == f"hammer-ros: warning: {path}: 1 message(s) over 16 MiB skipped (/y: 24,000,020 bytes)"
    assert undecodable.startswith(f"hammer-ros: warning: {path}: 1 message(s) that do not decode skipped (/cmd: ")
    small = Bag(tmp_path / "long.mcap", chunk_size=1 << 20)
    for k in range(1, 4):
        small.write("/cmd", kind, k * 1000.0, multiarray_cdr(v[:100_000]))
        small.write("/y", kind, k * 1000.0, multiarray_cdr(y[:100_000]))
    monkeypatch.setattr(bag_reader, "MAX_RECORD_SAMPLES", 150_000)  # identify holds the record: bounded
    rate = write_csv(tmp_path, "hammer_ros:\n  ros__parameters:\n    sample_rate: 100.0\n", "rate.yaml")
    assert_usage_error(capsys, ["identify", small.close(), "--input", "/cmd:data[:]", "--output", "/y:data[:]",
                                "--config", rate], "more than 150,000 aligned samples", "hammer-ros replay")


# ------------------------------------------------------------------------------------ CSV / NPZ
def write_csv(tmp_path, text: str, name: str = "data.csv", encoding: str = "utf-8") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding=encoding)
    return path


def good_rows(n: int = 600) -> str:
    rng = np.random.default_rng(0)
    u = rng.normal(size=n)
    y = np.convolve(u + 0.5 * u**3, [0.0, 1.0, 0.5])[:n]
    return "".join(f"{a:.6f},{b:.6f},label{k % 3}\n" for k, (a, b) in enumerate(zip(u, y)))


@pytest.mark.parametrize("text, needle", [
    ("", "data.csv: empty file"),
    ("u,y\n", "data.csv: header only, no data rows"),
    ("a,b\n1,2\n3,4\n", "data.csv: no column 'u' (set --input; columns are a, b)"),
    ("u,y\n1,2\n3,abc\n", "data.csv:3: column 'y': not a number: 'abc'"),
    ("u,y\n1,2\n,3\n", "data.csv:3: column 'u': empty cell"),
    ("u,y\n1,2\n3,4,5\n", "data.csv:3: expected 2 columns, found 3"),
    ("u,y\n1,2\n1e200,4\n", "data.csv: column 'u' has a non-finite or out-of-range value (1e+200) at sample 1"),
    ("u,y\n1,nan\n3,4\n", "data.csv: column 'y' has a non-finite or out-of-range value (nan) at sample 0"),
])
def test_bad_csv_files_are_one_line_errors(capsys, tmp_path, text, needle):
    assert_usage_error(capsys, ["identify", write_csv(tmp_path, text), "--order", "2"], needle)


@pytest.mark.parametrize("header, separator, encoding", [
    ("u,y,label", ",", "utf-8"),  # an extra text column is fine: only u and y must be numbers
    ("u,y,label", ",", "utf-8-sig"),  # a byte-order mark (Excel)
    ("u;y;label", ";", "utf-8"),  # semicolons (a European locale)
])
def test_csv_variants_that_are_fine(capsys, tmp_path, header, separator, encoding):
    """Each variant gives the model of the plain two-column file."""
    plain = write_csv(tmp_path, "u,y\n" + "".join(r.rsplit(",", 1)[0] + "\n" for r in good_rows().splitlines()),
                      "plain.csv")
    path = write_csv(tmp_path, header + "\n" + good_rows().replace(",", separator), encoding=encoding)
    reference = run(capsys, "identify", plain, "--order", "2", "--json")[1]
    code, out, err = run(capsys, "identify", path, "--order", "2", "--json")
    assert code == 0 and err == ""
    assert json.loads(out) == json.loads(reference)


def test_bad_npz_files_are_one_line_errors_and_never_unpickled(capsys, tmp_path):
    np.savez(tmp_path / "objects.npz", u=np.array([{"a": 1}] * 3, dtype=object), y=np.zeros(3))
    assert_usage_error(capsys, ["identify", tmp_path / "objects.npz"], "array 'u' holds Python objects")
    np.savez(tmp_path / "matrix.npz", u=np.zeros((100, 2)), y=np.zeros(100))
    assert_usage_error(capsys, ["identify", tmp_path / "matrix.npz"], "array 'u' has shape (100, 2)")
    (tmp_path / "empty.npz").write_bytes(b"")
    assert_usage_error(capsys, ["identify", tmp_path / "empty.npz"], "empty.npz: not a readable .npz file")
    (tmp_path / "text.npz").write_text("u,y\n")
    assert_usage_error(capsys, ["identify", tmp_path / "text.npz"], "text.npz: not a readable .npz file")


# ------------------------------------------------------------------------------------ configs
TOPICS = ("    excitation_topic: /cmd\n    excitation_field: data\n    response_topic: /response\n"
          "    response_field: \"data[:]\"\n")


@pytest.mark.parametrize("body, needle", [
    ("hammer_ros:\n  ros__parameters:\n    window: [1,\n", "bad.yaml: not valid YAML at line 4, column 1"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    window: abc\n", "window: must be an integer (got 'abc')"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    partition: 5\n", "partition: must be a list of breakpoints"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    solve_rate: fast\n", "solve_rate: must be > 0 (got 'fast')"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    windw: 100\n", "unknown parameter 'windw'"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    window: 100000000\n", "window: must be <= 1000000 samples"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    tau_max: 5000\n", "tau_max: must be in 1..2000"),
    ("hammer_ros:\n  ros__parameters:\n" + TOPICS + "    min_excitation: 3\n", "min_excitation: must be in [0, 1]"),
    ("", "bad.yaml: expected a ROS 2 params file"),
])
def test_bad_configs_are_one_line_errors_naming_file_and_key(capsys, tmp_path, body, needle):
    config = write_csv(tmp_path, body, "bad.yaml")
    assert_usage_error(capsys, ["replay", FLOAT64_BAG, "--config", config], "bad.yaml", needle)


def test_yaml_is_loaded_safely(capsys, tmp_path):
    marker = tmp_path / "pwned"
    config = write_csv(tmp_path, f'hammer_ros: !!python/object/apply:os.system ["touch {marker}"]\n', "evil.yaml")
    assert_usage_error(capsys, ["replay", FLOAT64_BAG, "--config", config], "evil.yaml: not valid YAML",
                       "could not determine a constructor")
    assert not marker.exists()
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    assert_usage_error(capsys, ["replay", FLOAT64_BAG, "--config", binary], "binary.yaml: not a text (UTF-8) file")


# ------------------------------------------------------------------------------------ options
@pytest.mark.parametrize("argv, needle", [
    (["identify", "{csv}", "--method", "cls-arx", "--mu", "5"], "--mu: not used by --method cls-arx"),
    (["identify", "{csv}", "--method", "bf-hammerstein", "--partition", "-0.5,0.5"],
     "--partition: not used by --method bf-hammerstein"),
    (["identify", "{csv}", "--method", "nls-arx", "--tau-max", "40"], "--tau-max: not used by --method nls-arx"),
    (["identify", "{csv}", "--order", "2", "--delay", "3"], "--delay: relative degree 3 exceeds --order 2"),
    (["identify", "{csv}", "--config", str(FLOAT64_CONFIG)], "--config: a msg_config maps bag topics"),
    (["identify", "{csv}", "--input", "/cmd:data"], "--input: '/cmd:data' is a bag topic:field"),
    (["identify", "{csv}", "--method", "plls-hammerstein", "--order", "2", "--partition", "5,6,7"],
     "data.csv: input partition interval (5, 6] holds no sample"),
    (["replay", str(FLOAT64_BAG), "--config", str(FLOAT64_CONFIG), "--harmonic", "{csv}"],
     "--harmonic: not used by --method cls-markov"),
    (["replay", str(FLOAT64_BAG), "--config", str(FLOAT64_CONFIG), "--window", "20"], "--window: must be >="),
    (["replay", str(FLOAT64_BAG), "--config", str(FLOAT64_CONFIG), "--rate", "0"], "--rate: must be > 0"),
    (["demo", "--duration", "-5"], "--duration: must be > 0 seconds"),
    (["replay", str(FLOAT64_BAG), "--config", str(FLOAT64_CONFIG), "--method", "plls-hammerstein", "--partition",
      "5,6,7"], "no model identified (plls-hammerstein: input partition interval (5, 6] holds no sample"),
])
def test_contradictory_options_are_one_line_errors(capsys, tmp_path, argv, needle):
    csv = write_csv(tmp_path, "u,y,label\n" + good_rows())
    assert_usage_error(capsys, [a.replace("{csv}", str(csv)) for a in argv], needle)


def test_out_never_overwrites_the_bag_being_replayed(capsys, tmp_path):
    bag = tmp_path / "copy.mcap"
    shutil.copy(FLOAT64_BAG, bag)
    before = bag.read_bytes()
    assert_usage_error(capsys, ["replay", bag, "--config", FLOAT64_CONFIG, "--out", tmp_path / "." / "copy.mcap"],
                       "--out:", "is the bag being replayed")
    assert bag.read_bytes() == before


def test_console_script_reports_a_damaged_bag_and_a_bad_config_without_traceback(tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(g1_bag(tmp_path / "whole.mcap").read_bytes()[:150_000])
    proc = subprocess.run([HAMMER_ROS, "identify", str(cut), "--input", "/cmd:data", "--output", "/y:data", "--json"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and json.loads(proc.stdout)["method"] == "cls-markov"
    assert proc.stderr.startswith(f"hammer-ros: warning: {cut}: truncated") and "Traceback" not in proc.stderr
    bad = write_csv(tmp_path, "hammer_ros: {ros__parameters: {window: [1, 2}\n", "bad.yaml")
    proc = subprocess.run([HAMMER_ROS, "replay", str(cut), "--config", str(bad)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and proc.stdout == "" and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "bad.yaml: not valid YAML at line 1" in proc.stderr


def test_nothing_from_a_file_or_topic_is_ever_executed():
    """No pickle, eval, exec or unsafe YAML anywhere in the package; every np.load refuses pickles."""
    forbidden = re.compile(r"\bpickle\b|\beval\(|\bexec\(|yaml\.(unsafe_)?load\(|yaml\.Loader|marshal\.")
    offenders = []
    for source in (REPO / "hammer_ros").rglob("*.py"):
        for number, line in enumerate(source.read_text().splitlines(), start=1):
            code = line.split("#", 1)[0]
            if forbidden.search(code) or ("np.load(" in code and "allow_pickle=False" not in code):
                offenders.append(f"{source.relative_to(REPO)}:{number}: {line.strip()}")
    assert offenders == []
