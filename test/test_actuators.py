"""Real-actuator physics (issue 35): the servo loop against a simulated position servo under gravity,
input coverage against a DC motor staircase, and the ties between extensions."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.diagnosis.actuators import (
    GRAVITY,
    DcMotor,
    ServoArm,
    dc_motor_staircase,
    servo_record,
    simulate_servo,
)
from hammer_ros.diagnosis.coverage import COVERAGE_BOUND, auto_split, input_coverage
from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.report import render_report
from hammer_ros.diagnosis.servo_loop import fit_servo_loop
from hammer_ros.diagnosis.split import Split, from_rest_at, split_record
from hammer_ros.identification import compiled_loops
from hammer_ros.identification.static_maps import PiecewiseLinearMap

SAMPLE_TIME = 0.01


def test_compiled_and_fallback_servo_loops_agree():
    pytest.importorskip("numba")
    rng = np.random.default_rng(1)
    f = PiecewiseLinearMap([-0.3, 0.0, 0.3], [-0.004, 0.0, 0.004], 0.0, 0.0)
    h = PiecewiseLinearMap([-1.0, 0.0, 1.0], [-0.0005, 0.0, 0.0005], 0.0004, 0.0004)
    phi = PiecewiseLinearMap([-0.01, 0.0, 0.01], [-0.002, 0.0, 0.002], 0.1, 0.1)
    u = np.repeat(rng.uniform(-1.0, 1.0, 40), 100)
    compiled = compiled_loops.servo_loop(u, 0.0, f, h, phi, 1e-4, compiled=True)
    fallback = compiled_loops.servo_loop(u, 0.0, f, h, phi, 1e-4, compiled=False)
    assert np.ptp(compiled) > 1.0  # the loop follows the steps
    np.testing.assert_allclose(compiled, fallback, rtol=0, atol=1e-12)


def test_the_servo_loop_matches_its_recursion_by_hand():
    """y(k+1) = y(k) + w(k) + f(u(k) - y(k)) - h(y(k)) - phi(w(k)) - c sign(w(k)), from rest at y0."""
    f = PiecewiseLinearMap([0.0], [0.0], 0.5, 0.5)
    h = PiecewiseLinearMap([0.0], [0.0], 0.1, 0.1)
    phi = PiecewiseLinearMap([0.0], [0.0], 0.2, 0.2)
    y = compiled_loops.servo_loop(np.ones(3), 0.0, f, h, phi, 0.01)
    y1 = 0.5 * 1.0  # w = 0: no friction yet
    w1 = y1
    y2 = y1 + w1 + 0.5 * (1.0 - y1) - 0.1 * y1 - 0.2 * w1 - 0.01
    assert y[0] == 0.0 and y[1] == pytest.approx(y1, abs=1e-15) and y[2] == pytest.approx(y2, abs=1e-15)


def test_the_servo_simulator_is_a_position_loop_under_gravity():
    arm = ServoArm()
    q = simulate_servo(arm, np.full(300, 0.5))
    counts = q / (2 * np.pi / arm.counts)
    assert np.allclose(counts, np.round(counts))  # quantised to the encoder
    weight = arm.mass * GRAVITY * arm.length
    sag = weight * np.sin(q[-1] - arm.hanging_angle) / arm.gain  # P loop: K (u - q) = gravity at rest
    assert abs(0.5 - q[-1] - sag) <= arm.coulomb / arm.gain + 2 * np.pi / arm.counts
    step = simulate_servo(arm, np.concatenate([np.zeros(50), np.full(150, 1.0)]), q0=0.0)
    rate = np.max(np.diff(step)) / SAMPLE_TIME
    inertia = arm.rotor_inertia + arm.mass * arm.length**2
    assert rate <= arm.torque_limit / arm.viscous * 1.05  # the torque limit bounds the speed
    assert rate > 0.3 * arm.torque_limit / arm.viscous * (1 - np.exp(-0.1 * arm.viscous / inertia))


@pytest.fixture(scope="module")
def servo():
    arm = ServoArm()
    return arm, servo_record(arm, seconds=4.0), servo_record(arm, seconds=4.0, torque_noise=0.0)


def test_the_servo_loop_finds_gravity_friction_and_the_torque_limit(servo):
    arm, record, clean = servo
    fit = fit_servo_loop(record.u_est, record.y_est)
    out = from_rest_at(fit.simulate, record.u_val, float(np.mean(record.y_val[:3])), record.u_est)
    floor = float(np.sqrt(np.mean((clean.y_val - record.y_val) ** 2)))  # the disturbance and the encoder
    assert np.sqrt(np.mean((out - record.y_val) ** 2)) <= 4.0 * floor
    f, h, _ = fit.layout.maps(fit.theta)
    scale = SAMPLE_TIME**2 / (arm.rotor_inertia + arm.mass * arm.length**2)  # torque -> output per sample^2
    q = np.linspace(np.quantile(record.y_est, 0.05), np.quantile(record.y_est, 0.95), 50)
    gravity = arm.mass * GRAVITY * arm.length * np.sin(q - arm.hanging_angle) * scale
    assert np.corrcoef(h(q), gravity)[0, 1] >= 0.85
    limit = arm.torque_limit * scale
    error = np.array([-0.6, 0.6])  # beyond the error at which the torque saturates (1.2 / 6 = 0.2 rad)
    assert np.ptp(f(error)) == pytest.approx(2 * limit, rel=0.25)
    assert fit.theta[-1] == pytest.approx(arm.coulomb * scale, rel=0.6)


@pytest.mark.parametrize("arm", [ServoArm(), ServoArm(mass=0.4, length=0.25, gain=10.0, torque_limit=1.8),
                                 ServoArm(mass=0.08, length=0.1, gain=3.0, damping_gain=0.05)],
                         ids=["nominal", "heavy-stiff", "light-soft-PD"])
def test_one_physics_one_cause_across_configurations(arm):
    """A position servo under gravity is named output_feedback with the servo loop at every load and
    gain, and the loop predicts the validation runs far better than the Hammerstein baseline."""
    record = servo_record(arm, seconds=4.0)
    d = diagnose(Split(record.u_est, record.y_est, record.u_val, record.y_val, continuous=False)).diagnosis
    assert d.cause == "output_feedback", d.candidates
    assert d.steps[0].structure.startswith("servo loop")
    assert d.gain >= 4.0
    assert next(e for e in d.evidence if e.test == "input_range").passed


def test_input_coverage_counts_samples_outside_and_their_memory():
    v_est = np.linspace(-1.0, 1.0, 1000)
    v_val = np.concatenate([np.zeros(100), np.full(10, 3.0), np.zeros(90)])
    coverage = input_coverage(v_est, v_val, memory=20)
    assert coverage.outside == pytest.approx(10 / 200)
    assert not coverage.passed and coverage.evidence().test == "input_range"
    assert coverage.evidence().bound == COVERAGE_BOUND
    assert np.all(coverage.covered[:100]) and not np.any(coverage.covered[100:130])
    assert np.all(coverage.covered[130:])
    assert input_coverage(v_est, np.clip(v_val, -1.0, 1.0), memory=20).passed


@pytest.fixture(scope="module")
def motor():
    return dc_motor_staircase(DcMotor())


def test_an_extrapolation_is_not_blamed_on_time_variation(motor):
    """The staircase's large negative steps lie only in the last 30 %: the default split's validation
    leaves the estimation range, the input_range row fails, the models are judged on the covered
    samples and the record (a Hammerstein plant: dead zone, then a first-order lag) gets no cause."""
    v, y = motor
    run = diagnose(split_record(v, y, 0.7), order=1)
    d = run.diagnosis
    row = next(e for e in d.evidence if e.test == "input_range")
    assert not row.passed and row.value > 0.3
    assert d.cause != "time_varying" and d.cause == "none"
    assert d.coverage["judged_samples"] < d.coverage["validation_samples"]
    assert "outside the estimation range" in d.coverage["judged_on"]
    assert d.baseline.fit_percent > 90.0  # on the covered samples the map's own range predicts well
    assert "Input coverage: " + d.coverage["judged_on"] in render_report(run)  # the report says what was judged


def test_split_auto_picks_an_estimation_part_that_covers(motor):
    v, y = motor
    split = auto_split(v, y)
    assert "first 30 %" in split.note and not split.continuous
    assert input_coverage(split.v_est, split.v_val, 0).passed
    assert np.min(split.v_est) <= np.min(split.v_val) and np.max(split.v_est) >= np.max(split.v_val)


def test_cli_split_auto(tmp_path, capsys, motor):
    v, y = motor
    path = tmp_path / "motor.csv"
    np.savetxt(path, np.column_stack([v, y]), delimiter=",", header="u,y", comments="")
    assert main(["diagnose", str(path), "--order", "1", "--split", "auto", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "first 30 %" in doc["split"] and doc["cause"] != "time_varying"
    row = next(e for e in doc["evidence"] if e["test"] == "input_range")
    assert row["passed"] and row["value"] <= row["bound"]
    assert main(["diagnose", str(path), "--split", "half"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--split" in err[0]


def test_the_servo_sample_bag_is_diagnosed_as_a_servo_loop(capsys):
    """bags/servo_arm (rosbag2, JointState with named joints, a Float64MultiArray command): the
    diagnosis of the elbow names its own position loop."""
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    assert main(["diagnose", str(repo / "bags" / "servo_arm"), "--config", str(repo / "msg_config" / "servo_arm.yaml"),
                 "--order", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["cause"] == "output_feedback" and doc["extended"]["form"] == "servo_loop"
    assert doc["gain"]["rms_ratio"] >= 5.0
    assert doc["extended"]["rms"] < 0.01  # rad, against a baseline near 0.03


def test_the_block_test_tells_a_better_model_from_one_within_noise():
    """``_block_t``: the log ratio of two validation outputs' block MSEs, t-tested. Two models with
    errors of one spread are within noise; 10 % less error on every block is significant, and a
    gain made by one block of a few large errors is not."""
    from hammer_ros.diagnosis.diagnose import _beats_the_baseline, _block_t

    rng = np.random.default_rng(4)
    n = 1000
    y = np.zeros(n)
    split = Split(np.zeros(10), np.zeros(10), np.zeros(n), y, continuous=False)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    t, blocks = _block_t(split, y - a, y - b)
    assert blocks == 20 and abs(t) < 2.1
    assert _beats_the_baseline(split, y - 0.9 * b, y - b)
    spike = b.copy()
    spike[:20] *= 10.0  # a few large errors in one block: the RMS ratio is 1.6, but 19 blocks are equal
    assert np.sqrt(np.mean(spike**2) / np.mean(b**2)) > 1.5
    assert not _beats_the_baseline(split, y - b, y - spike)
