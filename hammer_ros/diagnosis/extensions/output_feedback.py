"""The extension of ``output_feedback``: the output fed back through static maps, as the
non-linear feedback loop, two storages in series or the servo loop, with the tails of
their maps chosen on held-back data."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ...errors import IdentificationError
from ...identification.compiled_loops import feedback_loop
from ...identification.linear import LinearModel
from ...identification.piecewise_linear_ls import drop_empty_intervals, plls, point_slope_basis, point_slope_map
from ...identification.regression import solve_least_squares
from ...identification.simulate import simulate_hammerstein_feedback
from ...identification.simulation_error import (
    preroll_simulate,
    refine,
    refine_starts,
    settling_samples,
    stabilised_denominator,
    steady_state_filter,
)
from ...identification.static_maps import TAILS, PiecewiseLinearMap, with_tails
from ..hammerstein import bic, quantile_partition
from ..physical_servo import PhysicalServoFit, choose_servo_form
from ..servo_loop import ServoFit, fit_servo_loop
from ..split import INITIAL_SAMPLES, Split, held_back, per_run, rest_input
from ..storage_cascade import CascadeLayout, cascade_starts, plausible_rest
from .common import NUMERICAL_FAILURES, Context, ExtendedModel, NotFitted, failure_reason, map_plot, order_details

SCREENED_STARTS = 6  # the PLLS and baseline starts and the random ones with the smallest simulation error
SCREEN_ITERATIONS = 6  # LM iterations of every screened start before the best ones are refined to the end
FEEDBACK_ITERATIONS = 40
STORAGE_CASCADE = ("two storages in series: x1+ = x1 + f(u) - h1(x1), x2+ = x2 + g(x1+) - h2(x2), y = x2 "
                   "(non-linear feedback of both levels)")
SERVO_LOOP = ("servo loop: y = G[f(u - y) - h(y) - phi(dy)], G a double integrator (the controller's map on the "
              "loop error, gravity on the output, friction on its difference)")
PHYSICAL_SERVO = ("servo loop, physical form: y = G[sat_T(K (u + o - y)) - G_g sin(y - p) - B dy - C sign(dy)], G a "
                  "double integrator (a saturated P controller, a pendulum's gravity, viscous and Coulomb friction)")
KEPT_STARTS = 2  # starts refined to the end
KEPT_CASCADES = 4  # storages in series refined to the end on a short record (all screened there); the best
# whose rest states are plausible is kept
SHORT_RECORD = 1500  # estimation samples below which a record is short: fewer breakpoints of h, every start
# of the storages in series screened
TAIL_ITERATIONS = 10  # LM iterations of the fit without the held-back quarter (tail choice)
TAIL_MARGIN = 0.02  # a tail other than the last slope must lower the held-back error by this share


def feedback_breakpoints(samples: int) -> int:
    """Breakpoints of h: 3 for short records (the loop over-fits them), 5 from SHORT_RECORD on."""
    return 3 if samples < SHORT_RECORD else 5


def random_starts(samples: int) -> int:
    """Random starts of the feedback loop: 12 up to 20000 samples, fewer (at least 5) beyond,
    where each costs more."""
    return int(np.clip(12 - (samples - 20000) // 10000, 5, 12))


def _feedback_simulator(a, b, f_map, h_map, preroll: int) -> Callable[[np.ndarray], np.ndarray]:
    """y = B/A [f(u) - h(y)] (paper 001, eq. 2) from rest at u(0): ``preroll`` samples of the
    constant u(0) are simulated first from zero initial conditions and dropped. The loop runs
    in the compiled kernel of ``compiled_loops`` (h piecewise linear)."""
    linear = LinearModel(b, a)

    def run(u: np.ndarray) -> np.ndarray:
        return simulate_hammerstein_feedback(u, f_map, h_map, linear)

    return lambda u: preroll_simulate(run, u, preroll)


@dataclass(frozen=True, eq=False)
class FeedbackLayout:
    """theta <-> (A, B, f, h) of the Hammerstein / non-linear feedback model y = B/A [f(v) - h(y)]
    (paper 001, eq. 2), f and h in the point-slope form of eqs. 5-11 on the partitions
    ``f_part`` and ``h_part`` (primary indices r and s, 1-based).

    The representation is fixed as in paper 001 (sec. 2, eq. 3): B keeps ``b_template``'s
    largest coefficient (the scale of G against f and h); h(d_s) = 0 (its offset is in f's
    kappa, eq. 71 with gamma = 0); the slopes of h sum to zero over its q + 1 intervals
    (alpha = 0, eq. 60: the linear part of the feedback lives in A), which removes the ridge
    (h - alpha y, A + alpha B) along which the refinement would drift. The slope of h on the
    interval next to d_s is the dependent one.
    theta = [a_1..a_n, b (free lags), slopes of f, f(c_r), slopes of h but the dependent one].
    """

    order: int
    b_template: np.ndarray
    free_b: np.ndarray
    f_part: np.ndarray
    f_primary: int
    h_part: np.ndarray
    h_primary: int

    @property
    def h_dependent(self) -> int:
        q = self.h_part.size
        inner = [i for i in (self.h_primary, self.h_primary - 1) if 1 <= i <= q - 1]
        return inner[0] if inner else q

    @property
    def size(self) -> int:
        return self.order + self.free_b.size + self.f_part.size + 2 + self.h_part.size

    def unpack(self, theta: np.ndarray):
        """(a, b, f, h) of theta."""
        theta = np.asarray(theta, dtype=float)
        n = self.order
        a = np.concatenate([[1.0], theta[:n]])
        b = self.b_template.copy()
        b[self.free_b] = theta[n : n + self.free_b.size]
        k = n + self.free_b.size
        nf = self.f_part.size + 1
        f_map = point_slope_map(self.f_part, self.f_primary, theta[k : k + nf], float(theta[k + nf]))
        free_h = theta[k + nf + 1 :]
        h_slopes = np.insert(free_h, self.h_dependent, -np.sum(free_h))
        return a, b, f_map, point_slope_map(self.h_part, self.h_primary, h_slopes, 0.0)

    def pack(self, a: np.ndarray, b: np.ndarray, f_map: PiecewiseLinearMap, h_map: PiecewiseLinearMap) -> np.ndarray:
        """theta of a model on this layout's partitions: scaled to the fixed coefficient (b / scale,
        f * scale, h * scale is the same model), the linear part of h moved into A (eq. 3), its
        offset into f's."""
        size = self.b_template.size
        a = np.pad(np.asarray(a, dtype=float), (0, max(0, self.order + 1 - np.size(a))))[: self.order + 1]
        b = np.pad(np.asarray(b, dtype=float), (0, max(0, size - np.size(b))))[:size]
        scale = b[self.fixed_b] / self.b_template[self.fixed_b]
        b = b / scale
        h_slopes = h_map.slopes * scale
        alpha = float(np.mean(h_slopes))
        a = a + alpha * np.concatenate([[0.0], b[1 : self.order + 1]])
        d_s = self.h_part[self.h_primary - 1]
        h_at_ds = scale * float(h_map(np.array([d_s]))[0]) - alpha * d_s
        kappa = scale * float(f_map(np.array([self.f_part[self.f_primary - 1]]))[0]) - h_at_ds
        parts = [a[1:], b[self.free_b], f_map.slopes * scale, [kappa], np.delete(h_slopes - alpha, self.h_dependent)]
        return np.concatenate([np.asarray(p, dtype=float) for p in parts])

    @property
    def fixed_b(self) -> int:
        return int(np.setdiff1d(np.flatnonzero(self.b_template), self.free_b)[0])

    def runner(self, u: np.ndarray, preroll: int) -> Callable[[np.ndarray], np.ndarray]:
        """[level, theta] -> the loop's output for the input u, started at rest at the constant
        input ``level`` (``preroll`` samples of it simulated first from zero initial conditions
        and dropped): ``unpack`` and ``simulate_hammerstein_feedback`` with the point-slope bases
        of u and of h's knots computed once (the refinement's inner loop)."""
        eta = np.column_stack([point_slope_basis(u, self.f_part, self.f_primary), np.ones(np.size(u))])
        at_knots = point_slope_basis(self.h_part, self.h_part, self.h_primary)
        n, nb, nf = self.order, self.free_b.size, self.f_part.size + 2

        def run(extended: np.ndarray) -> np.ndarray:
            level, theta = extended[0], extended[1:]
            b = self.b_template.copy()
            b[self.free_b] = theta[n : n + nb]
            coefficients = theta[n + nb : n + nb + nf]
            at_level = np.append(point_slope_basis(np.array([level]), self.f_part, self.f_primary)[0], 1.0)
            drive = np.concatenate([np.full(preroll, at_level @ coefficients), eta @ coefficients])
            forced = np.convolve(drive, b)[: drive.size]
            free_h = theta[n + nb + nf :]
            h_slopes = np.insert(free_h, self.h_dependent, -np.sum(free_h))
            return feedback_loop(forced, b[1:], theta[:n], self.h_part, at_knots @ h_slopes, h_slopes)[preroll:]

        return run

    def simulator(self, theta: np.ndarray, preroll: int, tails: tuple | None = None):
        """The simulator of theta; ``tails``: (f range, f tails, h range, h tails) for ``with_tails``."""
        a, b, f_map, h_map = self.unpack(theta)
        if tails is not None:
            f_map, h_map = with_tails(f_map, *tails[0], *tails[1]), with_tails(h_map, *tails[2], *tails[3])
        return _feedback_simulator(a, b, f_map, h_map, preroll)


