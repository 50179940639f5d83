"""The shared core: linear blocks, RSS matching, regression builder, correlation estimator,
data loading and the CLI's error contract."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hammer_ros.errors import UsageError
from hammer_ros.identification.correlation import auto_correlation, cross_correlation
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.regression import build_regression, solve_least_squares
from hammer_ros.io.records import load_record

REPO = Path(__file__).resolve().parents[1]
def test_g1_matches_paper(g1):
    assert np.allclose(g1.poles, np.sort_complex(np.array([0.245 - 0.574j, 0.245 + 0.574j, 0.95])), atol=1e-12)
    assert np.allclose(np.sort(g1.zeros.real), [0.5, 1.25])
    assert g1.delay == 1 and g1.order == 3
    assert g1.dc_gain == pytest.approx(1.0)
    h = g1.markov_parameters(5)
    assert h[0] == 0.0 and h[1] == pytest.approx(g1.b[1])


def test_rss_matches_closest_one_to_one():
    true = [0.245 + 0.574j, 0.245 - 0.574j, 0.95]
    est = [0.939, 0.239 - 0.576j, 0.239 + 0.576j]
    expected = np.sqrt(2 * (0.006**2 + 0.002**2) + 0.011**2)
    assert root_rss_error(true, est) == pytest.approx(expected)
    assert root_rss_error([1.0], [1.0, 0.5]) == pytest.approx(0.5)


def test_arx_regression_recovers_exact_linear_model(g1, rng):
    v = rng.standard_normal(500)
    y = g1.simulate(v)
    reg = build_regression(y, v, order=3, delay=1)
    theta = solve_least_squares(reg.phi, reg.target)
    a, b = reg.split(theta)
    assert np.allclose(a, g1.a[1:], atol=1e-10)
    assert np.allclose(b[:, 0], g1.b[1:], atol=1e-10)


def test_markov_regression_lags():
    reg = build_regression(np.arange(50.0), np.arange(50.0), order=3, delay=1, mu=4)
    assert reg.output_lags.tolist() == [4, 5, 6]
    assert reg.input_lags.tolist() == [1, 2, 3, 4, 5, 6]


def test_correlation_estimator_is_paper_eq8(rng):
    x, y, tau_max = rng.standard_normal(41), rng.standard_normal(41), 5
    n = x.size - 2 * tau_max - 1
    brute = [sum(y[k] * x[k - tau] for k in range(tau_max, tau_max + n + 1)) / (n + 1)
             for tau in range(-tau_max, tau_max + 1)]
    assert np.allclose(cross_correlation(x, y, tau_max), brute, atol=1e-14)
    phi = auto_correlation(x, tau_max)
    assert phi[tau_max] > 0 and phi.size == 2 * tau_max + 1


def test_load_record_errors_name_the_problem(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("u,y\n1,2\n3,x\n")
    with pytest.raises(UsageError, match=r"bad.csv:3: column 'y'"):
        load_record(bad)
    ok = tmp_path / "ok.csv"
    ok.write_text("t,cmd,y\n0,1,2\n1,3,4\n")
    with pytest.raises(UsageError, match="no column 'u'"):
        load_record(ok)
    rec = load_record(ok, input_name="cmd")
    assert rec.v.tolist() == [1.0, 3.0] and rec.t.tolist() == [0.0, 1.0]


@pytest.mark.parametrize("argv, needle", [
    (["identify", "missing.csv"], "missing.csv"),
    (["identify", "{csv}", "--method", "nope"], "--method"),
    (["identify", "{csv}", "--order", "2", "--delay", "3"], "--delay"),
    (["identify", "{csv}", "--partition", "1,0"], "--partition"),
])
def test_cli_user_errors_exit_2_with_one_line(tmp_path, argv, needle):
    csv = tmp_path / "d.csv"
    csv.write_text("u,y\n" + "\n".join(f"{i},{i}" for i in range(20)))
    argv = [a.replace("{csv}", str(csv)) for a in argv]
    proc = subprocess.run([sys.executable, "-m", "hammer_ros.cli", *argv], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in proc.stderr


def test_result_json_flags_an_unstable_model(g1):
    from hammer_ros.identification.linear import LinearModel
    from hammer_ros.identification.result import IdentificationResult

    unstable = LinearModel([0.0, 1.0], [1.0, -1.1])
    for linear, expected in ((g1, True), (unstable, False)):
        doc = IdentificationResult("ls-arx", linear, linear.simulate).to_json()
        assert doc["stable"] is expected
