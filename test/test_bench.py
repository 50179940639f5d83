"""Smoke test of the ``hammer-ros bench`` machinery on tiny sizes (no timing thresholds: speed is
the benchmark's business, not the tests'). The live-node rate section is left to ``test_node``
/ ``ros_rate_probe``; the memory section runs a real node over DDS."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hammer_ros.identification.correlation import cross_correlation, weighted_cross_correlation
from hammer_ros.tools import bench

TINY = bench.Plan(
    name="tiny", repeats=1, ingest_samples=6000, ingest_taus=(5, 20), ingest_windows=(1000, 3000),
    ingest_forgetting=(1.0, 0.99), ingest_chunk=500, node_rates={}, node_seconds=0.0,
    replay_messages={1: 600, 20: 40}, replay_repeats=1, solve_windows=(600,), solve_repeats=3, slow_solve_repeats=1,
    peer_frols=((2, 2, 4),), memory_windows=(2000,),
)


def test_batch_fft_reference_is_paper_000_eq_8():
    v, y = bench.hammerstein_record(700, seed=3)
    phi = bench.batch_correlations_fft(v, y, 12)
    assert np.allclose(phi[0], cross_correlation(v, v, 12), atol=1e-15)
    assert np.allclose(phi[1], cross_correlation(v, y, 12), atol=1e-15)
    assert np.allclose(phi[2], cross_correlation(v * v, y, 12), atol=1e-15)
    weighted = bench.batch_correlations_fft(v, y, 12, forgetting=0.98)
    assert np.allclose(weighted[1], weighted_cross_correlation(v, y, 12, 0.98), atol=1e-15)


def test_bench_sections_run_on_tiny_sizes():
    sections = bench.run_sections(TINY, ("ingest", "replay", "solve", "peers", "memory"))
    ingest = sections["ingest"].rows
    assert len(ingest) == 2 * 2 * 2  # tau_max x W x (sliding, forgetting)
    for row in ingest:
        assert row["engine"] > 0 and row["reference"] > 0 and row["ratio"] > 0
        assert row["check"] < 1e-12  # the engine's sums are the batch correlations of its window
    replay = sections["replay"].rows
    assert len(replay) == 2 * len(bench.REPLAY_MODES)
    assert all(r["replay"] > 0 and r["reference"] > 0 for r in replay)
    assert all(r["cpu_s"]["reading"] > 0 and r["cpu_s"]["solver"] >= 0 and r["cpu_s"]["bare"] > 0 for r in replay)
    solve = sections["solve"].rows
    assert {r["method"] for r in solve} >= {"cls-arx", "cls-markov", "plls-hammerstein", "plls-feedback",
                                             "plls-hammerstein-feedback", "diagnose"}
    assert all(r["p50"] <= r["p99"] for r in solve if "p50" in r)
    compiled_plls = [r for r in solve if r["method"] == "plls-hammerstein (compiled)"]
    assert compiled_plls and all(r["poles_equal"] and r["reference"] > 0 and r["ratio"] > 0 for r in compiled_plls)
    loaded = [r for r in solve if "ingest_rate" in r]  # the mu-Markov solve beside ingestion: thread, process
    assert all("reference" in r for r in solve if r["method"].startswith("cls") and "p50" in r and r not in loaded)
    assert [r["method"] for r in loaded] == ["cls-markov (thread)", "cls-markov (process)", "end to end"]
    for row in loaded:
        assert row["mu"] == 30 and row["p50"] > 0
        assert 0 < row["ingest_rate"] <= 0.6 * row["ingest_limit"]  # capped at half its limit
    there, end_to_end = loaded[1:]
    assert there["p99"] == there["solve_p99"] and end_to_end["p99"] >= end_to_end["solve_p99"]  # the hand-back costs
    peers = sections["peers"].rows
    g1 = {r["method"]: r for r in peers if r["case"].startswith("G1")}
    assert g1["cls-markov"]["nrmse"] < 0.3  # the identified model simulates the plant
    if bench.sysidentpy_available():
        assert g1["FROLS"]["seconds"] > 0 and g1["cls-markov"]["speedup"] > 0
    else:
        assert any("SysIdentPy rows skipped" in note for note in sections["peers"].notes)
    memory = sections["memory"].rows
    assert memory[0]["window"] == 2000 and memory[0]["reference"] > 0 and memory[0]["solve"] >= 0
    assert memory[0]["node_complete"], memory[0]  # a real node over DDS filled its window, solved, diagnosed
    assert 50 < memory[0]["node_idle"] <= memory[0]["node_peak"] < 2000, memory[0]

    table = bench.goals(sections)
    assert {r["goal"].split(" ")[0] for r in table.rows} >= {"engine", "replay", "CLS"}
    text = bench.markdown(bench.machine(), sections, table, TINY, 1.0)
    for section in sections.values():
        assert section.title in text
    json.dumps(bench._json_safe({"sections": [s.to_json() for s in sections.values()]}), allow_nan=False)


def test_fleet_section_runs_on_tiny_sizes():
    section = bench.fleet_section(bags=8, rounds=1)
    [row] = section.rows
    assert row["serial"] > 0 and row["fleet"] > 0 and row["ratio"] > 0 and row["task"] > 0 and row["startup"] > 0
    assert 0 < row["cpu"] < 3600  # CPU seconds per hour of recorded data: far less than real time
    assert row["plain"] > 0
    assert "8 bags" in row["case"]
    assert any(g["goal"].startswith("fleet") for g in bench.goals({"fleet": section}).rows)


def test_replay_reports_the_cpu_of_its_solver_process(tmp_path):
    """``run_replay`` of a bag whose 399 periodic solves go to a forked solver process: the
    worker's CPU (a child, counted once waited for) is reported beside the reading process's, and
    it is at least what 399 CLS solves cost (more than 0.1 ms each)."""
    path = tmp_path / "bench_100.mcap"
    bench.write_bench_bag(path, 2000, 100)
    _, doc = bench.run_replay(path, 100, 4000)
    assert doc["solves"] + doc.get("solve_errors", 0) >= 390, doc
    assert doc["cpu_s"]["solver"] > 399 * 1e-4 and doc["cpu_s"]["reading"] > 0, doc["cpu_s"]


def test_the_rate_ladder_brackets_each_limit_and_narrows_it():
    """The node section's search (``_zero_loss_limits``) on a stand-in for ``ros_rate_probe``
    whose subscribers lose samples above fixed limits: each figure is a lossless rate below its
    limit with a lossy one at most x1.15 above (two geometric midpoints of a x1.5-1.7 step), the
    bare subscriber is followed past the plan's ladder, no subscriber runs above its first
    loss, and each lossy rate was confirmed by CONFIRMATIONS more runs."""
    limits = {"node": 9_200.0, "bare": 21_000.0, "foxglove": 7_400.0}
    names = {"node": "hammer_ros node", "bare": "bare rclpy", "foxglove": "hammer_ros node + foxglove client"}
    runs, calls = [], []

    def probe(rates, batch, seconds, subscribers):
        calls.append(rates[0])
        runs.extend((who, rates[0]) for who in subscribers)
        return [{"subscriber": names[who], "messages": rates[0] * seconds, "publish_seconds": seconds,
                 "lost": 0 if rates[0] <= limits[who] else 100} for who in subscribers]

    best, first_loss, tried, lower = bench._zero_loss_limits(1, (1000.0, 5000.0, 8500.0), 1.0, probe)
    assert lower == {"node": False, "bare": False, "foxglove": False}  # each lost samples above its figure
    for who, limit in limits.items():
        assert best[who] <= limit < first_loss[who] <= 1.15 * best[who], (who, best[who], first_loss[who])
        lossy = sorted({r for w, r in runs if w == who and r > limit})
        assert len(lossy) <= 1 + bench.REFINE_STEPS, (who, lossy)
        assert all(runs.count((who, r)) == 1 + bench.CONFIRMATIONS for r in lossy), (who, runs)
    assert first_loss["bare"] > 8500.0 and len(tried) == len(set(calls))


def test_a_node_that_refuses_a_rate_is_reported_not_measured():
    """A node that exits at startup (e.g. a sample rate out of its parameter range) is neither a
    lossless nor a lossy measurement of throughput: its reason is in the ``tried`` line, the
    node's figure is the highest rate it ran at without loss, a lower bound."""
    names = {"node": "hammer_ros node", "foxglove": "hammer_ros node + foxglove client"}

    def probe(rates, batch, seconds, subscribers):
        rows = []
        for who in subscribers:
            if who == "bare":
                rows.append({"subscriber": "bare rclpy", "messages": rates[0] * seconds, "publish_seconds": seconds,
                             "lost": 0 if rates[0] <= 12_000 else 100})
            elif rates[0] > 6_000:  # what ros_rate_probe._node returns for a node that exited
                rows.append({"subscriber": names[who], "messages": 0, "publish_seconds": 0.0, "lost": 0,
                             "error": "node exited 2: sample_rate: out of range"})
            else:
                rows.append({"subscriber": names[who], "messages": rates[0] * seconds,
                             "publish_seconds": seconds, "lost": 0})
        return rows

    best, first_loss, tried, lower = bench._zero_loss_limits(1, (1000.0, 5000.0, 8500.0), 1.0, probe)
    assert 5000.0 <= best["node"] <= 6000.0 < first_loss["node"] <= 8500.0
    assert lower["node"] and not lower["bare"]  # the node never lost a sample: its figure is a lower bound
    assert any("node exited 2: sample_rate: out of range" in line for line in tried)


