"""Section 2, node: the highest publish rate at which the live node loses no sample vs a bare rclpy
subscriber (``ros_rate_probe``), by ladders or by the seeded search from the last run's figures."""

from __future__ import annotations

import contextlib
import datetime
import functools
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .common import (
    DATA_DIR,
    Section,
)

LADDER_STEP = 1.5  # beyond the plan's ladder, each rate is this much above the one before
LADDER_CAP = 200_000.0  # msg/s; no publisher here gets near it
REFINE_STEPS = 2  # rates tried between a subscriber's last lossless rate and its first lossy one
REFINE_RATIO = 1.08  # ... while the two are further apart than this
STALL_RETRIES = 2  # reruns of a subscriber whose run the publisher spoiled (a stall, or short of the rate: ``_losses``)
CONFIRMATIONS = 1  # reruns of a subscriber that lost samples in a clean run, before the rate counts as lost
MAX_STALLS = 3  # more stalls in one run: the publisher cannot keep the rate (its average counts, stalls included)
SUBSCRIBER_KEYS = {"hammer_ros node": "node", "hammer_ros node + foxglove client": "foxglove"}  # else "bare"


def _past_the_bare_limit(ladder: Sequence[float], failed):
    """The plan's rates, then (while the bare subscriber has not lost a sample, i.e. is not in
    ``failed``) rates LADDER_STEP apart up to LADDER_CAP, so that the bare figure is a measured
    limit, not the ladder's top."""
    yield from ladder
    rate = float(ladder[-1]) if ladder else 1000.0
    while "bare" not in failed and rate * LADDER_STEP <= LADDER_CAP:
        rate = float(round(rate * LADDER_STEP, -2))
        yield rate


def _losses(probe, rate: float, batch: int, seconds: float, subscribers: tuple[str, ...],
            tried: list[str], cpu: dict[tuple[str, float], dict[str, float]] | None = None,
            confirmations: int = CONFIRMATIONS, retries: int = STALL_RETRIES,
            runs: dict[str, int] | None = None) -> dict[str, Any]:
    """Samples lost by each of ``subscribers`` at ``rate`` (or why the rate is not a measurement);
    a line for the table goes to ``tried``, the CPU of each run to ``cpu[(who, rate)]``
    (``_cpu_use``). The rate the publisher kept leaves out the time of up to MAX_STALLS stalls
    (``ros_rate_probe._publish``: it fell more than MAX_LAG behind its schedule); with more, its
    plain average counts, and below 95 % of ``rate``, or with fewer than 95 % of the run's
    messages sent, the run is not a measurement of the subscriber. A subscriber whose publisher
    fell short so, or that lost samples in a run in which the publisher stalled, is run again, up
    to ``retries`` (STALL_RETRIES) times: the instrument failed. A loss in a clean run is confirmed by
    ``confirmations`` (CONFIRMATIONS) more runs, so that one hiccup of the shared machine does not
    end a subscriber's ladder (both subscribers alike; the seeded search confirms only the loss
    that decides a figure). The figure is the last run's. ``runs``: each subscriber's count of
    probe runs, reruns included, is added to it."""
    lost: dict[str, Any] = {}
    reruns: dict[str, int] = {}
    confirmed: dict[str, int] = {}
    running = tuple(subscribers)
    while running:
        with contextlib.redirect_stdout(sys.stderr):  # the probe logs its rows on stdout
            results = probe([rate], batch=batch, seconds=seconds, subscribers=running)
        again = []
        for row in results:
            who = SUBSCRIBER_KEYS.get(row["subscriber"], "bare")
            if runs is not None:
                runs[who] = runs.get(who, 0) + 1
            stalled = row.get("stalled_seconds", 0.0) if row.get("stalls", 0) <= MAX_STALLS else 0.0
            achieved = row["messages"] / max(row["publish_seconds"] - stalled, 1e-9)
            planned = int(rate * seconds)
            slow, short = achieved < 0.95 * rate, row["messages"] < 0.95 * planned
            behind = slow or short
            lost[who] = (f"publisher {achieved:.0f}/s" if slow else
                         f"publisher sent {row['messages']} of {planned}" if short else row["lost"])
            if "error" in row:  # the node did not run at this rate
                lost[who] = row["error"]
            if row.get("foxglove_messages", 1) == 0:  # the client never connected: not a measurement
                lost[who] = "no Foxglove message"
            if cpu is not None:
                cpu[(who, rate)] = _cpu_use(row)
            lossy = isinstance(lost[who], int) and lost[who] > 0
            instrument = behind or (stalled > 0 and lossy)
            if "error" in row:
                continue
            if instrument and reruns.get(who, 0) < retries:
                reruns[who] = reruns.get(who, 0) + 1
                again.append(who)
            elif lossy and not instrument and confirmed.get(who, 0) < confirmations:
                confirmed[who] = confirmed.get(who, 0) + 1
                reruns[who] = reruns.get(who, 0) + 1
                again.append(who)
        running = tuple(again)

    def cell(who: str) -> str:
        return "-" if who not in lost else f"{lost[who]}" + (f" ({reruns[who]} rerun)" if who in reruns else "")

    tried.append(f"{rate:g}: {cell('node')} / {cell('bare')} / {cell('foxglove')}")
    return lost


