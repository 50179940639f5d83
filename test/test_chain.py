"""Compound explanations: the diagnosis extends its own extended model while a step gains."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from hammer_ros.diagnosis.chain import MIN_STEP_GAIN, constant_beyond, drifts, follow_output_nonlinearity
from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.extensions import ExtendedModel
from hammer_ros.diagnosis.split import Split, split_record
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.static_maps import PiecewiseLinearMap


def _record(seed: int, n: int, saturate: bool, path: bool):
    rng = np.random.default_rng(seed)
    v = signal.lfilter([1.0], [1.0, -0.5], rng.standard_normal(n))
    g = LinearModel.from_zeros_poles([], [0.85, 0.6 + 0.3j, 0.6 - 0.3j], 1.0)
    x = g.simulate(np.tanh(1.2 * v))
    y = np.minimum(x, np.quantile(x, 0.8)) if saturate else x
    if path:  # a second sensor path beside the saturated one
        y = y + signal.lfilter([0.0, 0.3], [1.0, -0.95], v)
    return v, y + 0.01 * np.std(y) * rng.standard_normal(n)


def test_two_effects_give_a_chain_of_two_steps():
    """A saturated Hammerstein branch and a linear path beside it: both are named, each step
    gaining, and the chain's model is better than any single extension."""
    v, y = _record(4, 4000, saturate=True, path=True)
    d = diagnose(split_record(v, y, 0.7), order=3).diagnosis
    doc = d.to_json()
    causes = [s["cause"] for s in doc["steps"]]
    assert set(causes[:2]) == {"parallel_path", "output_nonlinearity"}, doc["steps"]
    assert doc["cause"] == causes[0]
    assert all(s["gain"] >= MIN_STEP_GAIN for s in doc["steps"])
    product = np.prod([s["gain"] for s in doc["steps"]])
    assert np.isclose(doc["gain"]["rms_ratio"], product, rtol=1e-9)
    assert doc["extended"]["rms"] == doc["steps"][-1]["rms"]
    best_single = max(c["rms_ratio"] for c in doc["candidates"])  # every single extension's gain
    assert doc["gain"]["rms_ratio"] > MIN_STEP_GAIN * best_single
    assert doc["chain_stopped"]


def test_one_effect_gives_one_step_and_says_why_it_stopped():
    v, y = _record(5, 4000, saturate=False, path=True)
    doc = diagnose(split_record(v, y, 0.7), order=3).diagnosis.to_json()
    assert doc["cause"] == "parallel_path"
    assert [s["cause"] for s in doc["steps"]] == ["parallel_path"]
    assert "signature" in doc["chain_stopped"] or "gains" in doc["chain_stopped"]


def test_a_clean_record_has_no_chain():
    v, y = _record(6, 3000, saturate=False, path=False)
    doc = diagnose(split_record(v, y, 0.7), order=3).diagnosis.to_json()
    assert doc["cause"] == "none" and doc["steps"] == [] and doc["chain_stopped"] is None


def test_a_drifting_offset_is_a_further_step_with_its_slope():
    """A saturated Hammerstein branch whose output drifts by 0.3 of its standard deviation over
    the record: the saturation is named first, then the drift (``time_varying``), with a slope
    near the true one (the first step's fit absorbs a little of it) and a large gain; a
    separate validation record has no time axis to continue, so no drift is tried there."""
    v, y = _record(2, 4000, saturate=True, path=False)
    slope = 0.3 * np.std(y) / y.size
    result = diagnose(split_record(v, y + slope * np.arange(y.size), 0.7), order=3)
    doc = result.diagnosis.to_json()
    causes = [s["cause"] for s in doc["steps"]]
    assert causes[:2] == ["output_nonlinearity", "time_varying"], doc["steps"]
    assert doc["steps"][1]["gain"] > 2.0
    assert result.chain.models[1].details["drift"]["per_sample"] == pytest.approx(slope, rel=0.25)
    clean = diagnose(split_record(v, y, 0.7), order=3).diagnosis.to_json()
    assert "time_varying" not in [s["cause"] for s in clean["steps"]], clean["steps"]
    separate = Split(v[:2800], y[:2800] + slope * np.arange(2800), v[2800:], y[2800:] + slope * np.arange(2800, 4000),
                     continuous=False)
    assert not drifts(separate, result.chain.models[0], 0)


def test_an_output_map_chooses_a_constant_continuation_for_a_saturation():
    """Estimation data that reach the clip only in the held-back part: the map learns to stay
    constant beyond its data, where the last slope would run away."""
    rng = np.random.default_rng(1)
    v = np.concatenate([rng.uniform(-1.0, 1.0, 3000), rng.uniform(-1.0, 1.6, 1000)])
    y_true = np.minimum(v, 1.0)
    split = split_record(np.concatenate([v, rng.uniform(-1, 3, 1000)]),
                         np.concatenate([y_true, np.minimum(rng.uniform(-1, 3, 1000), 1.0)]), 0.8)
    identity = ExtendedModel("x", "identity", np.zeros(split.v_val.size), simulate=lambda u: np.asarray(u, float))
    step = follow_output_nonlinearity(split, identity, 0)
    assert step.details["output_map"]["continuation"] == "constant"
    assert np.max(np.abs(step.simulate(np.array([2.0, 3.0])) - 1.0)) < 0.05


def test_constant_beyond_keeps_the_map_inside_and_holds_it_outside():
    m = PiecewiseLinearMap(np.array([0.0, 1.0]), np.array([0.0, 2.0]), 1.0, 3.0)
    c = constant_beyond(m, -0.5, 1.5)
    grid = np.linspace(-0.5, 1.5, 9)
    assert np.allclose(c(grid), m(grid))
    assert np.allclose(c(np.array([-3.0, 9.0])), m(np.array([-0.5, 1.5])))


def test_an_extension_that_cannot_be_fitted_gives_its_reason_in_one_line():
    """A record too short for sliding windows and without spectral lines: the time-varying and
    periodic extensions raise NotFitted with a reason that names what is missing, and the
    diagnosis' ``fit`` turns it into a ``not_fitted`` row instead of a traceback."""
    from hammer_ros.diagnosis.evidence import spectral_lines, windowed_variation
    from hammer_ros.diagnosis.extensions import EXTENSIONS, Context, NotFitted, failure_reason
    from hammer_ros.diagnosis.hammerstein import fit_baseline

    v, y = _record(7, 160, saturate=False, path=False)
    split = split_record(v, y, 0.6)
    base = fit_baseline(split.v_est, split.y_est, 3, None)
    x_est = base.simulate(split.v_est)
    ctx = Context(split, base, spectral_lines(split.y_est - x_est, [split.v_est, x_est]),
                  windowed_variation(split.y_all, np.concatenate([x_est, split.validation_output(base.simulate)]), 0))
    reasons = {}
    for cause in ("time_varying", "periodic_disturbance"):
        try:
            EXTENSIONS[cause](ctx)
        except NotFitted as error:
            reasons[cause] = failure_reason(error)
    assert "samples" in reasons["time_varying"] and "\n" not in reasons["time_varying"]
    assert reasons["periodic_disturbance"] == "no spectral line in the estimation residual"
    assert failure_reason(ValueError("bad\nshape")) == "ValueError: bad shape"
    doc = diagnose(split, order=3).diagnosis.to_json()
    assert all(set(row) == {"cause", "reason"} and "\n" not in row["reason"] for row in doc["not_fitted"])
