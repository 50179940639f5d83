"""The per-bag task of ``hammer-ros fleet``: what ``hammer-ros replay`` runs on one bag
(``hammer_ros.io.replay``: the same checks, engine and solves), plus ``diagnose`` of its final
window with ``--diagnose``. It runs on a Dask worker, opens the bag by path and returns one small
dict (the row); every failure of the bag becomes the row's ``error``, never an exception.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import HammerRosError
from ..io.bags import StreamSpec, forget_warnings
from ..io.replay import check_replay_input, replay_bag
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

    def fingerprint(self) -> str:
        """The settings that decide a row (a resumed run must use the same)."""
        doc = {"excitation": str(self.excitation), "response": str(self.response), "config": asdict(self.config),
               "solve_rate": self.solve_rate, "diagnose": self.diagnose}
        if self.reference is not None:
            doc["reference"] = str(self.reference)
        return json.dumps(doc, sort_keys=True, default=str)


def run_bag(settings: FleetSettings, source: BagSource) -> dict[str, Any]:
    """Replay one bag; the row: path, group, labels, start/end (bag time, s), the ``replay --json``
    document (``model``), the diagnosis, the results MCAP, ``error`` and the task's seconds."""
    started = time.perf_counter()
    row: dict[str, Any] = {"path": source.path, "group": source.group, "labels": source.label_dict,
                           "start": None, "end": None, "model": None, "diagnosis": None, "out": None,
                           "warnings": [], "error": None}
    forget_warnings()
    try:
        out = Path(settings.results_dir) / source.name if settings.results_dir else None
        check_replay_input(source.path, settings.excitation, settings.response, out, reference=settings.reference)
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
        result = replay_bag(source.path, settings.excitation, settings.response, settings.config,
                            settings.solve_rate, frame_id=settings.frame_id, out=out, atomic=True,
                            keep_window=settings.diagnose, reference=settings.reference)
        row["warnings"] = result.read.warnings(source.path)
        row["start"], row["end"] = _finite(result.first_stamp), _finite(result.last_stamp)
        row["model"] = result.document()
        row["out"] = str(out) if out is not None else None
        if settings.diagnose and result.window is not None:
            row["diagnosis"] = diagnose_window(*result.window, settings.config)
    except HammerRosError as exc:
        row["error"] = str(exc)
    except (np.linalg.LinAlgError, FloatingPointError) as exc:
        row["error"] = f"{source.path}: numerical failure on this data ({exc})"
    except OSError as exc:
        row["error"] = f"{exc.filename or source.path}: {exc.strerror or exc}"
    except Exception as exc:  # a bag must never stop the fleet: its row says what happened
        row["error"] = f"{source.path}: {type(exc).__name__}: {exc}"
    row["seconds"] = time.perf_counter() - started
    return row


def diagnose_window(v: np.ndarray, y: np.ndarray, config: EngineConfig) -> dict[str, Any]:
    """``diagnose`` of the replay's final window (as the node diagnoses its window): cause and
    gain, or the reason it could not be diagnosed."""
    from ..diagnosis.diagnose import diagnose_record

    try:
        with np.errstate(all="ignore"):
            d = diagnose_record(v, y, order=config.order, delay=config.delay).to_json()
    except (HammerRosError, ValueError, np.linalg.LinAlgError) as exc:
        return {"cause": None, "gain": None, "error": f"window not diagnosable: {exc}"}
    gain = d.get("gain")
    return {"cause": d["cause"], "gain": gain.get("rms_ratio") if isinstance(gain, dict) else gain,
            "confidence": d.get("confidence")}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
