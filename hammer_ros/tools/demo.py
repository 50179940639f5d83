"""``hammer-ros demo``: the main job on a simulated plant, on a private ROS 2 graph.

Starts two processes on an exclusive ROS_DOMAIN_ID, DDS on loopback only:

- ``hammer_ros.ros.plant_node``: u = white Gaussian noise (std 0.5) at 500 Hz through a dead zone
  (half-width 0.2) and the resonant third-order block ``plant_node.DEMO_PLANT``, published as
  std_msgs/Float64 on /command and /response, the truth on /plant/truth;
- ``hammer_ros.ros.node``: the identification node (cls-markov, order 3, relative degree 2, a
  piecewise-linear F on 8 equally spaced breakpoints, window 4000 samples, 2 solves/s),

then listens to /plant/truth, /hammer_ros/model and /diagnostics and prints, every two seconds,
how far the latest model is from the truth: the RSS error of the poles and of the zeros (paper 000
sec. 4.2), the error of the nonlinearity (relative RMS over the estimate's input range, after the
best scale: the gain of a Hammerstein model is shared between F and G) and the free-run fit on
the window. Stops both processes with SIGINT and waits for them.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import UsageError
from ..identification.linear import root_rss_error
from ..ros.demo_watcher import DemoWatcher
from ..ros.environment import DomainLease, child_environment
from .processes import start_ros_process, stop_process

RATE = 500.0
PLANT_PARAMETERS = {"rate": RATE, "nonlinearity": "dead_zone", "threshold": 0.2, "amplitude": 0.5, "noise": 0.002}
# F piecewise linear on equally spaced breakpoints (not at the dead zone's corners): CLS step 2 in
# the point-slope basis (``correlation_least_squares.piecewise_linear_step``)
NODE_PARAMETERS = {"sample_rate": RATE, "method": "cls-markov", "order": 3, "delay": 2,
                   "partition": [-1.05, -0.75, -0.45, -0.15, 0.15, 0.45, 0.75, 1.05],
                   "window": 4000, "solve_rate": 2.0}
ROW_PERIOD = 2.0  # s between table rows
CONVERGED_POLE_RSS = 0.02
STOP_TIMEOUT = 5.0


def _roots(pairs) -> np.ndarray:
    return np.array([complex(re, im) for re, im in pairs], dtype=complex)


def maps_at(truth: dict, estimate: dict,
            u: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(u, true F(u), estimated F(u) at the least-squares scale onto the truth: F and G share
    the gain) at ``u`` (default the estimate's points); None without points or with a zero map."""
    points = np.asarray(estimate.get("points") or [], dtype=float)
    true_points = np.asarray(truth.get("points") or [], dtype=float)
    if points.size == 0 or true_points.size == 0:
        return None
    u = points[:, 0] if u is None else np.asarray(u, dtype=float)
    f = np.interp(u, points[:, 0], points[:, 1])
    g = np.interp(u, true_points[:, 0], true_points[:, 1])
    if not (f @ f > 0 and g @ g > 0):
        return None
    return u, g, (g @ f) / (f @ f) * f


def nonlinearity_error(truth: dict, estimate: dict) -> float | None:
    """Relative RMS distance (in %) between the true map and the scaled estimate (``maps_at``)
    on the estimate's points."""
    maps = maps_at(truth, estimate)
    if maps is None:
        return None
    _, g, f = maps
    return float(100.0 * np.linalg.norm(g - f) / np.linalg.norm(g))


def compare(truth: dict, model: dict) -> dict:
    """Errors of one ``~/model`` document against the plant's truth document."""
    return {
        "pole_rss": root_rss_error(_roots(truth["poles"]), _roots(model["poles"])),
        "zero_rss": root_rss_error(_roots(truth["zeros"]), _roots(model["zeros"])),
        "nonlinearity_percent": nonlinearity_error(truth.get("nonlinearity", {}), model.get("nonlinearity", {})),
        "fit_percent": model.get("fit_percent"),
        "samples": model.get("samples"),
    }


def _format_roots(pairs) -> str:
    return "  ".join(f"{re:+.4f}{im:+.4f}j" for re, im in pairs) or "-"


def _number(x, width: int, digits: int) -> str:
    return f"{x:{width}.{digits}f}" if isinstance(x, (int, float)) else f"{'-':>{width}}"




def _tail(log: Path, lines: int = 15) -> str:
    text = log.read_text(errors="replace").splitlines() if log.exists() else []
    return "\n".join("    " + line for line in text[-lines:])


