"""The diagnosis of several runs (issue 50): whole runs for validation, no simulation, lag or
correlation across a boundary, a servo whose runs start from rest at their own positions, and
the real XL330 servo runs shipped in hammer_ros/data/xl330_servo_arm."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.diagnosis.actuators import (
    ServoArm,
    fit_physical_servo,
    physical_servo_runs,
    servo_runs_record,
)
from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.evidence import windowed_variation
from hammer_ros.diagnosis.residual_tests import residual_tests
from hammer_ros.diagnosis.split import Split, split_runs
from hammer_ros.errors import UsageError
from hammer_ros.identification.runs import Runs
from hammer_ros.identification.simulation_error import steady_state_filter

REPO = Path(__file__).resolve().parents[1]
XL330 = REPO / "hammer_ros" / "data" / "xl330_servo_arm"


def _lag(u: np.ndarray) -> np.ndarray:
    """A slow first-order block from rest at u(0): its output remembers the input for ~200 samples."""
    return steady_state_filter(np.array([0.0, 0.02]), np.array([1.0, -0.98]), u)


def test_whole_runs_are_held_out_and_said():
    rng = np.random.default_rng(0)
    runs = Runs.from_lengths([300] * 8)
    v = rng.standard_normal(runs.total)
    split = split_runs(v, _lag(v), runs)
    assert split.runs_est.count == 6 and split.runs_val.count == 2  # round(0.3 x 8) whole runs
    assert split.n_est == 1800 and not split.continuous and split.run_count == 8
    assert split.note == "whole runs: estimation on runs 1-6, validation on runs 7-8 of 8"
    two = split_runs(v[:600], v[:600], Runs.from_lengths([300, 300]), 0.9)
    assert two.runs_val.count == 1 and "validation on run 2 of 2" in two.note  # at least one, never all
    with pytest.raises(UsageError, match="--split"):
        split_runs(v, v, runs, 1.2)


def test_no_simulation_crosses_a_run_boundary():
    """Every validation run starts from rest at its own first outputs: changing the input of one
    run changes no other run's output (it does when the record is simulated as one)."""
    rng = np.random.default_rng(1)
    runs = Runs.from_lengths([400, 400, 400])
    v = np.repeat(rng.uniform(-1, 1, 60), 20)
    y = np.concatenate([_lag(part) for part in runs.split(v)])  # each run from rest at its first input
    split = Split(v, y, v, y, continuous=False, runs_est=runs, runs_val=runs)
    changed = v.copy()
    changed[:400] += 1.0
    moved = Split(v, y, changed, y, continuous=False, runs_est=runs, runs_val=runs)
    a, b = split.validation_output(_lag), moved.validation_output(_lag)
    assert np.max(np.abs(a[:400] - b[:400])) > 0.5
    np.testing.assert_array_equal(a[400:], b[400:])
    np.testing.assert_allclose(a, y, atol=1e-3)  # every run from the rest that explains its first outputs
    assert np.max(np.abs(split.estimation_output(_lag) - y)) < 1e-3
    whole = Split(v, y, v, y, continuous=False).validation_output(_lag)
    assert np.max(np.abs(whole - y)) > 0.05  # as one record the state runs over the boundaries


def test_correlations_and_windows_stay_within_runs():
    """Lagged products pair samples of one run only: the whiteness test's autocorrelation of runs
    is the sum of every run's own lagged products (a residual that jumps between runs, as a
    concatenation of runs recorded at other operating points does, is not white either way, but
    its products across a boundary are not counted), and no window of the time-variation test
    straddles two runs."""
    rng = np.random.default_rng(2)
    runs = Runs.from_lengths([500] * 6)
    u = rng.standard_normal(runs.total)
    e = rng.standard_normal(runs.total)
    z = (e - e.mean()) / e.std()
    by_hand = sum(np.array([part[tau:] @ part[: part.size - tau] for tau in range(4)]) for part in runs.split(z))
    whiteness = residual_tests(u, u + e, e, max_lag=3, runs=runs)[0]
    np.testing.assert_allclose(whiteness.values, (by_hand / by_hand[0])[1:], atol=1e-12)
    joined = residual_tests(u, u + e, e, max_lag=3)[0]
    assert not np.allclose(joined.values, whiteness.values, atol=1e-12)  # the boundary products count there
    windows = windowed_variation(u + e, u, 0, permutations=50, runs=Runs.from_lengths([1000, 1000, 1000]))
    length = 3000 // 25
    assert 16 <= windows.starts.size < 25
    for start in windows.starts:
        assert start // 1000 == (start + length - 1) // 1000


