"""Bad input at the engine level (pure numpy, no ROS): what the node and replay inherit.

Non-finite and absurd samples, duplicate/late stamps, clock resets, a 10^6-sample batch,
gaps, an exception inside a solve, a standing-still robot, and the documented limits."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.errors import UsageError
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.simulate import HammersteinStream
from hammer_ros.messages.outputs import diagnostics_message, result_messages, stale_model_message
from hammer_ros.streaming import config as streaming_config
from hammer_ros.streaming import correlation_window
from hammer_ros.streaming import engine as streaming_engine
from hammer_ros.streaming.config import MAX_TAU_MAX, MAX_WINDOW, EngineConfig
from hammer_ros.streaming.engine import StreamingEngine

RATE = 100.0
CONFIG = EngineConfig(sample_rate=RATE, window=2000, tau_max=60, order=3, delay=1)


def cubic(v):
    return v + 4 * v**3


class Plant:
    """G1 after F(v) = v + 4 v^3 (paper 000), sampled at RATE; state and clock carry over."""

    def __init__(self, g1, seed: int = 1, t0: float = 10.0) -> None:
        self.stream = HammersteinStream(cubic, g1)
        self.rng = np.random.default_rng(seed)
        self.k = 0
        self.t0 = t0

    def take(self, n: int, constant: float | None = None, input_noise: float = 0.0):
        v = self.rng.normal(0.0, 0.3, n) if constant is None else constant + input_noise * self.rng.normal(size=n)
        y = self.stream(v) + 0.01 * self.rng.normal(size=n)
        t = self.t0 + (self.k + np.arange(n)) / RATE
        self.k += n
        return t, v, y


def feed(engine, t, v, y, batch=50):
    for s in range(0, t.size, batch):
        engine.add_excitation(t[s : s + batch], v[s : s + batch])
        engine.add_response(t[s : s + batch], y[s : s + batch])


def pole_error(g1, outcome) -> float:
    return root_rss_error(g1.poles, outcome.result.linear.poles)


def test_non_finite_and_absurd_samples_are_skipped_and_counted(g1):
    engine = StreamingEngine(CONFIG)
    t, v, y = Plant(g1).take(3000)
    v[[10, 500, 1700]] = [np.nan, np.inf, 1e200]
    y[[20, 21]] = [-np.inf, np.nan]
    t[2500] = np.nan  # a non-finite stamp
    feed(engine, t, v, y)
    assert engine.stats.nan_skipped == 3 + 2 + 2  # the nan stamp drops the sample of both streams
    assert engine.stats.missing("excitation") == engine.stats.missing("response") == 1  # only the unstamped one
    outcome = engine.solve()
    assert outcome.ok and np.all(np.isfinite(outcome.result.linear.a))
    assert pole_error(g1, outcome) < 0.05


def test_duplicate_and_late_stamps_are_skipped_and_counted(g1):
    engine = StreamingEngine(CONFIG)
    t, v, y = Plant(g1).take(2500)
    feed(engine, t[:2000], v[:2000], y[:2000])
    engine.add_excitation(t[1950:2000], v[1950:2000])  # re-sent: 1 duplicate of the newest stamp, 49 late
    engine.add_excitation(t[1990:1991], v[1990:1991])  # one sample out of order
    assert (engine.stats.duplicate, engine.stats.late, engine.stats.clock_resets) == (1, 50, 0)
    feed(engine, t[2000:], v[2000:], y[2000:])
    assert engine.stats.aligned == 2500 and engine.solve().ok


def test_a_clock_jump_back_of_both_streams_restarts_and_identifies_again(g1):
    """Sim time reset / bag loop: both streams' stamps go back to the start."""
    engine = StreamingEngine(CONFIG)
    plant = Plant(g1)
    t, v, y = plant.take(3000)
    feed(engine, t, v, y)
    assert engine.solve().ok
    plant.k = 0  # the clock restarts at t0; the plant goes on
    t, v, y = plant.take(3000)
    feed(engine, t, v, y)
    assert engine.stats.clock_resets == 1 and engine.stats.late == 0 and engine.stats.gaps == 0
    assert engine.stats.aligned == 6000  # nothing lost: the new timeline is aligned from its first sample
    assert engine.stats.rate("excitation") == pytest.approx(RATE)
    outcome = engine.solve()
    assert outcome.ok and outcome.stamp == pytest.approx(t[-1]) and pole_error(g1, outcome) < 0.05


def test_a_re_sent_stretch_of_one_stream_is_late_not_a_clock_reset(g1):
    engine = StreamingEngine(CONFIG)
    t, v, y = Plant(g1).take(3000)
    feed(engine, t, v, y)
    engine.add_excitation(t[:1000], v[:1000])  # 30 s back, but only this stream
    engine.add_excitation(t[-1] + 1 / RATE, 0.1)  # and on it goes
    assert engine.stats.clock_resets == 0 and engine.stats.late == 1000
    assert engine.solve().ok


def test_a_gap_restarts_the_window_and_the_model_comes_back(g1):
    engine = StreamingEngine(CONFIG)
    plant = Plant(g1)
    feed(engine, *plant.take(3000))
    first = engine.solve()
    plant.k += 300  # 3 s without samples on both streams
    t, v, y = plant.take(600)
    feed(engine, t, v, y)
    assert engine.stats.gaps == 1 and engine.stats.window_samples == 600
    feed(engine, *plant.take(1000))
    assert first.ok and engine.solve().ok


