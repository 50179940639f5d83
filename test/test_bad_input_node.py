"""Bad input fed to one running node (real processes over DDS, a private ROS_DOMAIN_ID): after
each, the node is alive, its /diagnostics counters match what was sent, and it identifies the
plant again once good data resumes. The tests run in order on the same node."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from ros_helpers import WAIT
from stamped_plant import NODE, RATE, WINDOW, pole_error, stamped_node

pytestmark = pytest.mark.ros

TAILS = 4  # tails sent after the burst until one arrives (each waited for WAIT / 2 s)
GOOD = 0.05  # RSS pole error of a model on one 10 s window (the truth's poles: 0.95, 0.245 +- 0.574j)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with stamped_node(tmp_path_factory.mktemp("bad_input_node"), NODE) as listener:
        while not listener.observer.count("received_response"):  # DDS may drop what precedes discovery
            listener.plant.send(100)
            listener.observer.next_solve()
        yield listener


def identifies(rig, n: int = WINDOW + 500) -> dict:
    """Good data again: a fresh model on a full window, near the truth."""
    t = rig.plant.send(n)
    model = rig.observer.fresh_model(t[-1])
    assert pole_error(model) < GOOD, model["poles"]
    assert rig.process.process.poll() is None
    return model


def test_good_data_is_identified(rig):
    identifies(rig)


def test_nan_and_inf_samples_are_skipped_and_counted(rig):
    obs = rig.observer
    before = obs.settle(rig.plant.last)
    t, v, y = rig.plant.take(1000)
    v[np.arange(3, 1000, 59)] = np.nan  # 17 samples
    y[[5, 6, 500, 900, 998]] = [np.inf, -np.inf, np.nan, np.inf, np.nan]
    rig.plant.publish(t, v, y)
    after = obs.settle(t[-1])
    assert delta(after, before, "received_excitation", "received_response", "nan_skipped", "missing_excitation",
                 "missing_response") == [1000, 1000, 17 + 5, 0, 0]
    identifies(rig)


def test_duplicate_and_out_of_order_stamps_are_skipped_and_counted(rig):
    obs = rig.observer
    t, v, y = rig.plant.take(300)
    rig.plant.publish(t, v, y)
    before = obs.settle(t[-1])
    rig.plant.publish(t[-100:], v[-100:], y[-100:])  # the last message again: 1 duplicate + 99 late per stream
    rig.plant.publish(t[100:200], v[100:200], y[100:200])  # 0.5-1 s old: out of order, not a clock reset
    after = rig.wait_for(lambda: delta(obs.diagnostics[-1], before, "received_excitation", "received_response")
                         == [200, 200] and obs.diagnostics[-1], what="the re-sent samples counted")
    assert delta(after, before, "duplicate", "late", "clock_resets", "aligned") == [2, 2 * 99 + 2 * 100, 0, 0]
    identifies(rig)


def test_a_gap_restarts_the_window_and_identification_resumes(rig):
    before = rig.observer.settle(rig.plant.last)
    rig.plant.k += int(2 * RATE)  # 2 s without samples
    identifies(rig)
    assert delta(rig.observer.settle(rig.plant.last), before, "gaps", "late", "clock_resets") == [1, 0, 0]


def test_the_clock_jumping_backwards_restarts_alignment(rig):
    """Sim time reset (or a bag played in a loop): the stamps start again from the beginning."""
    before = rig.observer.settle(rig.plant.last)
    rig.plant.k = 0
    model = identifies(rig)
    after = rig.observer.settle(rig.plant.last)
    assert delta(after, before, "clock_resets", "late", "gaps") == [1, 0, 0]
    assert model["stamp"] < 1000.0 + 2 * WINDOW / RATE


def test_a_burst_of_100000_messages_is_survived_and_counted(rig):
    """5 x 10^4 one-sample messages per topic as fast as Python can publish: what DDS or the
    subscription's history drops shows up as missing samples (holes in the stamps), what DDS
    drops also in ``*_dds_lost``."""
    from sensor_msgs.msg import JointState

    obs = rig.observer
    before = obs.settle(rig.plant.last)
    t, v, y = rig.plant.take(50_000)
    messages = {topic: JointState() for topic in rig.plant.publishers}
    cmd, state = (rig.plant.publishers[NODE[k]] for k in ("excitation_topic", "response_topic"))
    for k in range(t.size):
        ns = int(round(t[k] * 1e9))
        for publisher, field, value in ((cmd, "effort", v[k]), (state, "velocity", y[k])):
            msg = messages[publisher.topic_name]
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
            setattr(msg, field, [float(value)])
            publisher.publish(msg)
    sent = t.size
    for tails in range(1, TAILS + 1):  # a tail closes any hole at the end of the burst; DDS may drop it too
        sent += rig.plant.send(100).size
        try:
            after = obs.settle(rig.plant.last, timeout=WAIT / 2)
            break
        except AssertionError:
            if tails == TAILS:
                raise
    for stream in ("excitation", "response"):
        received, missing = delta(after, before, f"received_{stream}", f"missing_{stream}")
        assert received + missing == sent and received > 100, (stream, received, missing)
        # the middleware's own count (its message-lost status, read when /diagnostics is made) is a
        # part of the holes, possibly none of them: the rest were overwritten in the subscription's
        # history (1 100-1 800 of 8 000-12 000 before the shared decode; 0 of 199 in a CI run after)
        lost = delta(after, before, f"{stream}_dds_lost")[0]
        assert 0 <= lost <= missing, (stream, lost, missing)
    assert rig.process.process.poll() is None
    identifies(rig)


WRONG_TYPE_PUBLISHER = """
import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("wrong_type")
publisher = node.create_publisher(String, "/bi/cmd", 10)
node.create_timer(0.05, lambda: publisher.publish(String(data="not a JointState")))
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""