def test_a_subscriber_the_publisher_could_not_outrun_has_a_lower_bound():
    """The bare subscriber never loses a sample, but above 60 000 msg/s the publisher keeps only
    80 % of the rate: the bare figure is the highest rate the publisher kept, marked as a lower
    bound (what the full run of 2026-12-03 21:19 reported as a measured limit), while the node,
    which lost samples above its figure, is measured."""
    names = {"node": "hammer_ros node", "bare": "bare rclpy", "foxglove": "hammer_ros node + foxglove client"}
    limits = {"node": 50_000.0, "bare": math.inf, "foxglove": 45_000.0}

    def probe(rates, batch, seconds, subscribers):
        kept = 1.0 if rates[0] <= 60_000 else 0.8
        return [{"subscriber": names[who], "messages": int(kept * rates[0] * seconds), "publish_seconds": seconds,
                 "lost": 0 if rates[0] <= limits[who] else 100} for who in subscribers]

    best, first_loss, tried, lower = bench._zero_loss_limits(1, (10_000.0, 30_000.0), 1.0, probe)
    assert lower == {"node": False, "bare": True, "foxglove": False}
    assert 45_000 < best["bare"] <= 60_000 < first_loss["bare"]
    assert best["node"] <= 50_000 < first_loss["node"]
    assert any("publisher" in line.split(" / ")[1] for line in tried)


