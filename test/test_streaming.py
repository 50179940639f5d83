"""The streaming engine equals the batch core on the same window (paper 000 eq. 8), aligns and
screens timestamped streams, and keeps its samples across reconfiguration."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.errors import UsageError
from hammer_ros.identification.correlation import cross_correlation, weighted_cross_correlation
from hammer_ros.identification.correlation_least_squares import cls_from_correlations
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.methods import identify
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.streaming.config import EngineConfig
from hammer_ros.streaming.correlation_window import by_fft
from hammer_ros.streaming.engine import StreamingEngine


def cubic(v):
    return v + 4 * v**3


@pytest.fixture
def record(g1):
    rng = np.random.default_rng(7)
    n = 12_000
    v = rng.standard_normal(n) / (2 * np.pi)
    y = simulate_hammerstein(v, cubic, g1) + 0.002 * rng.standard_normal(n)
    t = 100.0 + np.arange(n) / 100.0
    return t, v, y


def feed_randomly(engine, t, v, y, seed=3, largest=700):
    """Feed both streams in interleaved batches of random sizes (the response lagging)."""
    rng = np.random.default_rng(seed)
    i = j = 0
    while i < t.size or j < t.size:
        m = int(rng.integers(1, largest))
        engine.add_excitation(t[i : i + m], v[i : i + m])
        i += m
        m = int(rng.integers(1, largest))
        engine.add_response(t[j : j + m], y[j : j + m])
        j += m


def assert_sums_match(snapshot, tau_max, reference):
    v, y = snapshot.v, snapshot.y
    np.testing.assert_allclose(snapshot.phi_vv, reference(v, v, tau_max), rtol=0, atol=1e-9)
    np.testing.assert_allclose(snapshot.phi_yv, reference(v, y, tau_max), rtol=0, atol=1e-9)
    np.testing.assert_allclose(snapshot.phi_yvv, reference(v**2, y, tau_max), rtol=0, atol=1e-9)


@pytest.mark.parametrize("tau_max", [25, 150])  # direct lag loops; FFT block sums (but for the shortest)
def test_sliding_window_sums_equal_batch_cross_correlation(record, tau_max):
    t, v, y = record
    assert by_fft(1000, tau_max) == (tau_max == 150) and not by_fft(100, 150)
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=1500, tau_max=tau_max))
    feed_randomly(engine, t, v, y, largest=5000)  # batches shorter and longer than the window
    snap = engine.snapshot()
    assert engine.stats.aligned == t.size and engine.stats.gaps == 0
    np.testing.assert_array_equal(snap.v, v[-1500:])
    np.testing.assert_array_equal(snap.y, y[-1500:])
    assert snap.weight == 1500 - 2 * tau_max  # N + 1 products per lag (paper 000 Remark 2)
    assert_sums_match(snap, tau_max, cross_correlation)


def test_sliding_sums_stay_exact_at_every_step_of_a_long_stream():
    """Blocks of centres enter and leave the window in pieces of every size (1 sample to more
    than the window); after each piece the sums are the batch correlations of the window."""
    rng = np.random.default_rng(8)
    n = 30_000
    t = np.arange(n) / 100.0
    v = rng.standard_normal(n)
    y = np.convolve(v, [0.0, 0.5, 0.3], "full")[:n] + 0.1 * v**2
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=700, tau_max=20))
    i, checked = 0, 0
    while i < n:
        m = int(rng.choice([1, 3, 50, 255, 700, 1500]))
        engine.add_excitation(t[i : i + m], v[i : i + m])
        engine.add_response(t[i : i + m], y[i : i + m])
        i += m
        snap = engine.snapshot()
        if snap.v.size >= 2 * 20 + 1:
            aligned = engine.stats.aligned  # (the newest sample waits for the next grid point)
            np.testing.assert_array_equal(snap.v, v[aligned - snap.v.size : aligned])
            assert_sums_match(snap, 20, cross_correlation)
            checked += 1
    assert checked > 50 and engine.stats.aligned >= n - 1


def test_sums_before_the_window_is_full_use_every_sample(record):
    t, v, y = record
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=5000, tau_max=30))
    engine.add_excitation(t[:800], v[:800])
    engine.add_response(t[:800], y[:800])
    snap = engine.snapshot()
    assert snap.v.size == 800 and engine.stats.window_fill == pytest.approx(800 / 5000)
    assert_sums_match(snap, 30, cross_correlation)


def test_a_batch_longer_than_the_window_sums_only_its_newest_window(record, monkeypatch):
    """A live flush or a replay batch far longer than W: the lag products of samples that have
    left the window by the end of the add are never formed (they would be added, then
    subtracted); the sums are still the batch correlations of the window."""
    import hammer_ros.streaming.correlation_window as correlation_window

    t, v, y = record
    summed = []
    products = correlation_window._lag_products
    monkeypatch.setattr(correlation_window, "_lag_products",
                        lambda v, y, tau_max, weights=None: summed.append(v.size) or products(v, y, tau_max, weights))
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=1000, tau_max=20))
    engine.add_excitation(t[:200], v[:200])
    engine.add_response(t[:200], y[:200])
    summed.clear()
    engine.add_excitation(t[200:], v[200:])  # 11 800 samples in one batch
    engine.add_response(t[200:], y[200:])
    snap = engine.snapshot()
    assert sum(summed) <= 1000 + 2 * 20 and snap.v.size == 1000
    np.testing.assert_array_equal(snap.v, v[engine.stats.aligned - 1000 : engine.stats.aligned])
    assert_sums_match(snap, 20, cross_correlation)


@pytest.mark.parametrize("tau_max", [20, 150])
def test_forgetting_sums_equal_weighted_batch_reference(record, tau_max):
    t, v, y = record
    lam = 0.998
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=1000, tau_max=tau_max, forgetting=lam))
    feed_randomly(engine, t, v, y, seed=11)
    snap = engine.snapshot()
    np.testing.assert_allclose(snap.phi_vv, weighted_cross_correlation(v, v, tau_max, lam), rtol=0, atol=1e-9)
    np.testing.assert_allclose(snap.phi_yv, weighted_cross_correlation(v, y, tau_max, lam), rtol=0, atol=1e-9)
    np.testing.assert_allclose(snap.phi_yvv, weighted_cross_correlation(v**2, y, tau_max, lam), rtol=0, atol=1e-9)
    # one batch longer than the window: every centre is still weighted in
    whole = StreamingEngine(EngineConfig(sample_rate=100.0, window=1000, tau_max=20, forgetting=lam))
    whole.add_excitation(t, v)
    whole.add_response(t, y)
    np.testing.assert_allclose(whole.snapshot().phi_yv, weighted_cross_correlation(v, y, 20, lam), rtol=0, atol=1e-9)
    # lambda = 1 is the unweighted estimator of eq. 8
    np.testing.assert_allclose(weighted_cross_correlation(v, y, 20, 1.0), cross_correlation(v, y, 20), atol=1e-15)


@pytest.mark.parametrize(("method", "partition"), [("cls-markov", None), ("cls-arx", None), ("nls-arx", None),
                                                   ("plls-hammerstein", None), ("cls-markov", (-0.1, 0.0, 0.1))])
def test_streaming_solve_equals_batch_identify_on_the_same_window(record, g1, method, partition):
    t, v, y = record
    config = EngineConfig(sample_rate=100.0, window=4000, tau_max=60, method=method, partition=partition)
    engine = StreamingEngine(config)
    feed_randomly(engine, t, v, y, seed=5)
    outcome = engine.solve()
    assert outcome.ok, outcome.reason
    batch = identify(method, v[-4000:], y[-4000:], config.identify_options())
    assert root_rss_error(batch.poles, outcome.result.poles) < 1e-9
    np.testing.assert_allclose(outcome.result.linear.b, batch.linear.b, atol=1e-9)
    assert outcome.doc["method"] == method and outcome.samples == 4000
    assert outcome.stamp == pytest.approx(t[-1])
    assert engine.stats.solves == 1
    if method.startswith("cls"):
        assert root_rss_error(g1.poles, outcome.result.poles) < 0.1  # and it is the right plant


def test_refine_solves_equal_batch_identify_refine_on_the_same_window(record, g1):
    """The node's ``refine`` parameter: each solve is ``identify --refine`` of the window."""
    from hammer_ros.identification.refinement import refine_result

    t, v, y = record
    config = EngineConfig(sample_rate=100.0, window=4000, tau_max=60, method="nls-arx", refine=True)
    engine = StreamingEngine(config)
    feed_randomly(engine, t, v, y, seed=5)
    outcome = engine.solve()
    assert outcome.ok, outcome.reason
    batch = identify("nls-arx", v[-4000:], y[-4000:], config.identify_options())
    refined = refine_result(batch, v[-4000:], y[-4000:])
    assert root_rss_error(refined.poles, outcome.result.poles) < 1e-9
    assert outcome.doc["refined"]["cost"] <= outcome.doc["refined"]["cost_start"]
    assert root_rss_error(g1.poles, outcome.result.poles) < 0.05
    with pytest.raises(UsageError, match="refine"):
        EngineConfig(refine="yes").validated()


