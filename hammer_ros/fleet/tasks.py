"""The per-bag task of ``hammer-ros fleet``: what ``hammer-ros replay`` runs on one bag
(``hammer_ros.io.replay``: the same checks, engine and solves), plus ``diagnose`` of its final
window with ``--diagnose``. It runs on a Dask worker, opens the bag by path and returns small
dicts (the rows: one per bag, or one per channel of a config with several, ``replay_channels``
reading the topics they share once); every failure becomes a row's ``error``, never an exception.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import HammerRosError
from ..io.bag_config import StreamSpec
from ..io.replay import ChannelReplay, check_replay_input, replay_bag, replay_channels
from ..streaming.config import EngineConfig
from .sources import BagSource


@dataclass(frozen=True)
class FleetSettings:
    """What every task of one fleet run shares (sent once per task; a few hundred bytes)."""

    excitation: StreamSpec
    response: StreamSpec
    config: EngineConfig
    solve_rate: float
    frame_id: str = ""
    diagnose: bool = False
    results_dir: str | None = None  # each bag's results MCAP goes to results_dir / source.name
    reference: StreamSpec | None = None  # a closed loop's reference, the solves' instrument (``replay --reference``)
    # several channels (``replay_channels``): a row per channel; the fields above are the first channel's
    channels: tuple[ChannelReplay, ...] = ()

    def fingerprint(self) -> str:
        """The settings that decide a row (a resumed run must use the same)."""
        doc = {"excitation": str(self.excitation), "response": str(self.response), "config": asdict(self.config),
               "solve_rate": self.solve_rate, "diagnose": self.diagnose}
        if self.reference is not None:
            doc["reference"] = str(self.reference)
        if self.channels:
            doc["channels"] = [{"name": c.name, "excitation": str(c.excitation), "response": str(c.response),
                                "config": asdict(c.config), "solve_rate": c.solve_rate} for c in self.channels]
        return json.dumps(doc, sort_keys=True, default=str)


def bag_rows(settings: FleetSettings, source: BagSource) -> list[dict[str, Any]]:
    """The rows of one bag: ``run_bag``'s, or ``run_channels_bag``'s with several channels."""
    return run_channels_bag(settings, source) if settings.channels else [run_bag(settings, source)]


def run_bag(settings: FleetSettings, source: BagSource) -> dict[str, Any]:
    """Replay one bag; the row: path, group, labels, start/end (bag time, s), the ``replay --json``
    document (``model``), the diagnosis, the results MCAP, ``error`` and the task's seconds."""
    started = time.perf_counter()
    row = empty_row(source)
    try:
        out = _results_path(settings, source)
        check_replay_input(source.path, settings.excitation, settings.response, out, reference=settings.reference)
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
        result = replay_bag(source.path, settings.excitation, settings.response, settings.config,
                            settings.solve_rate, frame_id=settings.frame_id, out=out, atomic=True,
                            diagnose=settings.diagnose, reference=settings.reference)
        row["warnings"] = result.read.warnings(source.path)
        row["start"], row["end"] = _finite(result.first_stamp), _finite(result.last_stamp)
        row["model"] = result.document()
        row["out"] = str(out) if out is not None else None
        row["diagnosis"] = row_diagnosis(result.diagnosis)
    except Exception as exc:  # a bag must never stop the fleet: its row says what happened
        row["error"] = error_text(exc, source.path)
    row["seconds"] = time.perf_counter() - started
    return row


def run_channels_bag(settings: FleetSettings, source: BagSource) -> list[dict[str, Any]]:
    """Every channel of ``settings.channels`` on one bag in one pass (``replay_channels``): a row
    per channel, in the config's order, each with its ``channel`` name and its own model or error
    (a bag that cannot be read: the same error in every channel's row). The seconds of the pass
    are shared out evenly between the rows (their sum is the task's time)."""
    started = time.perf_counter()
    rows = [{**empty_row(source), "channel": c.name} for c in settings.channels]
    try:
        out = _results_path(settings, source)
        for c in settings.channels:
            check_replay_input(source.path, c.excitation, c.response, out)
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
        results = replay_channels(source.path, list(settings.channels), frame_id=settings.frame_id, out=out,
                                  diagnose=settings.diagnose)
        for row, c in zip(rows, settings.channels, strict=True):
            result = results[c.name]
            row["warnings"] = result.read.warnings(source.path)
            row["start"], row["end"] = _finite(result.first_stamp), _finite(result.last_stamp)
            row["out"] = str(out) if out is not None else None
            row["diagnosis"] = row_diagnosis(result.diagnosis)
            try:
                row["model"] = result.document()
            except HammerRosError as exc:
                row["error"] = f"{exc} (channel {c.name!r})"
    except Exception as exc:  # a bag must never stop the fleet: its rows say what happened
        for row in rows:
            row["error"] = error_text(exc, source.path)
    seconds = (time.perf_counter() - started) / len(rows)
    for row in rows:
        row["seconds"] = seconds
    return rows


def empty_row(source: BagSource) -> dict[str, Any]:
    """A bag's row before its replay (no model, no error yet)."""
    return {"path": source.path, "group": source.group, "labels": source.label_dict, "start": None, "end": None,
            "model": None, "diagnosis": None, "out": None, "warnings": [], "error": None}


def error_text(exc: Exception, path: str) -> str:
    """A row's ``error`` for what stopped the replay of the bag at ``path``."""
    if isinstance(exc, HammerRosError):
        return str(exc)
    if isinstance(exc, (np.linalg.LinAlgError, FloatingPointError)):
        return f"{path}: numerical failure on this data ({exc})"
    if isinstance(exc, OSError):
        return f"{exc.filename or path}: {exc.strerror or exc}"
    return f"{path}: {type(exc).__name__}: {exc}"


def _results_path(settings: FleetSettings, source: BagSource) -> Path | None:
    return Path(settings.results_dir) / source.name if settings.results_dir else None


def row_diagnosis(doc: dict[str, Any] | None) -> dict[str, Any] | None:
    """A row's diagnosis from the replay's (``replay --diagnose``: the newest 10 000 samples,
    instrumented by ``--reference``): cause, gain (rms ratio) and confidence, or the reason the
    window could not be diagnosed; None without ``--diagnose``."""
    if doc is None:
        return None
    if "error" in doc:
        return {"cause": None, "gain": None, "error": doc["error"]}
    gain = doc.get("gain")
    return {"cause": doc["cause"], "gain": gain.get("rms_ratio") if isinstance(gain, dict) else gain,
            "confidence": doc.get("confidence")}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