def test_a_loss_while_the_publisher_stalled_is_measured_again():
    """``_losses`` runs a subscriber again when it lost samples in a run in which the publisher
    stalled, at most STALL_RETRIES times; a stalled run without loss is taken as it is."""
    names = {"node": "hammer_ros node", "bare": "bare rclpy", "foxglove": "hammer_ros node + foxglove client"}
    script = {  # per subscriber, the (stalled_seconds, lost) of its successive runs
        "node": [(0.3, 900), (0.0, 0)],  # a burst after a stall, then a clean run: lossless
        "bare": [(0.2, 0)],  # stalled but nothing lost: no rerun
        "foxglove": [(0.3, 50), (0.25, 40), (0.3, 30), (0.0, 0)],  # stalls every time: the last of 3 runs counts
    }
    calls = []

    def probe(rates, batch, seconds, subscribers):
        calls.append(subscribers)
        rows = []
        for who in subscribers:
            stalled, lost = script[who].pop(0)
            rows.append({"subscriber": names[who], "messages": rates[0] * seconds,
                         "publish_seconds": seconds + stalled, "stalled_seconds": stalled, "stalls": int(stalled > 0),
                         "lost": lost})
        return rows

    tried: list[str] = []
    lost = bench._losses(probe, 7000.0, 1, 1.0, ("node", "bare", "foxglove"), tried)
    assert lost == {"node": 0, "bare": 0, "foxglove": 30}
    assert calls == [("node", "bare", "foxglove"), ("node", "foxglove"), ("foxglove",)]
    assert tried == ["7000: 0 (1 rerun) / 0 / 30 (2 rerun)"]