def _cpu_use(row: dict[str, Any]) -> dict[str, float]:
    """Of one probe run: the subscriber's CPU microseconds per message received (both topics'
    messages) and the cores it and the publisher kept busy on average (CPU seconds / publishing
    time); empty where the probe could not read them."""
    messages = 2 * row["messages"]
    subscriber, publisher = row.get("subscriber_cpu_seconds"), row.get("publisher_cpu_seconds")
    if subscriber is None or publisher is None or not messages or row["publish_seconds"] <= 0:
        return {}
    return {"us_per_message": 1e6 * subscriber / messages, "subscriber_cores": subscriber / row["publish_seconds"],
            "publisher_cores": publisher / row["publish_seconds"]}


def _cpu_cell(use: dict[str, float]) -> str:
    if not use:
        return "-"
    return f"{use['us_per_message']:.0f} us, {use['subscriber_cores']:.2f} + {use['publisher_cores']:.2f}"


def _zero_loss_limits(batch: int, ladder: Sequence[float], seconds: float, probe, cpu: dict | None = None,
                      subscribers: tuple[str, ...] = ("node", "bare", "foxglove")):
    """(highest lossless rate, first rate that was not lossless, rates tried, lower bounds) of the
    node, the bare subscriber and the node with a Foxglove client: the ladder
    (``_past_the_bare_limit``), then REFINE_STEPS geometric midpoints between each one's last
    lossless and first other rate. A figure is a lower bound (``lower[who]``) when no run of that
    subscriber lost samples: every rate above it was not a measurement (the publisher could not
    keep it, the node refused it) or the ladder reached its cap. ``cpu``: filled as by ``_losses``;
    ``subscribers``: those searched (the six-joint row has no Foxglove client)."""
    best = dict.fromkeys(subscribers, 0.0)
    first_loss: dict[str, float] = {}
    lossy: set[str] = set()  # subscribers that lost samples in a run (not only a failed instrument)
    tried: list[str] = []

    def measure(rate: float, running: tuple[str, ...]) -> None:
        for who, lost in _losses(probe, rate, batch, seconds, running, tried, cpu).items():
            if lost == 0:
                best[who] = rate
            else:
                first_loss[who] = min(rate, first_loss.get(who, math.inf))
                if isinstance(lost, int):
                    lossy.add(who)

    for rate in _past_the_bare_limit(ladder, first_loss):
        measure(rate, tuple(w for w in best if w not in first_loss))
        if len(first_loss) == len(best):
            break
    for who in best:
        for _ in range(REFINE_STEPS if best[who] and who in first_loss else 0):
            if first_loss[who] <= REFINE_RATIO * best[who]:
                break
            measure(float(round(math.sqrt(best[who] * first_loss[who]), -2)), (who,))
    return best, first_loss, tried, {who: who not in lossy for who in best}


