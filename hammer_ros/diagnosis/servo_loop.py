"""A system inside its own position loop: the servo-loop form of ``output_feedback``.

Most robot actuators run inside a loop of their own (servo firmware, a ros2_control position
controller): the command u is a goal, the controller's torque is a saturating function of the
loop error, and gravity and friction act on the arm. In the non-linear feedback family of
paper 001 (eq. 2, y = G[f(.) - h(y)]) that is

    y(k+1) = y(k) + w(k) + f(u(k-d) - y(k)) - h(y(k)) - phi(w(k)) - c sign(w(k)),    w(k) = y(k) - y(k-1),

i.e. G = q^-1 / (1 - q^-1)^2 (the arm's inertia: torque -> acceleration -> position, in units of
the output per sample^2), f the controller on the loop error (its gain and torque limit), h the
output's static feedback (gravity m g l sin(y - y_down), a spring), phi the friction on the
output's difference (viscous: its slope; a Stribeck curve: its breakpoints) and c sign(w) the
Coulomb friction's step at w = 0. All three maps are continuous piecewise linear in the
point-slope form of paper 001 (eqs. 5-11): f on quantiles of the measured loop error, h on
quantiles of y (h = 0 at its primary breakpoint: the offset lives in f's), phi with a breakpoint
at 0 (phi(0) = 0). ``d`` (the loop's input delay, 0..MAX_DELAY samples) is chosen on the
estimation data.

The start is the equation-error least-squares fit (linear in every map coefficient when the
measured output stands in the loop: the series-parallel form of paper 001, eq. 63, on a lightly
smoothed output so that the second difference of a quantised position is not mostly noise),
then the simulation error is refined (Levenberg-Marquardt, ``refine_starts``) from it and from
starts with the controller's gain and the damping scaled, the loop running in the compiled
kernel ``compiled_loops.servo_loop``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..errors import IdentificationError
from ..identification.compiled_loops import servo_loop
from ..identification.piecewise_linear_ls import point_slope_basis, point_slope_map
from ..identification.regression import solve_least_squares
from ..identification.runs import Runs
from ..identification.simulation_error import refine_starts
from ..identification.static_maps import PiecewiseLinearMap
from .split import held_back, per_run

MAX_DELAY = 2
ERROR_LEVELS = (0.1, 0.5, 0.9)  # quantiles of the loop error among f's breakpoints
# and these shares of its largest |value| on either side: a torque limit is reached in the last per cent of the
# samples (after a step of the command), where quantiles put no breakpoint
ERROR_SPREAD = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.55, 0.75, 0.9)
OUTPUT_LEVELS = (0.1, 0.3, 0.5, 0.7, 0.9)  # quantiles of the output: h's breakpoints
SPEED_LEVELS = (0.15, 0.7)  # quantiles of |w| among moving samples: phi's breakpoints besides 0
MIN_INTERVAL_SHARE = 0.005  # of the samples in every interval of a map
MIN_INTERVAL_SAMPLES = 20
SCALES = ((1.0, 1.0), (0.6, 1.0), (1.5, 1.0), (1.0, 0.5), (1.0, 2.0))  # (gain, damping) factors of the starts
SCREEN_ITERATIONS = 200  # evaluations of the simulation (LM counts those of its finite-difference Jacobian)
ITERATIONS = 2000
KEPT = 2
SMOOTHING = 0.3  # cut-off of the zero-phase low-pass of the output for the start (share of Nyquist)


def _supported(knots: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The sorted knots, each interval between them (and beyond the outer ones) holding at least
    MIN_INTERVAL_SHARE of the samples x (at least MIN_INTERVAL_SAMPLES): a knot is dropped while
    the interval it closes holds fewer, from the left, then from the right for the outer interval."""
    x = np.sort(np.asarray(x, dtype=float))
    least = max(MIN_INTERVAL_SAMPLES, int(MIN_INTERVAL_SHARE * x.size))
    keep: list[float] = []
    last = -np.inf
    for knot in np.unique(knots):
        if np.searchsorted(x, knot, "right") - np.searchsorted(x, last, "right") >= least:
            keep.append(float(knot))
            last = knot
    while keep and x.size - np.searchsorted(x, keep[-1], "right") < least:
        keep.pop()
    return np.asarray(keep)


