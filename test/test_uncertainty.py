"""Confidence bounds (poles_std, zeros_std, gain_std, nonlinearity.points_std) against Monte Carlo ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.identification.methods import IdentifyOptions, identify
from hammer_ros.tools.uncertainty_check import SYSTEMS, Z95, _matched, monte_carlo, record

RUNS = 30  # per system; ~0.1 s per realisation for both methods


@pytest.mark.parametrize("method", ["cls-markov", "plls-hammerstein"])
def test_pole_intervals_cover_the_truth_at_their_nominal_rate(method):
    """The issue's check (three systems, 30 dB, N = 6000, 30 realisations): 95 % intervals cover the true
    poles' parts in 88-99 % of cases pooled (binomial sd ~2 % over ~330 intervals), no system below 85 %,
    and the median reported sd is 0.5-2 x the Monte Carlo spread (measured 0.82-1.16)."""
    rows = [monte_carlo(system, method, RUNS) for system in SYSTEMS]
    pooled = sum(r["coverage"] * r["intervals"] for r in rows) / sum(r["intervals"] for r in rows)
    assert 0.88 <= pooled <= 0.99, rows
    assert all(r["coverage"] >= 0.85 for r in rows), rows
    assert all(0.5 <= ratio <= 2.0 for r in rows for ratio in r["sd_ratio"]), rows


def _coverage(errors: list, sds: list) -> float:
    errors, sds = np.abs(np.concatenate(errors)), np.concatenate(sds)
    return float(np.mean(errors <= Z95 * sds))


def test_cls_zeros_gain_and_map_points_are_calibrated():
    """G1 with F = v + 4 v^3 (in CLS's cubic class): the zeros' real parts and the gain figure
    h_1 F'(mean v) are covered at about their nominal rate; the sd of the unit-slope map
    F(u) / F'(mean v) on |u| <= 0.3 (2 input sds) is 0.7-1.5 x its Monte Carlo spread (measured
    0.95-1.2). Its coverage is not checked: CLS mu-Markov's step 2 has an errors-in-variables bias of
    order 1/N from the 30 noisy Markov taps it filters with (docs/methods.md, about 1.5 sd at u = 0.3)."""
    system = SYSTEMS[0]
    grid = np.linspace(-0.3, 0.3, 7)
    zeros, gains, points, points_std = ([], []), ([], []), [], []
    for run in range(RUNS):
        v, y = record(system, 100 + run)
        result = identify("cls-markov", v, y, IdentifyOptions(order=3, delay=1))
        doc = result.to_json(v, y)
        z, sd = _matched(system.linear.zeros, doc["zeros"], doc["zeros_std"])
        zeros[0].append(z.real - system.linear.zeros.real)
        zeros[1].append(sd[:, 0])
        slope = 1.0 + 12.0 * v.mean() ** 2  # F'(mean v)
        gains[0].append([doc["gain"] - system.linear.markov_parameters(2)[1] * slope])
        gains[1].append([doc["gain_std"]])
        points.append(result.nonlinearity(grid) - system.nonlinearity(grid) / slope)
        points_std.append(result.uncertainty.points_std(result.nonlinearity, grid))
    for name, (errors, sds) in (("zeros", zeros), ("gain", gains)):
        assert 0.85 <= _coverage(errors, sds) <= 0.99, name
    ratio = np.median(points_std, axis=0) / np.std(points, axis=0, ddof=1)
    assert np.all((0.7 <= ratio) & (ratio <= 1.5)), ratio


def test_plls_map_points_are_calibrated_on_a_map_in_its_class():
    """The dead zone of the third system on the partition (-0.05, 0.05), where PLLS's map class holds it:
    the knots' values and the map at the data's ends are covered at about the nominal rate."""
    system = SYSTEMS[2]
    errors, sds = [], []
    for run in range(RUNS):
        v, y = record(system, 200 + run)
        doc = identify("plls-hammerstein", v, y, IdentifyOptions(order=2, delay=1, partition=(-0.05, 0.05))).to_json(v)
        u, f = np.asarray(doc["nonlinearity"]["points"]).T
        errors.append(f - system.nonlinearity(u))
        sds.append(np.asarray(doc["nonlinearity"]["points_std"]))
    assert 0.88 <= _coverage(errors, sds) <= 0.99


@pytest.mark.parametrize("method, extra", [("cls-arx", []), ("cls-markov", []),
                                           ("cls-markov", ["--partition", "-0.05,0.05"]), ("plls-hammerstein", []),
                                           ("nls-markov", []), ("bf-hammerstein", [])])
def test_every_model_json_carries_aligned_bounds(method, extra, tmp_path, capsys):
    """identify --json: poles_std / zeros_std aligned with poles / zeros, a real pole's sd_im 0, points_std
    one per point, gain_std beside gain; all finite and positive."""
    v, y = record(SYSTEMS[2], 7)
    path = tmp_path / "record.npz"
    np.savez(path, u=v, y=y)
    assert main(["identify", str(path), "--method", method, "--order", "2", *extra, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    for roots in ("poles", "zeros"):
        sd = np.asarray(doc[f"{roots}_std"])
        assert sd.shape == (len(doc[roots]), 2) and np.all(np.isfinite(sd)) and np.all(sd[:, 0] > 0)
        assert np.all(sd[np.asarray(doc[roots])[:, 1] == 0, 1] == 0.0)
    points_std = doc["nonlinearity"]["points_std"]
    assert len(points_std) == len(doc["nonlinearity"]["points"]) and min(points_std) >= 0.0
    assert ("gain_std" in doc) == ("gain" in doc)


def test_refined_estimates_carry_the_output_error_covariance():
    """identify --refine: the sandwich of the simulation-error fit covers the true poles (resonant pair,
    tanh map, 20 realisations: measured 0.975, sd / spread 0.99-1.2)."""
    from hammer_ros.identification.refinement import refine_result

    system = SYSTEMS[1]
    errors, sds = [], []
    for run in range(20):
        v, y = record(system, 300 + run)
        result = refine_result(identify("cls-markov", v, y, IdentifyOptions(order=2, delay=1)), v, y)
        doc = result.to_json()
        p, sd = _matched(system.linear.poles, doc["poles"], doc["poles_std"])
        errors.append(np.concatenate([p.real - system.linear.poles.real, p.imag - system.linear.poles.imag]))
        sds.append(np.concatenate([sd[:, 0], sd[:, 1]]))
    assert 0.88 <= _coverage(errors, sds) <= 0.995


def test_a_solve_with_wide_bounds_is_uncertain_and_the_confident_model_stays():
    """The streaming engine: a window whose output is mostly noise (SNR -10 dB) gives a model whose
    pole intervals are wide; it is counted ``uncertain`` and the published model stays, which
    /diagnostics reports as a warning with the last model republished as stale."""
    from hammer_ros.messages.outputs import DIAGNOSTIC_WARN, diagnostics_message
    from hammer_ros.streaming.config import EngineConfig
    from hammer_ros.streaming.engine import StreamingEngine

    system = SYSTEMS[2]
    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=1500, tau_max=30, method="cls-arx", order=2,
                                          min_excitation=0.0))
    v, y = record(system, 400)
    v, y, t = v[:3000], y[:3000], np.arange(3000) / 100.0
    engine.add_excitation(t[:1500], v[:1500])
    engine.add_response(t[:1500], y[:1500])
    confident = engine.solve()
    assert confident.ok and engine.stats.uncertain == 0
    noisy = y[1500:] + 3.0 * np.std(y) * np.random.default_rng(1).standard_normal(1500)
    engine.add_excitation(t[1500:], v[1500:])
    engine.add_response(t[1500:], noisy)
    outcome = engine.solve()
    assert not outcome.ok and outcome.status == "uncertain" and outcome.reason.startswith("uncertain model: ")
    assert engine.stats.uncertain == 1 and engine.snapshot().published is confident.result
    status = diagnostics_message(engine.stats, outcome, 0)["status"][0]
    assert status["level"] == DIAGNOSTIC_WARN and status["message"].endswith("publishing the last good model as stale")
    assert {"key": "uncertain", "value": "1"} in status["values"]
    engine.reconfigure(max_relative_sd=0.0)  # off: the same window's model is published
    assert engine.solve().ok


def test_the_dashboard_draws_the_intervals():
    """The Foxglove channels of a solve: each pole's 95 % intervals of re, im and |p| around it, and the
    map's band F -+ 1.96 sd at every point drawn."""
    from hammer_ros.messages.dashboard import dashboard_messages
    from hammer_ros.messages.outputs import result_messages
    from hammer_ros.streaming.config import EngineConfig
    from hammer_ros.streaming.engine import StreamingEngine

    engine = StreamingEngine(EngineConfig(sample_rate=100.0, window=4000, tau_max=30, method="cls-arx", order=2))
    v, y = record(SYSTEMS[2], 500)
    t = np.arange(v.size) / 100.0
    engine.add_excitation(t, v)
    engine.add_response(t, y)
    outcome = engine.solve()
    channels = dict(dashboard_messages(result_messages(outcome, 1_000_000_000), 1_000_000_000))
    poles, fmap = channels["poles"], channels["nonlinearity"]
    for part in ("real", "magnitude"):
        value = np.array(poles[part])
        assert np.all(np.array(poles[f"{part}_lower"]) < value) and np.all(np.array(poles[f"{part}_upper"]) > value)
    sd = np.asarray(outcome.doc["poles_std"])[:, 0]
    assert np.allclose(np.array(poles["real_upper"]) - poles["real"], 1.96 * sd)
    assert len(fmap["y_lower"]) == len(fmap["y"]) and np.all(np.array(fmap["y_lower"]) <= fmap["y"])
    assert np.all(np.array(fmap["y_upper"]) > np.array(fmap["y_lower"]))


