"""rosbag2 directories: which files a bag has, in which storage, and how they are compressed.

A bag is a ``.mcap`` file (also ``.db3``, ``.mcap.zstd``, ``.db3.zstd``) or a rosbag2 directory
whose ``metadata.yaml`` (any version: Humble writes 5, Iron 6-8, Jazzy 9) lists its files in
``relative_file_paths`` (a split bag: several; the reader merges their messages by time). A
file's storage is its suffix: ``.db3`` is rosbag2's SQLite storage (``rosbag2_sqlite``),
anything else MCAP. Compression (rosbag2's
``compression_format: zstd``): FILE mode compresses each file whole (``x.db3.zstd``: read
through a decompressed copy in a temporary directory, removed at exit), MESSAGE mode each
message's serialized bytes (``decompress_message``).
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import yaml

from ..errors import UsageError

STORAGES = ("mcap", "sqlite3")
COMPRESSION_MODES = ("", "NONE", "FILE", "MESSAGE")


@dataclass(frozen=True)
class BagLayout:
    """A bag's files in reading order; ``message_compressed``: each message's data is zstd;
    ``note``: a warning for the user (how the files were found without a usable metadata.yaml)."""

    files: tuple[Path, ...]
    message_compressed: bool = False
    note: str = ""


def storage_of(file: Path) -> str:
    """'sqlite3' for ``x.db3`` and ``x.db3.zstd``, else 'mcap'."""
    name = file.name.lower().removesuffix(".zstd")
    return "sqlite3" if name.endswith(".db3") else "mcap"


def _is_bag_file(file: Path) -> bool:
    return file.name.lower().removesuffix(".zstd").endswith((".mcap", ".db3"))


def read_layout(path: str | Path) -> BagLayout:
    """The files of a bag: the file itself, or those listed in a rosbag2 metadata.yaml (without
    a usable metadata.yaml, e.g. a recording that was killed: the directory's .mcap/.db3 files
    in name order, with a note). A missing file, an unknown storage or compression is a
    UsageError naming the bag."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such bag (expected a .mcap file or a rosbag2 directory)")
    if path.is_file():
        if not _is_bag_file(path):
            raise UsageError(f"{path}: not a .mcap file (nor a rosbag2 .db3 file)")
        return BagLayout((path,))
    meta = path / "metadata.yaml"
    found = tuple(sorted(p for p in path.iterdir() if p.is_file() and _is_bag_file(p)))
    if not meta.is_file():
        if not found:
            raise UsageError(f"{path}: not a rosbag2 directory (no metadata.yaml and no .mcap or .db3 files)")
        return BagLayout(found, note=f"{path}: no metadata.yaml; reading its {len(found)} bag file(s) in name order")
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        storage = info.get("storage_identifier") or "mcap"
        files = tuple(path / f for f in info.get("relative_file_paths") or ())
        mode = str(info.get("compression_mode") or "").upper()
        compression = str(info.get("compression_format") or "").lower()
    except (yaml.YAMLError, KeyError, TypeError, AttributeError, UnicodeDecodeError):
        if not found:
            raise UsageError(f"{meta}: not a rosbag2 metadata file (and no .mcap or .db3 files beside it)") from None
        return BagLayout(found, note=f"{meta}: not a rosbag2 metadata file; reading the {len(found)} bag file(s) "
                                     "in name order")
    if storage not in STORAGES:
        raise UsageError(f"{path}: storage {storage!r} is not supported (mcap and sqlite3 are)")
    if mode not in COMPRESSION_MODES:
        raise UsageError(f"{meta}: compression_mode {mode!r} is not supported (FILE and MESSAGE are)")
    if mode in ("FILE", "MESSAGE") and compression != "zstd":
        raise UsageError(f"{meta}: compression_format {compression!r} is not supported (zstd is)")
    files = files or found
    missing = [f for f in files if not f.is_file()]
    if not files or missing:
        raise UsageError(f"{path}: bag file {missing[0] if missing else '*.mcap'} is missing")
    return BagLayout(files, mode == "MESSAGE")


_decompressed: dict[tuple[str, int, int], Path] = {}


def readable_file(file: Path) -> Path:
    """The file to open for ``file``: itself, or for ``x.zstd`` its decompressed copy (made once
    per process). A file that is not zstd is a UsageError naming it."""
    if file.suffix.lower() != ".zstd":
        return file
    import zstandard

    stat = file.stat()
    key = (str(file.resolve()), stat.st_mtime_ns, stat.st_size)
    copy = _decompressed.get(key)
    if copy is None or not copy.is_file():
        copy = _scratch_dir() / f"{len(_decompressed)}_{file.stem}"
        try:
            with open(file, "rb") as source, open(copy, "wb") as target:
                zstandard.ZstdDecompressor().copy_stream(source, target)
        except zstandard.ZstdError as exc:
            copy.unlink(missing_ok=True)
            raise UsageError(f"{file}: not a zstd-compressed file ({exc})") from None
        _decompressed[key] = copy
    return copy


_scratch: list[Path] = []


def _scratch_dir() -> Path:
    """A temporary directory for decompressed files, removed when the process exits."""
    if not _scratch:
        _scratch.append(Path(tempfile.mkdtemp(prefix="hammer_ros_bag_")))
        atexit.register(shutil.rmtree, _scratch[0], True)
    return _scratch[0]


def decompress_message(data: bytes, limit: int) -> bytes:
    """A message's serialized bytes from its zstd frame (MESSAGE mode); ValueError when they
    are not zstd or over ``limit`` bytes."""
    import zstandard

    try:
        size = zstandard.frame_content_size(data)
        if size > limit:
            raise ValueError(f"zstd frame of {size:,} bytes, over the {limit:,} byte limit")
        return zstandard.decompress(data, max_output_size=limit)
    except zstandard.ZstdError as exc:
        raise ValueError(f"not a zstd frame ({exc})") from None
