"""Bags as rosbag2 records them: SQLite storage (``.db3``; Jazzy's metadata version 9 and
Humble's version 5 without stored message definitions), a bag split into several files, and
zstd compression of whole files (FILE) or of each message (MESSAGE), all written by ``rosbags``
(or from its output with ``sqlite3``) from the saturation + resonant plant of
``make_sample_bags``. Each gives ``identify`` the samples and the model of the same data in the
committed MCAP bag, poles near the truth; ``replay`` and ``fleet`` read a SQLite bag; broken
bags are exit 2 with one line naming the file, a damaged ``.db3`` gives the messages before the
damage."""

from __future__ import annotations

import contextlib
import io
import json
import re
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import yaml
from make_sample_bags import RESONANT, write_joint_state_bag

from hammer_ros.cli import main
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.io.bags import load_bag_record

REPO = Path(__file__).resolve().parents[1]
MCAP_BAG = REPO / "bags" / "joint_state_saturation"  # write_joint_state_bag's data in MCAP storage
SPECS = ["--input", "/cmd:data", "--output", "/joint_states:velocity[0]"]
IDENTIFY = ["--order", "2", "--delay", "1"]
FORMS = ("sqlite3", "humble", "split", "sqlite3_file", "sqlite3_message", "mcap_file", "mcap_message")


def cli_json(*argv: str) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(list(argv)) == 0
    return json.loads(out.getvalue())


def _metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())


def _write_metadata(bag: Path, doc: dict) -> None:
    (bag / "metadata.yaml").write_text(yaml.safe_dump(doc))


def make_humble(source: Path, bag: Path) -> None:
    """The SQLite bag as Humble records it: metadata version 5, a topics table without
    type_description_hash, no message_definitions (nor schema/metadata) tables."""
    shutil.copytree(source, bag)
    old = next(bag.glob("*.db3"))
    db3 = old.rename(bag / "humble_0.db3")
    with contextlib.closing(sqlite3.connect(db3)) as db:
        db.executescript("""
            CREATE TABLE topics_humble(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
                                       serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL);
            INSERT INTO topics_humble SELECT id, name, type, serialization_format, offered_qos_profiles FROM topics;
            DROP TABLE topics; ALTER TABLE topics_humble RENAME TO topics;
            DROP TABLE message_definitions; DROP TABLE schema; DROP TABLE metadata;""")
    doc = _metadata(bag)
    info = doc["rosbag2_bagfile_information"]
    info.update(version=5, relative_file_paths=[db3.name])
    info["files"][0]["path"] = db3.name
    for key in ("custom_data", "ros_distro"):
        info.pop(key)
    for topic in info["topics_with_message_count"]:
        topic["topic_metadata"].pop("type_description_hash")
        topic["topic_metadata"]["offered_qos_profiles"] = ""
    _write_metadata(bag, doc)


def make_split(source: Path, bag: Path) -> None:
    """The SQLite bag split at its middle into split_0.db3 and split_1.db3 (as ``ros2 bag record
    --max-bag-duration`` does), listed in that order."""
    bag.mkdir()
    db3 = next(source.glob("*.db3"))
    with contextlib.closing(sqlite3.connect(db3)) as db:
        middle = db.execute("SELECT (MIN(timestamp) + MAX(timestamp)) / 2 FROM messages").fetchone()[0]
    names = []
    for part, keep in enumerate(("timestamp < ?", "timestamp >= ?")):
        names.append(f"split_{part}.db3")
        shutil.copy(db3, bag / names[-1])
        with contextlib.closing(sqlite3.connect(bag / names[-1])) as db:
            db.execute(f"DELETE FROM messages WHERE NOT ({keep})", (middle,))
            db.commit()
            db.execute("VACUUM")
    doc = _metadata(source)
    info = doc["rosbag2_bagfile_information"]
    info["relative_file_paths"] = names
    info["files"] = [{**info["files"][0], "path": name} for name in names]
    _write_metadata(bag, doc)


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("formats")
    made = {}
    for storage in ("sqlite3", "mcap"):
        for compression in ("", "file", "message"):
            if storage == "mcap" and not compression:
                continue  # the committed MCAP bag
            name = f"{storage}_{compression}" if compression else storage
            made[name] = root / name
            write_joint_state_bag(made[name], storage, compression)
    made["humble"], made["split"] = root / "humble", root / "split"
    make_humble(made["sqlite3"], made["humble"])
    make_split(made["sqlite3"], made["split"])
    return made


@pytest.fixture(scope="module")
def mcap_model() -> dict:
    return cli_json("identify", str(MCAP_BAG), *SPECS, *IDENTIFY, "--json")


