"""The estimation fits of the extensions on a record of several runs (issue 50): every filter,
regressor and simulation of the fit run by run, each run from rest at its first input. The
records are runs of one plant with a hidden effect, each from rest at its own operating point (a
random level held first), concatenated with jumps at the boundaries: given as runs, the
extension fits each run to the noise and the cause is named; fitted on the concatenation (the
runs ignored by the fit) it is charged with the jumps."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.extensions import EXTENSIONS, NotFitted
from hammer_ros.diagnosis.extensions.common import Context
from hammer_ros.diagnosis.hammerstein import fit_baseline
from hammer_ros.diagnosis.split import Split
from hammer_ros.identification.runs import Runs, per_run
from hammer_ros.identification.simulate import play_operator
from hammer_ros.identification.simulation_error import steady_state_filter

NOISE = 0.005
# validation RMS of the extension fitted on the concatenation over its fit on runs, at least (measured:
# output map x3.4, L-N-L rejected on the concatenation, backlash x1.05: there the fit's own error dominates)
CONCATENATED_MARGIN = {"output_nonlinearity": 1.5, "input_dynamics": 1.5, "backlash": 1.0}


def _block(b: list[float], a: list[float]):
    return lambda x: steady_state_filter(np.array(b), np.array(a), x)


_G = _block([0.0, 0.06, 0.03], [1.0, -1.5, 0.59])  # unit gain, poles 0.75 +- 0.17j


def _play_cubic(v: np.ndarray) -> np.ndarray:
    z = play_operator(v, 0.4)
    return z + 0.3 * z**3


PLANTS = {
    "output_nonlinearity": lambda v: np.clip(_G(np.tanh(1.5 * v)), -0.45, 0.55),
    "input_dynamics": lambda v: _G(np.tanh(1.5 * _block([0.0, 0.15], [1.0, -0.85])(v))),
    "parallel_path": lambda v: _G(np.tanh(1.5 * v)) + 0.8 * _block([0.0, 0.04], [1.0, -0.96])(v),
    "backlash": lambda v: _G(_play_cubic(v)),
}


def _runs_record(plant, seed: int, count: int, samples: int = 400) -> tuple[np.ndarray, np.ndarray, Runs]:
    """``count`` runs of ``plant``, each from rest at a random level held for 40 samples, then
    steps of 8 samples around it; white noise of NOISE."""
    rng = np.random.default_rng(seed)
    inputs, outputs = [], []
    for _ in range(count):
        level = rng.uniform(-1.0, 1.0)
        steps = np.repeat(rng.standard_normal(samples // 8), 8)[: samples - 40]
        v = np.concatenate([np.full(40, level), level + 0.6 * steps])
        inputs.append(v)
        outputs.append(plant(v) + NOISE * rng.standard_normal(v.size))
    return np.concatenate(inputs), np.concatenate(outputs), Runs.from_lengths([samples] * count)


def _split(cause: str) -> Split:
    v_est, y_est, runs_est = _runs_record(PLANTS[cause], 1, 8)
    v_val, y_val, runs_val = _runs_record(PLANTS[cause], 2, 3)
    assert np.max(np.abs(np.diff(y_est)[np.array(runs_est.starts[1:]) - 1])) > 0.1  # jumps at the boundaries
    return Split(v_est, y_est, v_val, y_val, continuous=False, runs_est=runs_est, runs_val=runs_val)


def _concatenated_rms(split: Split, baseline, cause: str) -> float:
    """Validation RMS of the extension fitted on the estimation runs as one record (inf when
    that fit is rejected)."""
    try:
        extended = EXTENSIONS[cause](Context(replace(split, runs_est=None), baseline, None, None))
    except NotFitted:
        return np.inf
    return split.validation_rms(extended.validation_output)


@pytest.mark.parametrize("cause", ["output_nonlinearity", "input_dynamics", "backlash"])
def test_runs_name_the_hidden_cause_and_fit_each_run(cause):
    """Named right; the extension's simulation of every estimation run (from rest at its first
    input) at most half the baseline's error (within 3x the noise where the extension holds the
    plant: the play width search with G fixed at the baseline's underestimates the width, on one
    record too); on validation better than the same extension fitted on the concatenation
    (``CONCATENATED_MARGIN``)."""
    split = _split(cause)
    run = diagnose(split)
    assert run.diagnosis.cause == cause
    s = run.split

    def estimation_rms(simulate) -> float:
        return float(np.sqrt(np.mean((s.y_est - per_run(simulate, s.v_est, s.runs_est))[100:] ** 2)))

    rms = estimation_rms(run.extensions[cause].simulate)
    concatenated = _concatenated_rms(s, run.baseline, cause)
    assert rms < 0.5 * estimation_rms(run.baseline.simulate)
    if cause != "backlash":
        assert rms < 3 * NOISE
    assert concatenated > CONCATENATED_MARGIN[cause] * run.diagnosis.extended.rms


def test_parallel_path_fits_runs_where_the_concatenation_does_not():
    """The feedforward extension on runs: its validation RMS near the noise and 5x below the
    same fit on the concatenation (a slow path remembers the previous run's level there)."""
    split = _split("parallel_path")
    baseline = fit_baseline(split.v_est, split.y_est, None, None, split.runs_est)
    extended = EXTENSIONS["parallel_path"](Context(split, baseline, None, None))
    rms = split.validation_rms(extended.validation_output)
    assert rms < 2 * NOISE
    assert _concatenated_rms(split, baseline, "parallel_path") > 5 * rms
