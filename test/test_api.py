"""The Python API (``import hammer_ros``) gives the command line's numbers: ``identify``'s document
is the CLI's JSON, ``diagnose`` the same cause and baseline, and the model simulates, converts to
scipy and plots as it says; docs/python.md runs as written."""

from __future__ import annotations

import contextlib
import io
import json
import re

import numpy as np
import pytest
from conftest import REPO
from scipy import signal

import hammer_ros
from hammer_ros.cli import main
from hammer_ros.errors import UsageError
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.identification.static_maps import PolynomialMap

TANKS = REPO / "hammer_ros" / "data" / "cascaded_tanks"
BAG, BAG_CONFIG = REPO / "bags" / "float64_cubic_g1.mcap", REPO / "msg_config" / "float64_cubic_g1.yaml"


def cli_json(*argv: str) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main([*argv, "--json"]) == 0
    return json.loads(out.getvalue())


def assert_same_diagnosis(mine: dict, doc: dict) -> None:
    """The API's diagnose document is the CLI's: the same keys, cause, baseline and evidence rows,
    the same extended structure, and its rms to 1e-3 (the extended model's iterative refinement may
    end a little elsewhere in a process that has done other work first: last-bit differences grow
    along its iterations)."""
    assert mine.keys() == doc.keys()
    assert mine["cause"] == doc["cause"] and mine["baseline"] == doc["baseline"] and mine["runs"] == doc["runs"]
    assert [e["test"] for e in mine["evidence"]] == [e["test"] for e in doc["evidence"]]
    assert (mine["extended"] is None) == (doc["extended"] is None)
    if doc["extended"] is not None:
        assert mine["extended"]["structure"] == doc["extended"]["structure"]
        assert mine["extended"]["rms"] == pytest.approx(doc["extended"]["rms"], rel=1e-3)


def roots(pairs) -> np.ndarray:
    return np.array([complex(re, im) for re, im in pairs])


@pytest.fixture(scope="module")
def plant_record(tmp_path_factory):
    """Paper 000's G1 after a cubic F, white input, from zero state, a little output noise."""
    g = LinearModel.from_zeros_poles([1.25, 0.5], [0.95, 0.245 + 0.574j, 0.245 - 0.574j], dc_gain=1.0)
    rng = np.random.default_rng(7)
    u = rng.standard_normal(6000)
    y = simulate_hammerstein(u, PolynomialMap([0.0, 1.0, 0.0, 0.3]), g) + 0.005 * rng.standard_normal(u.size)
    path = tmp_path_factory.mktemp("api") / "plant.csv"
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    return path, u, y, g


@pytest.mark.parametrize("argv, read, options", [
    (["--order", "3", "--delay", "1"], {}, {"order": 3, "delay": 1}),
    (["--method", "plls-hammerstein", "--order", "2"], {}, {"method": "plls-hammerstein", "order": 2}),
    (["--order", "2", "--refine"], {}, {"order": 2, "refine": True}),
])
def test_identify_gives_the_cli_document(plant_record, argv, read, options):
    path, u, y, g = plant_record
    doc = cli_json("identify", str(path), *argv)
    model = hammer_ros.identify(hammer_ros.read(path, **read), **options)
    assert model.to_dict() == doc  # every key, every number
    assert np.allclose(np.sort_complex(model.poles), np.sort_complex(roots(doc["poles"])), atol=1e-9, rtol=0)
    from_arrays = hammer_ros.identify(u, y, **options)  # the arrays alone: the same model
    assert np.allclose(np.sort_complex(from_arrays.poles), np.sort_complex(model.poles), atol=1e-9, rtol=0)
    if model.result.linear.order == 3:  # against the truth, not only against the CLI
        assert np.max(np.abs(np.sort_complex(model.poles) - np.sort_complex(g.poles))) < 0.02


def test_identify_a_bag_and_runs_as_the_cli():
    doc = cli_json("identify", str(BAG), "--config", str(BAG_CONFIG))
    model = hammer_ros.identify(hammer_ros.read(BAG, config=BAG_CONFIG))
    assert model.to_dict() == doc
    paths = [TANKS / "estimation.csv", TANKS / "test.csv"]
    doc = cli_json("identify", *map(str, paths), "--order", "2")
    record = hammer_ros.read(paths)
    assert record.run_count == 2 and doc["runs"] == 2
    model = hammer_ros.identify(record, order=2)
    assert model.to_dict() == doc
    by_lengths = hammer_ros.identify(record.u, record.y, order=2, runs=record.runs.lengths)
    assert by_lengths.to_dict()["rms"] == doc["rms"]


