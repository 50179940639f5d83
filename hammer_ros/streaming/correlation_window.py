"""Step 4 of the engine (``hammer_ros.streaming.engine``): the correlation sums of the sliding (or
exponentially forgetting) window, updated per block of lag products."""

from __future__ import annotations

from collections import deque

import numpy as np
import scipy.fft

from .config import BLOCK_CENTRES, BLOCKS_PER_WINDOW, CHUNK

# Cost model of ``_lag_products`` (2-core bench VM, 2026-12-03, single-threaded): the direct loops take
# about DIRECT_NS per centre and lag, the real FFTs about FFT_FIXED_NS + FFT_NS per centre; the cheaper
# way is used (tau_max 66: FFTs from about 1 200 centres, 4096 centres 172 -> 114 us; tau_max 15: never;
# tau_max 128: from about 400 centres).
DIRECT_NS, FFT_FIXED_NS, FFT_NS = 0.32, 25_000.0, 22.0


def by_fft(centres: int, tau_max: int) -> bool:
    """Whether ``_lag_products`` sums ``centres`` centres at lags -tau_max..tau_max by FFT."""
    return centres * (DIRECT_NS * (2 * tau_max + 1) - FFT_NS) > FFT_FIXED_NS



def _lag_products(v: np.ndarray, y: np.ndarray, tau_max: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Sums over the centres k = T..len-1-T of [v(k), y(k), y(k)] times [v, v, v^2](k - tau),
    tau = -T..T, as a (3, 2T+1) array (optionally weighted per centre).

    ``np.correlate(x, c, 'valid')[j] = sum_n x(n + j) c(n)``: with x = v from the first sample
    and c the centres, j = T - tau; one C loop per row, no lag matrix in memory. When that is
    dearer (``by_fft``: many centres and lags) the same sums come from real FFTs of length
    >= len(v) (c is shorter than x, so the circular correlation does not wrap for j <= 2T)."""
    rows = v.size - 2 * tau_max
    centre_v, centre_y = v[tau_max : tau_max + rows], y[tau_max : tau_max + rows]
    if weights is not None:
        centre_v, centre_y = centre_v * weights[:rows], centre_y * weights[:rows]
    if by_fft(rows, tau_max):
        n = scipy.fft.next_fast_len(v.size, real=True)
        x = scipy.fft.rfft(np.stack([v, v * v]), n, axis=1)
        c = np.conj(scipy.fft.rfft(np.stack([centre_v, centre_y]), n, axis=1))
        sums = scipy.fft.irfft(np.stack([x[0] * c[0], x[0] * c[1], x[1] * c[1]]), n, axis=1)[:, : 2 * tau_max + 1]
        return sums[:, ::-1]
    sums = np.empty((3, 2 * tau_max + 1))  # tau = T..-T, reversed on return
    sums[0], sums[1], sums[2] = (np.correlate(v, centre_v, "valid"), np.correlate(v, centre_y, "valid"),
                                 np.correlate(v * v, centre_y, "valid"))
    return sums[:, ::-1]



class _Block:
    """Lag-product sums of the consecutive centres lo..hi (a sliding window's unit of removal)."""

    __slots__ = ("hi", "lo", "sums")

    def __init__(self, lo: int, hi: int, sums: np.ndarray) -> None:
        self.lo, self.hi, self.sums = lo, hi, sums



class CorrelationWindow:
    """Raw window of aligned samples and the recursive correlation sums over it.

    Sliding window (forgetting 1): the products of every centre are formed once, when it
    arrives (of a batch longer than W only those of its newest W samples: the others have left
    the window by the end of the add, so their products would be added only to be subtracted
    again; a live flush at 10^6 samples/s is many windows long), and summed into blocks of
    >= ``block`` consecutive centres; ``sums`` is the total of the blocks. A block leaves whole
    (its sums subtracted) once the window has passed it; the part of the oldest block already
    outside is subtracted only when the correlations are read (once per solve), and ``sums`` is
    re-added from the blocks every W samples, so rounding cannot drift. Forgetting: ``sums``
    decays and the new products are added."""

    def __init__(self, window: int, tau_max: int, forgetting: float) -> None:
        self.window, self.tau_max, self.forgetting = window, tau_max, forgetting
        self.block = max(BLOCK_CENTRES, window // BLOCKS_PER_WINDOW)
        self.capacity = window + self.block + 2 * (CHUNK + tau_max)  # the oldest block's samples too
        self.v = np.empty(self.capacity)
        self.y = np.empty(self.capacity)
        self.reset()

    def reset(self) -> None:
        self.count = 0  # samples since the (re)start of the segment
        self.stored = 0  # samples held in self.v[:stored] (the newest ones)
        self.window_start = 0  # segment index of the window's oldest sample
        self.sums = np.zeros((3, 2 * self.tau_max + 1))
        self.weight = 0.0
        self.centres = (0, -1)  # [lo, hi] segment indices of the window's centres
        self.blocks: deque[_Block] = deque()  # sliding: consecutive centre blocks, oldest first
        self.since_resync = 0

    def _restart_at(self, count: int) -> None:
        """An empty window whose next sample is the segment's sample ``count``."""
        self.reset()
        self.count = self.window_start = count

    def _local(self, start: int, stop: int) -> slice:
        """Slice of the stored arrays holding segment indices start..stop-1."""
        offset = self.count - self.stored
        return slice(start - offset, stop - offset)

    def _products(self, lo: int, hi: int, weights: np.ndarray | None = None) -> np.ndarray:
        if hi < lo:
            return np.zeros_like(self.sums)
        s = self._local(lo - self.tau_max, hi + self.tau_max + 1)
        return _lag_products(self.v[s], self.y[s], self.tau_max, weights)

    def _target_centres(self) -> tuple[int, int]:
        return self.window_start + self.tau_max, self.count - 1 - self.tau_max

    def add(self, v: np.ndarray, y: np.ndarray) -> None:
        """Append aligned samples and update the sums (sliding: a batch longer than W restarts
        the window at its newest W samples)."""
        if self.forgetting >= 1.0 and v.size > self.window:
            self._restart_at(self.count + v.size - self.window)
            v, y = v[-self.window :], y[-self.window :]
        for start in range(0, v.size, CHUNK):
            self._add_chunk(v[start : start + CHUNK], y[start : start + CHUNK])

    def _add_chunk(self, v: np.ndarray, y: np.ndarray) -> None:
        m = v.size
        if self.stored + m > self.capacity:
            oldest = min(self.window_start, self.blocks[0].lo - self.tau_max) if self.blocks else self.window_start
            keep = min(self.stored, self.count - oldest)
            self.v[:keep] = self.v[self.stored - keep : self.stored]
            self.y[:keep] = self.y[self.stored - keep : self.stored]
            self.stored = keep
        self.v[self.stored : self.stored + m] = v
        self.y[self.stored : self.stored + m] = y
        self.stored += m
        self.count += m
        self.window_start = max(self.window_start, self.count - self.window)
        if self.forgetting < 1.0:
            self._update_forgetting()
        else:
            self._update_sliding(m)

    def _update_sliding(self, m: int) -> None:
        new_lo, new_hi = self._target_centres()
        first = self.blocks[-1].hi + 1 if self.blocks else new_lo
        if first < new_lo:  # a chunk longer than the window: everything summed so far has left it
            self.blocks.clear()
            self.sums = np.zeros_like(self.sums)
            first = new_lo
        if new_hi >= first:
            products = self._products(first, new_hi)
            self.sums += products
            last = self.blocks[-1] if self.blocks else None
            if last is not None and last.hi - last.lo + 1 < self.block:
                last.sums += products
                last.hi = new_hi
            else:
                self.blocks.append(_Block(first, new_hi, products))
        while self.blocks and self.blocks[0].hi < new_lo:
            self.sums -= self.blocks.popleft().sums
        self.since_resync += m
        if self.since_resync >= self.window:
            self.sums = np.sum([b.sums for b in self.blocks], axis=0) if self.blocks else np.zeros_like(self.sums)
            self.since_resync = 0
        self.centres = (new_lo, new_hi)
        self.weight = float(max(0, new_hi - new_lo + 1))

    def window_sums(self) -> np.ndarray:
        """The sums over the window's centres (sliding: without the oldest block's part outside)."""
        if self.forgetting < 1.0 or not self.blocks or self.blocks[0].lo >= self.centres[0]:
            return self.sums
        return self.sums - self._products(self.blocks[0].lo, self.centres[0] - 1)

    def _update_forgetting(self) -> None:
        """Every centre since the (re)start is weighted in, also when a chunk exceeds the window."""
        lo, hi = self.centres
        new_hi = self.count - 1 - self.tau_max
        first = hi + 1 if hi >= lo else self.tau_max
        if new_hi < first:
            return
        decay = self.forgetting ** np.arange(new_hi - first, -1, -1)
        shrink = self.forgetting ** (new_hi - hi) if hi >= lo else 0.0
        self.sums = shrink * self.sums + self._products(first, new_hi, decay)
        self.weight = shrink * self.weight + float(decay.sum())
        self.centres = (lo if hi >= lo else first, new_hi)

    def rebuild(self, window: int, tau_max: int, forgetting: float) -> None:
        """New W / tau_max / lambda: keep the newest samples, recompute the sums from them."""
        keep = min(self.stored, window, self.count - self.window_start)
        v, y = self.v[self.stored - keep : self.stored].copy(), self.y[self.stored - keep : self.stored].copy()
        self.__init__(window, tau_max, forgetting)
        self.add(v, y)

    def raw(self) -> tuple[np.ndarray, np.ndarray]:
        s = self._local(self.window_start, self.count)
        return self.v[s].copy(), self.y[s].copy()

    def correlations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        scale = 1.0 / self.weight if self.weight > 0 else 0.0
        sums = self.window_sums()
        return sums[0] * scale, sums[1] * scale, sums[2] * scale