JOINTS = 6  # the node section's JointState row: joints of one topic, each a channel of one node
NODE_LIMITS = DATA_DIR / "bench_node_limits.json"  # the last run's figures: where the quick search starts
SEARCH_RUNS = 9  # probe runs per subscriber at most in the seeded search, reruns included (a seed 2.3 x off takes 9)
SEARCH_RETRIES = 1  # its reruns of a run the publisher spoiled (the ladders': STALL_RETRIES)


@dataclass
class _Search:
    """One subscriber's search on rungs k (rate = anchor x step^k): from its seed's rung up while
    lossless, down while not, by 1, 2, 4 ... rungs, until a lossless rung lies below a lossy one;
    then bisection until they are adjacent. The lossy rung that decides the figure is run once
    more (the ladder's CONFIRMATIONS, for the one loss that matters): lossless then, the search
    climbs on from the next rung. Its figure is then known to within one step."""

    index: int
    lossless: int | None = None
    lossy: int | None = None
    confirmed: bool = False  # the run at ``lossy`` was confirmed (or was not a sample loss)
    stride: int = 1
    runs: int = 0  # probe runs, reruns included (``_seeded_limits`` counts them)

    def record(self, ok: bool, sample_loss: bool) -> None:
        if self.lossy is not None and self.index == self.lossy and self.lossless == self.index - 1:  # confirming
            self.confirmed = not ok
            if ok:  # its limit is near: climb one rung, then 2, 4 ...
                self.lossless, self.lossy, self.stride = self.index, None, 1
                self.index += 1
            return
        if ok:
            self.lossless = self.index if self.lossless is None else max(self.lossless, self.index)
        elif self.lossy is None or self.index < self.lossy:
            self.lossy, self.confirmed = self.index, not sample_loss
        if self.lossless is not None and self.lossy is not None:
            gap = self.lossy - self.lossless
            self.index = (self.lossless + self.lossy) // 2 if gap > 1 else self.lossy
        else:
            self.index += self.stride if ok else -self.stride
            self.stride *= 2

    @property
    def done(self) -> bool:
        return (self.lossless is not None and self.lossy is not None and self.lossy - self.lossless <= 1
                and self.confirmed)


def _seeded_limits(batch: int, seeds: dict[str, float], step: float, seconds: float, probe,
                   cpu: dict | None = None, deadline: float = math.inf):
    """What ``_zero_loss_limits`` returns, by a search (``_Search``) of each subscriber from its
    seed (the last run's figure) on one grid of rungs ``step`` apart anchored at the bare
    subscriber's seed, so that node / bare is a power of ``step`` and each figure lies within one
    step of its limit. Each round runs the subscribers still searching (those at the same rate
    in one ``_losses`` call, with its reruns of a failed instrument). A subscriber that would go
    above LADDER_CAP stops there, below 100 msg/s at 0; one stops after SEARCH_RUNS probe runs
    (reruns of a spoiled run, at most SEARCH_RETRIES each, included; its
    figure a lower bound when nothing above it was lossy then, its bracket wider than a rung when
    a lossy rung lies further up). No run starts once ``time.monotonic()`` has reached ``deadline`` (the
    quick bench's time): the searches stop where they are, with the same figures and flags as
    one out of runs (``tried`` ends with "time up" then)."""
    anchor = seeds["bare"]

    def rate(k: int) -> float:
        return float(round(anchor * step**k, -2))

    searches = {who: _Search(round(math.log(seeds[who] / anchor) / math.log(step))) for who in ("node", "bare",
                                                                                                "foxglove")}
    lossy: set[str] = set()
    tried: list[str] = []

    def searching(who: str) -> bool:
        search = searches[who]
        return not search.done and search.runs < SEARCH_RUNS and 100.0 <= rate(search.index) <= LADDER_CAP

    while (running := [who for who in searches if searching(who)]) and time.monotonic() < deadline:
        rungs = {who: searches[who].index for who in running}  # one run of each per round
        for k in sorted(set(rungs.values())):
            if time.monotonic() >= deadline:
                break
            group = tuple(who for who in running if rungs[who] == k)
            runs: dict[str, int] = {}
            for who, lost in _losses(probe, rate(k), batch, seconds, group, tried, cpu, confirmations=0,
                                     retries=SEARCH_RETRIES, runs=runs).items():
                searches[who].runs += runs.get(who, 0)
                sample_loss = isinstance(lost, int) and lost > 0
                searches[who].record(lost == 0, sample_loss)
                if sample_loss:
                    lossy.add(who)
    if any(searching(who) for who in searches):
        tried.append("time up")
    best = {who: rate(s.lossless) if s.lossless is not None else 0.0 for who, s in searches.items()}
    first_loss = {who: rate(s.lossy) for who, s in searches.items() if s.lossy is not None}
    # a lower bound: no sample lost at all, or nothing lossy above the figure when the search stopped
    return best, first_loss, tried, {who: who not in lossy or s.lossy is None for who, s in searches.items()}