@pytest.mark.parametrize("form", FORMS)
def test_every_form_gives_the_samples_and_model_of_the_mcap_bag(bags, mcap_model, form):
    bag = bags[form]
    files = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["relative_file_paths"]
    assert files == {"humble": ["humble_0.db3"], "split": ["split_0.db3", "split_1.db3"]}.get(
        form, [f"{form}.{'mcap' if form.startswith('mcap') else 'db3'}{'.zstd' if form.endswith('file') else ''}"])
    expected, record = load_bag_record(MCAP_BAG, *SPECS[1::2]), load_bag_record(bag, *SPECS[1::2])
    assert record.v.size > 5000
    for name in ("t", "v", "y"):
        np.testing.assert_array_equal(getattr(record, name), getattr(expected, name))
    model = cli_json("identify", str(bag), *SPECS, *IDENTIFY, "--json")
    assert model == mcap_model
    poles = np.array([complex(*p) for p in model["poles"]])
    assert root_rss_error(RESONANT.poles, poles) < 0.02


def test_replay_reads_a_sqlite_bag(bags):
    argv = [*SPECS, *IDENTIFY, "--window", "2000", "--json"]
    replayed = cli_json("replay", str(bags["sqlite3"]), *argv)
    expected = cli_json("replay", str(MCAP_BAG), *argv)
    for doc in (replayed, expected):
        doc.pop("wall_s")
    assert replayed == expected and replayed["samples"] > 5000


def test_fleet_finds_and_reads_a_sqlite_bag(bags, tmp_path):
    """A directory with the SQLite bag and the MCAP bag: both found (as rosbag2 directories),
    both rows the same model."""
    fleet = tmp_path / "fleet"
    shutil.copytree(bags["sqlite3"], fleet / "sqlite3")
    shutil.copytree(MCAP_BAG, fleet / "mcap")
    doc = cli_json("fleet", str(fleet), *SPECS, *IDENTIFY, "--window", "2000", "--workers", "1",
                   "--out", str(tmp_path / "out"), "--json")
    assert (doc["bags"], doc["ok"], doc["failed"]) == (2, 2, 0)
    rows = {Path(r["path"]).name: r for r in doc["rows"]}
    assert set(rows) == {"sqlite3", "mcap"}
    assert rows["sqlite3"]["poles"] == rows["mcap"]["poles"]
    poles = np.array([complex(*p) for p in rows["sqlite3"]["poles"]])
    assert root_rss_error(RESONANT.poles, poles) < 0.02


def _corrupt_db3(bag: Path) -> str:
    db3 = next(bag.glob("*.db3"))
    db3.write_bytes(b"\0" * 100 + db3.read_bytes()[100:])
    return rf"{db3.name}: not a readable rosbag2 SQLite file \(DatabaseError: file is not a database\)"


def _missing_file(bag: Path) -> str:
    doc = _metadata(bag)
    doc["rosbag2_bagfile_information"]["relative_file_paths"].append("sqlite3_1.db3")
    _write_metadata(bag, doc)
    return r"bag file .*sqlite3_1\.db3 is missing"


def _unknown_compression(bag: Path) -> str:
    doc = _metadata(bag)
    doc["rosbag2_bagfile_information"].update(compression_mode="FILE", compression_format="lz4")
    _write_metadata(bag, doc)
    return r"metadata\.yaml: compression_format 'lz4' is not supported \(zstd is\)"


def _not_zstd(bag: Path) -> str:
    db3 = next(bag.glob("*.db3"))
    db3.rename(db3.with_name("sqlite3.db3.zstd"))
    doc = _metadata(bag)
    doc["rosbag2_bagfile_information"].update(relative_file_paths=["sqlite3.db3.zstd"], compression_mode="FILE",
                                              compression_format="zstd")
    _write_metadata(bag, doc)
    return r"sqlite3\.db3\.zstd: not a zstd-compressed file"


@pytest.mark.parametrize("damage", [_corrupt_db3, _missing_file, _unknown_compression, _not_zstd],
                         ids=lambda f: f.__name__.strip("_"))
def test_a_broken_bag_is_exit_2_naming_the_file(bags, tmp_path, capsys, damage):
    bag = tmp_path / "bag"
    shutil.copytree(bags["sqlite3"], bag)
    message = damage(bag)
    capsys.readouterr()
    assert main(["identify", str(bag), *SPECS, "--json"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert captured.out == "" and len(lines) == 1, captured.err
    assert str(bag) in lines[0]
    assert re.search(message, lines[0]), lines[0]


def test_a_damaged_db3_gives_the_messages_before_the_damage(bags, tmp_path, capsys):
    """A zeroed page in the middle of the messages: the samples before it (those of the MCAP
    bag), with a warning naming the file."""
    bag = tmp_path / "bag"
    shutil.copytree(bags["sqlite3"], bag)
    db3 = bag / "sqlite3.db3"
    data = bytearray(db3.read_bytes())
    page = len(data) * 6 // 10 // 4096 * 4096
    data[page : page + 4096] = bytes(4096)
    db3.write_bytes(bytes(data))
    record, expected = load_bag_record(bag, *SPECS[1::2]), load_bag_record(MCAP_BAG, *SPECS[1::2])
    assert f"{db3}: unreadable (DatabaseError: database disk image is malformed); read the " in capsys.readouterr().err
    kept = record.v.size
    assert 1000 < kept < expected.v.size - 1000
    np.testing.assert_array_equal(record.v, expected.v[:kept])
    np.testing.assert_array_equal(record.y, expected.y[:kept])