def test_a_fleet_change_inside_the_models_combined_intervals_is_not_reported():
    """The change test: a 10 % step in a time constant is a change when the models' sds are 1 % (the step
    is 7 combined sds) and is not when they are 5 % (1.4 combined sds: inside the intervals)."""
    from hammer_ros.fleet.changes import group_changes

    times = np.arange(12) * 86400.0
    values = np.r_[np.full(6, 1.0), np.full(6, 1.1)] * (1 + 0.003 * np.sin(np.arange(12)))
    for sd, reported in ((0.01, True), (0.05, False)):
        _, changes = group_changes("joint", times, {"time_constant": values}, sds={"time_constant": np.full(12, sd)})
        assert bool(changes) is reported, sd


def test_fleet_parquet_holds_the_bounds(tmp_path):
    """fleet.parquet: poles_std / zeros_std columns aligned with the poles, gain_std and the time constant's
    sd from the slowest pole (sd(|p|) / (|p| ln^2 |p|) / sample rate)."""
    import pyarrow.parquet as pq

    from hammer_ros.fleet.table import write_parquet

    v, y = record(SYSTEMS[2], 9)
    doc = identify("cls-markov", v, y, IdentifyOptions(order=2, delay=1)).to_json(v, y)
    row = {"path": "a.mcap", "group": "joint", "labels": {}, "start": 0.0, "end": 60.0, "model": doc}
    write_parquet([row], tmp_path / "fleet.parquet", sample_rate=100.0)
    flat = pq.read_table(tmp_path / "fleet.parquet").to_pylist()[0]
    assert flat["poles_std_re"] == [s[0] for s in doc["poles_std"]] and len(flat["zeros_std_im"]) == len(doc["zeros"])
    assert flat["gain_std"] == doc["gain_std"]
    slowest = int(np.argmax([abs(complex(*p)) for p in doc["poles"]]))
    radius, sd = abs(complex(*doc["poles"][slowest])), doc["poles_std"][slowest][0]  # a real pole
    assert flat["time_constant_std"] == pytest.approx(sd / (radius * np.log(radius) ** 2) / 100.0)


def test_a_pole_interval_across_the_unit_circle_makes_the_model_uncertain():
    """A slow pole (0.99) from a short, noisy record (3000 samples, output noise half the output's std):
    0.978 +- 1.96 x 0.014 reaches past 1, whatever max_relative_sd allows; the same plant from a long
    clean record (0.9900 +- 0.0006) is confident."""
    from hammer_ros.identification.linear import LinearModel
    from hammer_ros.streaming.engine import too_uncertain

    plant = LinearModel.from_zeros_poles([], [0.99])
    rng = np.random.default_rng(3)
    v = rng.standard_normal(20000) / (2.0 * np.pi)
    x = plant.simulate(v + 4 * v**3)
    short = identify("cls-arx", v[:3000], x[:3000] + 0.5 * np.std(x) * rng.standard_normal(3000),
                     IdentifyOptions(order=1))
    assert "crosses the unit circle" in too_uncertain(short, 1e6)
    long = identify("cls-arx", v, x + 0.03 * np.std(x) * rng.standard_normal(v.size), IdentifyOptions(order=1))
    assert too_uncertain(long, 0.25) == ""