def test_servo_runs_from_their_own_rest_are_a_servo_loop():
    """A position servo under gravity, 8 estimation and 8 validation runs of 600 samples, each from
    rest at its own random start and ending anywhere: given as runs, the cause is the servo's own
    loop and its validation RMSE is at most the 7-parameter physical loop's (each run simulated
    from its own measured start)."""
    record = servo_runs_record(ServoArm(), seed=3)
    starts = record.runs_est.starts[1:]
    assert np.max(np.abs(record.y_est[list(starts)] - record.y_est[[s - 1 for s in starts]])) > 0.3  # jumps
    d = diagnose(Split(record.u_est, record.y_est, record.u_val, record.y_val, continuous=False,
                       runs_est=record.runs_est, runs_val=record.runs_val)).diagnosis
    theta, _ = fit_physical_servo(record.u_est, record.y_est, runs=record.runs_est)
    yardstick = physical_servo_runs(theta, record.u_val, record.y_val, record.runs_val)
    reference = float(np.sqrt(np.mean((yardstick - record.y_val) ** 2)))
    assert d.cause == "output_feedback" and d.details["form"] in ("servo_loop", "physical_servo")
    assert d.extended.rms <= reference
    assert d.gain >= 5.0


def test_cli_diagnoses_run_files_and_a_run_column(tmp_path, capsys):
    """Several DATA are runs; a `run` column too; the JSON says how many and which runs validate."""
    rng = np.random.default_rng(4)
    paths = []
    rows = []
    for i in range(4):
        u = np.repeat(rng.uniform(-1, 1, 20), 20)
        y = _lag(np.tanh(2 * u)) + 0.002 * rng.standard_normal(u.size)
        path = tmp_path / f"run{i}.csv"
        np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
        paths.append(str(path))
        rows.append(np.column_stack([u, y, np.full(u.size, i)]))
    assert main(["diagnose", *paths, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["runs"] == 4 and doc["split"] == "whole runs: estimation on runs 1-3, validation on run 4 of 4"
    table = tmp_path / "runs.csv"
    np.savetxt(table, np.vstack(rows), delimiter=",", header="u,y,run", comments="")
    assert main(["diagnose", str(table), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == doc
    assert main(["diagnose", *paths[:2], "--validation", *paths[2:], "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["runs"] == 4
    assert main(["diagnose", paths[0], "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["runs"] == 1


@pytest.mark.parametrize("kp", [400, 800])
def test_the_real_xl330_runs_are_a_servo_loop(kp, capsys):
    """A real Dynamixel XL330 in position mode swinging a 0.49 kg pendulum (hammer_ros/data/
    xl330_servo_arm, its own P loop at register gain kp): estimation on three runs, validation on
    the fourth (sin_time_square). Ground truth: the servo closes a position loop around its motor
    with gravity on the arm, i.e. output feedback. The servo loop cuts the baseline's
    validation RMS and beats the 7-parameter physical loop fitted on the same runs."""
    path = str(XL330 / f"kp{kp}.csv")
    assert main(["diagnose", path, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["runs"] == 4 and doc["split"] == "whole runs: estimation on runs 1-3, validation on run 4 of 4"
    assert doc["cause"] == "output_feedback" and doc["extended"]["form"] in ("servo_loop", "physical_servo")
    assert set(doc["extended"]["held_back_rms"]) == {"servo_loop", "physical_servo"}
    assert doc["gain"]["rms_ratio"] >= 1.5  # measured: x1.76 (kp 400), x2.38 (kp 800)
    from hammer_ros.io.records import load_record

    record = load_record(path)
    split = split_runs(record.v, record.y, record.runs)
    theta, _ = fit_physical_servo(split.v_est, split.y_est, runs=split.runs_est)
    yardstick = physical_servo_runs(theta, split.v_val, split.y_val, split.runs_val)
    assert doc["extended"]["rms"] < float(np.sqrt(np.mean((yardstick - split.y_val) ** 2)))


def test_a_diagnosis_is_the_same_in_another_process(capsys):
    """kp800's diagnosis, in this process and in another with another hash seed and memory layout, is
    the same document: scipy's C Levenberg-Marquardt gave another chain in about a quarter of
    processes (docs/notes/diagnosis-measurements.md); ``levenberg_marquardt`` gives the same bits."""
    path = str(XL330 / "kp800.csv")
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    other = subprocess.run([sys.executable, "-m", "hammer_ros.cli", "diagnose", path, "--json"], env=env,
                           capture_output=True, text=True, timeout=300, check=True)
    assert main(["diagnose", path, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(other.stdout)