def test_a_loss_in_a_clean_run_is_confirmed_by_another_run():
    """A subscriber that lost samples while the publisher kept its schedule runs once more
    (CONFIRMATIONS): a clean second run makes the rate lossless, a lossy one confirms the loss
    (its count is the figure); a subscriber without loss runs once."""
    script = {"node": [300, 0], "bare": [500, 200], "foxglove": [0]}
    names = {"node": "hammer_ros node", "bare": "bare rclpy", "foxglove": "hammer_ros node + foxglove client"}
    calls = []

    def probe(rates, batch, seconds, subscribers):
        calls.append(subscribers)
        return [{"subscriber": names[who], "messages": rates[0] * seconds, "publish_seconds": seconds,
                 "stalled_seconds": 0.0, "stalls": 0, "lost": script[who].pop(0)} for who in subscribers]

    tried: list[str] = []
    assert bench._losses(probe, 40_000.0, 1, 1.0, ("node", "bare", "foxglove"), tried) == {
        "node": 0, "bare": 200, "foxglove": 0}
    assert calls == [("node", "bare", "foxglove"), ("node", "bare")]
    assert tried == ["40000: 0 (1 rerun) / 200 (1 rerun) / 0"]


def test_a_publisher_that_cannot_keep_the_rate_is_not_a_measurement():
    """A publisher that falls behind again and again (more than MAX_STALLS stalls) did not keep the
    rate: its plain average counts and the rate is not a lossless one. The subscriber is run again
    (the instrument failed, e.g. on a loaded machine), at most STALL_RETRIES times; a run in which
    the publisher kept the rate is a measurement."""
    calls = []
    node_runs = [(50, 0), (0, 0)]  # (stalls, lost): the node's publisher fell short once, then kept the rate

    def probe(rates, batch, seconds, subscribers):
        calls.append(subscribers)
        rows = []
        for who in subscribers:
            stalls, lost = (50, 500) if who == "bare" else node_runs.pop(0)
            rows.append({"subscriber": "bare rclpy" if who == "bare" else "hammer_ros node",
                         "messages": rates[0] * seconds, "publish_seconds": (2 if stalls else 1) * seconds,
                         "stalled_seconds": seconds if stalls else 0.0, "stalls": stalls, "lost": lost})
        return rows

    tried: list[str] = []
    lost = bench._losses(probe, 100_000.0, 1, 1.0, ("node", "bare"), tried)
    assert lost == {"node": 0, "bare": "publisher 50000/s"}
    assert calls == [("node", "bare"), ("node", "bare"), ("bare",)]
    assert tried == ["100000: 0 (1 rerun) / publisher 50000/s (2 rerun) / -"]


