"""Loading input/output records from CSV and NPZ files (bags: see ``bag_io``)."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UsageError
from ..identification.runs import Runs, concatenate
from ..identification.trust import ModelWarning
from .resample import uniform_grid

RUN_COLUMN = "run"  # CSV/NPZ column of run labels: consecutive rows with one label form a run


@dataclass(frozen=True, eq=False)
class Record:
    """An input/output record: excitation v, response y, optional time stamps t (s), the
    external reference r of a closed loop (``--reference``, None when not given), its runs
    (separate experiments laid end to end; None: one continuous run) and what loading it had to
    say (``warnings``, e.g. ``irregular_sampling``: ``io.resample``)."""

    v: np.ndarray
    y: np.ndarray
    t: np.ndarray | None = None
    source: str = ""
    r: np.ndarray | None = None
    runs: Runs | None = None
    warnings: tuple[ModelWarning, ...] = ()

    def __len__(self) -> int:
        return self.v.size

    @property
    def u(self) -> np.ndarray:
        """The input (the excitation v; the Python API's name)."""
        return self.v

    @property
    def run_count(self) -> int:
        return 1 if self.runs is None else self.runs.count

    def split(self, fraction: float) -> tuple[Record, Record]:
        """(first fraction, rest), e.g. estimation and validation parts."""
        cut = int(round(fraction * len(self)))
        part = slice(0, cut), slice(cut, None)
        return tuple(
            Record(self.v[s], self.y[s], None if self.t is None else self.t[s], self.source,
                   None if self.r is None else self.r[s]) for s in part
        )


MAX_RECORD_SAMPLES = 10_000_000  # samples of a CSV/NPZ record (also bag_reader.MAX_RECORD_SAMPLES)
MAX_ABS_SAMPLE = 1e100  # larger magnitudes are data errors (their cubes overflow); as in the streaming engine


def load_columns(path: str | Path, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The numeric columns of a CSV (header row required) or arrays of an NPZ file: all of
    them, or only ``names`` (then the other columns may hold anything, e.g. labels)."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such file")
    if path.is_dir():
        raise UsageError(f"{path}: is a directory, expected a .csv or .npz file (or a bag with --input/--output)")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _read_npz(path, names)
    if suffix in (".csv", ".txt", ""):
        return _read_csv(path, names)
    raise UsageError(f"{path}: unsupported file type {suffix!r} (expected .csv, .npz, .mcap or a rosbag2 directory)")


def _read_npz(path: Path, names: tuple[str, ...] | None) -> dict[str, np.ndarray]:
    """Arrays of an NPZ (never unpickled); each array's header is checked before it is loaded,
    so a hostile file cannot make us allocate more than MAX_RECORD_SAMPLES values."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as npz, zipfile.ZipFile(path) as archive:
            out = {}
            for key in npz.files if names is None else [k for k in names if k in npz.files]:
                with archive.open(f"{key}.npy") as member:
                    version = np.lib.format.read_magic(member)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(member)
                if dtype.hasobject:
                    raise UsageError(f"{path}: array {key!r} holds Python objects (not loaded: only numbers are)")
                if sum(d > 1 for d in shape) > 1:
                    raise UsageError(f"{path}: array {key!r} has shape {shape}, expected a 1-D array")
                if math.prod(shape) > MAX_RECORD_SAMPLES:
                    raise UsageError(f"{path}: array {key!r} has {math.prod(shape):,} values "
                                     f"(at most {MAX_RECORD_SAMPLES:,})")
                out[key] = np.asarray(npz[key], dtype=float).ravel()
            return out
    except UsageError:
        raise
    except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise UsageError(f"{path}: not a readable .npz file ({exc})") from None


def _read_csv(path: Path, names: tuple[str, ...] | None) -> dict[str, np.ndarray]:
    """Streamed: numbers go straight into arrays, at most MAX_RECORD_SAMPLES rows. Accepts a
    UTF-8 byte-order mark and ',', ';' or tab as the delimiter (from the header line)."""
    from array import array

    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = (r for r in csv.reader(fh, delimiter=_delimiter(path)) if r and any(c.strip() for c in r))
            first = next(rows, None)
            if first is None:
                raise UsageError(f"{path}: empty file")
            header = [h.strip() for h in first]
            wanted = [i for i, h in enumerate(header) if names is None or h in names]
            columns = {header[i]: array("d") for i in wanted}
            line_no = 1
            for line_no, row in enumerate(rows, start=2):
                if len(row) != len(header):
                    raise UsageError(f"{path}:{line_no}: expected {len(header)} columns, found {len(row)}")
                if line_no - 1 > MAX_RECORD_SAMPLES:
                    raise UsageError(f"{path}: more than {MAX_RECORD_SAMPLES:,} rows")
                for i in wanted:
                    cell = row[i].strip()
                    try:
                        columns[header[i]].append(float(cell))
                    except ValueError:
                        what = "empty cell" if not cell else f"not a number: {cell!r}"
                        raise UsageError(f"{path}:{line_no}: column {header[i]!r}: {what}") from None
    except UnicodeDecodeError:
        raise UsageError(f"{path}: not a text CSV file") from None
    except csv.Error as exc:
        raise UsageError(f"{path}: not a CSV file ({exc})") from None
    if line_no == 1:
        raise UsageError(f"{path}: header only, no data rows")
    return {k: np.frombuffer(v, dtype=float) if len(v) else np.empty(0) for k, v in columns.items()}


def _delimiter(path: Path) -> str:
    with path.open(newline="", encoding="utf-8-sig", errors="replace") as fh:
        header = fh.readline()
    if "," in header:
        return ","
    return next((d for d in (";", "\t") if d in header), ",")


def load_record(path: str | Path, input_name: str = "u", output_name: str = "y", time_name: str = "t",
                reference_name: str | None = None) -> Record:
    """The (v, y[, t][, r]) record in a CSV/NPZ file; a missing column is a UsageError naming it."""
    named = (("--input", input_name), ("--output", output_name)) + (
        (("--reference", reference_name),) if reference_name else ())
    for option, name in named:
        if name.startswith("/") and ":" in name:
            raise UsageError(f"{option}: {name!r} is a bag topic:field, but {path} is a CSV/NPZ file (give a column)")
    columns = load_columns(path, (input_name, output_name, time_name, RUN_COLUMN)
                           + ((reference_name,) if reference_name else ()))
    for option, name in named:
        if name not in columns:
            available = load_columns_names(path)
            raise UsageError(
                f"{path}: no column {name!r} (set {option}; columns are {', '.join(available) or 'none'})"
            )
    v, y = columns[input_name], columns[output_name]
    r = columns[reference_name] if reference_name else None
    if v.size != y.size or (r is not None and r.size != v.size):
        raise UsageError(f"{path}: columns {input_name!r} and {output_name!r}"
                         f"{f' and {reference_name!r}' if r is not None else ''} differ in length")
    if v.size == 0:
        raise UsageError(f"{path}: no samples")
    for name, x in ((input_name, v), (output_name, y)) + (((reference_name, r),) if r is not None else ()):
        bad = ~np.isfinite(x) | (np.abs(x) > MAX_ABS_SAMPLE)
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise UsageError(f"{path}: column {name!r} has a non-finite or out-of-range value ({x[k]:g}) at sample {k} "
                             f"(|x| <= {MAX_ABS_SAMPLE:g})")
    t = columns.get(time_name)
    labels = columns.get(RUN_COLUMN)
    if labels is not None and (labels.size != v.size or not np.all(np.isfinite(labels))):
        raise UsageError(f"{path}: column {RUN_COLUMN!r} must hold a finite run label on every row")
    runs = None if labels is None else Runs.from_labels(labels)
    runs = None if runs is None or runs.count == 1 else runs
    if t is None:
        return Record(v, y, t, str(path), r, runs)
    if t.size != v.size or not np.all(np.isfinite(t)):
        raise UsageError(f"{path}: column {time_name!r} must hold a finite time on every row")
    even = uniform_grid(str(path), t, v, y, r, runs)  # uneven steps: resampled, with a warning
    return Record(even.v, even.y, even.t, str(path), even.r, even.runs, (even.warning,) if even.warning else ())


def concatenate_records(records: list[Record]) -> Record:
    """Several records (files, bags) as one record of runs: each record's runs, in order; nothing
    is fitted or simulated across a boundary (``identification.runs``)."""
    if len(records) == 1:
        return records[0]
    references = [rec.r for rec in records]
    if any(r is None for r in references) and any(r is not None for r in references):
        missing = next(rec.source for rec in records if rec.r is None)
        raise UsageError(f"{missing}: no reference signal, but another record has one")
    times = [rec.t for rec in records]
    return Record(
        np.concatenate([rec.v for rec in records]), np.concatenate([rec.y for rec in records]),
        None if any(t is None for t in times) else np.concatenate(times),
        ", ".join(rec.source for rec in records),
        None if references[0] is None else np.concatenate(references),
        concatenate([(rec.v, rec.runs) for rec in records]),
        tuple(w for rec in records for w in rec.warnings),
    )


def load_columns_names(path: str | Path) -> list[str]:
    """The column (CSV) or array (NPZ) names of a file, for error messages."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as npz:
            return list(npz.files)
    with path.open(newline="", encoding="utf-8-sig", errors="replace") as fh:
        return [h.strip() for h in next(csv.reader(fh, delimiter=_delimiter(path)), [])]
