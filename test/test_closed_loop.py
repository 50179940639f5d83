"""Closed-loop data (``identification.closed_loop`` records, a P or PI controller around a
third-order Hammerstein plant with a cubic map, coloured output noise at 4-8 dB): the plain
CLS and PLLS estimates are biased, the ones instrumented by the reference are not (against the
true poles); the ``closed_loop`` evidence row fails on closed-loop data and passes in open loop;
``identify --reference`` reads the reference from a CSV/NPZ column or a bag topic."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.diagnosis.closed_loop import closed_loop_evidence
from hammer_ros.identification.closed_loop import random_loop_pair
from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.methods import IdentifyOptions, identify

SEEDS = range(100, 106)
SAMPLES = 3000


@pytest.fixture(scope="module", params=[False, True], ids=["P", "PI"])
def loops(request):
    return [random_loop_pair(seed, samples=SAMPLES, integral=request.param) for seed in SEEDS]


def pole_error(record, method: str, reference=None) -> float:
    result = identify(method, record.u, record.y, IdentifyOptions(order=3, delay=1, reference=reference))
    return root_rss_error(record.linear.poles, result.poles)


def test_the_controller_feeds_the_noise_back_into_the_input(loops):
    for closed, opened in loops:
        assert abs(closed.snr_db - opened.snr_db) < 1e-12 and 4.0 <= closed.snr_db <= 8.0
        n = SAMPLES
        noise_closed, noise_open = closed.y - closed.x, opened.y - opened.x
        assert abs(np.corrcoef(closed.u, noise_closed)[0, 1]) > 5 / np.sqrt(n)
        assert abs(np.corrcoef(opened.u, noise_open)[0, 1]) < 4 / np.sqrt(n)
        assert abs(np.std(closed.u) / np.std(opened.u) - 1.0) < 0.1


@pytest.mark.parametrize(("method", "biased", "instrumented"), [("cls-markov", 0.15, 0.05),
                                                                  ("plls-hammerstein", 0.12, 0.07)])
def test_the_reference_as_instrument_removes_the_closed_loop_bias(loops, method, biased, instrumented):
    plain = np.median([pole_error(closed, method) for closed, _ in loops])
    with_reference = np.median([pole_error(closed, method, closed.r) for closed, _ in loops])
    assert plain > biased and with_reference < instrumented, (plain, with_reference)


def test_the_closed_loop_row_fails_in_closed_loop_and_passes_in_open_loop(loops):
    verdicts = {"closed": [], "open": []}
    for closed, opened in loops:
        for name, record in (("closed", closed), ("open", opened)):
            model = identify("cls-markov", record.u, record.y, IdentifyOptions(order=3, delay=1))
            validation = slice(int(0.7 * SAMPLES), None)
            residual = record.y[validation] - model.simulate(record.u)[validation]
            evidence = closed_loop_evidence(record.u[validation], residual)
            assert evidence.test == "closed_loop" and evidence.bound > 0
            verdicts[name].append(evidence.passed)
    assert not any(verdicts["closed"]) and sum(verdicts["open"]) >= len(SEEDS) - 1, verdicts


@pytest.fixture(scope="module")
def loop_files(tmp_path_factory):
    """One closed-loop record as NPZ (u, y, r) and as an MCAP bag (/cmd, /ref, /position)."""
    from hammer_ros.io.bags import ResultWriter

    closed, opened = random_loop_pair(104, samples=SAMPLES)
    root = tmp_path_factory.mktemp("loop")
    np.savez(root / "closed.npz", u=closed.u, y=closed.y, r=closed.r)
    np.savez(root / "open.npz", u=opened.u, y=opened.y)
    with ResultWriter(root / "closed.mcap") as out:
        for k in range(SAMPLES):
            t = 1_700_000_000_000_000_000 + k * 10_000_000
            for topic, x in (("/cmd", closed.u), ("/ref", closed.r), ("/position", closed.y)):
                out.write(topic, "std_msgs/msg/Float64", {"data": float(x[k])}, t)
    return root, closed


def run_json(capsys, *argv) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def test_identify_reference_from_a_column_or_a_topic(loop_files, capsys):
    root, closed = loop_files
    column = run_json(capsys, "identify", str(root / "closed.npz"), "--reference", "r", "--order", "3", "--json")
    topic = run_json(capsys, "identify", str(root / "closed.mcap"), "--input", "/cmd:data", "--output",
                     "/position:data", "--reference", "/ref:data", "--order", "3", "--json")
    plain = run_json(capsys, "identify", str(root / "closed.npz"), "--order", "3", "--json")
    refined = run_json(capsys, "identify", str(root / "closed.npz"), "--reference", "r", "--order", "3", "--refine",
                       "--json")
    poles = {name: np.array([complex(*p) for p in doc["poles"]])
             for name, doc in (("column", column), ("topic", topic), ("plain", plain), ("refined", refined))}
    assert root_rss_error(poles["column"], poles["topic"]) < 1e-6
    truth = closed.linear.poles
    assert root_rss_error(truth, poles["column"]) < 0.05 < root_rss_error(truth, poles["plain"])
    assert root_rss_error(truth, poles["refined"]) < 0.05


@pytest.mark.parametrize("method", ["cls-markov", "plls-hammerstein"])
def test_replay_with_the_reference_equals_identify(loop_files, capsys, method):
    """The streaming engine holds the reference on its grid; a window of the whole bag gives the
    batch estimate exactly (no published model is kept over it: the free-run fit on a closed
    loop's input says nothing), and the reference removes the bias there too."""
    root, closed = loop_files
    common = ["--input", "/cmd:data", "--output", "/position:data", "--order", "3", "--method", method]
    bag = str(root / "closed.mcap")
    batch = run_json(capsys, "identify", bag, *common, "--reference", "/ref:data", "--json")
    streamed = run_json(capsys, "replay", bag, *common, "--reference", "/ref:data", "--window", str(SAMPLES), "--json")
    plain = run_json(capsys, "replay", bag, *common, "--window", str(SAMPLES), "--json")
    poles = {name: np.array([complex(*p) for p in doc["poles"]])
             for name, doc in (("batch", batch), ("streamed", streamed), ("plain", plain))}
    assert streamed["samples"] == SAMPLES and streamed["solves"] > 10
    assert root_rss_error(poles["batch"], poles["streamed"]) < 1e-9
    assert root_rss_error(closed.linear.poles, poles["streamed"]) < 0.05 < root_rss_error(closed.linear.poles,
                                                                                           poles["plain"])


def test_fleet_with_the_reference_gives_the_replay_model(loop_files, capsys, tmp_path):
    """And ``--diagnose``: the row's diagnosis is replay's, instrumented by the reference."""
    from hammer_ros.fleet.tasks import row_diagnosis

    root, _ = loop_files
    common = ["--input", "/cmd:data", "--output", "/position:data", "--order", "3", "--reference", "/ref:data",
              "--diagnose"]
    replayed = run_json(capsys, "replay", str(root / "closed.mcap"), *common, "--json")
    assert replayed["diagnosis"]["baseline"]["input"] == "reference_part"
    done = subprocess.run([str(Path(sys.executable).parent / "hammer-ros"), "fleet", str(root / "closed.mcap"),
                           *common, "--workers", "1", "--out", str(tmp_path / "fleet"), "--json"],
                          capture_output=True, text=True, timeout=300)  # a cluster of its own: a process
    assert done.returncode == 0, done.stderr[-2000:]
    fleet = json.loads(done.stdout)
    assert fleet["ok"] == 1 and fleet["rows"][0]["poles"] == replayed["poles"]
    assert fleet["rows"][0]["diagnosis"] == row_diagnosis(replayed["diagnosis"])


@pytest.mark.parametrize(("argv", "reason"), [
    (["closed.npz", "--reference", "rr"], "closed.npz: no column 'rr' (set --reference; columns are u, y, r)"),
    (["closed.npz", "--reference", "r", "--method", "nls-arx"], "--reference: not for nls-arx"),
    (["closed.mcap", "--input", "/cmd:data", "--output", "/position:data", "--reference", "/setpoint:data"],
     "--reference: "),
    (["open.npz", "--reference", "u", "--method", "plls-feedback"], "--reference: not for plls-feedback"),
])
def test_a_bad_reference_exits_2_with_one_line_naming_it(loop_files, capsys, argv, reason):
    root, _ = loop_files
    assert main(["identify", str(root / argv[0]), *argv[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and "\n" not in err, err


@pytest.mark.parametrize(("options", "reason"), [
    (["--reference", "/setpoint:data"], "--reference: "),
    (["--reference", "/ref:data", "--method", "nls-arx"], "--reference: not for nls-arx"),
    (["--reference", "ref"], "--reference: expected /topic:field.path"),
])
def test_replay_names_a_bad_reference(loop_files, capsys, options, reason):
    root, _ = loop_files
    argv = ["replay", str(root / "closed.mcap"), "--input", "/cmd:data", "--output", "/position:data", *options]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and "\n" not in err, err


def test_diagnose_says_closed_loop(loop_files, capsys):
    root, _ = loop_files
    rows = {}
    for name in ("closed", "open"):
        doc = run_json(capsys, "diagnose", str(root / f"{name}.npz"), "--order", "3", "--json")
        rows[name] = [e for e in doc["evidence"] if e["test"] == "closed_loop"]
    assert len(rows["closed"]) == len(rows["open"]) == 1
    assert rows["closed"][0]["passed"] is False and rows["open"][0]["passed"] is True
    assert rows["closed"][0]["value"] > rows["closed"][0]["bound"]


def test_diagnose_with_the_reference_fits_the_baseline_on_its_part_of_the_input(loop_files, capsys):
    """``diagnose --reference``: the baseline fitted and judged on the reference's part of the
    input (two-stage) has the plant's poles where the plain baseline's are biased, and names no
    cause for the plain Hammerstein plant; the ``closed_loop`` row stays (on the measured input)
    and says the reference was used; a bag's /topic:field gives the column's diagnosis, and so does
    ``replay --reference --diagnose`` of a window holding the whole bag."""
    root, closed = loop_files
    plain = run_json(capsys, "diagnose", str(root / "closed.npz"), "--order", "3", "--json")
    column = run_json(capsys, "diagnose", str(root / "closed.npz"), "--order", "3", "--reference", "r", "--json")
    topic = run_json(capsys, "diagnose", str(root / "closed.mcap"), "--input", "/cmd:data", "--output",
                     "/position:data", "--reference", "/ref:data", "--order", "3", "--json")
    poles = {name: np.array([complex(*p) for p in doc["baseline"]["poles"]])
             for name, doc in (("plain", plain), ("column", column), ("topic", topic))}
    truth = closed.linear.poles
    assert root_rss_error(truth, poles["column"]) < 0.03 < 0.06 < root_rss_error(truth, poles["plain"])  # .013, .085
    assert root_rss_error(poles["column"], poles["topic"]) < 1e-6
    replayed = run_json(capsys, "replay", str(root / "closed.mcap"), "--input", "/cmd:data", "--output",
                        "/position:data", "--reference", "/ref:data", "--order", "3", "--window", str(SAMPLES),
                        "--diagnose", "--json")
    final = replayed["diagnosis"]  # the final window (the whole bag) diagnosed with the engine's reference
    assert final["samples"] == SAMPLES and final["baseline"]["input"] == "reference_part"
    assert root_rss_error(poles["column"], np.array([complex(*p) for p in final["baseline"]["poles"]])) < 1e-6
    assert column["baseline"]["input"] == "reference_part" and "input" not in plain["baseline"]
    assert column["cause"] == "none"  # the plain diagnosis reads the feedback as a parallel path
    row = [e for e in column["evidence"] if e["test"] == "closed_loop"]
    assert len(row) == 1 and row[0]["passed"] is False and "the reference was used" in row[0]["note"]
    assert "without a reference are biased" in next(e for e in plain["evidence"] if e["test"] == "closed_loop")["note"]


@pytest.mark.parametrize(("argv", "reason"), [
    (["closed.npz", "--reference", "rr"], "closed.npz: no column 'rr' (set --reference; columns are u, y, r)"),
    (["closed.npz", "--reference", "r", "--validation", "open.npz"], "open.npz: no column 'r' (set --reference"),
    (["closed.mcap", "--input", "/cmd:data", "--output", "/position:data", "--reference", "/setpoint:data"],
     "--reference: "),
])
def test_diagnose_names_a_bad_reference(loop_files, capsys, argv, reason):
    root, _ = loop_files
    assert main(["diagnose", str(root / argv[0]), *[str(root / a) if a.endswith(".npz") else a for a in argv[1:]]]) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and "\n" not in err, err


@pytest.mark.ros
def test_the_live_node_uses_its_reference_topic(ros_env, tmp_path):
    """A closed loop published live (header-stamped JointStates on /cmd, /ref, /position): with
    reference_topic the node's model is the instrumented one, near the true poles, and so is its
    diagnosis's baseline (~/diagnose, in the diagnosis process: fitted on the reference's part)."""
    import signal

    from ros_helpers import Listener, RosProcess
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    closed, _ = random_loop_pair(104, samples=SAMPLES)
    fields = {f"{role}_{key}": value for role, topic in (("excitation", "/cmd"), ("response", "/position"),
                                                         ("reference", "/ref"))
              for key, value in (("topic", topic), ("type", "sensor_msgs/msg/JointState"), ("field", "position[j]"))}
    node = RosProcess("hammer_ros.ros.node", {**fields, "sample_rate": 100.0, "order": 3, "window": SAMPLES,
                                              "tau_max": 66, "solve_rate": 2.0, "min_fill": 0.9,
                                              "diagnosis_period": 0.0}, ros_env, tmp_path / "node.log")
    listener = Listener(ros_env)
    try:
        models = listener.subscribe_json("/hammer_ros/model")
        publishers = {topic: listener.node.create_publisher(JointState, topic, 1000)
                      for topic in ("/cmd", "/ref", "/position")}
        listener.wait_for(lambda: all(p.get_subscription_count() for p in publishers.values()),
                          what="the node's subscriptions")
        start = 1_700_000_000
        for k in range(SAMPLES):
            for topic, x in (("/cmd", closed.u), ("/ref", closed.r), ("/position", closed.y)):
                msg = JointState(name=["j"], position=[float(x[k])])
                msg.header.stamp.sec, msg.header.stamp.nanosec = start + k // 100, (k % 100) * 10_000_000
                publishers[topic].publish(msg)
            if k % 50 == 49:
                listener.executor.spin_once(timeout_sec=0.01)  # pace the burst: the queue holds 1000
        model = listener.wait_for(lambda: [m for m in models if m["samples"] >= SAMPLES - 100],
                                  what="a model of the whole record")[-1]
        poles = np.array([complex(*p) for p in model["poles"]])
        assert root_rss_error(closed.linear.poles, poles) < 0.08, model
        client = listener.node.create_client(Trigger, "/hammer_ros/diagnose")  # in the diagnosis process
        listener.wait_for(client.service_is_ready, what="~/diagnose")
        answer = listener.wait_future(lambda: client.call_async(Trigger.Request()), timeout=120)
        assert answer.success, answer.message
        diagnosis = json.loads(answer.message)  # instrumented by the node's reference, as replay --diagnose
        assert diagnosis["baseline"]["input"] == "reference_part", diagnosis
        baseline = np.array([complex(*p) for p in diagnosis["baseline"]["poles"]])
        assert root_rss_error(closed.linear.poles, baseline) < 0.08, diagnosis["baseline"]
        row = [e for e in diagnosis["evidence"] if e["test"] == "closed_loop"]
        assert len(row) == 1 and row[0]["passed"] is False and "the reference was used" in row[0]["note"]
    finally:
        listener.close()
        code = node.stop(signal.SIGINT)
    assert code == 0, node.output()[-2000:]


def test_the_reference_is_held_on_the_grid_and_none_across_a_gap():
    from hammer_ros.streaming.reference import ReferenceTrack

    track = ReferenceTrack(10)
    track.grid(np.arange(5.0))
    track.add(np.arange(5.0), 10 * np.arange(5.0))
    np.testing.assert_array_equal(track.window(5, 1e-3, 3.0), [0, 10, 20, 30, 40])
    track.grid(np.arange(5.0, 12.0))
    track.add(np.arange(5.0, 9.0), 10 * np.arange(5.0, 9.0))
    held = track.window(10, 1e-3, 2.5)  # the newest 10 grid times 2..11; none at 11 (3 s after the last)
    np.testing.assert_array_equal(held[:-1], [20, 30, 40, 50, 60, 70, 80, 80, 80])
    assert np.isnan(held[-1])
    track.add(np.array([0.5]), np.array([-1.0]))  # a clock reset: the track starts again
    track.grid(np.array([0.5, 0.6]))
    np.testing.assert_array_equal(track.window(2, 1e-3, 2.5), [-1.0, -1.0])