def test_a_run_that_sent_too_few_messages_is_not_a_measurement():
    """A publisher that sent one message and stopped (what a stall made of the publisher's loop
    before ``Schedule.run``) kept the rate over the time it ran, but its run measured nothing:
    the subscriber is run again, and the table says why."""
    runs = [1, 1, 1]

    def probe(rates, batch, seconds, subscribers):
        return [{"subscriber": "hammer_ros node", "messages": runs.pop(0), "publish_seconds": 0.333,
                 "stalled_seconds": 0.333, "stalls": 1, "lost": 0}]

    tried: list[str] = []
    assert bench._losses(probe, 28_500.0, 100, 2.0, ("node",), tried) == {"node": "publisher sent 1 of 57000"}
    assert not runs and tried == ["28500: publisher sent 1 of 57000 (2 rerun) / - / -"]


def test_the_cpu_of_each_run_is_kept_per_subscriber_and_rate():
    """``_losses`` hands each run's CPU to the caller: the subscriber's microseconds per message
    received on the two topics and the cores it and the publisher kept busy; a row without the
    readings (no /proc) gives none, and the node's rerun replaces its first run's figures."""
    rows = {"node": [(0.3, 900, 1.40), (0.0, 0, 0.84)], "bare": [(0.0, 0, None)]}
    names = {"node": "hammer_ros node", "bare": "bare rclpy"}

    def probe(rates, batch, seconds, subscribers):
        out = []
        for who in subscribers:
            stalled, lost, cpu = rows[who].pop(0)
            out.append({"subscriber": names[who], "messages": 7000, "publish_seconds": 2.0 + stalled,
                        "stalled_seconds": stalled, "stalls": int(stalled > 0), "lost": lost,
                        "subscriber_cpu_seconds": cpu, "publisher_cpu_seconds": 0.5})
        return out

    cpu: dict = {}
    assert bench._losses(probe, 3500.0, 1, 2.0, ("node", "bare"), [], cpu) == {"node": 0, "bare": 0}
    node = cpu[("node", 3500.0)]
    assert node["us_per_message"] == pytest.approx(1e6 * 0.84 / 14_000)  # 60 us
    assert node["subscriber_cores"] == pytest.approx(0.42) and node["publisher_cores"] == pytest.approx(0.25)
    assert cpu[("bare", 3500.0)] == {}
    assert bench._cpu_cell(node) == "60 us, 0.42 + 0.25" and bench._cpu_cell({}) == "-"


def test_the_rate_probe_runs_both_subscribers_and_reads_their_cpu():
    """A real ``ros_rate_probe`` run at 300 Float64 messages/s for 1 s (publisher, node and bare
    subscriber over DDS on a private domain): every row has the messages sent and received and
    CPU seconds of the subscriber's process and of the publisher that are positive and no more
    than two cores' worth of the run (the node's read from /proc, the bare one's in process)."""
    from hammer_ros.tools.ros_rate_probe import probe

    rows = probe([300.0], batch=1, seconds=1.0, subscribers=("bare", "node"))
    assert [row["subscriber"] for row in rows] == ["bare rclpy (EventsExecutor)", "hammer_ros node"]
    for row in rows:
        assert row["messages"] >= 250 and row["received"] > 0, row
        budget = 2 * (row["publish_seconds"] + 3.0)  # two cores over the run and the counting after it
        assert 0 < row["subscriber_cpu_seconds"] < budget and 0 < row["publisher_cpu_seconds"] < budget, row