def _numerator_layout(b: np.ndarray, delay: int) -> tuple[np.ndarray, np.ndarray]:
    """(template, free indices): lags delay..n free but the largest coefficient's."""
    fixed = delay + int(np.argmax(np.abs(b[delay:])))
    template = b.astype(float).copy()
    template[:delay] = 0.0
    return template, np.array([i for i in range(delay, b.size) if i != fixed], dtype=int)


def map_on(partition: np.ndarray, primary: int, x: np.ndarray, target: np.ndarray) -> PiecewiseLinearMap:
    """The point-slope map on ``partition`` fitting target(x) in least squares."""
    theta = solve_least_squares(np.column_stack([point_slope_basis(x, partition, primary), np.ones(x.size)]), target)
    return point_slope_map(partition, primary, theta[:-1], float(theta[-1]))


def _loop_start(layout: FeedbackLayout, a: np.ndarray, h_map: PiecewiseLinearMap, v: np.ndarray,
                y: np.ndarray, skip: int) -> np.ndarray:
    """theta with the given A and h, B the template, f by least squares on the series-parallel
    form y + B/A [h(y)] = B/A [f(v)] (the measured y in the feedback path)."""
    b = layout.b_template
    eta = np.column_stack([point_slope_basis(v, layout.f_part, layout.f_primary), np.ones(v.size)])
    columns = np.column_stack([steady_state_filter(b, a, col) for col in eta.T])
    target = y + steady_state_filter(b, a, h_map(y))
    theta = solve_least_squares(columns[skip:], target[skip:])
    f_map = point_slope_map(layout.f_part, layout.f_primary, theta[:-1], float(theta[-1]))
    return layout.pack(a, b, f_map, h_map)


