"""A servo step as Humble records it (issue 50's acceptance, on a simulated recording): rosbag2
SQLite storage with Humble's metadata (version 5, no stored message definitions), the set point a
JointState at 1 Hz with every header stamp zero, the state a JointState at 25 Hz, the joint at
rest at its first set point when the recording starts, one step. Every piece must work together:
the .db3 reader, the held set point, the zero stamps, the step input, the simulation from rest."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from held_setpoint import CONFIG, model_on, played_into_node, pole, write_bag
from scipy import optimize, signal
from test_bag_formats import make_humble

RATE = 25.0
LEVELS = np.concatenate([np.full(12, 0.35), np.full(38, 1.15)])  # rad: at rest, one step at 12 s, 50 s in all


@pytest.fixture(scope="module")
def humble(tmp_path_factory):
    root = tmp_path_factory.mktemp("humble")
    state = write_bag(root / "jazzy", LEVELS.size, levels=LEVELS, rate=RATE, sqlite=True, seed=5)
    make_humble(root / "jazzy", root / "humble")
    (root / "config.yaml").write_text(CONFIG + f"    sample_rate: {RATE}\n")
    return root, state


def identify(root, *options: str) -> dict:
    done = subprocess.run([sys.executable, "-m", "hammer_ros.cli", "identify", str(root / "humble"), "--config",
                           str(root / "config.yaml"), "--json", *options], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def output_error_fit(u: np.ndarray, y: np.ndarray) -> float:
    """The ten lines of scipy a user writes: a second-order output-error model (static gain g, poles
    r e^(+-i theta), the numerator split c, an offset), from rest at the first output, fitted on the
    simulation error; its fit %."""
    def simulate(p):
        g, r, theta, c, offset = p
        a = [1.0, -2 * r * np.cos(theta), r * r]
        b = [0.0, g * sum(a) * c, g * sum(a) * (1 - c)]
        zi = signal.lfilter_zi(b, a) * (y[0] - offset) / g
        return signal.lfilter(b, a, u, zi=zi)[0] + offset

    p = optimize.least_squares(lambda p: simulate(p) - y, [1.0, 0.8, 0.2, 0.5, 0.0],
                               bounds=([0.1, 0.0, 0.0, 0.0, -5], [10, 0.999, np.pi, 1.0, 5])).x
    return 100 * (1 - np.linalg.norm(y - simulate(p)) / np.linalg.norm(y - y.mean()))


def test_refined_identification_of_a_humble_servo_step_fits_like_an_output_error_fit(humble):
    root, state = humble
    refined = identify(root, "--refine", "--order", "2")
    assert refined["runs"] == 1
    held = np.repeat(LEVELS, int(RATE))
    reference = output_error_fit(held[: state.size], state)
    assert reference > 97.0  # the yardstick itself: it explains the step
    assert refined["fit_percent"] >= 90.0, refined
    truth = pole(RATE)
    found = complex(*max(refined["poles"], key=lambda p: p[1]))
    assert abs(found - truth) < 0.05, (found, truth)


def test_the_default_method_on_a_step_fits_or_warns(humble):
    root, _ = humble
    doc = identify(root, "--order", "2")
    codes = {w["code"] for w in doc["warnings"]}
    assert doc["fit_percent"] >= 90.0 or codes & {"input_not_white", "poor_fit", "not_exciting"}, doc


@pytest.mark.ros
def test_the_node_identifies_the_humble_step_played_live_at_twice_its_speed(humble, ros_env, tmp_path):
    """The acceptance's live line: the recording's two topics played as recorded at 2x into
    ``hammer-ros node`` (a params file naming them, 50 Hz grid, window 1000, plls-hammerstein,
    order 2): ``~/model`` arrives with at least 500 samples in its window, with no gap, the set
    point held, the 25 Hz state interpolated onto the grid, and the servo's slowest pole."""
    root, _ = humble
    with played_into_node(root / "humble", "    sample_rate: 50.0\n    window: 1000\n    method: plls-hammerstein\n"
                          "    order: 2\n    solve_rate: 2.0\n    diagnosis_period: 0.0\n", ros_env, tmp_path) as live:
        _, listener, models, diagnostics = live
        model = model_on(listener, models)
        slowest = max(abs(complex(re, im)) for re, im in model["poles"])  # plls without --refine: biased a little
        assert slowest < 1.0 and abs(slowest - abs(pole(50.0))) < 0.08, model
        status = listener.wait_for(lambda: diagnostics and diagnostics[-1], what="diagnostics")
        assert int(status["gaps"]) == 0 and status["excitation_held"] == "True", status
