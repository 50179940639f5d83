"""``SolverProcess``: solves in a worker process give the outcomes of in-process solves (the
published model for the keep check included), so do diagnoses, replay with it writes the same
results, and a worker that dies is reported instead of hanging."""

from __future__ import annotations

import os
import signal
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from hammer_ros.io.bags import bag_duration, parse_stream_spec
from hammer_ros.io.replay import replay_bag
from hammer_ros.streaming.config import EngineConfig
from hammer_ros.streaming.engine import StreamingEngine, decide_outcome, estimate_snapshot, solve_snapshot
from hammer_ros.streaming.solver_process import SolverProcess, diagnose_window
from hammer_ros.tools.bench import feed_engine, hammerstein_record

REPO = Path(__file__).resolve().parents[1]
FLOAT64_BAG = REPO / "bags" / "float64_cubic_g1.mcap"
CONFIG = EngineConfig(sample_rate=1000.0, window=2000, tau_max=66, method="cls-markov", mu=30, min_fill=0.25)


@pytest.fixture(scope="module")
def solver():
    with SolverProcess() as process:
        yield process


def test_a_sequence_of_solves_equals_the_in_process_one(solver):
    v, y = hammerstein_record(12_000, seed=3)
    statuses = []
    for here, there in _fed_in_parts(np.arange(v.size) / 1000.0, v, y, 400):
        local = here.solve()
        remote = solver.solve(there.snapshot())
        there.record(remote)
        statuses.append(local.status)
        assert (remote.ok, remote.status, remote.reason) == (local.ok, local.status, local.reason)
        assert remote.result is None and remote.doc == local.doc and remote.markov == local.markov
        if local.ok:
            assert len(local.markov) == len(local.doc["markov"]) > 2 * CONFIG.order
    assert statuses[0] == "filling" and statuses[-1] == "ok"
    assert here.stats.solves == there.stats.solves > 10