def test_forgetting_solve_equals_cls_on_weighted_correlations(record):
    t, v, y = record
    config = EngineConfig(sample_rate=100.0, window=3000, tau_max=60, forgetting=0.9995, method="cls-markov")
    engine = StreamingEngine(config)
    feed_randomly(engine, t, v, y)
    outcome = engine.solve()
    assert outcome.ok, outcome.reason
    batch = cls_from_correlations(weighted_cross_correlation(v, v, 60, 0.9995),
                                  weighted_cross_correlation(v, y, 60, 0.9995),
                                  v[-3000:], y[-3000:], config.identify_options(), structure="markov")
    assert root_rss_error(batch.poles, outcome.result.poles) < 1e-9


def test_zero_order_hold_and_linear_alignment_of_two_rates():
    """Excitation at 100 Hz, response at 300 Hz with an offset: the grid is the 100 Hz one."""
    t_v = 5.0 + np.arange(500) / 100.0
    t_y = 5.0 + 0.0013 + np.arange(1500) / 300.0
    v = np.sin(2 * np.pi * 1.1 * t_v) + 0.3 * np.cos(2 * np.pi * 7 * t_v)
    y = np.cos(2 * np.pi * 2.3 * t_y)
    expected_grid = t_v[t_v >= t_y[0]]
    for interpolation in ("zoh", "linear"):
        engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=1000, tau_max=5, interpolation=interpolation))
        for k in range(0, 1500, 37):  # response arrives in its own batches
            engine.add_response(t_y[k : k + 37], y[k : k + 37])
            engine.add_excitation(t_v[k // 3 : (k + 37) // 3], v[k // 3 : (k + 37) // 3])
        engine.add_excitation(t_v, v)  # the rest (already accepted ones count as duplicate/late)
        snap = engine.snapshot()
        grid = expected_grid[expected_grid <= t_y[-1] + 1e-4]
        assert snap.v.size == grid.size
        np.testing.assert_array_equal(snap.v, v[np.searchsorted(t_v, grid)])
        if interpolation == "zoh":
            held = y[np.searchsorted(t_y, grid, side="right") - 1]
            np.testing.assert_array_equal(snap.y, held)
        else:
            np.testing.assert_allclose(snap.y, np.interp(grid, t_y, y), atol=1e-12)


@pytest.mark.parametrize("missing", [None, 700])
def test_zero_order_hold_of_a_stream_at_the_grid_rate_with_another_phase(missing):
    """Both streams at the grid rate, the response 0.37 of a period later (two clocks, or the
    arrival stamps of two topics): each grid point holds the response's previous sample. With a
    response sample missing, the point after it holds the one before (no phase at all)."""
    n = 3000
    t = 20.0 + np.arange(n) / 1000.0
    rng = np.random.default_rng(4)
    v, y = rng.standard_normal(n), rng.standard_normal(n)
    t_y = t + 0.37e-3
    keep = np.ones(n, bool)
    if missing is not None:
        keep[missing] = False
    engine = StreamingEngine(EngineConfig(sample_rate=1000.0, window=n, tau_max=5))
    for k in range(0, n, 250):
        engine.add_streams({"excitation": (t[k : k + 250], v[k : k + 250]),
                            "response": (t_y[k : k + 250][keep[k : k + 250]], y[k : k + 250][keep[k : k + 250]])})
    snap = engine.snapshot()
    grid = t[1 : 1 + snap.v.size]  # the grid starts at the first excitation stamp after the response's first
    np.testing.assert_array_equal(snap.v, v[1 : 1 + snap.v.size])
    held = np.searchsorted(t_y[keep], grid + 1e-5, side="right") - 1
    np.testing.assert_array_equal(snap.y, y[keep][held])
    assert snap.v.size >= n - 2


def test_grid_at_a_configured_rate_below_the_stream_rates():
    t = np.arange(1000) / 200.0
    engine = StreamingEngine(EngineConfig(sample_rate=50.0, window=500, tau_max=5))
    engine.add_excitation(t, t * 2.0)
    engine.add_response(t, -t)
    snap = engine.snapshot()
    np.testing.assert_allclose(snap.v, 2.0 * np.arange(snap.v.size) / 50.0, atol=1e-12)
    np.testing.assert_allclose(snap.y, -np.arange(snap.v.size) / 50.0, atol=1e-12)
    assert snap.v.size == 250


def test_inferred_rate_uses_the_excitation_stamps_as_the_grid():
    rng = np.random.default_rng(2)
    t = 1.7e9 + np.cumsum(0.01 + 0.0005 * rng.uniform(-1, 1, 3000))  # jittered 100 Hz, epoch stamps
    engine = StreamingEngine(EngineConfig(window=2000, tau_max=10))
    engine.add_excitation(t, np.sin(t - t[0]))
    engine.add_response(t + 0.002, np.cos(t - t[0]))
    assert engine.sample_rate == pytest.approx(100.0, rel=0.03)
    snap = engine.snapshot()
    assert engine.stats.aligned == t.size - 1  # the first precedes the first response sample
    np.testing.assert_array_equal(snap.v, np.sin(t - t[0])[-2000:])


def test_gap_restarts_the_window_and_is_counted():
    fs = 100.0
    t = np.concatenate([np.arange(600), np.arange(750, 1500)]) / fs  # a 1.5 s hole in both streams
    v = np.sin(0.37 * np.arange(t.size))
    engine = StreamingEngine(EngineConfig(sample_rate=fs, window=1000, tau_max=10))
    engine.add_excitation(t, v)
    engine.add_response(t + 0.2 / fs, 2 * v)
    assert engine.stats.gaps == 1
    snap = engine.snapshot()
    # only samples after the gap are in the window (from the first grid point with both streams)
    np.testing.assert_array_equal(snap.v, v[601:])
    assert_sums_match(snap, 10, cross_correlation)


def test_response_gap_alone_also_restarts_the_window():
    fs = 100.0
    t = np.arange(2000) / fs
    ty = np.delete(t, np.arange(900, 960))
    engine = StreamingEngine(EngineConfig(sample_rate=fs, window=5000, tau_max=10))
    engine.add_excitation(t, np.arange(t.size, dtype=float))
    engine.add_response(ty, np.ones(ty.size))
    assert engine.stats.gaps == 1
    np.testing.assert_array_equal(engine.snapshot().v, np.arange(960, 2000, dtype=float))


def test_nan_late_and_duplicate_samples_are_skipped_and_counted():
    t = np.arange(100) / 100.0
    v = np.arange(100, dtype=float)
    v[[5, 17]] = np.nan
    v[30] = np.inf
    t_bad = t.copy()
    t_bad[40] = np.nan
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=100, tau_max=3))
    accepted = engine.add_excitation(t_bad, v)
    assert accepted == 96
    assert engine.add_excitation([t[50], t[99], t[98]], [1.0, 2.0, 3.0]) == 0
    engine.add_response(t, np.zeros(100))
    stats = engine.stats
    assert (stats.nan_skipped, stats.duplicate, stats.late) == (4, 1, 2)
    assert stats.received_excitation == 103 and stats.received_response == 100
    snap = engine.snapshot()
    assert snap.v.size == 100 and np.all(np.isfinite(snap.v))
    assert snap.v[5] == 4.0  # zero-order hold over the skipped sample


