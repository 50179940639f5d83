"""ArrivalStamper: stamps for unstamped messages from jittered, bursty receive times."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.streaming.sample_clock import ArrivalStamper

RATE = 500.0


def receive_times(n: int, rng, start: float = 1000.0, per_message: int = 1) -> np.ndarray:
    """Receive times of n messages sent every per_message/RATE s: latency 0.1-0.4 ms, plus
    stalls of the subscriber (every message of a 10-40 ms stall is delivered at its end)."""
    sent = start + (np.arange(n) + 1) * per_message / RATE - 1 / RATE
    received = sent + rng.uniform(1e-4, 4e-4, n)
    for stall_start in rng.choice(np.arange(50, n - 50), 20, replace=False):
        stall_end = received[stall_start] + rng.uniform(0.01, 0.04)
        inside = (received >= received[stall_start]) & (received < stall_end)
        received[inside] = stall_end + 1e-6 * np.arange(inside.sum())
    return received


def test_jitter_and_stalls_never_move_a_sample(rng):
    stamper = ArrivalStamper(RATE)
    t_u = receive_times(3000, rng)
    t_y = t_u + rng.uniform(0.0, 3e-4, t_u.size)  # the response arrives a little later
    u = np.concatenate([stamper.stamps("excitation", t, 1) for t in t_u])
    y = np.concatenate([stamper.stamps("response", t, 1) for t in t_y])
    np.testing.assert_allclose(np.diff(u), 1 / RATE, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(u, y)  # sample k of both streams on the same grid point
    assert stamper.restarts == 0
    assert 0 <= t_u[0] - u[0] < 1e-3  # anchored on the least delayed arrivals


def test_batches_put_the_last_sample_at_the_arrival(rng):
    stamper = ArrivalStamper(RATE)
    t = receive_times(300, rng, per_message=10)
    stamps = np.concatenate([stamper.stamps("excitation", r, 10) for r in t])
    np.testing.assert_allclose(np.diff(stamps), 1 / RATE, rtol=0, atol=1e-7)
    assert 0 <= t[0] - stamps[9] < 1e-3


def test_a_publisher_pause_restarts_the_count(rng):
    stamper = ArrivalStamper(RATE, resync=0.5)
    before = [stamper.first_stamp("excitation", t, 1) for t in receive_times(500, rng)]
    resumed_at = before[-1] + 2.0
    after = [stamper.first_stamp("excitation", t, 1) for t in receive_times(500, rng, start=resumed_at)]
    assert stamper.restarts == 1
    # the first message after the pause cannot tell it from a stall: it continues the count;
    # the next one, arriving at fs and not in a burst, restarts the count at the first
    assert after[0] - before[-1] == pytest.approx(1 / RATE, abs=1e-9)
    assert after[1] - before[-1] == pytest.approx(2.0 + 1 / RATE, abs=2e-3)
    np.testing.assert_allclose(np.diff(after[1:]), 1 / RATE, rtol=0, atol=1e-7)


def test_a_second_pause_after_the_first_late_message_restarts_at_the_next(rng):
    """A message after a 1 s pause, then another 1 s pause: the count restarts at the message
    after the second pause (not at the lone message between them, which would put the second
    pause's samples 1 s early), and every later sample lies at its send time."""
    stamper = ArrivalStamper(RATE, resync=0.5)
    before = [stamper.first_stamp("excitation", t, 1) for t in receive_times(500, rng)]
    lone = before[-1] + 1.0
    stamper.first_stamp("excitation", lone + 2e-4, 1)
    resumed = receive_times(500, rng, start=lone + 1.0)
    after = np.array([stamper.first_stamp("excitation", t, 1) for t in resumed])
    sent = lone + 1.0 + np.arange(500) / RATE
    assert stamper.restarts == 1
    assert np.abs(after - sent).max() < 1e-3
    np.testing.assert_allclose(np.diff(after), 1 / RATE, rtol=0, atol=1e-7)


@pytest.mark.parametrize("stall, drain", [(0.8, 100.0), (0.8, 3.0), (3.0, 100.0)])
def test_a_stall_longer_than_resync_is_not_a_pause(rng, stall, drain):
    """The subscriber stalls for ``stall`` s (longer than ``resync``; 3 s is past the horizon)
    and then delivers the queued messages of both streams at ``drain`` x fs: nothing restarts,
    no stamp repeats, and sample k of both streams stays on one grid point. (Restarting the
    count at the stall's first message put each stream's place a period back per message of
    the burst: repeated stamps, and the response a sample off the excitation.)"""
    stamper = ArrivalStamper(RATE, resync=0.5)
    t_u = receive_times(3000, rng)
    t_y = np.maximum.accumulate(t_u + rng.uniform(0.0, 3e-4, t_u.size))  # each topic in order
    sent = 1000.0 + np.arange(t_u.size) / RATE
    begin = sent[1500]
    queued = t_u >= begin  # after the stall, both streams are delivered at drain x fs until caught up
    t_u[queued] = np.maximum(t_u[queued], begin + stall + np.arange(queued.sum()) / (drain * RATE))
    t_y[queued] = np.maximum(t_y[queued], t_u[queued] + 1e-6)
    order = np.argsort(np.concatenate([t_u, t_y]), kind="stable")
    stamps = np.empty(2 * t_u.size)
    for k in order:
        stream, t = ("excitation", t_u[k]) if k < t_u.size else ("response", t_y[k - t_u.size])
        stamps[k] = stamper.first_stamp(stream, float(t), 1)
    u, y = stamps[: t_u.size], stamps[t_u.size:]
    assert stamper.restarts == 0
    np.testing.assert_allclose(np.diff(u), 1 / RATE, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(u, y)


def test_rate_is_inferred_from_arrivals_when_not_configured(rng):
    stamper = ArrivalStamper(0.0)
    placed = [stamper.stamps("excitation", t, 1) for t in receive_times(1500, rng)]
    assert stamper.rate == RATE
    assert placed[0] is None and placed[-1] is not None


def test_streams_published_together_stay_together_when_their_bases_straddle_a_half_period(rng):
    """The first arrival is late by half a period (say, discovery), so the least delayed
    arrivals later put both streams' bases near a half period from the anchor; the response is
    handled up to 60 us after the excitation. Rounding each base on its own split the streams
    by one sample for most of a run in about one run in ten; placed from the reference stream,
    sample k of both streams keeps one grid point through load phases too."""
    n = 5000
    for _ in range(20):
        delay = rng.uniform(1e-4, 4e-4, n)
        delay[0] = 1e-4 + 0.5 / RATE + rng.uniform(-3e-5, 3e-5)
        for start in range(0, n, 1000):  # 2 s phases of extra latency up to 0.3 periods
            delay[start:start + 1000] += rng.uniform(0, 6e-4)
        t_u = 1000.0 + np.arange(n) / RATE + delay
        t_y = t_u + rng.uniform(0, 6e-5, n)
        stamper = ArrivalStamper(RATE)
        u, y = zip(*[(stamper.first_stamp("excitation", a, 1), stamper.first_stamp("response", b, 1))
                     for a, b in zip(t_u, t_y)])
        np.testing.assert_array_equal(u, y)
        assert stamper.restarts == 0


def test_a_pause_of_the_reference_stream_alone_moves_only_its_samples(rng):
    """The response keeps its count-based stamps when the excitation (the reference, which
    places it) pauses for 0.2 s (less than ``resync``) and resumes: the reference's base jumps,
    the response's place relative to it jumps back by as much."""
    stamper = ArrivalStamper(RATE, horizon=0.1)
    t = receive_times(1000, rng)
    paused = (t > t[300]) & (t < t[300] + 0.2)
    y = []
    for k, r in enumerate(t):
        if not paused[k]:
            stamper.first_stamp("excitation", r, 1)
        y.append(stamper.first_stamp("response", r + 5e-5, 1))
    np.testing.assert_allclose(np.diff(y), 1 / RATE, rtol=0, atol=1e-7)


@pytest.mark.parametrize("rate", [RATE, 0.0])
def test_a_flush_stamped_at_once_equals_one_message_at_a_time(rng, rate):
    """``first_stamps`` (the node's ingest, one call per stream and flush) gives exactly the
    floats of ``first_stamp`` per message, through stalls (one longer than resync), a pause that restarts the count, a
    receive clock that steps back, rate inference and flushes longer than the horizon."""
    per_message = 10
    t_u = receive_times(3000, rng, per_message=per_message)
    t_u[1500:] += 1.0  # a publisher pause: the count restarts
    stalled = (t_u > t_u[700]) & (t_u < t_u[700] + 0.8)  # a subscriber stall longer than resync
    t_u[stalled] = t_u[700] + 0.8 + 1e-5 * np.arange(stalled.sum())
    t_u[2200:] -= 0.05  # the receive clock steps back (2.5 messages)
    t_y = t_u + rng.uniform(0.0, 3e-4, t_u.size)
    one, flushes = ArrivalStamper(rate, horizon=0.5), ArrivalStamper(rate, horizon=0.5)
    expected, got = [], []
    start = 0
    while start < t_u.size:
        stop = start + int(rng.choice([1, 3, 40, 400]))
        for stream, t in (("excitation", t_u[start:stop]), ("response", t_y[start:stop])):
            for r in t:
                first = one.first_stamp(stream, float(r), per_message)
                expected.append(np.nan if first is None else first)
            got.extend(flushes.first_stamps(stream, t, per_message))
        start = stop
    np.testing.assert_array_equal(got, expected)
    assert flushes.restarts == one.restarts >= 1
    assert flushes.rate == RATE
    assert np.isfinite(got).sum() > 0.9 * len(got)