@dataclass(frozen=True, eq=False)
class ServoLayout:
    """theta <-> (f, h, phi, c) of the servo loop: f's slopes and f(c_r), h's slopes (h(d_s) = 0),
    phi's slopes (phi(0) = 0), on fixed partitions, and the Coulomb step c; ``delay`` of the command."""

    delay: int
    error_part: np.ndarray
    output_part: np.ndarray
    speed_part: np.ndarray

    @property
    def error_primary(self) -> int:
        return int(np.argmin(np.abs(self.error_part))) + 1

    @property
    def output_primary(self) -> int:
        return self.output_part.size // 2 + 1

    @property
    def speed_primary(self) -> int:
        return int(np.flatnonzero(self.speed_part == 0.0)[0]) + 1

    @property
    def sizes(self) -> tuple[int, int, int]:
        return self.error_part.size + 2, self.output_part.size + 1, self.speed_part.size + 1

    @property
    def size(self) -> int:
        return sum(self.sizes) + 1

    def maps(self, theta: np.ndarray) -> tuple[PiecewiseLinearMap, PiecewiseLinearMap, PiecewiseLinearMap]:
        nf, nh, _ = self.sizes
        f = point_slope_map(self.error_part, self.error_primary, theta[: nf - 1], float(theta[nf - 1]))
        h = point_slope_map(self.output_part, self.output_primary, theta[nf : nf + nh], 0.0)
        phi = point_slope_map(self.speed_part, self.speed_primary, theta[nf + nh : -1], 0.0)
        return f, h, phi

    def simulator(self, theta: np.ndarray, y0: float) -> Callable[[np.ndarray], np.ndarray]:
        """u -> y of the loop with these maps, from rest at y0."""
        theta = np.asarray(theta, dtype=float)
        f, h, phi = self.maps(theta)
        coulomb = float(theta[-1])

        def simulate(u: np.ndarray) -> np.ndarray:
            u = np.asarray(u, dtype=float)
            return servo_loop(held_back(u, self.delay), y0, f, h, phi, coulomb)

        return simulate

    def regressors(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(columns, target) of the equation-error form: y(k+1) - 2 y(k) + y(k-1) =
        f(e(k)) - h(y(k)) - phi(w(k)) - c sign(w(k)), linear in theta (rows k = 1..N-2)."""
        ud = held_back(u, self.delay)
        e, w = ud - y, np.diff(y, prepend=y[0])
        rows = slice(1, y.size - 1)
        columns = np.column_stack([point_slope_basis(e, self.error_part, self.error_primary), np.ones(y.size),
                                   -point_slope_basis(y, self.output_part, self.output_primary),
                                   -point_slope_basis(w, self.speed_part, self.speed_primary), -np.sign(w)])
        target = y[2:] - 2.0 * y[1:-1] + y[:-2]
        return columns[rows], target


def servo_layout(u: np.ndarray, y: np.ndarray, delay: int, runs: Runs | None = None) -> ServoLayout:
    """The partitions of the three maps on the estimation data (``ERROR_LEVELS``,
    ``OUTPUT_LEVELS``, ``SPEED_LEVELS``; ``runs``: no delay or difference across a boundary)."""
    e = per_run(lambda part: held_back(part, delay), u, runs) - y
    w = np.concatenate([np.diff(part) for part in (runs.split(y) if runs is not None else [y])])
    moving = np.abs(w[np.abs(w) > 0])
    if moving.size < 20:
        raise IdentificationError("the output hardly moves: no loop to fit")
    speeds = np.quantile(moving, SPEED_LEVELS)
    speeds = speeds[np.concatenate([[True], np.diff(speeds) > 0])]
    reach = float(np.max(np.abs(e)))
    spread = np.concatenate([-reach * np.asarray(ERROR_SPREAD), reach * np.asarray(ERROR_SPREAD)])
    spread = spread[(spread > np.min(e)) & (spread < np.max(e))]
    error_part = _supported(np.concatenate([np.quantile(e, ERROR_LEVELS), spread]), e)
    output_part = _supported(np.quantile(y, OUTPUT_LEVELS), y)
    if error_part.size == 0 or output_part.size == 0:
        raise IdentificationError("too few samples for the loop's maps")
    return ServoLayout(delay, error_part, output_part,
                       np.concatenate([-speeds[::-1], [0.0], speeds]))


def _smoothed(y: np.ndarray) -> np.ndarray:
    if y.size < 30:
        return y
    b, a = signal.butter(2, SMOOTHING)
    return signal.filtfilt(b, a, y)


def _scaled(layout: ServoLayout, theta: np.ndarray, gain: float, damping: float) -> np.ndarray:
    nf, nh, _ = layout.sizes
    out = theta.copy()
    out[: nf - 1] *= gain
    out[nf + nh :] *= damping  # the viscous slopes and the Coulomb step
    return out


@dataclass(frozen=True, eq=False)
class ServoFit:
    """The refined loop: its layout, theta, the start position, the estimation SSE and the
    number of starts."""

    layout: ServoLayout
    theta: np.ndarray
    y0: float
    sse: float
    starts: int

    def from_rest(self, y0: float) -> Callable[[np.ndarray], np.ndarray]:
        """u -> y of the loop from rest at y0."""
        return self.layout.simulator(self.theta, y0)

    @property
    def simulate(self) -> Callable[[np.ndarray], np.ndarray]:
        return self.from_rest(self.y0)

    @property
    def parameter_count(self) -> int:
        return self.layout.size + 1  # and the delay

    @property
    def delay(self) -> int:
        return self.layout.delay

    def maps(self) -> tuple[PiecewiseLinearMap, PiecewiseLinearMap, PiecewiseLinearMap]:
        """(f, h, phi): the map on the loop error, on the output and on its difference."""
        return self.layout.maps(self.theta)

    def details(self, u: np.ndarray, y: np.ndarray) -> dict:
        """The fitted maps in the JSON form (points over the estimation data's ranges)."""
        f, h, phi = self.layout.maps(self.theta)
        e = held_back(u, self.layout.delay) - y
        w = np.diff(y)
        return {"form": "servo_loop", "delay": self.layout.delay, "starts": self.starts,
                "loop_error_map": f.to_json((float(np.min(e)), float(np.max(e)))),
                "output_feedback_map": h.to_json((float(np.min(y)), float(np.max(y)))),
                "friction_map": phi.to_json((float(np.min(w)), float(np.max(w)))),
                "coulomb_step": float(self.theta[-1])}


def fit_servo_loop(u: np.ndarray, y: np.ndarray, runs: Runs | None = None) -> ServoFit:
    """The servo loop (module docstring) on the estimation record (u command, y output): for
    every delay 0..MAX_DELAY the least-squares start and its gain/damping variants (``SCALES``),
    screened and refined on the simulation error from rest at y(0); the best fit. With ``runs``
    (separate experiments) every run is smoothed, regressed and simulated on its own, each from
    rest at its own first measured position."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    runs = None if runs is None or runs.count == 1 else runs
    y0 = float(y[0])
    smooth = per_run(_smoothed, y, runs)
    candidates = []
    for delay in range(MAX_DELAY + 1):
        try:
            layout = servo_layout(u, y, delay, runs)
            if runs is None:
                columns, target = layout.regressors(u, smooth)
            else:
                pieces = [layout.regressors(part_u, part_y) for part_u, part_y in zip(runs.split(u), runs.split(smooth))
                          if part_y.size >= 3]
                columns, target = np.vstack([c for c, _ in pieces]), np.concatenate([t for _, t in pieces])
            theta = solve_least_squares(columns, target)
        except (IdentificationError, np.linalg.LinAlgError, ValueError):
            continue
        if np.all(np.isfinite(theta)):
            candidates += [(layout, _scaled(layout, theta, g, c)) for g, c in SCALES]
    if not candidates:
        raise IdentificationError("no start of the servo loop could be computed")
    starts = [(_runner(layout, u, y, runs), theta) for layout, theta in candidates]
    fits = refine_starts(starts, y, 0, 2 * (MAX_DELAY + 1), SCREEN_ITERATIONS, KEPT, ITERATIONS)
    if not fits:
        raise IdentificationError("the simulation of every start of the servo loop diverges")
    i, theta, sse = fits[0]
    return ServoFit(candidates[i][0], theta, y0, sse, len(candidates))


def _runner(layout: ServoLayout, u: np.ndarray, y: np.ndarray, runs: Runs | None) -> Callable[[np.ndarray], np.ndarray]:
    """theta -> the loop's output on u, from rest at y(0) (with ``runs``: every run from its own y(start))."""
    return lambda theta: from_first_positions(lambda y0: layout.simulator(theta, y0), u, y, runs)


def from_first_positions(from_rest: Callable[[float], Callable[[np.ndarray], np.ndarray]], u: np.ndarray,
                         y: np.ndarray, runs: Runs | None) -> np.ndarray:
    """The output of a loop whose state at rest is its position: every run of u (one without
    ``runs``) simulated by ``from_rest(y0)`` from rest at its own first measured position, concatenated."""
    runs = Runs.one(np.size(u)) if runs is None else runs
    return np.concatenate([from_rest(float(part_y[0]))(part_u) for part_u, part_y in zip(runs.split(u), runs.split(y))])