def test_reconfigure_window_and_tau_max_keeps_samples(record):
    t, v, y = record
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=3000, tau_max=20))
    engine.add_excitation(t[:5000], v[:5000])
    engine.add_response(t[:5000], y[:5000])
    engine.reconfigure(window=2000)
    snap = engine.snapshot()
    np.testing.assert_array_equal(snap.v, v[3000:5000])
    assert_sums_match(snap, 20, cross_correlation)
    engine.reconfigure(tau_max=40, window=4000)  # grows: keeps the 2000 it has, fills up again
    snap = engine.snapshot()
    np.testing.assert_array_equal(snap.v, v[3000:5000])
    assert_sums_match(snap, 40, cross_correlation)
    feed_randomly(engine, t[5000:9000], v[5000:9000], y[5000:9000])
    snap = engine.snapshot()
    np.testing.assert_array_equal(snap.v, v[5000:9000])
    assert_sums_match(snap, 40, cross_correlation)
    engine.reconfigure(method="cls-arx", order=2, delay=1)
    assert engine.config.method == "cls-arx" and engine.snapshot().v.size == 4000


@pytest.mark.parametrize(("change", "field"), [
    ({"window": 10}, "window"), ({"tau_max": 0}, "tau_max"), ({"forgetting": 1.5}, "forgetting"),
    ({"method": "magic"}, "method"), ({"delay": 5}, "delay"), ({"interpolation": "cubic"}, "interpolation"),
    ({"sample_rate": -1.0}, "sample_rate"), ({"bogus": 1}, "bogus"), ({"window": 100, "tau_max": 60}, "window"),
])
def test_invalid_reconfiguration_is_rejected_naming_the_field(change, field):
    engine = StreamingEngine(EngineConfig(sample_rate=100.0))
    with pytest.raises(UsageError, match=f"^{field}:"):
        engine.reconfigure(**change)
    assert engine.config == EngineConfig(sample_rate=100.0)


