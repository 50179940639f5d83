"""Simulators of two real robot actuators, the test bench of the diagnosis on actuator physics.

**Position servo under gravity** (``ServoArm``, ``servo_record``): a hobby-grade position servo
swinging a weighted arm, sampled at ``rate`` (100 Hz). The servo's firmware closes its own P (or
PD) position loop on its encoder at ``substeps`` x the sample rate, its torque limited:

    tau = clip(K_p (u - q_enc) - K_d w, -tau_max, tau_max),
    J dw/dt = tau - m g l sin(q - q_down) - b w - c sign(w)     (static friction: w = 0 while
                                                                  |tau - gravity| <= c at rest),
    dq/dt = w,

u the goal position (rad), q the arm angle, q_enc = q quantised to ``counts`` a turn (the
measured output as well), J the rotor's reflected inertia plus m l^2. Runs start at rest at
their first command. ``servo_record``: runs that start and end at 0, so that they concatenate
seamlessly; ``servo_runs_record``: runs as real experiments come, each from rest at its own random
goal (the arm reset between runs) and ending wherever its trajectory leaves it, so that their
concatenation jumps at every boundary; they are given as runs (``identification.runs.Runs``).

**DC motor behind an H-bridge** (``dc_motor_staircase``): armature voltage v through an
asymmetric dead zone (the bridge's and the brushes' threshold: nothing below +d_pos or above
-d_neg), a first-order speed response tau_m dw/dt = K (v - d) - w in rpm, under a staircase of
voltage steps 0, +a_1, -a_1, +a_2, -a_2, ... or (``interleaved=False``) all positive steps first,
then the negative ones, so that the largest negative steps lie only at the end of the record.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..identification.runs import Runs

GRAVITY = 9.81


@dataclass(frozen=True)
class ServoArm:
    """The servo's and the arm's physical constants (SI units)."""

    mass: float = 0.15  # kg at the arm's end
    length: float = 0.15  # m
    gain: float = 6.0  # K_p, N m / rad
    damping_gain: float = 0.0  # K_d, N m s / rad (0: a P loop)
    torque_limit: float = 1.2  # N m
    rotor_inertia: float = 4e-3  # kg m^2, reflected through the gear
    viscous: float = 0.15  # N m s / rad (gear friction and back-EMF)
    coulomb: float = 0.05  # N m
    hanging_angle: float = -np.pi / 2  # q at which the arm hangs straight down (q = 0: horizontal)
    counts: int = 4096  # encoder counts a turn
    rate: float = 100.0  # Hz
    substeps: int = 10  # firmware steps per sample


def quantised(q: np.ndarray | float, counts: int) -> np.ndarray:
    """q rounded to the encoder's resolution 2 pi / counts."""
    step = 2.0 * np.pi / counts
    return np.round(np.asarray(q, dtype=float) / step) * step


def simulate_servo(arm: ServoArm, u: np.ndarray, q0: float | None = None, seed: int = 0,
                   torque_noise: float = 0.0) -> np.ndarray:
    """The measured position (quantised) at each sample for the goal positions u (one run, from
    rest at q0, default u(0) less the sag under gravity); ``torque_noise``: the sd of a random
    disturbance torque held over each sample (ripple, cable drag), drawn from ``seed``."""
    u = np.asarray(u, dtype=float)
    rng = np.random.default_rng(seed)
    disturbance = torque_noise * rng.standard_normal(u.size)
    dt = 1.0 / (arm.rate * arm.substeps)
    inertia = arm.rotor_inertia + arm.mass * arm.length**2
    weight = arm.mass * GRAVITY * arm.length
    q = rest_position(arm, float(u[0])) if q0 is None else float(q0)
    w = 0.0
    out = np.empty(u.size)
    for k in range(u.size):
        out[k] = quantised(q, arm.counts)
        for _ in range(arm.substeps):
            encoder = float(quantised(q, arm.counts))
            tau = min(max(arm.gain * (u[k] - encoder) - arm.damping_gain * w, -arm.torque_limit), arm.torque_limit)
            drive = tau + disturbance[k] - weight * np.sin(q - arm.hanging_angle) - arm.viscous * w
            if w == 0.0 and abs(drive) <= arm.coulomb:
                continue  # static friction holds the arm
            step = w + dt * (drive - arm.coulomb * np.sign(w if w != 0.0 else drive)) / inertia
            w = 0.0 if w != 0.0 and step * w < 0.0 else step  # Coulomb friction stops, never reverses
            q += dt * w
    return out


