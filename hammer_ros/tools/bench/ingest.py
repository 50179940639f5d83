"""Section 1, ingest: samples/s through ``StreamingEngine`` vs the batch FFT correlations of the record."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ...streaming.config import EngineConfig
from .common import (
    SAMPLE_RATE,
    Section,
    _median,
    _timed,
    batch_correlations_fft,
    engine_correlations,
    feed_engine,
    hammerstein_record,
)


def ingest_section(samples: int, taus: Sequence[int], windows: Sequence[int], forgetting: Sequence[float],
                   chunk: int, repeats: int) -> Section:
    """Engine ingest rate vs the batch FFT correlations of the same record (paired repeats)."""
    section = Section("ingest", f"1. Engine ingest ({samples:,} samples, {chunk} per call)", [
        ("case", "tau_max, W, mode"), ("engine", "engine samples/s"), ("us_per_sample", "engine us/sample"),
        ("reference", "batch FFT samples/s"), ("ratio", "engine / FFT"), ("check", "max abs error vs FFT"),
        ("goal", "goal >= 0.5")])
    v, y = hammerstein_record(samples, seed=1)
    for tau_max in taus:
        for window in windows:
            for lam in forgetting:
                config = EngineConfig(sample_rate=SAMPLE_RATE, window=window, tau_max=tau_max, forgetting=lam,
                                      min_fill=1.0)
                engine_s, fft_s, ratios = [], [], []
                for _ in range(repeats):
                    te, engine = _timed(lambda config=config: feed_engine(config, v, y, chunk))
                    tf, _ = _timed(lambda tau_max=tau_max, lam=lam: batch_correlations_fft(v, y, tau_max, lam))
                    engine_s.append(te)
                    fft_s.append(tf)
                    ratios.append(tf / te)
                # the engine's sums at the end = the batch correlations of its window (sliding) or of
                # the whole record (forgetting: every centre since the start, weighted)
                tail = slice(-window, None) if lam == 1.0 else slice(None)
                error = float(np.max(np.abs(engine_correlations(engine)
                                            - batch_correlations_fft(v[tail], y[tail], tau_max, lam))))
                ratio = _median(ratios)
                mode = "sliding" if lam == 1.0 else f"forgetting {lam}"
                section.rows.append({
                    "case": f"{tau_max}, {window:,}, {mode}", "tau_max": tau_max, "window": window,
                    "forgetting": lam, "engine": samples / _median(engine_s),
                    "us_per_sample": 1e6 * _median(engine_s) / samples, "reference": samples / _median(fft_s),
                    "ratio": ratio, "check": error, "goal": ratio >= 0.5})
    section.notes += _growth_notes(section.rows)
    return section


def _growth_notes(rows: list[dict]) -> list[str]:
    """How the engine's cost per sample grows with tau_max and with W."""
    notes = []
    cost = {(r["tau_max"], r["window"], r["forgetting"]): r["us_per_sample"] for r in rows}
    taus = sorted({k[0] for k in cost})
    windows = sorted({k[1] for k in cost})
    for lam in sorted({k[2] for k in cost}, reverse=True):
        mode = "sliding" if lam == 1.0 else f"forgetting {lam}"
        if len(taus) > 1:
            growth = [cost[(taus[-1], w, lam)] / cost[(taus[0], w, lam)] for w in windows]
            notes.append(f"{mode}: cost per sample x{_median(growth):.2f} from tau_max {taus[0]} to {taus[-1]} "
                         f"(lag count x{(2 * taus[-1] + 1) / (2 * taus[0] + 1):.2f}); FFT ~flat in tau_max")
        if len(windows) > 1:
            growth = [cost[(t, windows[-1], lam)] / cost[(t, windows[0], lam)] for t in taus]
            notes.append(f"{mode}: cost per sample x{_median(growth):.2f} from W {windows[0]:,} to {windows[-1]:,}")
    return notes


