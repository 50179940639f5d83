"""Loading input/output records from CSV and NPZ files (bags: see ``bag_io``)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import UsageError


@dataclass(frozen=True, eq=False)
class Record:
    """An input/output record: excitation v, response y, optional time stamps t (s)."""

    v: np.ndarray
    y: np.ndarray
    t: np.ndarray | None = None
    source: str = ""

    def __len__(self) -> int:
        return self.v.size

    def split(self, fraction: float) -> tuple[Record, Record]:
        """(first fraction, rest), e.g. estimation and validation parts."""
        cut = int(round(fraction * len(self)))
        part = slice(0, cut), slice(cut, None)
        return tuple(
            Record(self.v[s], self.y[s], None if self.t is None else self.t[s], self.source) for s in part
        )


def load_columns(path: str | Path) -> dict[str, np.ndarray]:
    """All numeric columns of a CSV (header row required) or arrays of an NPZ file."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such file")
    if path.is_dir():
        raise UsageError(f"{path}: is a directory, expected a .csv or .npz file (or a bag with --input/--output)")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as npz:
                return {k: np.asarray(npz[k], dtype=float).ravel() for k in npz.files}
        except (ValueError, OSError, EOFError) as exc:
            raise UsageError(f"{path}: not a readable .npz file ({exc})") from None
    if suffix in (".csv", ".txt", ""):
        return _read_csv(path)
    raise UsageError(f"{path}: unsupported file type {suffix!r} (expected .csv, .npz, .mcap or a rosbag2 directory)")


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except UnicodeDecodeError:
        raise UsageError(f"{path}: not a text CSV file") from None
    rows = [r for r in rows if r and any(cell.strip() for cell in r)]
    if not rows:
        raise UsageError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    if len(rows) < 2:
        raise UsageError(f"{path}: header only, no data rows")
    columns: dict[str, list[float]] = {h: [] for h in header}
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise UsageError(f"{path}:{line_no}: expected {len(header)} columns, found {len(row)}")
        for name, cell in zip(header, row):
            try:
                columns[name].append(float(cell))
            except ValueError:
                raise UsageError(f"{path}:{line_no}: column {name!r}: not a number: {cell.strip()!r}") from None
    return {k: np.asarray(v) for k, v in columns.items()}


def load_record(path: str | Path, input_name: str = "u", output_name: str = "y", time_name: str = "t") -> Record:
    """The (v, y[, t]) record in a CSV/NPZ file; a missing column is a UsageError naming it."""
    columns = load_columns(path)
    for option, name in (("--input", input_name), ("--output", output_name)):
        if name not in columns:
            raise UsageError(
                f"{path}: no column {name!r} (set {option}; columns are {', '.join(columns) or 'none'})"
            )
    v, y = columns[input_name], columns[output_name]
    if v.size != y.size:
        raise UsageError(f"{path}: columns {input_name!r} and {output_name!r} differ in length")
    if v.size == 0:
        raise UsageError(f"{path}: no samples")
    for name, x in ((input_name, v), (output_name, y)):
        if not np.all(np.isfinite(x)):
            bad = int(np.flatnonzero(~np.isfinite(x))[0])
            raise UsageError(f"{path}: column {name!r} has a non-finite value at sample {bad}")
    t = columns.get(time_name)
    return Record(v, y, t, str(path))