def _random_denominator(rng: np.random.Generator, poles: np.ndarray) -> np.ndarray:
    """Poles moved at random: time constants scaled by exp(N(0, 0.5)), angles by exp(N(0, 0.3))."""
    moved = []
    for p in poles:
        radius = min(abs(p), 0.999) ** float(np.exp(0.5 * rng.standard_normal()))
        if abs(p.imag) > 1e-9:
            if p.imag > 0:
                angle = float(np.clip(np.angle(p) * np.exp(0.3 * rng.standard_normal()), 0.01, np.pi - 0.01))
                moved += [radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]
        else:
            moved.append(np.sign(p.real or 1.0) * radius)
    return stabilised_denominator(np.real(np.poly(moved))) if moved else np.ones(1)


def extend_output_feedback(ctx: Context) -> ExtendedModel:
    """The output fed back through static maps, in the family that fits the estimation data best
    by its simulation-error BIC (``bic``, ``parameters`` in the details): the non-linear feedback
    loop y = G[f(v) - h(y)] or two storages in series (``feedback_loop_model``), or the servo loop
    y = G[f(v - y) - h(y) - phi(dy)] of a system inside its own position loop (its maps'
    fit, ``servo_loop.fit_servo_loop``: the map on the loop error, friction on the output's
    difference). When the servo loop wins, its form (its maps or its physical constants) is chosen
    on held-back estimation data (``servo_loop_model``). Either family may fail on a record; the
    other is then the extension."""
    s = ctx.split
    skip = min(ctx.skip, s.n_est // 5)

    def score(simulate: Callable[[np.ndarray], np.ndarray], parameters: int) -> float:
        return bic(s.y_est[skip:], s.estimation_output(simulate)[skip:], parameters)

    loop = servo = None
    failures = []
    try:
        loop = feedback_loop_model(ctx)
    except NUMERICAL_FAILURES as error:
        failures.append(failure_reason(error))
    try:
        servo = fit_servo_loop(s.v_est, s.y_est, s.runs_est)
    except IdentificationError as error:
        failures.append(failure_reason(NotFitted(f"servo loop: {error}")))
    if servo is not None and (loop is None or score(servo.simulate, servo.parameter_count)
                              < score(loop.simulate, loop.details["parameters"])):
        return servo_loop_model(ctx, servo)
    if loop is None:
        raise NotFitted("; ".join(failures))
    return loop


def servo_loop_model(ctx: Context, maps: ServoFit) -> ExtendedModel:
    """The servo loop as an extension of ``output_feedback``: its maps (``maps``, fitted on the
    estimation data) or its physical form (``physical_servo``), whichever simulates held-back
    estimation runs better (``physical_servo.choose_servo_form``; both held-back RMS in the details)."""
    s = ctx.split
    choice = choose_servo_form(s.v_est, s.y_est, s.runs_est, maps)
    fit = choice.fit
    simulate = fit.simulate
    output = s.validation_output(simulate)
    e = per_run(lambda u: held_back(u, fit.delay), s.v_est, s.runs_est) - s.y_est
    f, h, phi = fit.maps()
    plots = (map_plot("f (controller on the loop error u - y)", f, e),
             map_plot("h (output feedback: gravity)", h, s.y_est),
             map_plot("phi (friction on the output's difference)", phi, np.diff(s.y_est)))
    details = {**fit.details(s.v_est, s.y_est), "parameters": fit.parameter_count,
               "held_back_rms": choice.held_back_rms}
    structure = PHYSICAL_SERVO if isinstance(fit, PhysicalServoFit) else SERVO_LOOP
    return ExtendedModel("output_feedback", structure, output, details, plots, simulate)


def feedback_loop_model(ctx: Context) -> ExtendedModel:
    """Hammerstein / non-linear feedback y = G[f(v) - h(y)] (paper 001, eq. 2 and sec. 4.3), f on
    the baseline's breakpoints and h on quantiles of y, refined on the simulation error of the
    whole estimation record (the loop runs in the compiled kernel of ``compiled_loops``).

    Starts (``FeedbackLayout`` fixes the representation): PLLS for this structure on the raw
    estimation data (eqs. 63-71), the baseline (h = 0), and ``random_starts`` random ones (the
    baseline's or PLLS's poles moved at random, a random h, f by least squares with the measured
    y in the loop, ``_loop_start``), ranked by their simulation error. The record is taken to
    start at rest at an unknown constant input (the initial state, ``initial_input``), which is
    refined with the loop from the baseline's ``rest_input`` at the first outputs, so that no
    estimation sample is dropped as a transient (the start of a record can hold its most
    informative excursion). PLLS, the baseline and the best random ones (SCREENED_STARTS in
    all) are refined SCREEN_ITERATIONS LM steps on the simulation error; the KEPT_STARTS best
    are refined to the end and the best on the estimation data is kept. Then the tails of f and
    h (``_choose_tails``) are chosen on held-back estimation data; when the chosen tails drive
    the loop unstable on the validation input (its output alone decides nothing), both maps
    continue with their last slopes.

    A second form competes from baseline order 2 on: two first-order storages in series, each
    with its own level-dependent outflow (``storage_cascade``: the lower of two tanks feels the
    upper tank's outflow, a function of a level the output does not carry), started from the
    baseline's two slowest poles in both orders and from random ones, refined the same way; the form
    with the smaller simulation error on the estimation data is kept (``form`` in the details): the
    best refined cascade whose rest states over the record's input range stay near the measured
    outputs (``plausible_rest``). On a short record (below SHORT_RECORD samples, where a few slow
    excursions leave many local minima and a simulation is cheap) every start of the cascade is
    screened and KEPT_CASCADES are refined to the end; beyond that the loop's schedule."""
    base, s = ctx.baseline, ctx.split
    v, y = s.v_est, s.y_est
    delay = max(base.delay, 1)
    skip = min(ctx.skip, v.size // 5)
    try:
        f_part = drop_empty_intervals(v, base.partition)
        h_part = quantile_partition(y, feedback_breakpoints(y.size))
    except IdentificationError as error:
        raise NotFitted(f"the feedback map's breakpoints: {error}") from error
    est = None
    try:
        est = plls(v, y, base.order, delay, "hammerstein_feedback", partition=f_part, feedback_partition=h_part)
        if not np.all(np.isfinite(est.linear.b)) or not np.any(est.linear.b[delay:]):
            est = None
    except (IdentificationError, np.linalg.LinAlgError, ValueError):
        est = None
    n = base.order
    if base.delay >= 1:
        b_template = np.pad(base.b, (0, max(0, n + 1 - base.b.size)))[: n + 1]
    elif est is not None:
        b_template = est.linear.b
    else:
        raise NotFitted("no start for the loop: the baseline has no delay and PLLS for the loop failed")
    b_template, free_b = _numerator_layout(b_template, delay)
    layout = FeedbackLayout(n, b_template, free_b, f_part, max(1, f_part.size // 2), h_part, max(1, h_part.size // 2))
    preroll = settling_samples(base.linear.poles, cap=1000)
    zero_h = point_slope_map(h_part, layout.h_primary, np.zeros(h_part.size + 1), 0.0)

    starts = []
    if est is not None:
        starts.append(layout.pack(stabilised_denominator(est.linear.a), est.linear.b, est.nonlinearity,
                                  est.feedback))
    if base.delay >= 1:
        starts.append(layout.pack(base.a, base.b, map_on(f_part, layout.f_primary, v, base.static(v)), zero_h))
    deterministic = len(starts)
    rng = np.random.default_rng(0)
    scale = float(np.std(base.static(v))) or 1.0
    pole_sets = [base.linear.poles] + ([np.roots(stabilised_denominator(est.linear.a))] if est is not None else [])
    for i in range(random_starts(v.size)):
        a = _random_denominator(rng, pole_sets[i % len(pole_sets)])
        if a.size != n + 1:
            continue
        slopes = rng.standard_normal(h_part.size + 1)
        h_map = point_slope_map(h_part, layout.h_primary, slopes - slopes.mean(), 0.0)
        strength = scale / (float(np.std(h_map(y))) or 1.0) * float(np.exp(rng.uniform(np.log(0.05), 0.0)))
        h_map = point_slope_map(h_part, layout.h_primary, (slopes - slopes.mean()) * strength, 0.0)
        try:
            starts.append(_loop_start(layout, a, h_map, v, y, skip))
        except (np.linalg.LinAlgError, ValueError):
            continue
    deterministic = sum(np.all(np.isfinite(t)) for t in starts[:deterministic])
    starts = [t for t in starts if np.all(np.isfinite(t))]
    if not starts:
        raise NotFitted("no start of the loop is finite")

    level = rest_input(base.simulate, float(np.mean(y[:INITIAL_SAMPLES])), v)
    starts = [np.concatenate([[level], t]) for t in starts]  # [initial level, theta]
    parts = s.est_runs.split(v)  # the first run from rest at the refined level, the others at their first input
    runners = [layout.runner(part, preroll) for part in parts]

    def run(extended: np.ndarray) -> np.ndarray:
        return np.concatenate([runners[0](extended)] + [r(np.concatenate([[part[0]], extended[1:]]))
                                                        for r, part in zip(runners[1:], parts[1:])])

    def tailed(t: np.ndarray, tails: tuple) -> np.ndarray:
        simulate = layout.simulator(t[1:], 0, tails)
        return np.concatenate([simulate(np.concatenate([np.full(preroll, t[0] if i == 0 else part[0]), part]))[preroll:]
                               for i, part in enumerate(parts)])

    fit, cost = _tail_fitting(run, tailed, y)

    schedule = (SCREENED_STARTS, SCREEN_ITERATIONS, KEPT_STARTS, FEEDBACK_ITERATIONS)
    loop_fits = refine_starts([(run, t) for t in starts], y, deterministic, *schedule)
    loop_cost = loop_fits[0][2] if loop_fits else np.inf
    # the storage cascade's runner simulates the record as one: not tried on several runs
    cascade = [] if s.has_runs else cascade_starts(base, f_part, v, level, preroll, delay, random_starts(v.size))
    short = v.size < SHORT_RECORD  # every start screened, more refined: cheap on a short record
    cascade_schedule = (len(cascade) if short else SCREENED_STARTS, SCREEN_ITERATIONS,
                        KEPT_CASCADES if short else KEPT_STARTS, FEEDBACK_ITERATIONS)
    for i, cascade_theta, cascade_cost in refine_starts([(r, t) for _, r, t in cascade], y, 2, *cascade_schedule):
        if cascade_cost >= loop_cost:
            break
        if plausible_rest(cascade[i][0], cascade_theta[1:], v, y, preroll):
            try:
                return _storage_cascade_model(s, cascade[i][0], cascade[i][1], cascade_theta, preroll, v, y)
            except NotFitted:
                break  # the loop's model, when it does not diverge too
    if not loop_fits:
        raise NotFitted("the simulation of every start of the loop diverges on the estimation data")
    theta = loop_fits[0][1]
    a, b, f_fit, h_fit = layout.unpack(theta[1:])

    def simulator(tails: tuple) -> Callable[[np.ndarray], np.ndarray]:
        f_map, h_map = with_tails(f_fit, *tails[0], *tails[1]), with_tails(h_fit, *tails[2], *tails[3])
        return _feedback_simulator(a, b, f_map, h_map, preroll)

    tails, simulate, output = _stable_tails(s, y, simulator, _choose_tails(theta, v, y, fit, cost), "loop")
    f_map, h_map = with_tails(f_fit, *tails[0], *tails[1]), with_tails(h_fit, *tails[2], *tails[3])
    maps = (map_plot("f (input map)", f_map, v), map_plot("h (feedback map; its linear part is in A)", h_map, y))
    details = {"form": "loop", "parameters": theta.size, "feedback_breakpoints": h_part.tolist(), "starts": len(starts),
               "initial_input": float(theta[0]),
               "a": a.tolist(), "b": b.tolist(),
               "tails": _tails_details(tails), **order_details(replace(base, a=a, b=b))}
    return ExtendedModel("output_feedback", "hammerstein / non-linear feedback (PLLS)", output, details, maps,
                         simulate)


def _storage_cascade_model(split: Split, layout: CascadeLayout, run: Callable[[np.ndarray], np.ndarray],
                           theta: np.ndarray, preroll: int, v: np.ndarray, y: np.ndarray) -> ExtendedModel:
    """The extension of ``output_feedback`` as two storages in series (``storage_cascade``),
    simulated from rest at the input's first value like the loop, its input map f and the
    output's outflow h2 continued by the tails chosen on held-back data (``_choose_tails``);
    ``run``: the layout's runner on the estimation input (the one it was refined with)."""
    fit, cost = _tail_fitting(run, lambda t, tails: layout.simulate(t[1:], v, t[0], preroll, tails), y)

    def simulator(tails: tuple) -> Callable[[np.ndarray], np.ndarray]:
        return lambda u: layout.simulate(theta[1:], np.asarray(u, dtype=float), float(u[0]), preroll, tails)

    chosen = _choose_tails(theta, v, y, fit, cost)
    tails, simulate, output = _stable_tails(split, y, simulator, chosen, "storage cascade")
    f_map, h1, g, h2 = layout.maps(theta[1:])
    f_map, h2 = with_tails(f_map, *tails[0], *tails[1]), with_tails(h2, *tails[2], *tails[3])
    span = np.ptp(layout.x_part) or 1.0
    levels = np.array([layout.x_part[0] - 0.5 * span, layout.x_part[-1] + 0.5 * span])
    maps = (map_plot("f (inflow of the first storage)", f_map, v),
            map_plot("h1 (outflow of the first storage)", h1, levels),
            map_plot("g (inflow of the second storage, from the first level)", g, levels),
            map_plot("h2 (outflow of the second storage: the output's feedback)", h2, y))
    details = {"form": "storage_cascade", "parameters": theta.size, "initial_input": float(theta[0]),
               "delay": layout.delay,
               "first_level_breakpoints": layout.x_part.tolist(), "feedback_breakpoints": layout.y_part.tolist(),
               "tails": _tails_details(tails)}
    return ExtendedModel("output_feedback", STORAGE_CASCADE, output, details, maps, simulate)


def _tail_fitting(run: Callable[[np.ndarray], np.ndarray], tailed: Callable[[np.ndarray, tuple], np.ndarray],
                  y: np.ndarray):
    """(fit, cost) of a model refined on the simulation error, as ``_choose_tails`` needs them:
    ``run``(theta) its output on the estimation input, ``tailed``(theta, tails) the same with its
    maps continued by ``tails``; fit(theta, iterations, keep) -> (theta, cost on ``keep``),
    cost(theta, keep, tails=None) -> the sum of squared errors on ``keep`` (inf when not finite)."""
    everything = np.ones(y.size, dtype=bool)

    def cost(theta: np.ndarray, keep: np.ndarray, tails: tuple | None = None) -> float:
        with np.errstate(all="ignore"):
            out = run(theta) if tails is None else tailed(theta, tails)
            c = float(np.sum((out[keep] - y[keep]) ** 2))
        return c if np.isfinite(c) else np.inf

    def fit(theta: np.ndarray, iterations: int, keep: np.ndarray | None = None):
        keep = everything if keep is None else keep
        theta = refine(lambda t: run(t)[keep], theta, y[keep], iterations)
        return theta, cost(theta, keep)

    return fit, cost


def _stable_tails(split: Split, y: np.ndarray, simulator: Callable[[tuple], Callable[[np.ndarray], np.ndarray]],
                  chosen: tuple, what: str) -> tuple[tuple, Callable[[np.ndarray], np.ndarray], np.ndarray]:
    """(tails, simulate, validation output) with the ``chosen`` tails, or with the last slopes when
    those drive the model unstable on the validation input (its output alone decides nothing)."""
    for tails in (chosen, _slope_tails(split.v_est, y)):
        simulate = simulator(tails)
        output = split.validation_output(simulate)
        if np.all(np.isfinite(output)) and np.max(np.abs(output - np.mean(y))) <= 100 * np.ptp(y):
            return tails, simulate, output
    raise NotFitted(f"the fitted {what} diverges on the validation input")


def _tails_details(tails: tuple) -> dict:
    return {"f": dict(zip(("left", "right"), tails[1])), "h": dict(zip(("left", "right"), tails[3]))}


def _held_back(x: np.ndarray, side: int, parts: int = 4) -> slice:
    """The quarter of the record whose samples reach furthest beyond the range of the others on
    ``side`` (0: below, 1: above; summed excess): the held-back data on which a tail is chosen."""
    bounds = np.linspace(0, x.size, parts + 1).astype(int)
    best, best_excess = slice(bounds[-2], bounds[-1]), -1.0
    for i in range(parts):
        inside, rest = x[bounds[i] : bounds[i + 1]], np.concatenate([x[: bounds[i]], x[bounds[i + 1] :]])
        beyond = inside - rest.max() if side else rest.min() - inside
        excess = float(np.sum(np.maximum(beyond, 0.0)))
        if excess > best_excess:
            best, best_excess = slice(bounds[i], bounds[i + 1]), excess
    return best


def _slope_tails(v: np.ndarray, y: np.ndarray) -> tuple:
    """Both maps continued with their last slopes (``_choose_tails``' form)."""
    return (float(v.min()), float(v.max())), ("slope", "slope"), (float(y.min()), float(y.max())), ("slope", "slope")


def _choose_tails(theta: np.ndarray, v: np.ndarray, y: np.ndarray, fit, cost) -> tuple:
    """How f (on v) and h (on y) continue beyond the estimation data (``with_tails``), each side
    on its own: the model is refined (TAIL_ITERATIONS from ``theta``) on the estimation data
    less the held-back quarter (``_held_back``: the one reaching furthest beyond the others on
    that side), its map continued beyond the range of the rest by each of TAILS, and scored on
    the held-back quarter; a tail other than ``slope`` is kept when it lowers that error by
    TAIL_MARGIN. Returns ((v range), (f tails), (y range), (h tails)) of the whole record."""
    v_range, f_tails, y_range, h_tails = _slope_tails(v, y)
    ranges, chosen = [v_range, y_range], [list(f_tails), list(h_tails)]
    fits = {}
    for m, x in enumerate((v, y)):
        for side in (0, 1):
            held = _held_back(x, side)
            keep = np.ones(v.size, dtype=bool)
            keep[held] = False
            if held.start not in fits:
                fits[held.start] = fit(theta, TAIL_ITERATIONS, keep)[0]
            test = np.zeros(v.size, dtype=bool)
            test[held] = True
            rest = [(float(z[keep].min()), float(z[keep].max())) for z in (v, y)]
            scores = {}
            for tail in TAILS:
                tails = [list(t) for t in chosen]
                tails[m][side] = tail
                scores[tail] = cost(fits[held.start], test, (rest[0], tails[0], rest[1], tails[1]))
            best = min(scores, key=scores.get)
            if best != "slope" and scores[best] < (1.0 - TAIL_MARGIN) * scores["slope"]:
                chosen[m][side] = best
    return ranges[0], tuple(chosen[0]), ranges[1], tuple(chosen[1])