def test_channels_sharing_one_worker_get_their_in_process_outcomes(solver):
    """Three engines (a node's channels), each solved from its own thread in one worker (its
    ``lane``), step by step in turn: every outcome is that engine's in-process one. Their inputs
    fade to 2 % after 5000 samples, so the later windows are refused as not exciting relative to
    the model published before: the worker keeps each lane's published model and window apart."""
    import threading

    from hammer_ros.identification.simulate import simulate_hammerstein
    from hammer_ros.tools.bench.common import F2, G1

    records = []
    for seed in (11, 12, 13):
        v, _ = hammerstein_record(9_000, seed=seed)
        v[5000:] *= 0.02
        records.append((v, simulate_hammerstein(v, F2, G1)))
    turns = threading.Barrier(3, timeout=60)
    mismatches: list[str] = []
    statuses: list[set[str]] = [set(), set(), set()]

    def channel(lane: int) -> None:
        v, y = records[lane]
        for here, there in _fed_in_parts(np.arange(v.size) / 1000.0, v, y, 300):
            turns.wait()  # every lane solves each step before any solves the next
            local, remote = here.solve(), solver.solve(there.snapshot(), lane)
            there.record(remote)
            statuses[lane].add(local.status)
            if (remote.status, remote.reason, remote.doc, remote.markov) != (local.status, local.reason, local.doc,
                                                                              local.markov):
                mismatches.append(f"lane {lane} at {here.stats.aligned}: {remote.reason} vs {local.reason}")

    threads = [threading.Thread(target=channel, args=(lane,)) for lane in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not any(thread.is_alive() for thread in threads)
    assert mismatches == [] and all({"ok", "not_exciting"} <= found for found in statuses), (mismatches, statuses)


def _fed_in_parts(t: np.ndarray, v: np.ndarray, y: np.ndarray, size: int):
    """Two engines fed the record in parts of ``size`` samples: yields (here, there) after each part."""
    here, there = StreamingEngine(CONFIG), StreamingEngine(CONFIG)
    for start in range(0, v.size, size):
        part = slice(start, start + size)
        for engine in (here, there):
            engine.add_excitation(t[part], v[part])
            engine.add_response(t[part], y[part])
        yield here, there


def _solve_beside(process: SolverProcess, t: np.ndarray, v: np.ndarray, y: np.ndarray,
                  kept: list[int] | None = None) -> tuple[list, StreamingEngine]:
    """Feed the record in parts of 500 samples to two engines: solve one in process after each part,
    submit the other's snapshot to ``process`` (``kept``: collects how much of each window the worker
    already held). Returns the in-process outcomes and that engine."""
    expected = []
    for here, there in _fed_in_parts(t, v, y, 500):
        expected.append(here.solve())
        snapshot = there.snapshot()
        if kept is not None:
            kept.append(process._kept(snapshot))
        process.submit(snapshot)
    return expected, here


def test_batches_of_slid_windows_give_the_in_process_outcomes():
    """Snapshots submitted in batches of 3 with at most 2 batches unanswered (replay's pipeline),
    their windows sent as the samples new since the last snapshot: the outcomes are those of the
    in-process solves, also across a gap that restarts the window (sent whole again)."""
    v, y = hammerstein_record(16_000, seed=5)
    t = np.arange(v.size) / 1000.0
    t[9000:] += 5.0  # a 5 s gap in both streams: the window restarts empty after it
    kept = []
    with SolverProcess("fork", batch=3) as process:
        process.max_sent = 6
        expected, here = _solve_beside(process, t, v, y, kept)
        outcomes = [process.result() for _ in expected]
    assert here.stats.gaps == 1 and kept.count(0) >= 2 and max(kept) == CONFIG.window - 500
    for local, remote in zip(expected, outcomes, strict=True):
        assert (remote.status, remote.reason, remote.doc, remote.markov) == (local.status, local.reason, local.doc,
                                                                              local.markov)
    assert sum(o.ok for o in outcomes) > 10


def test_without_documents_the_outcomes_are_the_in_process_ones_and_the_last_good_model_is_documented():
    """``documents=False`` (replay without --out): every outcome has the in-process status and
    reason (the keep check uses the fit alone) but no doc or markov; ``document`` then gives the
    last ok outcome's doc and markov exactly as the in-process solve made them."""
    v, y = hammerstein_record(12_000, seed=7)
    t = np.arange(v.size) / 1000.0
    with SolverProcess("fork", batch=4, documents=False) as process:
        assert process.document() is None  # no model yet
        expected, _ = _solve_beside(process, t, v, y)
        with pytest.raises(RuntimeError, match="in flight"):
            process.document()
        outcomes = [process.result() for _ in expected]
        documented = process.document()
    for local, remote in zip(expected, outcomes, strict=True):
        assert (remote.ok, remote.status, remote.reason) == (local.ok, local.status, local.reason)
        assert remote.doc is None and remote.markov == ()
    last_ok = [o for o in expected if o.ok][-1]
    assert sum(o.ok for o in outcomes) > 10 and documented.result is None
    assert (documented.doc, documented.markov, documented.stamp) == (last_ok.doc, last_ok.markov, last_ok.stamp)


def test_an_engine_solving_without_documents_documents_its_last_good_model_as_one_with_them():
    """``StreamingEngine.solve(document=False)`` (replay in process without --out, a fleet task):
    the outcomes of ``solve()`` without doc and markov, through ok, kept (slow noise on the output)
    and uncertain; ``documented`` gives the last ok one the doc and markov ``solve()`` gave it, and
    leaves any other outcome as it is."""
    v, y = hammerstein_record(12_000, seed=7)
    slow = np.convolve(np.random.default_rng(3).standard_normal(y.size), 0.97 ** np.arange(200))[: y.size]
    y[6000:8000] += np.std(y) * slow[6000:8000]
    pairs = []
    for here, there in _fed_in_parts(np.arange(v.size) / 1000.0, v, y, 500):
        pairs.append((here.solve(), there.solve(document=False)))
    for full, bare in pairs:
        assert (bare.ok, bare.status, bare.reason) == (full.ok, full.status, full.reason)
        assert bare.doc is None and bare.markov == ()
    assert {"ok", "kept", "uncertain"} <= {bare.status for _, bare in pairs}
    good = [pair for pair in pairs if pair[1].ok]
    (full, last), earlier = good[-1], good[0][1]
    documented = there.documented(last)
    assert len(good) > 10 and full.doc is not None
    assert (documented.doc, documented.markov, documented.stamp) == (full.doc, full.markov, full.stamp)
    kept = next(bare for _, bare in pairs if bare.status == "kept")
    assert there.documented(earlier) is earlier and there.documented(kept) is kept


@pytest.mark.parametrize("documents", [True, False])
def test_estimates_made_by_the_owner_give_the_in_process_outcomes(documents):
    """Replay's reading loop estimates some snapshots itself when the worker is behind
    (``estimate_snapshot``, with the reference std of the outcomes it has collected, here none) and
    the worker only decides them: every outcome is the in-process one, through filling, ok, kept
    (slow noise on the output), not exciting relative to the published models (a faded input) and
    a gap."""
    v, y = hammerstein_record(20_000, seed=11)
    t = np.arange(v.size) / 1000.0
    t[14_000:] += 5.0  # a gap: the window restarts
    slow = np.convolve(np.random.default_rng(3).standard_normal(y.size), 0.97 ** np.arange(200))[: y.size]
    y[6000:8000] += np.std(y) * slow[6000:8000]
    v[9000:13_000] *= 0.03
    expected, sent = [], 0
    with SolverProcess("fork", batch=3, documents=documents) as process:
        for i, (here, there) in enumerate(_fed_in_parts(t, v, y, 400)):
            expected.append(solve_snapshot(replace(here.snapshot(), published=here._published,
                                                   reference_std=here._reference_std), documents))
            here.record(expected[-1])
            snapshot = there.snapshot()
            estimate = estimate_snapshot(snapshot, documents) if i % 3 else None
            sent += estimate is not None and estimate.result is not None
            process.submit(snapshot, estimate)
        outcomes = [process.result() for _ in expected]
    statuses = {o.status for o in expected}
    assert {"filling", "ok", "kept", "not_exciting"} <= statuses and sent > 5, statuses
    for local, remote in zip(expected, outcomes, strict=True):
        assert (remote.ok, remote.status, remote.reason, remote.doc, remote.markov) == (
            local.ok, local.status, local.reason, local.doc, local.markov)
        assert np.array_equal([remote.condition_number, remote.input_std], [local.condition_number, local.input_std],
                              equal_nan=True)


def test_an_estimate_stopped_by_a_larger_reference_is_made_again_when_the_decision_passes():
    """``decide_outcome`` of an estimate that a reference std larger than the snapshot's stopped
    (no model) estimates the window again: the outcome is the one of ``solve_snapshot``."""
    v, y = hammerstein_record(3000, seed=4)
    snapshot = feed_engine(replace(CONFIG, window=2000), v, y, chunk=3000).snapshot()
    stopped = estimate_snapshot(replace(snapshot, reference_std=1e6))
    assert stopped.result is None and not stopped.status
    decided, direct = decide_outcome(snapshot, stopped), solve_snapshot(snapshot)
    assert decided.ok and (decided.doc, decided.markov) == (direct.doc, direct.markov)


def test_the_worker_keeps_the_published_model_of_the_epoch_for_the_keep_check(solver):
    """A window whose own estimate is poor (slow coloured output noise over few samples) keeps
    the model of a clean window: the worker uses the model it made in the same epoch, which never
    left it, also when both snapshots are in flight at once; a new epoch starts without one."""
    # max_relative_sd off: the poor window's bounds are wide, which would make its estimate 'uncertain'
    config = replace(CONFIG, window=1000, tau_max=40, min_fill=0.5, max_relative_sd=0.0)
    v, y = hammerstein_record(1000, seed=1)
    clean = feed_engine(config, v, y, chunk=1000).snapshot()
    slow = np.convolve(np.random.default_rng(2).standard_normal(y.size), 0.97 ** np.arange(200))[: y.size]
    noisy = replace(feed_engine(config, v, y + 0.3 * np.std(y) * slow, chunk=1000).snapshot(), epoch=clean.epoch)
    published = solve_snapshot(clean)
    local = solve_snapshot(replace(noisy, published=published.result, reference_std=published.input_std))
    assert published.ok and local.status == "kept", local.reason  # the case this test is about
    solver.submit(clean)
    solver.submit(noisy)
    first, second = solver.result(), solver.result()
    assert first.ok and (second.status, second.reason) == (local.status, local.reason)
    fresh = solver.solve(replace(noisy, epoch=noisy.epoch + 10_000))  # a reset engine: the estimate is published
    assert fresh.ok


def test_a_diagnosis_in_the_worker_is_the_in_process_one(solver):
    """``diagnose`` runs ``diagnose_window`` in the worker (the node's diagnosis process): the same
    document as in process, an unsaturated Hammerstein window diagnosed as such; a window that
    cannot be diagnosed gives the same error."""
    v, y = hammerstein_record(3000, seed=4)
    there = solver.diagnose(v, y, 3)
    _assert_same_document(there, diagnose_window(v, y, 3))
    assert there["cause"] == "none" and {"baseline", "confidence", "evidence"} <= set(there)
    short = solver.diagnose(v[:20], y[:20], 3)
    assert short == diagnose_window(v[:20], y[:20], 3) and short["error"].startswith("window not diagnosable")


def _assert_same_document(a, b, path: str = "") -> None:
    """The same keys, strings and flags; numbers within 1e-6 relative: the candidates' iterative fits
    move in the last bits with the arrays' memory alignment, which differs between processes."""
    assert type(a) is type(b), path
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for key in a:
            _assert_same_document(a[key], b[key], f"{path}/{key}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, z) in enumerate(zip(a, b, strict=True)):
            _assert_same_document(x, z, f"{path}[{i}]")
    elif isinstance(a, float):
        assert a == pytest.approx(b, rel=1e-6, abs=1e-12), path
    else:
        assert a == b, path


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]


@pytest.mark.parametrize("owner_estimates_from", [None, 0])
def test_replay_with_the_solver_process_writes_the_same_results(solver, tmp_path, monkeypatch, owner_estimates_from):
    """Also when the reading loop estimates every snapshot itself (``OWNER_ESTIMATES_FROM`` 0)."""
    if owner_estimates_from is not None:
        monkeypatch.setattr("hammer_ros.io.replay.OWNER_ESTIMATES_FROM", owner_estimates_from)
    excitation, response = parse_stream_spec("/cmd:data", "--input"), parse_stream_spec("/response:data", "--output")
    config = EngineConfig(sample_rate=100.0, window=2000)
    assert 2.0 * bag_duration(FLOAT64_BAG) > 100  # enough solves to overlap
    here = replay_bag(FLOAT64_BAG, excitation, response, config, 2.0, out=tmp_path / "here.mcap")
    there = replay_bag(FLOAT64_BAG, excitation, response, config, 2.0, out=tmp_path / "there.mcap", solver=solver)
    a, b = here.document(), there.document()
    a.pop("wall_s"), b.pop("wall_s")
    assert a == b and a["solves"] > 100
    ma, mb = _messages(tmp_path / "here.mcap"), _messages(tmp_path / "there.mcap")
    assert [(t, s) for t, s, _ in ma] == [(t, s) for t, s, _ in mb]
    differ = {t for (t, _, x), (_, _, z) in zip(ma, mb) if x != z}
    assert differ <= {"/diagnostics", "/hammer_ros/dashboard/diagnostics"}  # the solve times
    assert any(t == "/hammer_ros/model" for t, _, _ in ma)


def test_a_worker_that_dies_is_reported_not_waited_for():
    process = SolverProcess()
    try:
        v, y = hammerstein_record(2000, seed=2)
        snapshot = feed_engine(CONFIG, v, y, chunk=1000).snapshot()
        assert process.solve(snapshot).ok
        os.kill(process.pid, signal.SIGKILL)
        with pytest.raises(RuntimeError, match=r"solver process exited \(exit code -9\)"):
            process.solve(snapshot)
    finally:
        process.close()


def test_a_worker_says_when_it_is_ready_and_a_dead_one_never_is():
    """``wait_ready``: a spawned worker is ready once it has imported the solve's modules (the
    node waits for it before subscribing); a worker killed before it could start is not, and
    the wait ends when it exits instead of running to the timeout."""
    with SolverProcess() as process:
        assert process.wait_ready(60.0)
        v, y = hammerstein_record(2000, seed=2)
        assert process.solve(feed_engine(CONFIG, v, y, chunk=1000).snapshot()).ok
    process = SolverProcess()
    try:
        os.kill(process.pid, signal.SIGKILL)  # before its interpreter is up: it never reaches the imports
        assert not process.wait_ready(60.0)
    finally:
        process.close()


def test_a_snapshot_pickles_to_its_fields():
    """``EngineSnapshot`` crosses the pipe with its arrays packed (``__reduce__``): every field comes
    back, the arrays equal and writable (the compiled solve takes them as they are), with and without
    a published model, counters and a closed loop's reference."""
    import pickle

    from hammer_ros.streaming.engine import EngineSnapshot

    v, y = hammerstein_record(3000, seed=5)
    engine = StreamingEngine(CONFIG)
    engine.add_streams({"excitation": (np.arange(v.size) / 1000.0, v), "response": (np.arange(v.size) / 1000.0, y)})
    outcome = engine.solve()
    assert outcome.ok
    snapshot = engine.snapshot()
    with_reference = replace(snapshot, stats=None, published=None, reference_window=np.linspace(0.0, 1.0, v.size))
    for sent in (snapshot, with_reference):
        got = pickle.loads(pickle.dumps(sent))
        assert isinstance(got, EngineSnapshot)
        for field in ("phi_vv", "phi_yv", "phi_yvv", "v", "y", "reference_window"):
            expected, arrived = getattr(sent, field), getattr(got, field)
            assert (arrived is None) == (expected is None)
            if expected is not None:
                assert arrived.dtype == float and arrived.flags.writeable and np.array_equal(arrived, expected)
        for field in ("config", "weight", "stamp", "reference_std", "epoch"):
            assert getattr(got, field) == getattr(sent, field)
        assert (got.stats is None) == (sent.stats is None) and (got.published is None) == (sent.published is None)
    got = pickle.loads(pickle.dumps(snapshot))
    assert got.stats.aligned == snapshot.stats.aligned
    assert got.published.poles.tolist() == snapshot.published.poles.tolist()
    assert solve_snapshot(got).doc == solve_snapshot(snapshot).doc