def rest_position(arm: ServoArm, goal: float) -> float:
    """The angle at which the loop's torque balances gravity for a constant goal (friction aside):
    K_p (goal - q) = m g l sin(q - q_down), solved by bisection within the torque limit."""
    weight = arm.mass * GRAVITY * arm.length
    lo, hi = goal - np.pi / 2, goal + np.pi / 2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        balance = np.clip(arm.gain * (goal - mid), -arm.torque_limit, arm.torque_limit) - weight * np.sin(
            mid - arm.hanging_angle)
        lo, hi = (mid, hi) if balance > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def servo_trajectories(rate: float = 100.0, seconds: float = 8.0, amplitude: float = 1.0,
                       seed: int = 0) -> list[np.ndarray]:
    """Four goal-position trajectories of ``seconds`` each, every one starting and ending held at 0
    (so that runs concatenate at rest): steps of random size held 0.6-1.4 s, a triangle sweep,
    a chirp of growing frequency, and a smooth random path (low-passed noise)."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate))
    hold = int(round(0.5 * rate))
    inner = n - 2 * hold
    t = np.arange(inner) / rate
    steps = np.zeros(inner)
    k = 0
    while k < inner:
        length = int(rate * rng.uniform(0.6, 1.4))
        steps[k : k + length] = amplitude * rng.uniform(-1.0, 1.0)
        k += length
    triangle = amplitude * signal.sawtooth(2 * np.pi * t / (inner / rate / 2), 0.5) * np.sin(np.pi * t / t[-1])
    chirp = amplitude * 0.8 * np.sin(np.pi * t / t[-1]) * signal.chirp(t, 0.1, t[-1], 1.5, phi=-90)
    b, a = signal.butter(2, 0.8 / (rate / 2))
    smooth = signal.filtfilt(b, a, rng.standard_normal(inner))
    smooth = amplitude * np.sin(np.pi * t / t[-1]) * smooth / np.max(np.abs(smooth))
    pad = np.zeros(hold)
    return [np.concatenate([pad, x, pad]) for x in (steps, triangle, chirp, smooth)]


@dataclass(frozen=True, eq=False)
class ServoRecord:
    """Estimation and validation records of one servo configuration: each is the four
    trajectories run ``repeats`` times, concatenated (the validation repeats have their own
    disturbance draws)."""

    arm: ServoArm
    u_est: np.ndarray
    y_est: np.ndarray
    u_val: np.ndarray
    y_val: np.ndarray
    runs_est: Runs | None = None  # the separate experiments of each part (None: runs that concatenate at rest)
    runs_val: Runs | None = None


RUN_KINDS = ("steps", "ramps", "chirp", "smooth")
START_HOLD = (0.2, 0.6)  # s at the start level before the trajectory moves (the run starts at rest)


def run_trajectory(kind: str, rng: np.random.Generator, samples: int, rate: float, amplitude: float) -> np.ndarray:
    """One goal trajectory as an experiment is run: held at a random start level (the arm reset
    there, at rest) for START_HOLD, then ``kind``: random steps held 0.6-1.4 s, ramps to random
    levels, a chirp of growing frequency and amplitude about the start level, or a smooth random
    path; it ends wherever it is (not at rest, not at the start). Within +-1.2 ``amplitude``."""
    start = amplitude * rng.uniform(-0.8, 0.8)
    hold = int(round(rate * rng.uniform(*START_HOLD)))
    n = samples - hold
    t = np.arange(n) / rate
    if kind == "steps":
        moving = np.concatenate([np.full(int(rate * rng.uniform(0.6, 1.4)), amplitude * rng.uniform(-1.0, 1.0))
                                 for _ in range(int(n / (0.6 * rate)) + 1)])[:n]
    elif kind == "ramps":
        knots = np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 1.5, int(n / (0.5 * rate)) + 2))]) * rate
        levels = np.concatenate([[start], amplitude * rng.uniform(-1.0, 1.0, knots.size - 1)])
        moving = np.interp(np.arange(n), knots, levels)
    elif kind == "chirp":
        growth = np.minimum(1.0, t / max(t[-1], 1e-9) * 2.0)
        moving = start + amplitude * rng.uniform(0.3, 0.7) * growth * signal.chirp(t, 0.2, t[-1], rng.uniform(1.0, 2.0))
    else:
        b, a = signal.butter(2, 0.8 / (rate / 2))
        path = signal.lfilter(b, a, rng.standard_normal(n))
        moving = start + amplitude * 0.8 * path / (np.max(np.abs(path)) or 1.0)
    return np.clip(np.concatenate([np.full(hold, start), moving]), -1.2 * amplitude, 1.2 * amplitude)


def servo_runs_record(arm: ServoArm, runs: int = 8, samples: int = 600, amplitude: float = 1.0,
                      torque_noise: float = 0.01, seed: int = 0) -> ServoRecord:
    """``runs`` estimation and ``runs`` validation experiments of ``samples`` each (the kinds of
    ``run_trajectory`` in turn, every one with its own draws), each from rest at its own start
    (``simulate_servo`` at rest at the run's first goal), concatenated and given as runs."""
    rng = np.random.default_rng([seed, 50])

    def record(first: int) -> tuple[np.ndarray, np.ndarray]:
        goals = [run_trajectory(RUN_KINDS[i % len(RUN_KINDS)], rng, samples, arm.rate, amplitude) for i in range(runs)]
        outputs = [simulate_servo(arm, u, seed=1000 * seed + first + i, torque_noise=torque_noise)
                   for i, u in enumerate(goals)]
        return np.concatenate(goals), np.concatenate(outputs)

    u_est, y_est = record(0)
    u_val, y_val = record(500)
    lengths = [samples] * runs
    return ServoRecord(arm, u_est, y_est, u_val, y_val, Runs.from_lengths(lengths), Runs.from_lengths(lengths))


def servo_record(arm: ServoArm, seconds: float = 8.0, repeats: int = 2, amplitude: float = 1.0,
                 torque_noise: float = 0.01, seed: int = 0) -> ServoRecord:
    """Estimation on ``repeats`` repeats of the four trajectories, validation on ``repeats`` other
    repeats (same commands, other disturbance draws), each run started at rest."""
    trajectories = servo_trajectories(arm.rate, seconds, amplitude, seed)

    def record(first: int) -> tuple[np.ndarray, np.ndarray]:
        runs = [(u, simulate_servo(arm, u, seed=1000 * seed + first + 10 * r + i, torque_noise=torque_noise))
                for r in range(repeats) for i, u in enumerate(trajectories)]
        return np.concatenate([u for u, _ in runs]), np.concatenate([y for _, y in runs])

    u_est, y_est = record(0)
    u_val, y_val = record(500)
    return ServoRecord(arm, u_est, y_est, u_val, y_val)


@dataclass(frozen=True)
class DcMotor:
    """Armature-voltage to speed: dead zone [-dead_negative, +dead_positive] V, gain rpm / V,
    mechanical time constant (s), sampled at ``rate`` Hz, speed noise sd (rpm)."""

    dead_positive: float = 0.8
    dead_negative: float = 1.3
    gain: float = 120.0
    time_constant: float = 0.12
    rate: float = 100.0
    noise: float = 2.0


def dead_zone(v: np.ndarray, negative: float, positive: float) -> np.ndarray:
    """v - positive above +positive, v + negative below -negative, 0 between."""
    v = np.asarray(v, dtype=float)
    return np.where(v > positive, v - positive, np.where(v < -negative, v + negative, 0.0))


def staircase(levels: np.ndarray, hold: int, interleaved: bool = True) -> np.ndarray:
    """0, then each level and its negative held ``hold`` samples, returning to 0 between steps:
    interleaved (+a1, -a1, +a2, -a2, ...) or all positive steps first, then the negative ones."""
    levels = np.asarray(levels, dtype=float)
    order = np.ravel(np.column_stack([levels, -levels])) if interleaved else np.concatenate([levels, -levels])
    pieces = [np.zeros(hold)]
    for level in order:
        pieces += [np.full(hold, level), np.zeros(hold // 2)]
    return np.concatenate(pieces)


def dc_motor_staircase(motor: DcMotor = DcMotor(), hold_seconds: float = 1.0, top: float = 8.8,
                       interleaved: bool = False, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(voltage, speed in rpm) of the motor under the staircase 0, +-0.5 ... +-top V."""
    levels = np.arange(0.5, top + 1e-9, 0.5)
    levels[-1] = top
    v = staircase(levels, int(round(hold_seconds * motor.rate)), interleaved)
    pole = float(np.exp(-1.0 / (motor.rate * motor.time_constant)))
    drive = motor.gain * dead_zone(v, motor.dead_negative, motor.dead_positive)
    speed = signal.lfilter([0.0, 1.0 - pole], [1.0, -pole], drive)
    rng = np.random.default_rng(seed)
    return v, speed + motor.noise * rng.standard_normal(v.size)


def _physical_servo(theta, u, y0: float) -> np.ndarray:
    """The 7-parameter discrete servo loop at the sample rate (``fit_physical_servo``)."""
    gain, limit, weight, phase, viscous, coulomb, offset = (float(t) for t in theta)
    q, w = y0, 0.0
    out = [0.0] * len(u)
    for k, goal in enumerate(u):
        out[k] = q
        tau = min(max(gain * (goal + offset - q), -limit), limit)
        w = w + tau - weight * np.sin(q - phase) - viscous * w - coulomb * (1.0 if w > 0 else -1.0 if w < 0 else 0.0)
        q = q + w
        if abs(q) > 1e6:
            return np.full(len(u), 1e6)
    return np.asarray(out)


def physical_servo_runs(theta, u: np.ndarray, y: np.ndarray, runs: Runs | None = None) -> np.ndarray:
    """The 7-parameter loop on every run of (u, y), each from rest at its own measured y(start)."""
    runs = Runs.one(np.size(u)) if runs is None else runs
    return np.concatenate([_physical_servo(theta, part, float(first[0]))
                           for part, first in zip(runs.split(u), runs.split(y))])


def fit_physical_servo(u: np.ndarray, y: np.ndarray, starts: int = 4, seed: int = 0, runs: Runs | None = None):
    """The yardstick a control engineer writes in a few lines: the discrete servo loop
    w(k+1) = w(k) + clip(K (u + o - y), -T, T) - G sin(y - p) - B w - C sign(w), y(k+1) = y(k) + w(k+1)
    (7 parameters: K, T, G, p, B, C, o) fitted on the simulation error (scipy least_squares from
    ``starts`` random starts; with ``runs`` every run simulated from rest at its own measured
    y(start), ``physical_servo_runs``). Returns (theta, simulate: u -> y from rest at y(0))."""
    from scipy.optimize import least_squares

    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    rng = np.random.default_rng(seed)
    best = None
    for _ in range(starts):
        theta0 = np.array([rng.uniform(0.005, 0.05), rng.uniform(0.002, 0.02), rng.uniform(0.0, 0.01),
                           rng.uniform(-np.pi, np.pi), rng.uniform(0.05, 0.4), rng.uniform(0.0, 0.002), 0.0])
        try:
            found = least_squares(lambda t: physical_servo_runs(t, u, y, runs) - y, theta0, max_nfev=300)
        except ValueError:
            continue
        if best is None or found.cost < best.cost:
            best = found
    theta = best.x
    return theta, lambda v: _physical_servo(theta, np.asarray(v, dtype=float), float(y[0]))