def test_the_publisher_resumes_after_a_stall_without_a_burst():
    """``ros_rate_probe.Schedule``: on time, the messages due follow the rate; after a 0.3 s stall
    at 7000/s the next call releases at most one message (not the 2000 missed), counts the stall
    and its time, and the slots go on from there; the total caps what is due."""
    from hammer_ros.tools.ros_rate_probe import MAX_LAG, Schedule

    schedule = Schedule(7000.0, 14_000, now=100.0)
    assert schedule.due(100.0) == 1
    schedule.sent = 1
    assert schedule.due(100.001) == 8  # 1 ms later: 7 more
    schedule.sent = 8
    assert schedule.due(100.0115) == 81 and schedule.stalls == 0  # 10.4 ms behind: within MAX_LAG, caught up
    schedule.sent = 81
    assert schedule.due(100.3) - 81 <= 1  # 0.29 s behind: the schedule restarts, no burst
    assert schedule.stalls == 1 and schedule.stalled == pytest.approx(0.3 - 81 / 7000.0)
    assert schedule.slot(81) == pytest.approx(100.3)
    schedule.sent = 82
    assert schedule.due(100.3105) == 155 and schedule.stalls == 1  # 10.5 ms later: at the rate again
    schedule.sent = 13_999
    assert schedule.due(schedule.slot(13_999) + MAX_LAG / 2) == 14_000 and schedule.stalls == 1


@pytest.mark.parametrize("stall", [0.05 + 0.0073 * i for i in range(40)])
def test_the_publisher_sends_every_message_through_a_stall(stall):
    """``Schedule.run`` on a monotonic clock of a long-running machine (46 000 s): after a stall
    the restarted schedule puts the next slot at now, where rounding can make no message due yet;
    the loop sleeps and goes on instead of ending (the loop before it sent 1 message of 200 here)."""
    from hammer_ros.tools.ros_rate_probe import Schedule

    now = [46_000.123]
    sent: list[int] = []

    def sleep(seconds: float) -> None:
        now[0] += seconds + 1e-6
        if len(sent) == 1 and not schedule.stalls:
            now[0] += stall  # descheduled after the first message

    schedule = Schedule(37_800.0, 200, now=now[0])
    schedule.run(sent.append, clock=lambda: now[0], sleep=sleep)
    assert sent == list(range(200)) and schedule.stalls == 1
    assert schedule.stalled == pytest.approx(stall, abs=1e-4)


def _stand_in_probe(limits: dict[str, float], runs: list):
    """A ``ros_rate_probe.probe`` whose subscribers lose samples above fixed limits."""
    names = {"node": "hammer_ros node", "bare": "bare rclpy", "foxglove": "hammer_ros node + foxglove client"}

    def probe(rates, batch, seconds, subscribers):
        runs.extend((who, rates[0]) for who in subscribers)
        return [{"subscriber": names[who], "messages": rates[0] * seconds, "publish_seconds": seconds,
                 "lost": 0 if rates[0] <= limits[who] else 100} for who in subscribers]

    return probe


@pytest.mark.parametrize("seeds", [
    {"node": 36_700.0, "bare": 30_000.0, "foxglove": 33_200.0},  # the last full run's figures, near the limits
    {"node": 15_000.0, "bare": 15_000.0, "foxglove": 15_000.0},  # no stored figures: the plan's start, far below
    {"node": 90_000.0, "bare": 60_000.0, "foxglove": 90_000.0},  # another machine's, far above
])
def test_the_seeded_search_brackets_each_limit_within_one_rung(seeds):
    """The quick bench's search (``_seeded_limits``) from any seeds: each figure is a lossless
    rung with the next rung of the grid lossy, that loss confirmed by CONFIRMATIONS more runs,
    node / bare is a power of the step (one grid), the range is the ratio's at one rung's
    resolution, and seeds near the limits cost three runs per subscriber."""
    limits = {"node": 34_000.0, "bare": 31_000.0, "foxglove": 30_500.0}
    runs: list = []
    best, first_loss, tried, lower = bench._seeded_limits(1, seeds, 1.1, 1.0, _stand_in_probe(limits, runs))
    assert lower == {"node": False, "bare": False, "foxglove": False}
    for who, limit in limits.items():
        assert best[who] <= limit < first_loss[who] <= 1.11 * best[who], (who, best[who], first_loss[who])
        assert runs.count((who, first_loss[who])) == 1 + bench.CONFIRMATIONS, (who, runs)
    steps = math.log(best["node"] / best["bare"]) / math.log(1.1)
    assert abs(steps - round(steps)) < 0.05  # the same grid for both (up to the rounding to 100 msg/s)
    row = bench._node_row(1, best, first_loss, tried, lower, {})
    low, high = row["ratio_range"]
    assert low == pytest.approx(best["node"] / first_loss["bare"]) and high == pytest.approx(
        first_loss["node"] / best["bare"]) and low < row["ratio"] < high
    per_subscriber = {who: sum(1 for w, _ in runs if w == who) for who in limits}
    if seeds["bare"] == 30_000.0:
        assert max(per_subscriber.values()) <= 3, runs  # the seed's rung, the one above and its confirmation
    assert max(per_subscriber.values()) <= bench.SEARCH_RUNS


