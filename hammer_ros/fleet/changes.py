"""What changed: a robust sequential change test on each model quantity of each group (pure numpy).

The test (``cusum_change``) is a two-sided **CUSUM on robust z-scores** (Page 1954), with the
reference taken from the group's own history:

1. The first ``MIN_HISTORY`` = 3 bags of the group (in start-time order) are its history.
2. Each later bag k gets z_k = (x_k - m) / s, where m is the **median** of the history and
   s = max(b_n 1.4826 MAD(history), max(sigma_fleet, ``REL_FLOOR``) |m|) its robust scale
   (MAD: median absolute deviation; 1.4826 MAD estimates a standard deviation, b_n is the
   small-sample consistency factor of Croux & Rousseeuw 1992, 1.495 for n = 3 bags,
   n / (n - 0.8) above 9). A history of a few bags can be tight by chance, so the scale has two
   floors: sigma_fleet, the bag-to-bag scatter of the quantity relative to its level measured
   on the whole fleet (``relative_noise``: the MAD of first differences, which a step or a
   drift barely moves; how much one bag's estimate scatters is a property of the bags and the
   method, not of one joint), and ``REL_FLOOR`` = 2 % (a smaller relative change is never one
   standard deviation).
3. S+_k = max(0, S+_{k-1} + z_k - K) and S-_k = max(0, S-_{k-1} - z_k - K) with the standard
   allowance K = 0.5 (tuned to detect a shift of one scale unit) and decision threshold
   H = 5 (for Gaussian z an in-control average run length of about 930 bags per side).
4. Self-starting (Hawkins 1987): every bag tested without an alarm joins the history, so the
   reference sharpens as the group ages; since a median of n bags is itself uncertain, z is
   divided by sqrt(1 + pi / (2 n)) (the variance of a prediction error about a median of n).
   A drift is absorbed into the history only at the rate the median moves, far slower than
   the CUSUM accumulates it.
5. When S+ or S- exceeds H the group has changed. The run that crossed starts after the last
   bag with S = 0 (Page's change-point estimate); the **onset** is the first bag of the
   unbroken streak of bags at least 2K = 1 scale unit away on the side of the change that ends
   at the alarm (so a bag that opened the run by noise is not taken for the onset, and the
   first day of a drift is), or the start of the run when the alarm bag itself is closer.
   Every bag from the onset on is flagged; the size is the median of the last up to 3 bags
   relative to the reference median. The test stops at
   the first change (a later change of the same quantity is part of "changed since the onset").

A single outlier (e.g. one bad recording) raises S by |z| - K once and decays again: it is
flagged only if |z| > H + K = 5.5 scale units. The trend of a series is its Theil-Sen slope
(the median of the pairwise slopes, robust to such outliers) per day.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

MIN_HISTORY = 3
REL_FLOOR = 0.02
ABS_FLOOR = 1e-12  # scale floor of a quantity whose median is 0
ALLOWANCE = 0.5  # K
THRESHOLD = 5.0  # H
MAD_TO_SIGMA = 1.4826
SIZE_BAGS = 3  # the size of a change: median of the last SIZE_BAGS bags vs the reference
DAY = 86400.0


@dataclass(frozen=True)
class Change:
    """A departure of one quantity from the group's history; indices refer to the series."""

    quantity: str
    onset: int  # first flagged bag
    alarm: int  # the bag at which the CUSUM crossed the threshold
    reference: float  # median of the history at the onset
    scale: float
    size: float  # relative change (fraction): latest bags vs reference
    direction: int  # +1 up, -1 down
    flagged: tuple[int, ...]  # onset .. end (finite values only)


@dataclass(frozen=True)
class SeriesTest:
    """The change test of one quantity of one group."""

    quantity: str
    z: tuple[float, ...]  # robust z-score of each bag (nan: history or missing)
    cusum_up: tuple[float, ...]
    cusum_down: tuple[float, ...]
    change: Change | None
    trend_per_day: float  # Theil-Sen slope of the series, relative to its median, per day


@dataclass(frozen=True)
class GroupChange:
    """A change as the fleet reports it: group, quantity, first bag, size and how many bags."""

    group: str
    quantity: str
    first_index: int  # into the group's series
    bags: int
    size: float  # fraction
    reference: float
    latest: float
    trend_per_day: float


# small-sample consistency factors b_n of the MAD (Croux & Rousseeuw 1992), n = 2..9
MAD_SMALL_SAMPLE = {2: 1.196, 3: 1.495, 4: 1.363, 5: 1.206, 6: 1.200, 7: 1.140, 8: 1.129, 9: 1.107}


def robust_scale(history: np.ndarray, noise: float = 0.0) -> tuple[float, float]:
    """(median, scale) of a history: scale = max(b_n 1.4826 MAD, max(REL_FLOOR, noise) |median|,
    ABS_FLOOR)."""
    m = float(np.median(history))
    n = len(history)
    b = MAD_SMALL_SAMPLE.get(n, n / (n - 0.8) if n > 9 else 1.0)
    mad = float(np.median(np.abs(history - m)))
    return m, max(b * MAD_TO_SIGMA * mad, max(REL_FLOOR, noise) * abs(m), ABS_FLOOR)