def stored_node_limits(path: Path = NODE_LIMITS) -> dict[str, Any]:
    """The figures the last run stored ({"date", "plan", "limits": {batch: {subscriber: msg/s}}}), or {}."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _store_node_limits(rows: list[dict], path: Path = NODE_LIMITS, plan: str = "full") -> str:
    """Write each message row's three figures to ``path`` for the quick search (not the JointState
    row's: the quick bench has none); a note saying so (or why not)."""
    limits = {str(r["batch"]): {"node": r["node_rate"], "bare": r["reference_rate"], "foxglove": r["foxglove_rate"]}
              for r in rows if r.get("reference_rate") and not r.get("joints")}  # the quick search's seeds
    doc = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "plan": plan,
           "limits": limits}
    try:
        path.write_text(json.dumps(doc, indent=1) + "\n")
    except OSError as exc:
        return f"figures not stored for the quick search ({path}: {exc.strerror or exc})"
    return f"figures stored in `{path.name}` (hammer_ros/data), where `bench --quick` starts its search"


def _range_cell(low: float | None, high: float | None) -> str:
    if low is None and high is None:
        return "-"
    if low is None:
        return f"<= {high:.2f}"
    return f">= {low:.2f}" if high is None else f"{low:.2f} - {high:.2f}"


def _node_row(batch: int, best: dict[str, float], first_loss: dict[str, float], tried: list[str],
              lower: dict[str, bool], cpu: dict, joints: int = 0) -> dict[str, Any]:
    """The node section's row of one message type from a search's figures (``_zero_loss_limits``);
    ``joints``: the row of one JointState topic read by that many channels (no Foxglove run)."""
    at_limit = {who: cpu.get((who, rate), {}) for who, rate in best.items() if who in ("node", "bare")}
    at_loss = {who: cpu.get((who, rate), {}) for who, rate in first_loss.items() if who in ("node", "bare")}
    node, bare, foxglove = best["node"], best["bare"], best.get("foxglove")
    ratio = node / bare if bare else None
    foxglove_ratio = foxglove / node if node and foxglove is not None else None
    # each true limit lies in [figure, first other rate); a lower bound's bracket is open above
    low = node / first_loss["bare"] if "bare" in first_loss and not lower["bare"] else None
    high = first_loss["node"] / bare if "node" in first_loss and not lower["node"] and bare else None
    label = (f"JointState of {joints} joints, {joints} channels (1 sample each)" if joints else
             "Float64 (1 sample)" if batch == 1 else f"Float64MultiArray ({batch} samples)")
    at_least = {who: ">= " if lower[who] else "" for who in best}
    return {"case": label, "batch": batch, "node": f"{at_least['node']}{node:g} ({node * batch:g})",
            "node_rate": node, "reference": f"{at_least['bare']}{bare:g}", "reference_rate": bare,
            "ratio": ratio, "ratio_range": [low, high], "range": _range_cell(low, high),
            "foxglove": "-" if foxglove is None else f"{foxglove:g} ({foxglove_ratio or 0:.2f})",
            "foxglove_rate": foxglove, "foxglove_ratio": foxglove_ratio,
            "tried": "; ".join(tried), "ladder_top": lower["bare"], "lower_bound": lower,
            "first_other_rate": first_loss,
            "cpu": "; ".join(f"{who} {_cpu_cell(use)}" for who, use in at_limit.items()),
            "cpu_at_limit": at_limit, "cpu_at_first_loss": at_loss,
            "joints": joints,
            "goal": None if ratio is None or (foxglove_ratio is None and not joints) else
            ratio >= 0.9 and (bool(joints) or foxglove_ratio >= 0.9)}