def _row(elapsed: float, watcher: DemoWatcher) -> str:
    if watcher.model is None or watcher.truth is None:
        return f"{elapsed:7.1f}  {'-':>7}  {'-':>9}  {'-':>9}  {'-':>8}  {'-':>7}   {watcher.status}"
    c = compare(watcher.truth, watcher.model)
    return (f"{elapsed:7.1f}  {c['samples'] or 0:7d}  {_number(c['pole_rss'], 9, 4)}  {_number(c['zero_rss'], 9, 4)}  "
            f"{_number(c['nonlinearity_percent'], 8, 1)}  {_number(c['fit_percent'], 7, 1)}")


MAP_INPUTS = (-0.8, -0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6, 0.8)


def _map_rows(truth: dict, estimate: dict) -> list[str]:
    """The true and the (scaled, ``maps_at``) estimated map at MAP_INPUTS, as table rows."""
    maps = maps_at(truth, estimate, MAP_INPUTS)
    if maps is None:
        return []
    return [f"  {label:<13}" + " ".join(f"{x:+6.2f}" for x in row)
            for label, row in zip(("u", "F(u) true", "F(u) model"), maps)]


def _summary(watcher: DemoWatcher) -> tuple[str, bool]:
    truth, model = watcher.truth, watcher.model
    if truth is None or model is None:
        return "no model was identified (see the process logs above)", False
    c = compare(truth, model)
    ok = c["pole_rss"] < CONVERGED_POLE_RSS
    nl = model.get("nonlinearity", {})
    lines = [
        "",
        f"true poles       {_format_roots(truth['poles'])}",
        f"estimated poles  {_format_roots(model['poles'])}",
        f"true zeros       {_format_roots(truth['zeros'])}",
        f"estimated zeros  {_format_roots(model['zeros'])}",
        f"nonlinearity     true: dead zone +-{PLANT_PARAMETERS['threshold']}; estimated: {nl.get('kind', '-')}, "
        f"relative error {_number(c['nonlinearity_percent'], 0, 1)} % after scaling",
        *_map_rows(truth.get("nonlinearity", {}), nl),
        f"{'converged' if ok else 'NOT converged'}: pole RSS error {c['pole_rss']:.4f} "
        f"({'<' if ok else '>='} {CONVERGED_POLE_RSS}), zero RSS error {c['zero_rss']:.4f}, "
        f"fit {_number(c['fit_percent'], 0, 1)} % after {watcher.models} models",
    ]
    return "\n".join(lines), ok


def run(args: argparse.Namespace) -> int:
    """Plant + node on a private graph for ``args.duration`` seconds; 0 when a model arrived."""
    duration = float(args.duration)
    if not (np.isfinite(duration) and duration > 0):
        raise UsageError(f"--duration: must be > 0 seconds (got {args.duration})")
    with DomainLease() as lease, tempfile.TemporaryDirectory(prefix="hammer_ros_demo_") as tmp:
        logs = Path(tmp)
        env = child_environment(lease.domain_id, log_dir=logs / "ros_log")
        os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR",
                                               "AMENT_PREFIX_PATH", "FASTRTPS_DEFAULT_PROFILES_FILE")})
        print(f"hammer_ros demo: simulated plant (dead zone + resonant 3rd-order block, {RATE:g} Hz) and the "
              f"identification node on ROS_DOMAIN_ID {lease.domain_id} (loopback), {duration:g} s", flush=True)
        processes = {
            "plant": start_ros_process("hammer_ros.ros.plant_node", PLANT_PARAMETERS, env, logs / "plant.log"),
            "node": start_ros_process("hammer_ros.ros.node", NODE_PARAMETERS, env, logs / "node.log"),
        }
        watcher = None
        failed = False
        try:
            watcher = DemoWatcher()
            print(f"{'t [s]':>7}  {'samples':>7}  {'pole RSS':>9}  {'zero RSS':>9}  {'F err %':>8}  {'fit %':>7}",
                  flush=True)
            start = time.monotonic()
            next_row = start + ROW_PERIOD
            while next_row <= start + duration + 1e-9:
                watcher.spin_until(next_row)
                print(_row(next_row - start, watcher), flush=True)
                dead = [name for name, p in processes.items() if p.poll() is not None]
                if dead:
                    failed = True
                    print(f"hammer_ros demo: {', '.join(dead)} exited early", file=sys.stderr)
                    break
                next_row += ROW_PERIOD
        except KeyboardInterrupt:
            print("\ninterrupted", flush=True)
        finally:
            codes = {name: stop_process(p, timeout=STOP_TIMEOUT) for name, p in processes.items()}
            if watcher is not None:
                summary, _ = _summary(watcher)
                print(summary, flush=True)
                watcher.close()
        bad = {name: code for name, code in codes.items() if code != 0}
        if failed or bad or watcher is None or watcher.model is None:
            for name in processes:
                print(f"--- {name} log (exit code {codes[name]}):\n{_tail(logs / f'{name}.log')}", file=sys.stderr)
            return 1
    return 0