def test_a_publisher_of_the_wrong_type_is_reported(rig, tmp_path):
    """Another process publishes std_msgs/String on the command topic: DDS never delivers it to
    the node's JointState subscription, so the node reports the publisher by its type."""
    obs = rig.observer
    with open(tmp_path / "wrong.log", "w") as log:
        wrong = subprocess.Popen([sys.executable, "-c", WRONG_TYPE_PUBLISHER], env=rig.env, stdout=log,
                                 stderr=subprocess.STDOUT)
    try:
        status = rig.wait_for(lambda: next((d for d in obs.diagnostics[-1:] if "std_msgs/msg/String" in d["message"]),
                                           None), what="the wrong type in /diagnostics")
        assert "excitation_topic /bi/cmd has publishers of std_msgs/msg/String, expected sensor_msgs/msg/JointState" \
            in status["message"] and status["level"] >= 1
        identifies(rig)  # the right publisher still gets through
    finally:
        wrong.send_signal(signal.SIGINT)
        assert wrong.wait(timeout=10) == 0
    rig.wait_for(lambda: "std_msgs/msg/String" not in obs.next_solve()["message"], what="the report to clear")


def test_a_publisher_that_dies_and_comes_back(rig):
    """The node goes on without input, says that no publisher is matched, and takes the
    publisher back (one gap)."""
    before = rig.observer.settle(rig.plant.last)
    assert (before["excitation_publishers"], before["response_publishers"]) == ("1", "1")
    assert 0 < float(before["cpu_percent"]) < 100 * os.cpu_count(), before["cpu_percent"]  # ingesting: busy
    rig.plant.destroy_publishers()
    rig.wait_for(lambda: rig.observer.next_solve()["excitation_publishers"] == "0", what="no matched publisher")
    rig.plant.create_publishers()
    rig.wait_for(lambda: rig.observer.next_solve()["response_publishers"] == "1", what="the publisher matched again")
    rig.plant.k += int(3 * RATE)  # it was gone for 3 s of its clock
    identifies(rig)
    assert delta(rig.observer.settle(rig.plant.last), before, "gaps") == [1]


