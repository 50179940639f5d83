"""The node's services ~/reset, ~/solve and ~/diagnose (std_srvs/srv/Trigger) on a running node
fed by the test (``stamped_plant``), so the window's content is known at every call. The tests
run in order on the same node."""

from __future__ import annotations

import json

import pytest
from stamped_plant import NODE, WINDOW, pole_error, stamped_node

pytestmark = pytest.mark.ros

SERVICE_NODE = {**NODE, "solve_rate": 0.01, "diagnosis_period": 0.0, "diagnosis_window": WINDOW}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with stamped_node(tmp_path_factory.mktemp("services"), SERVICE_NODE) as listener:
        listener.diagnoses = listener.subscribe_json("/hammer_ros/diagnosis")
        yield listener


def call(rig, service: str):
    """(success, message) of a Trigger call of /hammer_ros/<service>."""
    from std_srvs.srv import Trigger

    client = getattr(rig, f"client_{service}", None)
    if client is None:
        client = rig.node.create_client(Trigger, f"/hammer_ros/{service}")
        setattr(rig, f"client_{service}", client)
    rig.wait_for(client.service_is_ready, what=f"the service /hammer_ros/{service}")
    response = rig.wait_future(client.call_async(Trigger.Request()), what=f"the reply of /hammer_ros/{service}")
    return response.success, response.message


def call_until(rig, service: str, accept, what: str):
    """Call ``service`` until ``accept(success, message)`` (the samples sent are on their way)."""
    last = None

    def accepted():
        nonlocal last
        last = call(rig, service)
        return accept(*last)

    try:
        rig.wait_for(accepted, what=what)
    except AssertionError:
        raise AssertionError(f"{what}; last reply {last}") from None
    return last


def test_solve_and_diagnose_refuse_while_the_window_fills(rig):
    rig.plant.send(100)  # a twentieth of the window; the node needs a quarter
    ok, message = call(rig, "solve")
    assert not ok and "full (need 500 samples)" in message
    ok, message = call(rig, "diagnose")
    assert not ok and message.startswith("cannot diagnose: window") and "full" in message
    assert rig.process.process.poll() is None


def test_solve_replies_with_the_model_json_and_publishes_it(rig):
    t = rig.plant.send(WINDOW + 500)
    _, message = call_until(rig, "solve", lambda ok, m: ok and json.loads(m)["stamp"] == pytest.approx(t[-1]),
                            what="a model of the whole window from ~/solve")
    model = json.loads(message)
    assert model["samples"] == WINDOW and not model["stale"]
    assert pole_error(model) < 0.05
    assert {"poles", "zeros", "a", "b", "nonlinearity", "fit_percent"} <= set(model)
    rig.wait_for(lambda: rig.observer.models and rig.observer.models[-1] == model, what="the same model on ~/model")


def test_diagnose_replies_with_the_diagnosis_json_and_publishes_it(rig):
    ok, message = call(rig, "diagnose")
    assert ok, message
    doc = json.loads(message)
    assert doc["samples"] == WINDOW and doc["cause"] == "none"  # a clean Hammerstein system
    assert {"baseline", "confidence", "evidence", "seconds"} <= set(doc)
    rig.wait_for(lambda: rig.diagnoses and rig.diagnoses[-1] == doc, what="the same diagnosis on ~/diagnosis")
    call(rig, "solve")  # publishes /diagnostics
    rig.wait_for(lambda: rig.observer.diagnostics[-1]["diagnosis"].startswith("process "),  # never the node's lock
                 what="/diagnostics saying the diagnosis ran in the diagnosis process")
    assert rig.observer.diagnostics[-1]["diagnosis"] != rig.observer.diagnostics[-1]["solver"]


def test_a_lost_diagnosis_process_is_reported_and_the_node_diagnoses_on(rig):
    """When the diagnosis process is killed, the next diagnosis runs in the node's thread (the
    same answer) and /diagnostics says why."""
    import os
    import signal

    diagnosis = rig.observer.diagnostics[-1]["diagnosis"]
    assert diagnosis.startswith("process "), diagnosis
    os.kill(int(diagnosis.split()[1]), signal.SIGKILL)
    ok, message = call(rig, "diagnose")
    assert ok, message
    assert json.loads(message)["cause"] == "none"
    call(rig, "solve")  # publishes /diagnostics
    rig.wait_for(lambda: rig.observer.diagnostics[-1]["diagnosis"].startswith("thread (the diagnosis process exited "
                                                                               "(exit code -9))"),
                 what="/diagnostics reporting the lost diagnosis process")
    assert rig.process.process.poll() is None


def test_solve_and_diagnose_refuse_a_window_that_is_not_exciting(rig):
    rig.plant.send(WINDOW, constant=0.2)  # standing still for a whole window
    _, message = call_until(rig, "solve", lambda ok, m: not ok and "not persistently exciting" in m,
                            what="~/solve refusing a constant input")
    assert message.startswith("no model: not persistently exciting")
    ok, message = call(rig, "diagnose")
    assert not ok and message.startswith("cannot diagnose: not persistently exciting")


def test_reset_clears_the_window_and_keeps_the_parameters(rig):
    ok, message = call(rig, "reset")
    assert ok and f"({WINDOW} samples dropped)" in message and "parameters kept" in message
    ok, message = call(rig, "solve")
    assert not ok and "window 0 % full" in message
    t = rig.plant.send(WINDOW)
    _, message = call_until(rig, "solve", lambda ok, m: ok and json.loads(m)["stamp"] == pytest.approx(t[-1]),
                            what="a model of the new window after ~/reset")
    model = json.loads(message)
    assert model["samples"] == WINDOW and model["order"] == NODE["order"]  # the parameters stayed
    assert pole_error(model) < 0.05
    assert rig.process.process.poll() is None


def test_a_lost_solver_process_is_reported_and_the_node_solves_on(rig):
    """The node solves in a worker process of its own (``solver_process``); when that process is
    killed, the node says so on /diagnostics and solves in its own thread from then on."""
    import os
    import signal

    solver = rig.observer.diagnostics[-1]["solver"]
    assert solver.startswith("process "), solver
    os.kill(int(solver.split()[1]), signal.SIGKILL)
    t = rig.plant.send(500)
    _, message = call_until(rig, "solve", lambda ok, m: ok and json.loads(m)["stamp"] == pytest.approx(t[-1]),
                            what="a model from ~/solve after the solver process was killed")
    assert pole_error(json.loads(message)) < 0.05
    rig.wait_for(lambda: rig.observer.diagnostics[-1]["solver"].startswith("thread (the solver process exited "
                                                                            "(exit code -9))"),
                 what="/diagnostics reporting the lost solver process")
    assert rig.process.process.poll() is None