def node_section(rates: dict[int, Sequence[float]], seconds: float, step: float | None = None,
                 limits_path: Path = NODE_LIMITS, joint_rates: Sequence[float] = (),
                 budget: float | None = None) -> Section:
    """Highest zero-loss message rate of the node vs a bare rclpy subscriber (``ros_rate_probe``),
    climbing each ladder until both have lost samples (or the publisher cannot keep the rate),
    and storing the figures in ``limits_path``; with ``step``, by the seeded search from the
    figures stored there (``_seeded_limits``; ``rates[batch][-1]`` where there are none).
    ``joint_rates``: also the row of one JointState of JOINTS joints read by JOINTS channels of one
    node against a bare subscriber of that topic (``ProbeSession.joints_probe``), by the ladder.
    ``budget``: seconds for the seeded searches, each message type's search given an equal share
    of what is left when it starts (its processes' start included)."""
    section = Section("node", f"2. Live node: highest rate with zero lost samples ({seconds:g} s per rate)", [
        ("case", "message"), ("node", "node: max msg/s (samples/s)"), ("reference", "bare rclpy: max msg/s"),
        ("ratio", "node / bare"), ("range", "node / bare if each limit is anywhere in its bracket"),
        ("foxglove", "node + Foxglove client: max msg/s (/ node)"),
        ("tried", "msg/s per topic: samples lost by node / bare / node + Foxglove client"),
        ("cpu", "CPU at each one's max rate: us per message received; subscriber + publisher cores"),
        ("goal", "goal >= 0.9")])
    try:
        from ..ros_rate_probe import ProbeSession
    except ImportError as exc:  # rclpy missing: an apt ROS install not sourced, or no [ros] extra
        section.notes.append(f"skipped: {exc}")
        return section
    stored = stored_node_limits(limits_path) if step else {}
    end = time.monotonic() + (budget if budget is not None else math.inf)
    for left, (batch, ladder) in zip(range(len(rates), 0, -1), rates.items()):
        cpu: dict[tuple[str, float], dict[str, float]] = {}
        now = time.monotonic()
        deadline = now + (end - now) / left  # an equal share of the time left
        with ProbeSession() as session:  # one per message type: DDS keeps a topic's first type in a participant
            if step:
                seeds = stored.get("limits", {}).get(str(batch), {})
                seeds = {who: float(seeds.get(who) or ladder[-1]) for who in ("node", "bare", "foxglove")}
                best, first_loss, tried, lower = _seeded_limits(batch, seeds, step, seconds, session.probe, cpu,
                                                                deadline)
            else:
                best, first_loss, tried, lower = _zero_loss_limits(batch, ladder, seconds, session.probe, cpu)
        section.rows.append(_node_row(batch, best, first_loss, tried, lower, cpu))
    if joint_rates:
        cpu = {}
        who = ("node", "bare")
        with ProbeSession() as session:
            probe = functools.partial(session.joints_probe, joints=JOINTS)
            best, first_loss, tried, lower = _zero_loss_limits(1, joint_rates, seconds, probe, cpu, who)
        section.rows.append(_node_row(1, best, first_loss, tried, lower, cpu, joints=JOINTS))
    if step:
        origin = (f"the {stored.get('plan', 'full')} run of {stored['date']}" if stored.get("date") else
                  f"the plan's {', '.join(f'{r[-1]:g}' for r in rates.values())} msg/s (no figures stored)")
        section.notes.append(f"quick search: each subscriber starts at its figure of {origin} "
                             f"(`{limits_path.name}` in hammer_ros/data) on rungs x{step:g} apart (one grid per "
                             "message, anchored at the bare subscriber's figure), goes up while lossless and down "
                             "while not by 1, 2, 4 ... rungs, then bisects until its last lossless and first other "
                             f"rate are one rung apart (at most {SEARCH_RUNS} probe runs each, reruns of a run the "
                             f"publisher spoiled, at most {SEARCH_RETRIES} per rate, included): each figure is within "
                             f"x{step:g} of its limit (or its range says how far), and the range column is what "
                             "node / bare can be at that resolution"
                             + ("" if budget is None else
                                f"; the searches have {budget:g} s (each message type an equal share of what is "
                                "left when it starts): one that has not converged then stops where it is ('time up' "
                                "in the rates tried), its bracket wider than a rung"))
    if section.rows:
        section.notes.append(_store_node_limits(section.rows, limits_path, "quick" if step else "full"))
    section.notes.append("`ros_rate_probe`: one publisher process per message type sends both topics (reliable, "
                         "depth 1000) for the stated time, from the moment both ends have matched both topics, to "
                         "the bare subscriber (EventsExecutor, counting) and to a `hammer-ros node` (window 4000, "
                         "cls-markov, 4 solves/s; its /diagnostics counters), and "
                         "to one more with its Foxglove server on (`foxglove_port`) and one WebSocket client "
                         "subscribed to every channel (goal: >= 0.9 of the node's rate, i.e. at most 10 % lower); "
                         "each subscriber has topics of its own, and the publisher and the subscribers are started "
                         "once per message type and kept for all its runs (before each run the node's sample_rate "
                         "is set and its window and counters reset by ~/reset, after it reset again: it idles on "
                         "an empty window while the others run); "
                         "a rate counts when the publisher kept >= 95 % of it, sent >= 95 % of the run's messages "
                         "and every sample arrived. The "
                         "publisher sends each message in its slot; when it falls more than 20 ms behind (descheduled) "
                         "it resumes on a new schedule instead of sending the backlog in one burst; the rate kept "
                         f"leaves out up to {MAX_STALLS} stalls (more: the publisher could not keep the rate). A "
                         "subscriber that lost samples in such a run, or whose publisher fell short so, is "
                         f"run again (up to {STALL_RETRIES} times; 'rerun' in the table); a loss in a clean run "
                         f"is confirmed by {CONFIRMATIONS} more run (the figure is the last run's). "
                         + ("" if step else
                            f"The ladder climbs past the plan's rates (x{LADDER_STEP:g} a step) until the bare "
                            "subscriber loses samples or the publisher cannot keep the rate (a subscriber is not run "
                            f"again above its first loss); then up to {REFINE_STEPS} rates between each subscriber's "
                            f"last lossless and first lossy rate (geometric midpoints, while more than "
                            f"x{REFINE_RATIO:g} apart) narrow its limit. ")
                         + "A figure marked '>=' (`lower_bound` in the JSON, `ladder_top` for the bare "
                         "subscriber) is a lower bound: that subscriber lost no sample at any rate it ran, the "
                         f"runs above its figure were not measurements (the publisher could not keep the rate) or "
                         f"the search reached {LADDER_CAP:g} msg/s; '-' = not run at that rate. CPU: "
                         "the subscriber's process (all its threads; not the node's worker processes) from the "
                         "publisher's start until every sample was counted, per message received on both topics, "
                         "and in cores (CPU seconds / publishing time) beside the publisher's; the JSON also has "
                         "them at each one's first lossy rate (`cpu_at_first_loss`)")
    if joint_rates:
        section.notes.append(f"JointState row: one topic of {JOINTS} named joints (one message = one sample of each), "
                             f"read by one node of {JOINTS} channels (`position[joint_k]` -> `velocity[joint_k]`, "
                             "the topic subscribed and decoded once; window 4000, cls-markov, 4 solves/s each; "
                             "received = the smallest count of any channel's inputs in /diagnostics) and by the "
                             "bare subscriber of that topic, which builds every JointState; no Foxglove run (a "
                             "node of several channels has no Foxglove server); the full bench only (a "
                             "six-channel node takes 10-25 s to start: the row would add about 70 s to the quick one)")
    return section