def test_solve_reports_why_not(g1):
    t = np.arange(3000) / 100.0
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=4000, tau_max=30, min_fill=0.5))
    engine.add_excitation(t[:1000], np.ones(1000))
    engine.add_response(t[:1000], np.ones(1000))
    outcome = engine.solve()
    assert not outcome.ok and outcome.reason.startswith("window 25 % full")
    engine.add_excitation(t[1000:], np.ones(2000))
    engine.add_response(t[1000:], np.ones(2000))
    outcome = engine.solve()
    assert not outcome.ok and outcome.reason.startswith("not persistently exciting")
    sine = StreamingEngine(EngineConfig(sample_rate=100.0, window=2000, tau_max=30))
    v = np.sin(2 * np.pi * 3.0 * t)
    sine.add_excitation(t, v)
    sine.add_response(t, simulate_hammerstein(v, cubic, g1))
    outcome = sine.solve()
    assert not outcome.ok and outcome.reason.startswith("not persistently exciting")
    assert outcome.condition_number > 1e8
    assert sine.stats.solve_errors == 1 and sine.stats.solves == 0


def test_batch_messages_put_the_last_sample_at_the_stamp():
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=100, tau_max=3))
    np.testing.assert_allclose(engine.message_stamps("excitation", 2.0, 5), [1.96, 1.97, 1.98, 1.99, 2.0])
    inferred = StreamingEngine(EngineConfig(window=100, tau_max=3))
    assert inferred.add_message("response", 1.0, np.arange(10.0)) == 0  # spacing unknown yet
    assert inferred.stats.unstamped == 1
    assert inferred.add_message("response", 1.1, np.arange(10.0)) == 10
    # spacing from the previous message while fs is unknown
    np.testing.assert_allclose(inferred.message_stamps("response", 1.2, 4), [1.125, 1.15, 1.175, 1.2])
    # the offsets of one (count, spacing) are reused, a new count or spacing gets its own, every result is a new array
    first = engine.message_stamps("excitation", 3.0, 5)
    first[:] = 0.0
    np.testing.assert_allclose(engine.message_stamps("excitation", 4.0, 5), [3.96, 3.97, 3.98, 3.99, 4.0])
    np.testing.assert_allclose(engine.message_stamps("excitation", 5.0, 3), [4.98, 4.99, 5.0])
    np.testing.assert_allclose(inferred.message_stamps("response", 1.3, 4), [1.225, 1.25, 1.275, 1.3])
    np.testing.assert_allclose(inferred.message_stamps("response", 1.5, 4), [1.35, 1.4, 1.45, 1.5])