def test_a_million_sample_batch_is_aligned_without_overflow(g1):
    """One 10^6-element array message per stream (bag or topic): the streams are added in
    interleaved pieces, so nothing waits in (or overflows) the pending buffer."""
    engine = StreamingEngine(CONFIG)
    n = 1_000_000
    t = 10.0 + np.arange(n) / RATE
    v = np.random.default_rng(0).normal(0, 0.3, n)
    y = np.convolve(cubic(v), [0.0, 1.0, 0.5])[:n]
    engine.add_message("excitation", t[-1], v, flush=False)
    engine.add_message("response", t[-1], y, flush=False)
    engine.flush()
    assert (engine.stats.aligned, engine.stats.overflow) == (n, 0)
    assert engine.stats.window_samples == CONFIG.window


def test_a_flood_on_one_stream_is_bounded_and_counted(g1):
    """The response stalls: the excitation's pending samples are capped (oldest dropped, counted)."""
    engine = StreamingEngine(CONFIG)
    n = streaming_config.PENDING_SAMPLES + 50_000
    t = 10.0 + np.arange(n) / RATE
    engine.add_response(t[:10], np.zeros(10))
    for part in np.array_split(np.arange(n), 100):  # in many messages: linear cost, not quadratic
        engine.add_excitation(t[part], np.ones(part.size))
    assert engine.stats.overflow == n - 9 - streaming_config.PENDING_SAMPLES  # 9 consumed by the 10 grid points
    assert engine.stats.aligned <= 10


def test_an_exception_inside_a_solve_is_counted_and_loses_nothing(g1, monkeypatch):
    engine = StreamingEngine(EngineConfig(sample_rate=RATE, window=2000, tau_max=60, order=3, delay=1,
                                          method="nls-markov"))
    plant = Plant(g1)
    feed(engine, *plant.take(2500))

    def broken(*args, **kwargs):
        raise RuntimeError("bug in a method")

    monkeypatch.setattr(streaming_engine, "identify", broken)
    outcome = engine.solve()
    assert not outcome.ok and outcome.status == "exception" and "RuntimeError: bug in a method" in outcome.reason
    assert engine.stats.solve_exceptions == 1
    diagnostics = diagnostics_message(engine.stats, outcome, 10**9)["status"][0]
    assert diagnostics["level"] == 2 and "bug in a method" in diagnostics["message"]
    monkeypatch.undo()
    feed(engine, *plant.take(500))  # ingestion went on
    assert engine.stats.aligned == 3000 and engine.stats.window_samples == 2000
    assert engine.solve().ok


def test_an_empty_plls_interval_is_a_counted_failure_with_its_reason(g1):
    engine = StreamingEngine(EngineConfig(sample_rate=RATE, window=2000, tau_max=60, order=3, delay=1,
                                          method="plls-hammerstein", partition=(5.0, 6.0, 7.0)))
    feed(engine, *Plant(g1).take(2000))
    outcome = engine.solve()
    assert outcome.status == "failed" and "holds no sample" in outcome.reason
    assert engine.stats.solve_failures == 1


@pytest.mark.parametrize("input_noise", [0.0, 1e-3, 1e-2])
def test_standing_still_keeps_the_last_good_model_and_never_publishes_garbage(g1, input_noise):
    """Good data, then the robot stands still (constant command, possibly with jitter) for 30 s
    of stamps, 1.5 windows: every model published stays near the truth; once the window holds
    no excitation, the solve says why and the last good model is republished, marked stale."""
    engine = StreamingEngine(CONFIG)
    plant = Plant(g1)
    feed(engine, *plant.take(3000))
    published = engine.solve()
    assert published.ok
    worst, stale = pole_error(g1, published), None
    for _ in range(60):  # 30 s at 2 solves per second
        feed(engine, *plant.take(50, constant=0.4, input_noise=input_noise))
        outcome = engine.solve()
        if outcome.ok:
            published = outcome
            worst = max(worst, pole_error(g1, outcome))
            assert np.all(np.abs(outcome.result.linear.poles) < 1.0)
        else:
            stale = stale_model_message(published, outcome)
            assert result_messages(outcome, 0) == []
    assert worst < 0.15  # early windows of the transition are noisier, never absurd
    assert outcome.status == "not_exciting" and "not persistently exciting" in outcome.reason
    topic, _, message = stale
    assert topic == "~/model" and '"stale": true' in message["data"] and "not persistently exciting" in message["data"]
    level = diagnostics_message(engine.stats, outcome, 10**9)["status"][0]
    assert level["level"] == 1 and "publishing the last good model as stale" in level["message"]
    assert engine.stats.not_exciting >= 1
    feed(engine, *plant.take(2000))  # moving again: a fresh model
    assert engine.solve().ok


def test_limits_are_enforced_with_the_field_named():
    for changes, field in (({"window": MAX_WINDOW + 1}, "window"), ({"tau_max": MAX_TAU_MAX + 1}, "tau_max"),
                           ({"window": "4000"}, "window"), ({"partition": (0.5, "x")}, "partition"),
                           ({"min_excitation": 2.0}, "min_excitation"), ({"sample_rate": float("nan")}, "sample_rate")):
        with pytest.raises(UsageError, match=f"^{field}: "):
            EngineConfig(**changes).validated()


def test_big_windows_are_recomputed_in_bounded_memory():
    """The periodic exact recomputation over the whole window works in blocks of CHUNK rows
    (a W x (2 tau_max + 1) lag matrix would be 0.8 GB at W = 200 000, tau_max = 250)."""
    rng = np.random.default_rng(2)
    v, y = rng.normal(size=200_000), rng.normal(size=200_000)
    sums = correlation_window._lag_products(v, y, 250)
    centre = v[250:-250]
    np.testing.assert_allclose(sums[0, 250], centre @ centre, rtol=1e-12)
    np.testing.assert_allclose(sums[1, 250 + 3], y[250:-250] @ v[247:-253], rtol=1e-9)
