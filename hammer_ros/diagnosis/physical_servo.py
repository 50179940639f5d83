"""The servo loop in its physical form: seven constants instead of three maps.

``servo_loop`` fits y(k+1) = y(k) + w(k) + f(u(k-d) - y(k)) - h(y(k)) - phi(w(k)) - c sign(w(k))
(paper 001, eq. 2 with G = q^-1 / (1 - q^-1)^2) with f, h and phi piecewise linear: 20-odd
coefficients that follow any controller, spring or friction curve, and that extrapolate by their
outer slopes. A servo swinging an arm is, to a control engineer, a saturated proportional
controller, the gravity of a pendulum and viscous and Coulomb friction:

    f(e) = sat_T(K (e + o)),    h(y) = G sin(y - p),    phi(w) = B w,    c = C,

seven constants (K, T, o, G, p, B, C; the angle y in radians, the rest in units of the output per
sample^2) that continue correctly beyond the data (gravity is periodic, a torque limit is flat).
``fit_physical_servo`` fits them on the simulation error (every run from rest at its own first
position), started from the fitted maps of the servo loop projected onto these forms (least
squares over the samples the maps saw) and from that start with the gain and the damping scaled.
``choose_servo_form`` decides between the two forms on held-back estimation data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import IdentificationError
from ..identification.compiled_loops import physical_servo_loop
from ..identification.levenberg_marquardt import levenberg_marquardt
from ..identification.runs import Runs, several
from ..identification.simulation_error import refine_starts
from .servo_loop import MAX_DELAY, ServoFit, fit_servo_loop, from_first_positions
from .split import held_back, per_run

NAMES = ("gain", "torque_limit", "offset", "gravity", "gravity_angle", "viscous", "coulomb")
SCALES = ((1.0, 1.0), (0.6, 1.0), (1.5, 1.0), (1.0, 0.5), (1.0, 2.0))  # (gain, damping) factors of the starts
SCREEN_ITERATIONS = 100
ITERATIONS = 1000
KEPT = 2
HELD_BACK = 0.25  # share of the estimation data (whole runs when there are several) the forms are compared on


@dataclass(frozen=True, eq=False)
class PhysicalServoFit:
    """The refined physical loop: theta in the order of ``NAMES``, the command's delay, the start
    position, the estimation SSE and the number of starts (the interface of ``ServoFit``)."""

    theta: np.ndarray
    delay: int
    y0: float
    sse: float
    starts: int

    parameter_count = len(NAMES) + 1  # and the delay

    def from_rest(self, y0: float) -> Callable[[np.ndarray], np.ndarray]:
        """u -> y of the loop from rest at y0."""
        return _simulator(self.theta, self.delay, y0)

    @property
    def simulate(self) -> Callable[[np.ndarray], np.ndarray]:
        return self.from_rest(self.y0)

    def maps(self) -> tuple[Callable, Callable, Callable]:
        """(f, h, phi) as functions: the saturated controller on the loop error, gravity on the output,
        the friction on its difference (viscous and the Coulomb step)."""
        gain, limit, offset, gravity, angle, viscous, coulomb = self.theta
        return (lambda e: np.clip(gain * (e + offset), -limit, limit),
                lambda y: gravity * np.sin(y - angle),
                lambda w: viscous * w + coulomb * np.sign(w))

    def details(self, u: np.ndarray, y: np.ndarray) -> dict:
        """The constants (units of the output per sample^2 but the angle) and the output range they
        were fitted on (gravity beyond it is the sine's continuation)."""
        return {"form": "physical_servo", "delay": self.delay, "starts": self.starts,
                **{name: float(value) for name, value in zip(NAMES, self.theta)},
                "output_range": [float(np.min(y)), float(np.max(y))]}


def _simulator(theta: np.ndarray, delay: int, y0: float) -> Callable[[np.ndarray], np.ndarray]:
    gain, limit, offset, gravity, angle, viscous, coulomb = (float(t) for t in theta)

    def simulate(u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        return physical_servo_loop(held_back(u, delay) + offset, y0, gain, abs(limit), gravity, angle, abs(viscous),
                                   abs(coulomb))

    return simulate


def _runner(delay: int, u: np.ndarray, y: np.ndarray, runs: Runs | None) -> Callable[[np.ndarray], np.ndarray]:
    """theta -> the loop's output on u, every run from rest at its own first measured position."""
    return lambda theta: from_first_positions(lambda y0: _simulator(theta, delay, y0), u, y, runs)


def projected_start(servo: ServoFit, u: np.ndarray, y: np.ndarray, runs: Runs | None) -> np.ndarray:
    """theta of the physical form nearest the servo loop's maps over the samples they saw (least
    squares): h(y) ~ G sin(y - p) + c, f(e) - c ~ sat_T(K (e + o)), phi(w) + c_s sign(w) ~ B w + C sign(w)."""
    f, h, phi = servo.maps()
    e = per_run(lambda part: held_back(part, servo.delay), u, runs) - y
    w = np.concatenate([np.diff(part) for part in (runs.split(y) if runs is not None else [y])])
    (a, b, c), *_ = np.linalg.lstsq(np.column_stack([np.sin(y), np.cos(y), np.ones(y.size)]), h(y), rcond=None)
    gravity, angle = float(np.hypot(a, b)), float(np.arctan2(-b, a))
    target = f(e) - c
    slope = float(f.slopes[np.searchsorted(f.breakpoints, 0.0)])
    limit0 = float(np.max(np.abs(target))) or 1.0
    gain0 = slope if slope > 0 else limit0 / (float(np.max(np.abs(e))) or 1.0)
    offset0 = (float(f(np.zeros(1))[0]) - c) / gain0
    found = levenberg_marquardt(lambda t: np.clip(t[0] * (e + t[2]), -abs(t[1]), abs(t[1])) - target,
                                np.array([gain0, limit0, offset0]), 200)
    gain, limit, offset = found.x
    friction = phi(w) + float(servo.theta[-1]) * np.sign(w)
    (viscous, coulomb), *_ = np.linalg.lstsq(np.column_stack([w, np.sign(w)]), friction, rcond=None)
    return np.array([gain, abs(limit), offset, gravity, angle, abs(viscous), abs(coulomb)], dtype=float)


def fit_physical_servo(u: np.ndarray, y: np.ndarray, runs: Runs | None = None,
                       servo: ServoFit | None = None) -> PhysicalServoFit:
    """The physical form (module docstring) on the estimation record, refined on the simulation
    error from ``projected_start`` of ``servo`` (the servo loop's fit on the same data; fitted here
    when not given) and its gain/damping variants (``SCALES``), each with every delay of the
    command 0..MAX_DELAY (the maps may have absorbed a delay the constants cannot); the best."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    runs = several(runs)
    servo = fit_servo_loop(u, y, runs) if servo is None else servo
    try:
        start = projected_start(servo, u, y, runs)
    except (ValueError, np.linalg.LinAlgError) as error:
        raise IdentificationError(f"no start of the physical servo loop: {error}") from error
    if not np.all(np.isfinite(start)):
        raise IdentificationError("no finite start of the physical servo loop")
    variants = []
    for gain, damping in SCALES:
        theta = start.copy()
        theta[0] *= gain
        theta[5:] *= damping
        variants.append(theta)
    delays = range(MAX_DELAY + 1)
    starts = [(_runner(delay, u, y, runs), theta) for delay in delays for theta in variants]
    fits = refine_starts(starts, y, len(starts), len(starts), SCREEN_ITERATIONS, KEPT, ITERATIONS)
    if not fits:
        raise IdentificationError("the simulation of every start of the physical servo loop diverges")
    i, theta, sse = fits[0]
    theta = theta.copy()
    theta[[1, 5, 6]] = np.abs(theta[[1, 5, 6]])  # as simulated: a torque limit and friction are not negative
    return PhysicalServoFit(theta, delays[i // len(variants)], float(y[0]), sse, len(starts))


@dataclass(frozen=True, eq=False)
class ServoChoice:
    """The form kept (``fit``, fitted on all the estimation data), the maps' fit on all of it (``maps``:
    the servo family's best estimation fit, ``fit`` itself when the maps are kept) and the held-back
    RMS of both forms fitted without the held-back data (None: not compared)."""

    fit: ServoFit | PhysicalServoFit
    maps: ServoFit
    held_back_rms: dict[str, float] | None


def _held_back_part(samples: int, runs: Runs | None) -> tuple[int, Runs | None]:
    """(first held-back sample, the runs before it): the last whole runs, HELD_BACK of them (at least
    one), with several runs; else the last HELD_BACK of the samples."""
    if runs is not None:
        held = int(np.clip(round(HELD_BACK * runs.count), 1, runs.count - 1))
        return int(runs.starts[runs.count - held]), several(runs.select(range(runs.count - held))[1])
    return int(round((1.0 - HELD_BACK) * samples)), None


def _held_back_rms(fit: ServoFit | PhysicalServoFit, u: np.ndarray, y: np.ndarray, cut: int,
                   runs: Runs | None) -> float:
    """RMS of the fit on the held-back samples cut.. : every run from rest at its own first position
    (one record: the whole record simulated from its start)."""
    if runs is None:
        out = fit.simulate(u)[cut:]
    else:
        out = from_first_positions(fit.from_rest, u[cut:], y[cut:], runs.window(cut, u.size))
    with np.errstate(all="ignore"):
        value = float(np.sqrt(np.mean((out - y[cut:]) ** 2)))
    return value if np.isfinite(value) else np.inf


def choose_servo_form(u: np.ndarray, y: np.ndarray, runs: Runs | None = None,
                      maps: ServoFit | None = None) -> ServoChoice:
    """The servo loop's maps or its physical form, whichever simulates the held-back estimation data
    (``_held_back_part``) better when both are fitted on the rest (the physical form on a tie: fewer
    constants); the winner is then fitted on all the estimation data (``maps``: the maps' fit on all
    of it when the caller has it). A form that fails on the shorter data loses; when the comparison
    cannot be made at all, the maps."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    runs = several(runs)
    cut, fit_runs = _held_back_part(u.size, runs)
    scores: dict[str, float] = {}
    try:
        servo_part = fit_servo_loop(u[:cut], y[:cut], fit_runs)
        scores["servo_loop"] = _held_back_rms(servo_part, u, y, cut, runs)
        physical_part = fit_physical_servo(u[:cut], y[:cut], fit_runs, servo_part)
        scores["physical_servo"] = _held_back_rms(physical_part, u, y, cut, runs)
    except IdentificationError:
        pass
    servo = fit_servo_loop(u, y, runs) if maps is None else maps
    if scores.get("physical_servo", np.inf) <= scores.get("servo_loop", np.inf):
        try:
            return ServoChoice(fit_physical_servo(u, y, runs, servo), servo, scores)
        except IdentificationError:
            pass
    return ServoChoice(servo, servo, scores or None)
