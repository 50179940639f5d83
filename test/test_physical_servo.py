"""The servo loop's physical form (``diagnosis.physical_servo``): its recursion, the constants it
recovers from a simulated position servo given as runs from rest, and the held-back choice between
it and the servo loop's maps, both ways."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.diagnosis.actuators import GRAVITY, ServoArm, servo_runs_record
from hammer_ros.diagnosis.physical_servo import PhysicalServoFit, choose_servo_form
from hammer_ros.diagnosis.servo_loop import ServoFit
from hammer_ros.identification import compiled_loops


def test_compiled_and_fallback_physical_loops_agree():
    pytest.importorskip("numba")
    rng = np.random.default_rng(2)
    u = np.repeat(rng.uniform(-1.0, 1.0, 40), 100)
    constants = (0.05, 0.01, 0.002, -1.2, 0.15, 3e-4)
    compiled = compiled_loops.physical_servo_loop(u, 0.1, *constants, compiled=True)
    fallback = compiled_loops.physical_servo_loop(u, 0.1, *constants, compiled=False)
    assert np.ptp(compiled) > 1.0  # the loop follows the steps
    np.testing.assert_allclose(compiled, fallback, rtol=0, atol=1e-12)


def test_the_physical_loop_matches_its_recursion_by_hand():
    """w(k+1) = w(k) + sat_T(K (u - y)) - G sin(y - p) - B w - C sign(w), y(k+1) = y(k) + w(k+1)."""
    gain, limit, gravity, angle, viscous, coulomb = 0.5, 0.3, 0.1, -0.2, 0.2, 0.01
    y = compiled_loops.physical_servo_loop(np.ones(3), 0.0, gain, limit, gravity, angle, viscous, coulomb)
    w1 = min(gain * 1.0, limit) - gravity * np.sin(0.0 - angle)  # at rest: no friction yet
    y1 = w1
    w2 = w1 + min(gain * (1.0 - y1), limit) - gravity * np.sin(y1 - angle) - viscous * w1 - coulomb * np.sign(w1)
    assert y[0] == 0.0 and y[1] == pytest.approx(y1, abs=1e-15) and y[2] == pytest.approx(y1 + w2, abs=1e-15)


@pytest.fixture(scope="module")
def servo_runs():
    arm = ServoArm()
    return arm, servo_runs_record(arm, seed=3)


def test_the_physical_form_recovers_a_p_servo_and_is_chosen(servo_runs):
    """A P-loop servo under gravity (8 estimation runs from rest at random starts): the physical form
    simulates the held-back runs better than the maps and is kept; its constants are the arm's:
    the error at which the torque saturates T/K, the sag of the gravity m g l / K, the angle at which
    the arm hangs, the Coulomb friction's dead band C/K (ratios in the units of the output: the
    inertia and the sample time cancel)."""
    arm, record = servo_runs
    choice = choose_servo_form(record.u_est, record.y_est, record.runs_est)
    assert isinstance(choice.fit, PhysicalServoFit) and isinstance(choice.maps, ServoFit)
    assert choice.held_back_rms["physical_servo"] < choice.held_back_rms["servo_loop"]
    gain, limit, _, gravity, angle, _, coulomb = choice.fit.theta
    assert limit / gain == pytest.approx(arm.torque_limit / arm.gain, rel=0.2)  # measured: 0.218 / 0.200
    assert gravity / gain == pytest.approx(arm.mass * GRAVITY * arm.length / arm.gain, rel=0.1)  # 0.0369 / 0.0368
    assert np.angle(np.exp(1j * (angle - arm.hanging_angle))) == pytest.approx(0.0, abs=0.05)  # 0.006 rad off
    assert coulomb / gain == pytest.approx(arm.coulomb / arm.gain, rel=0.4)  # 0.0089 / 0.0083
    assert choice.fit.details(record.u_est, record.y_est)["form"] == "physical_servo"


def test_the_maps_are_kept_where_the_physics_does_not_hold(servo_runs):
    """The same servo measured in degrees: G sin(y - p) with y in degrees is no pendulum's gravity,
    the maps simulate the held-back runs better and are kept."""
    _, record = servo_runs
    degrees = 180.0 / np.pi
    choice = choose_servo_form(degrees * record.u_est, degrees * record.y_est, record.runs_est)
    assert isinstance(choice.fit, ServoFit) and choice.fit is choice.maps
    assert choice.held_back_rms["servo_loop"] < choice.held_back_rms["physical_servo"]
