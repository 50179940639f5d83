"""Fleet rows as a table: the model quantities of each row, ``fleet.parquet`` (pyarrow) and back.

One row per bag (per bag and channel with a config of several channels). Columns: ``path``,
``group``, ``channel`` (only with several channels), one column per label, ``start_time`` /
``end_time`` (UTC timestamps of the first and last sample), ``samples``, ``solves``, ``method``,
``order``, ``poles_re`` / ``poles_im`` / ``zeros_re`` / ``zeros_im`` (lists) with their sds
``poles_std_re`` / ``poles_std_im`` / ``zeros_std_re`` / ``zeros_std_im`` (lists), ``gain_std`` and
``time_constant_std`` (``quantity_sds``), the quantities of
``QUANTITIES``, ``nonlinearity_kind`` / ``nonlinearity_coefficients``, ``fit_percent``, ``rms``,
``diagnosis_cause`` / ``diagnosis_gain`` (with ``--diagnose``), ``out`` (results MCAP),
``error``, ``seconds`` (the task's time on its worker), and ``model_json`` / ``diagnosis_json`` /
``labels_json`` / ``warnings_json`` from which ``read_rows`` gives the rows back exactly (resume).
The run's settings are in the file's metadata (``hammer_ros_settings``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# key -> (label in tables and plots, unit)
QUANTITIES: dict[str, tuple[str, str]] = {
    "static_gain": ("static gain", ""),
    "time_constant": ("time constant", "s"),
    "small_signal_ratio": ("small-signal slope ratio", ""),
}
SETTINGS_KEY = b"hammer_ros_settings"
LARGE_SIGNAL_FRACTION = 0.5  # F's slope over the central half of the excited input range ...
SMALL_SIGNAL_FRACTION = 0.2  # ... and over its central fifth


def model_quantities(doc: dict, sample_rate: float = 0.0) -> dict[str, float]:
    """The quantities the change test follows, from a ``replay --json`` document:

    - ``static_gain``: G(1) times the chord slope of F over the central half of the excited input
      range (the identified points' range): the steady-state output per unit of command,
      invariant to how the method splits the scale between F and G, and not swayed by the few
      extreme samples that set the ends of the range;
    - ``time_constant``: -1 / ln|p| of the slowest pole p, in seconds (samples if the sample
      rate is unknown); nan for an unstable or oscillation-only model;
    - ``small_signal_ratio``: F's chord slope over the central fifth of the range divided by
      that over the central half (1: linear; < 1: a dead zone or a flat centre; > 1: saturation).
    """
    a, b = np.asarray(doc.get("a", []), float), np.asarray(doc.get("b", []), float)
    den = 1.0 + float(np.sum(a))
    dc = float(np.sum(b)) / den if abs(den) > 1e-12 else math.nan
    points = np.asarray(doc.get("nonlinearity", {}).get("points", []), float).reshape(-1, 2)
    large = small = math.nan
    if len(points) >= 2 and np.ptp(points[:, 0]) > 0:
        order = np.argsort(points[:, 0])
        x, f = points[order, 0], points[order, 1]
        centre, half = 0.5 * (x[0] + x[-1]), 0.5 * np.ptp(x)

        def chord(width: float) -> float:
            ends = np.interp([centre - width * half, centre + width * half], x, f)
            return float((ends[1] - ends[0]) / (2 * width * half))

        large, small = chord(LARGE_SIGNAL_FRACTION), chord(SMALL_SIGNAL_FRACTION)
    radii = [abs(complex(re, im)) for re, im in doc.get("poles", [])]
    slowest = max(radii, default=math.nan)
    tau = -1.0 / math.log(slowest) if 0 < slowest < 1 else math.nan
    if sample_rate > 0:
        tau /= sample_rate
    ratio = small / large if math.isfinite(large) and abs(large) > 1e-12 else math.nan
    return {"static_gain": dc * large, "time_constant": tau, "small_signal_ratio": ratio}


def quantity_sds(doc: dict, sample_rate: float = 0.0) -> dict[str, float]:
    """The sds of the quantities that the model's bounds give (``poles_std``, docs/methods.md):
    ``time_constant`` to first order, sd(tau) = sd(|p|) / (|p| ln^2 |p|), sd(|p|) =
    sqrt((re sd_re)^2 + (im sd_im)^2) / |p| of the slowest pole; nan without bounds."""
    poles, sds = doc.get("poles", []), doc.get("poles_std")
    if not poles or not sds or len(sds) != len(poles):
        return {"time_constant": math.nan}
    radius, (re, im), (sd_re, sd_im) = max((abs(complex(*p)), p, s) for p, s in zip(poles, sds, strict=True))
    if not 0 < radius < 1:
        return {"time_constant": math.nan}
    sd = math.hypot(re * sd_re, im * sd_im) / radius / (radius * math.log(radius) ** 2)
    return {"time_constant": sd / sample_rate if sample_rate > 0 else sd}


def label_keys(rows: Sequence[dict]) -> list[str]:
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row["labels"] if k not in keys]
    return keys


def has_channels(rows: Sequence[dict]) -> bool:
    """Whether the rows are per channel (a ``channel`` column)."""
    return any("channel" in row for row in rows)


def flat_rows(rows: Sequence[dict], sample_rate: float = 0.0) -> list[dict[str, Any]]:
    """The parquet columns of each row (see the module docstring)."""
    labels = label_keys(rows)
    channels = has_channels(rows)
    out = []
    for row in rows:
        doc, diag = row.get("model") or {}, row.get("diagnosis") or {}
        quantities = model_quantities(doc, sample_rate) if doc else dict.fromkeys(QUANTITIES, math.nan)
        poles, zeros = doc.get("poles", []), doc.get("zeros", [])
        poles_std, zeros_std = doc.get("poles_std", []), doc.get("zeros_std", [])
        flat: dict[str, Any] = {"path": row["path"], "group": row["group"]}
        if channels:
            flat["channel"] = row.get("channel")
        flat.update({f"label_{k}" if k in RESERVED else k: row["labels"].get(k) for k in labels})
        flat.update(
            start_time=_timestamp(row.get("start")), end_time=_timestamp(row.get("end")),
            samples=doc.get("samples"), solves=doc.get("solves"), method=doc.get("method"), order=doc.get("order"),
            poles_re=[p[0] for p in poles], poles_im=[p[1] for p in poles],
            zeros_re=[z[0] for z in zeros], zeros_im=[z[1] for z in zeros],
            poles_std_re=[s[0] for s in poles_std], poles_std_im=[s[1] for s in poles_std],
            zeros_std_re=[s[0] for s in zeros_std], zeros_std_im=[s[1] for s in zeros_std],
            gain_std=doc.get("gain_std"),
            time_constant_std=_finite(quantity_sds(doc, sample_rate)["time_constant"]) if doc else None,
            **{k: _finite(v) for k, v in quantities.items()},
            nonlinearity_kind=(doc.get("nonlinearity") or {}).get("kind"),
            nonlinearity_coefficients=(doc.get("nonlinearity") or {}).get("coefficients"),
            fit_percent=doc.get("fit_percent"), rms=doc.get("rms"),
            diagnosis_cause=diag.get("cause"), diagnosis_gain=diag.get("gain"),
            out=row.get("out"), error=row.get("error"), seconds=row.get("seconds"),
            model_json=json.dumps(row["model"], allow_nan=False) if row.get("model") else None,
            diagnosis_json=json.dumps(row["diagnosis"]) if row.get("diagnosis") else None,
            labels_json=json.dumps(row["labels"]), warnings_json=json.dumps(row.get("warnings") or []),
            start=row.get("start"), end=row.get("end"),
        )
        out.append(flat)
    return out


RESERVED = ("path", "group", "channel", "start_time", "end_time", "samples", "solves", "method", "order", "error",
            "out", "seconds", "rms", "start", "end", *QUANTITIES)


def _schema(labels: Sequence[str], channels: bool = False):
    import pyarrow as pa

    floats, texts = pa.float64(), pa.string()
    fields = [("path", texts), ("group", texts), *([("channel", texts)] if channels else [])]
    fields += [(f"label_{k}" if k in RESERVED else k, texts) for k in labels]
    fields += [("start_time", pa.timestamp("ns", tz="UTC")), ("end_time", pa.timestamp("ns", tz="UTC")),
               ("samples", pa.int64()), ("solves", pa.int64()), ("method", texts), ("order", pa.int64()),
               ("poles_re", pa.list_(floats)), ("poles_im", pa.list_(floats)),
               ("zeros_re", pa.list_(floats)), ("zeros_im", pa.list_(floats)),
               ("poles_std_re", pa.list_(floats)), ("poles_std_im", pa.list_(floats)),
               ("zeros_std_re", pa.list_(floats)), ("zeros_std_im", pa.list_(floats)),
               ("gain_std", floats), ("time_constant_std", floats)]
    fields += [(k, floats) for k in QUANTITIES]
    fields += [("nonlinearity_kind", texts), ("nonlinearity_coefficients", pa.list_(floats)),
               ("fit_percent", floats), ("rms", floats), ("diagnosis_cause", texts), ("diagnosis_gain", floats),
               ("out", texts), ("error", texts), ("seconds", floats), ("model_json", texts),
               ("diagnosis_json", texts), ("labels_json", texts), ("warnings_json", texts),
               ("start", floats), ("end", floats)]
    return pa.schema(fields)


def write_parquet(rows: Sequence[dict], path: str | Path, settings: str = "", sample_rate: float = 0.0) -> None:
    """``rows`` into ``path`` (written beside it and renamed: a reader, or a Ctrl-C, never sees
    half a file)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    flat = flat_rows(rows, sample_rate)
    schema = _schema(label_keys(rows), has_channels(rows)).with_metadata({SETTINGS_KEY: settings.encode()})
    table = pa.Table.from_pylist(flat, schema=schema)
    path = Path(path)
    partial = path.with_name(f".{path.name}.partial")
    pq.write_table(table, partial)
    os.replace(partial, path)


def read_rows(path: str | Path) -> tuple[list[dict], str]:
    """The rows of a ``fleet.parquet`` and the settings it was made with."""
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    settings = (table.schema.metadata or {}).get(SETTINGS_KEY, b"").decode()
    rows = []
    for flat in table.to_pylist():
        rows.append({"path": flat["path"], "group": flat["group"], "labels": json.loads(flat["labels_json"]),
                     "start": flat["start"], "end": flat["end"],
                     "model": json.loads(flat["model_json"]) if flat["model_json"] else None,
                     "diagnosis": json.loads(flat["diagnosis_json"]) if flat["diagnosis_json"] else None,
                     "out": flat["out"], "warnings": json.loads(flat["warnings_json"]), "error": flat["error"],
                     "seconds": flat["seconds"]})
        if "channel" in flat:
            rows[-1]["channel"] = flat["channel"]
    return rows, settings


def _timestamp(seconds: float | None):
    if seconds is None:
        return None
    import datetime

    return datetime.datetime.fromtimestamp(seconds, tz=datetime.timezone.utc)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


@dataclass(frozen=True)
class GroupSeries:
    """The bags of one group (and channel) with a model, in start-time order, and their quantities."""

    group: str
    rows: tuple[dict, ...]
    times: np.ndarray  # start of each bag, s since the epoch (bag time)
    values: dict[str, np.ndarray]  # quantity -> one value per bag (nan: not defined)
    sds: dict[str, np.ndarray] = field(default_factory=dict)  # quantity -> its sd per bag (``quantity_sds``)
    channel: str | None = None  # the channel of a config with several

    @property
    def key(self) -> str:
        """The series' name in the change test and the report: ``robot_01/joint2`` or
        ``robot_01 [elbow]``."""
        return self.group if self.channel is None else f"{self.group} [{self.channel}]"


def group_series(rows: Sequence[dict], sample_rate: float = 0.0) -> list[GroupSeries]:
    """Rows with a model, grouped by group and channel (by name) and ordered by their bag's start time."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        if row.get("model") and row.get("start") is not None:
            groups.setdefault((row["group"], row.get("channel") or ""), []).append(row)
    out = []
    for group, channel in sorted(groups):
        members = sorted(groups[(group, channel)], key=lambda r: (r["start"], r["path"]))
        quantities = [model_quantities(r["model"], sample_rate) for r in members]
        values = {q: np.array([v[q] for v in quantities], dtype=float) for q in QUANTITIES}
        sds = [quantity_sds(r["model"], sample_rate) for r in members]
        sds_by_quantity = {q: np.array([s[q] for s in sds], dtype=float) for q in sds[0]}
        out.append(GroupSeries(group, tuple(members), np.array([r["start"] for r in members], dtype=float), values,
                               sds_by_quantity, members[0].get("channel")))
    return out


def bag_date(row: dict) -> str:
    """The bag's date: its ``date`` label, else the UTC date of its first sample."""
    label = row.get("labels", {}).get("date")
    if label:
        return str(label)
    stamp = _timestamp(row.get("start"))
    return stamp.date().isoformat() if stamp else "?"