def test_the_seeded_search_stops_at_the_cap_with_a_lower_bound():
    """A subscriber that never loses a sample climbs to LADDER_CAP and stops there: its figure is
    a lower bound and the ratio's range is open on that side."""
    limits = {"node": 25_000.0, "bare": math.inf, "foxglove": 24_000.0}
    runs: list = []
    best, first_loss, tried, lower = bench._seeded_limits(
        100, {"node": 25_000.0, "bare": 150_000.0, "foxglove": 25_000.0}, 1.1, 1.0, _stand_in_probe(limits, runs))
    assert lower["bare"] and not lower["node"] and best["bare"] <= bench.LADDER_CAP
    assert "bare" not in first_loss and max(r for w, r in runs if w == "bare") <= bench.LADDER_CAP
    row = bench._node_row(100, best, first_loss, tried, lower, {})
    assert row["ratio_range"][0] is None and row["range"].startswith("<=")
    assert row["reference"].startswith(">= ")


def test_the_full_run_stores_its_figures_for_the_quick_search(tmp_path):
    """``_store_node_limits`` writes each message type's three figures; ``stored_node_limits``
    reads them back (and gives {} for a missing or broken file)."""
    path = tmp_path / "limits.json"
    rows = [{"batch": 1, "node_rate": 36_700.0, "reference_rate": 30_000.0, "foxglove_rate": 33_200.0},
            {"batch": 100, "node_rate": 25_700.0, "reference_rate": 23_200.0, "foxglove_rate": 23_200.0}]
    assert "stored" in bench._store_node_limits(rows, path)
    doc = bench.stored_node_limits(path)
    assert doc["limits"]["100"] == {"node": 25_700.0, "bare": 23_200.0, "foxglove": 23_200.0} and doc["date"]
    path.write_text("{not json")
    assert bench.stored_node_limits(path) == {} and bench.stored_node_limits(tmp_path / "none.json") == {}
    assert set(bench.stored_node_limits()["limits"]) == {"1", "100"}  # the repository's copy


def test_a_search_out_of_runs_below_its_limit_has_a_lower_bound(monkeypatch):
    """A subscriber whose search ends after SEARCH_RUNS runs while still climbing (a seed far
    below its limit) has nothing lossy above its figure: the figure is marked as a lower bound,
    not as its limit; one bracketed within its runs is measured."""
    monkeypatch.setattr(bench, "SEARCH_RUNS", 3)
    runs: list = []
    best, first_loss, _, lower = bench._seeded_limits(
        1, {"node": 10_000.0, "bare": 10_000.0, "foxglove": 10_000.0}, 1.1, 1.0,
        _stand_in_probe({"node": 50_000.0, "bare": 10_500.0, "foxglove": 50_000.0}, runs))
    assert lower["node"] and lower["foxglove"] and "node" not in first_loss and best["node"] > 10_000.0
    assert not lower["bare"] and best["bare"] <= 10_500.0 < first_loss["bare"]