def test_simulate_reproduces_the_reported_rms(plant_record):
    _, u, y, _ = plant_record
    model = hammer_ros.identify(u, y, order=3)
    reported = model.to_dict()["rms"]
    assert np.sqrt(np.mean((y - model.simulate(u)) ** 2)) == pytest.approx(reported, rel=1e-12)  # from zero state
    tanks = hammer_ros.read(TANKS / "estimation.csv")
    model = hammer_ros.identify(tanks, order=2)
    reported = model.to_dict()["rms"]
    assert np.sqrt(np.mean((tanks.y - model.simulate(tanks.u, tanks.y)) ** 2)) == pytest.approx(reported, rel=1e-12)


def test_to_scipy_is_the_linear_block(plant_record):
    _, u, y, _ = plant_record
    model = hammer_ros.identify(u, y, order=3)
    system = model.to_scipy()
    assert isinstance(system, signal.dlti) and system.dt is True  # no time stamps in the record
    assert np.allclose(np.sort_complex(system.poles), np.sort_complex(model.poles), atol=1e-9, rtol=0)
    v = model.nonlinearity(u[:300])
    _, out = signal.dlsim(system, v)
    assert np.allclose(out.ravel(), model.result.linear.simulate(v), atol=1e-9)
    assert hammer_ros.identify(hammer_ros.read(BAG, config=BAG_CONFIG)).to_scipy().dt == pytest.approx(0.01)


def test_diagnose_gives_the_cli_cause_and_baseline():
    path = TANKS / "estimation.csv"
    doc = cli_json("diagnose", str(path), "--order", "2")
    diagnosis = hammer_ros.diagnose(hammer_ros.read(path), order=2)
    assert diagnosis.cause == doc["cause"] and diagnosis.baseline_rms == doc["baseline"]["rms"]
    assert_same_diagnosis(diagnosis.to_dict(), doc)
    assert diagnosis.extended is not None
    test = TANKS / "test.csv"
    doc = cli_json("diagnose", str(path), "--validation", str(test), "--order", "2")
    held_out = hammer_ros.read(test)
    for validation in (held_out, (held_out.u, held_out.y)):
        d = hammer_ros.diagnose(hammer_ros.read(path), order=2, validation=validation)
        assert_same_diagnosis(d.to_dict(), doc)


def test_plot_draws_the_regions_and_the_band(plant_record, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    _, u, y, _ = plant_record
    model = hammer_ros.identify(u, y, order=3)
    figure = model.plot(tmp_path / "model.png")
    pz, nonlinearity = figure.axes
    assert len(pz.patches) == 1 + 3 + 2  # the unit circle, a region per pole and per zero
    assert nonlinearity.collections  # the band
    assert (tmp_path / "model.png").stat().st_size > 1000


def test_unknown_option_is_a_usage_error():
    with pytest.raises(UsageError, match="window"):
        hammer_ros.identify(np.zeros(10), np.zeros(10), window=4)
    with pytest.raises(UsageError, match="u and y"):
        hammer_ros.identify(np.zeros(10))
    with pytest.raises(UsageError, match="differ in length"):
        hammer_ros.diagnose(np.zeros(10), np.zeros(9))


def test_the_python_page_runs(monkeypatch, tmp_path):
    """docs/python.md's code blocks, in order, in one namespace, from the repository root."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "docs" / "python.md").read_text(), re.S)
    assert len(blocks) >= 5
    monkeypatch.chdir(REPO)
    namespace: dict = {}
    with contextlib.redirect_stdout(io.StringIO()):
        for block in blocks:
            exec(compile(block, "docs/python.md", "exec"), namespace)
    assert namespace["model"].to_dict()["rms"] == pytest.approx(
        np.sqrt(np.mean((namespace["bag"].y - namespace["y_model"]) ** 2)), rel=1e-12)
    assert namespace["diagnosis"].cause != ""