def relative_noise(series: Sequence[Sequence[float]]) -> float:
    """The bag-to-bag scatter of a quantity, relative to its level, pooled over many series
    (the groups of a fleet): 1.4826 MAD / sqrt(2) of the first differences of each series
    divided by its median, each centred on its own median difference (so that a step moves
    one difference only and a steady drift none). nan with fewer than 3 differences."""
    pooled = []
    for values in series:
        x = np.asarray(values, dtype=float)
        x = x[np.isfinite(x)]
        m = float(np.median(x)) if x.size else 0.0
        if x.size < 2 or m == 0:
            continue
        d = np.diff(x) / abs(m)
        pooled.append(d - np.median(d))
    if not pooled or sum(p.size for p in pooled) < 3:
        return math.nan
    return float(MAD_TO_SIGMA * np.median(np.abs(np.concatenate(pooled))) / math.sqrt(2))


def cusum_change(values: Sequence[float], quantity: str = "", times: Sequence[float] | None = None,
                 noise: float = 0.0) -> SeriesTest:
    """The change test (module docstring) of one series in time order; nan values are skipped;
    ``noise``: the relative bag-to-bag scatter known from elsewhere (``relative_noise``), a
    floor of the scale."""
    x = np.asarray(values, dtype=float)
    n = x.size
    z, up, down = np.full(n, np.nan), np.zeros(n), np.zeros(n)
    finite = [k for k in range(n) if math.isfinite(x[k])]
    history: list[float] = []
    s_up = s_down = 0.0
    change = None
    for k in finite:
        if len(history) < MIN_HISTORY:
            history.append(x[k])
            continue
        m, s = robust_scale(np.asarray(history), noise if math.isfinite(noise) else 0.0)
        z[k] = (x[k] - m) / (s * math.sqrt(1 + math.pi / (2 * len(history))))
        s_up = max(0.0, s_up + z[k] - ALLOWANCE)
        s_down = max(0.0, s_down - z[k] - ALLOWANCE)
        up[k], down[k] = s_up, s_down
        if s_up > THRESHOLD or s_down > THRESHOLD:
            direction = 1 if s_up > THRESHOLD else -1
            # the onset of this side: the first bag after the last one where its sum was 0
            side = up if direction > 0 else down
            tested = [j for j in finite if j <= k and not math.isnan(z[j])]
            zero_before = [j for j in tested if side[j] == 0.0]
            run = [j for j in tested if j > (zero_before[-1] if zero_before else -1)]
            # the unbroken streak of bags >= 2K away (on this side) that ends at the alarm
            streak = len(run)
            while streak > 0 and direction * z[run[streak - 1]] >= 2 * ALLOWANCE:
                streak -= 1
            onset = run[streak] if streak < len(run) else run[0]
            flagged = tuple(j for j in finite if j >= onset)
            latest = float(np.median(x[list(flagged[-SIZE_BAGS:])]))
            change = Change(quantity, onset, k, m, s, (latest - m) / m if m else math.inf, direction, flagged)
            break
        history.append(x[k])
    trend = math.nan
    if times is not None and len(finite) >= 2:
        t = np.asarray(times, dtype=float)[finite]
        median = float(np.median(x[finite]))
        trend = theil_sen(t / DAY, x[finite]) / median if median else math.nan
    return SeriesTest(quantity, tuple(z), tuple(up), tuple(down), change, trend)


def theil_sen(t: Sequence[float], x: Sequence[float]) -> float:
    """The median of the slopes (x_j - x_i) / (t_j - t_i) over all pairs with t_j > t_i."""
    t, x = np.asarray(t, dtype=float), np.asarray(x, dtype=float)
    i, j = np.triu_indices(t.size, 1)
    dt = t[j] - t[i]
    keep = dt != 0
    return float(np.median((x[j] - x[i])[keep] / dt[keep])) if keep.any() else math.nan


def within_intervals(change: Change, sds: Sequence[float]) -> bool:
    """Whether a change lies inside the models' own combined 95 % intervals: |latest - reference| <=
    1.96 sqrt(sd_latest^2 + sd_reference^2), sd_latest the median sd of the last ``SIZE_BAGS``
    flagged bags, sd_reference that of the bags before the onset (False when the sds are unknown)."""
    sd = np.asarray(sds, dtype=float)
    latest = change.reference * (1 + change.size) if math.isfinite(change.size) else math.inf
    before, after = sd[: change.onset], sd[list(change.flagged[-SIZE_BAGS:])]
    before, after = before[np.isfinite(before)], after[np.isfinite(after)]
    if not before.size or not after.size:
        return False
    return abs(latest - change.reference) <= 1.96 * math.hypot(float(np.median(after)), float(np.median(before)))


def group_changes(group: str, times: Sequence[float], series: Mapping[str, Sequence[float]],
                  noise: Mapping[str, float] | None = None,
                  sds: Mapping[str, Sequence[float]] | None = None) -> tuple[dict[str, SeriesTest], list[GroupChange]]:
    """The test of every quantity of one group (``times`` in seconds, the series in that order;
    ``noise``: quantity -> ``relative_noise`` of the fleet; ``sds``: quantity -> the sd of each bag's
    value from its model's bounds: a change inside the combined intervals (``within_intervals``) is
    not reported)."""
    tests, changes = {}, []
    for quantity, values in series.items():
        test = cusum_change(values, quantity, times, (noise or {}).get(quantity, 0.0))
        c = test.change
        if c is not None and quantity in (sds or {}) and within_intervals(c, sds[quantity]):
            test = replace(test, change=None)
            c = None
        tests[quantity] = test
        if c is not None:
            x = np.asarray(values, dtype=float)
            changes.append(GroupChange(group, quantity, c.onset, len(c.flagged), c.size, c.reference,
                                       float(x[c.flagged[-1]]), test.trend_per_day))
    return tests, changes