def test_the_six_joint_row_searches_the_node_and_the_bare_subscriber_only(tmp_path):
    """The six-joint row (no Foxglove run): the ladder brackets both limits, the goal is node / bare
    >= 0.9 alone, and its figures are not stored as seeds of the quick search (which has no such row)."""
    limits = {"node": 17_000.0, "bare": 15_500.0}
    runs: list = []
    best, first_loss, tried, lower = bench._zero_loss_limits(1, (4000.0, 8000.0, 16000.0, 24000.0), 1.0,
                                                             _stand_in_probe(limits, runs), None, ("node", "bare"))
    assert set(best) == {"node", "bare"} and {w for w, _ in runs} == {"node", "bare"}
    for who, limit in limits.items():
        assert best[who] <= limit < first_loss[who], (who, best[who], first_loss[who])
    row = bench._node_row(1, best, first_loss, tried, lower, {}, joints=6)
    assert row["case"].startswith("JointState of 6 joints") and row["foxglove"] == "-"
    assert row["goal"] is (row["ratio"] >= 0.9) and row["ratio"] >= 0.9
    slow = bench._node_row(1, {"node": 8000.0, "bare": 16000.0}, {"node": 9000.0, "bare": 18000.0}, [],
                           {"node": False, "bare": False}, {}, joints=6)
    assert slow["goal"] is False
    message = bench._node_row(1, {"node": 30_000.0, "bare": 30_000.0, "foxglove": 30_000.0},
                              {"node": 33_000.0, "bare": 33_000.0, "foxglove": 33_000.0}, [],
                              {"node": False, "bare": False, "foxglove": False}, {})
    path = tmp_path / "limits.json"
    bench._store_node_limits([message, row], path)
    assert bench.stored_node_limits(path)["limits"] == {"1": {"node": 30_000.0, "bare": 30_000.0,
                                                              "foxglove": 30_000.0}}


def test_the_quick_search_stops_at_its_time_budget(monkeypatch, tmp_path):
    """``node_section`` with a budget: each message type's search gets an equal share of the time
    left when it starts; no probe call (the runs of the subscribers at one rate) starts after its
    share, a search stopped unconverged says "time up", and its figures are still lossless rungs
    (the range says how wide the bracket is)."""
    import types

    from hammer_ros.tools import ros_rate_probe

    now = [1000.0]
    starts: list[tuple[int, float]] = []  # (batch, clock) at each probe call
    limits = {"node": 34_000.0, "bare": 31_000.0, "foxglove": 30_500.0}

    class Session:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def probe(self, rates, batch, seconds, subscribers):
            starts.append((batch, now[0]))
            now[0] += 2.0 * len(subscribers)  # one run: 2 s
            return _stand_in_probe(limits, [])(rates, batch, seconds, subscribers)

    monkeypatch.setattr(ros_rate_probe, "ProbeSession", Session)
    monkeypatch.setattr(bench.node, "time", types.SimpleNamespace(monotonic=lambda: now[0]))
    seeds = tmp_path / "limits.json"
    seeds.write_text(json.dumps({"limits": {"1": {"node": 15_000.0, "bare": 15_000.0, "foxglove": 15_000.0}}}))
    section = bench.node_section({1: (15_000.0,), 100: (36_000.0,)}, 1.0, 1.1, seeds, budget=20.0)
    first = [t for b, t in starts if b == 1]
    second = [t for b, t in starts if b == 100]
    assert first and second and max(first) < 1010.0  # half of 20 s
    assert min(second) > max(first) and max(second) < 1020.0
    rows = {row["batch"]: row for row in section.rows}
    assert rows[1]["tried"].endswith("time up")  # from 15 000 msg/s a search needs more than 5 runs
    for row in rows.values():
        for who, limit in limits.items():
            figure = {"node": row["node_rate"], "bare": row["reference_rate"], "foxglove": row["foxglove_rate"]}[who]
            assert figure <= limit
    assert any("20 s" in note for note in section.notes)