def test_solve_outcome_is_the_document_of_its_result(record):
    """An ok solve carries ``result.to_json`` on its window (poles, zeros, F, fit) and the Markov
    parameters of that document; the next solve compares against it as the published model. Its fit
    and rms are the compiled evaluation's (``window_fit``): the reference's to rounding."""
    from hammer_ros.identification.result import fit_percent
    from hammer_ros.streaming.engine import solve_snapshot

    t, v, y = record
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=4000, tau_max=66))
    engine.add_excitation(t[:6000], v[:6000])
    engine.add_response(t[:6000], y[:6000])
    snapshot = engine.snapshot()
    outcome = solve_snapshot(snapshot)
    assert outcome.ok and outcome.status == "ok"
    reference = outcome.result.to_json(snapshot.v, snapshot.y)
    compiled = outcome.result.evaluate(snapshot.v, snapshot.y, compiled=True)
    assert outcome.doc == outcome.result.to_json(snapshot.v, snapshot.y, evaluation=compiled)
    assert {k: v for k, v in outcome.doc.items() if k not in ("fit_percent", "rms")} == {
        k: v for k, v in reference.items() if k not in ("fit_percent", "rms")}
    assert outcome.doc["rms"] == pytest.approx(reference["rms"], rel=1e-12)
    assert outcome.markov == tuple(outcome.doc["markov"]) and len(outcome.markov) == 31
    assert outcome.doc["poles"] == [[p.real, p.imag] for p in outcome.result.linear.poles]
    assert outcome.doc["fit_percent"] == pytest.approx(fit_percent(snapshot.y, outcome.result.simulate(snapshot.v)),
                                                       rel=1e-12)
    assert outcome.input_std == pytest.approx(float(np.std(snapshot.v)), rel=1e-12)
    engine.record(outcome)
    engine.add_excitation(t[6000:], v[6000:])
    engine.add_response(t[6000:], y[6000:])
    again = solve_snapshot(engine.snapshot())
    assert again.ok and again.doc["fit_percent"] > 90.0


def test_excitation_condition_number_is_that_of_the_toeplitz_matrix(record):
    """cond(R_p) of the symmetrised autocorrelation's p x p Toeplitz matrix, p = 2n + 1, as numpy's
    eigvalsh gives it; inf for a rank-deficient (constant) input."""
    import scipy.linalg

    from hammer_ros.streaming.engine import excitation_condition_number

    _, v, _ = record
    tau_max = 20
    phi = cross_correlation(v[:3000], v[:3000], tau_max)
    for order in (1, 3, 5):
        p = 2 * order + 1
        symmetrised = 0.5 * (phi[tau_max : tau_max + p] + phi[tau_max - p + 1 : tau_max + 1][::-1])
        eig = np.linalg.eigvalsh(scipy.linalg.toeplitz(symmetrised))
        assert excitation_condition_number(phi, tau_max, order) == pytest.approx(eig[-1] / eig[0], rel=1e-9)
    constant = cross_correlation(np.ones(200), np.ones(200), tau_max)
    with np.errstate(all="ignore"):
        assert excitation_condition_number(constant, tau_max, 3) > 1e12
