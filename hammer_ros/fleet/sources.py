"""Which bags a fleet run replays, their labels and groups.

BAGS are .mcap files, rosbag2 directories (a directory with a metadata.yaml) or directories
searched recursively for both; a manifest is a CSV file with a ``path`` column (relative paths
are relative to the manifest) and any label columns (robot, joint, date, ...). Groups: the
manifest's labels other than the time ones (``TIME_LABELS``) joined by "/", e.g.
``robot_07/joint3``; without a manifest, the bag's directory relative to the fleet's common root.
Every user mistake is a UsageError naming the file, line or column.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import UsageError

TIME_LABELS = ("date", "day", "time", "timestamp", "start", "start_time")


@dataclass(frozen=True)
class BagSource:
    """One bag of the fleet: its path, group and labels; ``name`` is its results MCAP's path
    relative to the results directory."""

    path: str
    group: str
    labels: tuple[tuple[str, str], ...] = ()
    name: str = ""

    @property
    def label_dict(self) -> dict[str, str]:
        return dict(self.labels)


def is_rosbag2_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def discover(paths: Sequence[str]) -> list[Path]:
    """The bags named by ``paths`` (files, rosbag2 directories, directories searched
    recursively), absolute, sorted, without duplicates."""
    found: list[Path] = []
    for text in paths:
        path = Path(text)
        if not path.exists():
            raise UsageError(f"{text}: no such file or directory")
        if path.is_file():
            if path.suffix.lower() != ".mcap":
                raise UsageError(f"{text}: not a bag (expected a .mcap file or a directory)")
            found.append(path)
        elif is_rosbag2_dir(path):
            found.append(path)
        else:
            before = len(found)
            for root, dirs, files in os.walk(path):
                here = Path(root)
                bag_dirs = [d for d in dirs if is_rosbag2_dir(here / d)]
                found += [here / d for d in bag_dirs]
                dirs[:] = sorted(d for d in dirs if d not in bag_dirs and not d.startswith("."))
                found += [here / f for f in files if f.lower().endswith(".mcap") and not f.startswith(".")]
            if len(found) == before:
                raise UsageError(f"{text}: no bags in this directory (.mcap files or rosbag2 directories)")
    unique = sorted({p.resolve() for p in found})
    return unique


def _name(bag: Path, root: Path) -> str:
    relative = bag.relative_to(root) if bag.is_relative_to(root) else Path(bag.name)
    return (relative.with_suffix(".mcap") if bag.suffix.lower() == ".mcap" else Path(f"{relative}.mcap")).as_posix()


def sources_from_paths(paths: Sequence[str]) -> list[BagSource]:
    """BAGS grouped by their directory (relative to the common root of the bags' directories)."""
    bags = discover(paths)
    parents = [b.parent for b in bags]
    root = Path(os.path.commonpath(parents)) if parents else Path(".")
    if len(set(parents)) == 1:
        root = root.parent
    sources = []
    for bag in bags:
        group = bag.parent.relative_to(root).as_posix() if bag.parent != root else bag.parent.name
        sources.append(BagSource(str(bag), group or bag.parent.name, (), _name(bag, root)))
    return sources


def read_manifest(manifest: str) -> list[BagSource]:
    """The bags of a CSV manifest: a ``path`` column and label columns."""
    path = Path(manifest)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise UsageError(f"--manifest: {manifest}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"--manifest: {manifest}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        rows = list(csv.reader(text.splitlines()))
    except csv.Error as exc:
        raise UsageError(f"--manifest: {manifest}: not a CSV file ({exc})") from None
    rows = [r for r in rows if any(cell.strip() for cell in r)]
    if not rows:
        raise UsageError(f"--manifest: {manifest}: empty (expected a header with a 'path' column)")
    header = [h.strip() for h in rows[0]]
    if "path" not in header:
        raise UsageError(f"--manifest: {manifest}: no 'path' column (columns: {', '.join(header) or 'none'})")
    if len(set(header)) != len(header) or "" in header:
        raise UsageError(f"--manifest: {manifest}: empty or repeated column names in {', '.join(header)}")
    if len(rows) == 1:
        raise UsageError(f"--manifest: {manifest}: no bags (only a header)")
    labels = [h for h in header if h != "path"]
    group_labels = [h for h in labels if h.lower() not in TIME_LABELS]
    base = path.parent
    entries: list[tuple[Path, dict[str, str]]] = []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise UsageError(f"--manifest: {manifest}:{line}: {len(row)} columns, the header has {len(header)}")
        values = dict(zip(header, (cell.strip() for cell in row)))
        if not values["path"]:
            raise UsageError(f"--manifest: {manifest}:{line}: empty path")
        bag = Path(values["path"])
        bag = bag if bag.is_absolute() else base / bag
        if not (bag.is_file() and bag.suffix.lower() == ".mcap") and not bag.is_dir():
            raise UsageError(f"--manifest: {manifest}:{line}: no such bag: {values['path']}")
        entries.append((bag.resolve(), {k: values[k] for k in labels}))
    seen: set[Path] = set()
    sources = []
    root = Path(os.path.commonpath([b.parent for b, _ in entries]))
    for bag, values in entries:
        if bag in seen:
            continue
        seen.add(bag)
        group = "/".join(values[k] for k in group_labels if values[k]) or bag.parent.name
        sources.append(BagSource(str(bag), group, tuple(values.items()), _name(bag, root)))
    return sources
