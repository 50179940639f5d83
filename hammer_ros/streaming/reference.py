"""The external reference of a closed loop on the engine's sample grid (``replay --reference``):
the instrument of ``identification.instrumental``, read at the grid times of the window.

The engine hands every aligned grid time to ``grid`` and every reference sample to ``add``;
``window(n)`` is the reference at the newest n grid times (the window), zero-order hold: the
last reference sample at or before each grid time (within ``tolerance``), NaN where there is
none (before the first reference sample, or after a reference gap longer than ``max_gap``).
Both are kept for the newest ``capacity`` grid times only.
"""

from __future__ import annotations

import numpy as np

from .config import CLOCK_RESET_SECONDS


class ReferenceTrack:
    """Grid times and reference samples of the newest ``capacity`` grid points."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)  # at least the window (``StreamingEngine`` keeps it so)
        self._chunks: list[np.ndarray] = []  # grid times appended since the last consolidation
        self._grid = np.empty(0)
        self._t = np.empty(0)
        self._r = np.empty(0)

    def grid(self, times: np.ndarray) -> None:
        """The grid times of newly aligned samples (in order)."""
        self._chunks.append(np.asarray(times, dtype=float))
        if sum(c.size for c in self._chunks) > self.capacity:
            self._consolidate()

    def _consolidate(self) -> None:
        self._grid = np.concatenate([self._grid, *self._chunks])[-self.capacity:]
        self._chunks = []

    def add(self, t: np.ndarray, r: np.ndarray) -> None:
        """Reference samples r at stamps t (s); non-finite ones and stamps older than the newest
        kept one are skipped (the grid only moves forward), except after a jump back of more than
        CLOCK_RESET_SECONDS (a sim-time reset, a bag loop): the track then starts again."""
        t, r = np.atleast_1d(np.asarray(t, dtype=float)), np.atleast_1d(np.asarray(r, dtype=float))
        newest = self._t[-1] if self._t.size else -np.inf
        if t.size and t[0] < newest - CLOCK_RESET_SECONDS:
            self._t, self._r, newest = self._t[:0], self._r[:0], -np.inf
        keep = np.isfinite(t) & np.isfinite(r) & (t > newest)
        self._t, self._r = np.concatenate([self._t, t[keep]]), np.concatenate([self._r, r[keep]])
        if self._grid.size and self._t.size > 2 * self.capacity:
            first = max(int(np.searchsorted(self._t, self._grid[0], "right")) - 1, 0)
            self._t, self._r = self._t[first:], self._r[first:]

    def window(self, n: int, tolerance: float, max_gap: float) -> np.ndarray:
        """The reference at the newest ``n`` grid times (zero-order hold, NaN where none)."""
        self._consolidate()
        times = self._grid[-n:] if n else self._grid[:0]
        index = np.searchsorted(self._t, times + tolerance, "right") - 1
        values = np.full(times.size, np.nan)
        held = index >= 0
        values[held] = self._r[index[held]]
        values[held & (times - self._t[np.maximum(index, 0)] > max_gap)] = np.nan
        return values