def test_standing_still_keeps_the_last_good_model_marked_stale(rig):
    """After good data, a constant command for 30 s of stamps (3 windows, published in 1 s steps
    with a solve after each): no NaN or absurd pole is ever published; the node says the input is
    not persistently exciting and keeps publishing the last good model, marked stale."""
    good = identifies(rig)
    obs = rig.observer
    seen = len(obs.models)
    for _ in range(30):
        rig.plant.send(int(RATE), constant=0.3)
        obs.next_solve()
    status = rig.wait_for(lambda: next((d for d in obs.diagnostics[-1:] if "not persistently exciting" in d["message"]),
                                       None), what="'not persistently exciting' in /diagnostics")
    assert status["level"] == 1 and "publishing the last good model as stale" in status["message"]
    during = obs.models[seen:]
    assert during and all(np.all(np.isfinite(np.array(m["poles"], dtype=float))) for m in during)
    assert all(np.max(np.abs([complex(*p) for p in m["poles"]])) < 1.0 for m in during)
    assert all(pole_error(m) < 0.15 for m in during)
    last_fresh = [m for m in [good, *during] if not m["stale"]][-1]
    stale = rig.wait_for(lambda: obs.models[-1]["stale"] and obs.models[-1], what="a stale model")
    assert stale["poles"] == last_fresh["poles"] and "not persistently exciting" in stale["stale_reason"]
    assert obs.count("not_exciting") > 0
    identifies(rig)  # moving again


def test_plls_partition_with_an_empty_interval_is_reported_and_the_model_kept(rig):
    from rclpy.parameter import Parameter

    good = identifies(rig)
    results = set_parameters(rig, full=True, method="plls-hammerstein", partition=[5.0, 6.0, 7.0])
    assert [r.successful for r in results] == [True, True], [r.reason for r in results]
    status = rig.wait_for(lambda: next((d for d in rig.observer.diagnostics[-1:] if "holds no sample" in d["message"]),
                                       None), what="the empty interval in /diagnostics")
    assert status["level"] == 2 and rig.observer.count("solve_failures") > 0
    stale = rig.wait_for(lambda: rig.observer.models[-1]["stale"] and rig.observer.models[-1], what="a stale model")
    assert stale["poles"] == good["poles"]
    assert set_parameters(rig, method="cls-markov", partition=Parameter("partition", Parameter.Type.DOUBLE_ARRAY,
                                                                        [])) == [True, True]
    identifies(rig)


def test_bad_field_paths_are_rejected_or_counted(rig):
    obs = rig.observer
    [rejected] = set_parameters(rig, full=True, excitation_field="efort[:]")
    assert not rejected.successful and "efort" in rejected.reason
    assert set_parameters(rig, excitation_field="name[0]") == [True]  # exists at run time, but holds a string
    before = obs.count("excitation_field_errors")
    rig.plant.publish(*rig.plant.take(500), name=["joint0"])
    rig.wait_for(lambda: obs.count("excitation_field_errors") - before == 5, what="5 field errors")
    assert "not numeric" in obs.diagnostics[-1]["message"]
    assert set_parameters(rig, excitation_field="position[0]") == [True]  # an empty array in these messages
    rig.plant.publish(*rig.plant.take(300))
    rig.wait_for(lambda: obs.count("excitation_field_errors") - before == 8, what="3 more field errors")
    assert set_parameters(rig, excitation_field="effort[:]") == [True]
    identifies(rig)


def delta(after: dict, before: dict, *keys: str) -> list[int]:
    return [int(float(after[k])) - int(float(before[k])) for k in keys]


def set_parameters(rig, full: bool = False, **values):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(rig.node, "hammer_ros")
    rig.wait_for(client.services_are_ready, what="the node's parameter services")
    parameters = [v if isinstance(v, Parameter) else Parameter(k, value=v) for k, v in values.items()]
    results = rig.wait_future(client.set_parameters(parameters)).results
    return results if full else [r.successful for r in results]
