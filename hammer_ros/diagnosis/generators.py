"""Records with a hidden cause: a Hammerstein plant plus one effect it cannot represent.

Every case draws, from its seed, a random linear block (order 2-3; real poles, a complex pair,
an optional zero; any static gain), a random input (white Gaussian or uniform, low-pass
filtered, random steps, random-phase multisine; any mean and scale), a random input
nonlinearity (polynomial, saturation, dead zone, asymmetric piecewise-linear, tanh, signed
square, exponential, square root, relay with slope) and a random noise level (1-5 % of the
output's standard deviation; white or coloured), then adds one hidden effect of random kind
and size (``CAUSES``). The effect sizes are drawn so that the effect is visible above the
noise: the generators are the test bench of the diagnosis, not a detectability study.
Used by the tests and the benchmark.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..identification.linear import LinearModel
from ..identification.simulate import play_operator, simulate_hammerstein_feedback
from .causes import CAUSES

PREROLL = 400  # samples simulated and dropped so that every record starts in steady motion
Map = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True, eq=False)
class GeneratedCase:
    """A record (v, y) whose hidden ``cause`` the diagnosis must name; ``order`` is the
    nominal order to pass as ``--order``; ``description`` says what was drawn."""

    cause: str
    v: np.ndarray
    y: np.ndarray
    order: int
    seed: int
    description: str


# --------------------------------------------------------------------------- random blocks


def random_linear_block(rng: np.random.Generator, order: int) -> LinearModel:
    """Order 1-3, relative degree 1: a complex pair (radius 0.55-0.93, angle 0.15-1.3 rad)
    with probability 0.6 when order >= 2, the other poles real in 0.1-0.93, an optional real
    zero, static gain of either sign with magnitude 0.5-2."""
    poles: list[complex] = []
    if order >= 2 and rng.random() < 0.6:
        radius, angle = rng.uniform(0.55, 0.93), rng.uniform(0.15, 1.3)
        poles += [radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]
    poles += list(rng.uniform(0.1, 0.93, order - len(poles)))
    zeros = [rng.uniform(-0.6, 0.7)] if order >= 2 and rng.random() < 0.4 else []
    gain = rng.uniform(0.5, 2.0) * rng.choice([-1.0, 1.0])
    return LinearModel.from_zeros_poles(zeros, poles, gain)


def random_input(rng: np.random.Generator, n: int) -> tuple[np.ndarray, str, float]:
    """(v, kind, bandwidth in rad/sample) with random mean (0 or +-1) and scale (0.5-2)."""
    kind = str(rng.choice(["gaussian", "uniform", "lowpass", "steps", "multisine"]))
    bandwidth = np.pi
    if kind == "gaussian":
        z = rng.standard_normal(n)
    elif kind == "uniform":
        z = rng.uniform(-np.sqrt(3), np.sqrt(3), n)
    elif kind == "lowpass":
        pole = rng.uniform(0.3, 0.75)
        z = signal.lfilter([1.0], [1.0, -pole], rng.standard_normal(n))
        bandwidth = 2.0 * (1.0 - pole) + 0.2
    elif kind == "steps":
        holds = rng.geometric(1.0 / rng.uniform(1.5, 5.0), n)
        z = np.repeat(rng.standard_normal(n), holds)[:n]
        bandwidth = 2.0
    else:  # random-phase multisine, many lines up to a random band edge
        edge = rng.uniform(0.8, 3.0)
        omega = np.linspace(0.01, edge, 120)
        z = np.cos(np.outer(np.arange(n), omega) + rng.uniform(0, 2 * np.pi, omega.size)).sum(axis=1)
        bandwidth = edge
    z = (z - z.mean()) / z.std()
    mean = float(rng.choice([0.0, rng.uniform(-1.0, 1.0)]))
    scale = rng.uniform(0.5, 2.0)
    return mean + scale * z, kind, float(bandwidth)


NONLINEARITIES = ("polynomial", "saturation", "dead_zone", "asymmetric_pwl", "tanh", "signed_square",
                  "exponential", "sqrt", "relay_slope", "dead_zone_saturation")
STRONG_NONLINEARITIES = ("saturation", "dead_zone", "asymmetric_pwl", "signed_square", "exponential",
                         "relay_slope", "dead_zone_saturation")


def random_nonlinearity(rng: np.random.Generator, names=NONLINEARITIES) -> tuple[Map, str]:
    """A static map of the normalised input z (unit scale); returns (map, description)."""
    name = str(rng.choice(list(names)))
    if name == "polynomial":
        a2, a3 = rng.uniform(-0.4, 0.4), rng.uniform(0.1, 0.3) * rng.choice([-1, 1])
        return (lambda z: z + a2 * z**2 + a3 * z**3), f"polynomial z{a2:+.2f}z^2{a3:+.2f}z^3"
    if name == "saturation":
        lo, hi = rng.uniform(0.4, 1.2, 2)
        return (lambda z: np.clip(z, -lo, hi)), f"saturation [-{lo:.2f}, {hi:.2f}]"
    if name == "dead_zone":
        lo, hi = rng.uniform(0.2, 0.7, 2)
        return (lambda z: np.where(z > hi, z - hi, np.where(z < -lo, z + lo, 0.0))), f"dead zone [-{lo:.2f}, {hi:.2f}]"
    if name == "asymmetric_pwl":
        corner, ratio = rng.uniform(-0.5, 0.5), rng.uniform(0.1, 0.5)
        left, right = (ratio, 1.0) if rng.random() < 0.5 else (1.0, ratio)
        label = f"pwl slopes {left:.2f}|{right:.2f} at {corner:.2f}"
        return (lambda z: np.where(z > corner, right, left) * (z - corner)), label
    if name == "tanh":
        k = rng.uniform(0.8, 2.5)
        return (lambda z: np.tanh(k * z) / k), f"tanh({k:.2f} z)"
    if name == "signed_square":
        lin = rng.uniform(0.0, 0.5)
        return (lambda z: z * np.abs(z) + lin * z), f"z|z| + {lin:.2f} z"
    if name == "exponential":
        a = rng.uniform(0.5, 1.2) * rng.choice([-1, 1])
        return (lambda z: (np.exp(a * z) - 1.0) / a), f"(exp({a:.2f} z) - 1)/{a:.2f}"
    if name == "sqrt":
        return (lambda z: np.sign(z) * np.sqrt(np.abs(z))), "sign(z) sqrt|z|"
    if name == "relay_slope":
        jump = rng.uniform(0.2, 0.6)
        return (lambda z: jump * np.tanh(z / 0.05) + z), f"{jump:.2f} sign(z) + z"
    dz, sat = rng.uniform(0.15, 0.4), rng.uniform(0.8, 1.5)
    label = f"dead zone {dz:.2f} + saturation {sat:.2f}"
    return (lambda z: np.clip(np.sign(z) * np.maximum(np.abs(z) - dz, 0.0), -sat, sat)), label


def _noise(rng: np.random.Generator, n: int, std: float) -> tuple[np.ndarray, str]:
    """White, or (probability 0.25) AR(1)-coloured Gaussian noise with the given std."""
    e = rng.standard_normal(n)
    if rng.random() < 0.25:
        pole = rng.uniform(0.5, 0.9)
        e = signal.lfilter([1.0], [1.0, -pole], e)
        return std * e / e.std(), f"AR(1) {pole:.2f}"
    return std * e, "white"


def _normalised(x: np.ndarray) -> tuple[np.ndarray, float, float]:
    m, s = float(np.mean(x)), float(np.std(x))
    return (x - m) / s, m, s


def _continue_filter(linear: LinearModel, x: np.ndarray, y_past: np.ndarray, x_past: np.ndarray) -> np.ndarray:
    """linear's response to x continuing the recursion from past outputs and inputs."""
    zi = signal.lfiltic(linear.b, linear.a, y_past[::-1], x_past[::-1])
    return signal.lfilter(linear.b, linear.a, x, zi=zi)[0]


def _switched(first: LinearModel, second: LinearModel, x: np.ndarray, switch: int) -> np.ndarray:
    """Response to x of ``first`` up to sample ``switch`` and of ``second`` afterwards."""
    y1 = first.simulate(x[:switch])
    memory = max(second.a.size, second.b.size)
    y2 = _continue_filter(second, x[switch:], y1[-memory:], x[switch - memory : switch])
    return np.concatenate([y1, y2])


# --------------------------------------------------------------------------- the effects


def _effect(cause: str, rng, linear: LinearModel, fmap: Map, v: np.ndarray, bandwidth: float, order: int):
    """(clean output, nominal order, description) of the plant with the hidden effect."""
    u = fmap(v)
    x = linear.simulate(u)
    if cause == "none":
        return x, order, "clean Hammerstein"
    if cause == "output_feedback":
        y, label = _output_feedback(rng, linear, fmap, v, x)
        return y, order, label
    if cause == "parallel_path":
        g2, label = _parallel_block(rng, linear)
        path = g2.simulate(v)
        ratio = rng.uniform(0.35, 0.9)
        return x + ratio * np.std(x) / np.std(path) * path, order, f"parallel {label}, size {ratio:.2f}"
    if cause == "output_nonlinearity":
        y, label = _output_map(rng, x)
        return y, order, label
    if cause == "backlash":
        width = rng.uniform(0.25, 0.8) * np.std(v)
        if rng.random() < 0.65:
            return linear.simulate(fmap(play_operator(v, width))), order, f"play width {width:.3f}"
        widths = width * np.array([0.3, 0.7, 1.2])
        weights = rng.dirichlet(np.ones(3))
        hysteretic = sum(w * play_operator(v, r) for w, r in zip(weights, widths))
        return linear.simulate(fmap(hysteretic)), order, f"Prandtl-Ishlinskii hysteresis widths {np.round(widths, 3)}"
    if cause == "time_varying":
        y, label = _time_varying(rng, linear, u)
        return y, order, label
    if cause == "unmodeled_dynamics":
        extra, label = _extra_dynamics(rng, bandwidth)
        return extra.simulate(x), order, f"unmodelled {label}"
    if cause == "periodic_disturbance":
        omega = rng.uniform(0.03, 2.5)
        harmonics = int(rng.integers(1, 4))
        k = np.arange(v.size)
        d = sum(rng.uniform(0.3, 1.0) / h * np.sin(h * omega * k + rng.uniform(0, 2 * np.pi))
                for h in range(1, harmonics + 1) if h * omega < np.pi)
        ratio = rng.uniform(0.15, 0.45)
        return x + ratio * np.std(x) * d / np.std(d), order, f"periodic w={omega:.3f} x{harmonics}, size {ratio:.2f}"
    raise ValueError(f"unknown cause {cause!r}")


def _input_dynamics(rng, linear: LinearModel, fmap: Map, v: np.ndarray, bandwidth: float, order: int):
    """(output, its Hammerstein counterpart, nominal order, description) of a Wiener-Hammerstein
    plant y = G[F(L[v])]: a filter L ahead of the map (its output scaled to the input's spread).
    The counterpart c + g G[L[F(v)]] has the same blocks commuted: what differs from it is the effect."""
    front, label = _front_block(rng, bandwidth)
    w = front.simulate(v)
    scale = np.std(v) / np.std(w)
    y = linear.simulate(fmap(np.mean(v) + (w - np.mean(w)) * scale))
    commuted = np.column_stack([np.ones(v.size), linear.simulate(front.simulate(fmap(v)))])
    commuted = commuted @ np.linalg.lstsq(commuted[PREROLL:], y[PREROLL:], rcond=None)[0]  # its best gain and offset
    return y, commuted, order + front.order, f"front {label} (nominal order {order + front.order})"


def _front_block(rng, bandwidth: float) -> tuple[LinearModel, str]:
    """A unit-DC-gain filter ahead of the input map, its corner inside the input's band: a
    first-order low-pass, or a lightly damped pair (a sensor or amplifier resonance)."""
    if rng.random() < 0.6:
        pole = rng.uniform(max(0.5, 1.0 - 0.5 * bandwidth), 0.92)
        return LinearModel([1.0 - pole], [1.0, -pole]), f"low-pass pole {pole:.2f}"
    radius, angle = rng.uniform(0.6, 0.9), rng.uniform(0.2, min(1.2, 0.8 * bandwidth))
    den = np.real(np.poly([radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]))
    return LinearModel([np.sum(den)], den), f"pair r={radius:.2f} angle={angle:.2f}"


def _output_feedback(rng, linear: LinearModel, fmap: Map, v: np.ndarray, x: np.ndarray):
    """y = G[F(v) - h(y)] with a random non-linear h (its linear part only moves the poles)."""
    _, m, s = _normalised(x)
    kind = str(rng.choice(["cubic", "signed_square", "one_sided", "dead_zone", "sqrt"]))
    corner = rng.uniform(-0.3, 0.8)
    shapes = {
        "cubic": lambda w: w**3,
        "signed_square": lambda w: w * np.abs(w),
        "one_sided": lambda w: 2.0 * np.maximum(w - corner, 0.0),
        "dead_zone": lambda w: 2.0 * (w - np.clip(w, -abs(corner), abs(corner))),
        "sqrt": lambda w: np.sign(w) * np.sqrt(np.abs(w)),
    }
    strength = rng.uniform(0.25, 0.8) / abs(linear.dc_gain)
    for _ in range(8):
        k = strength

        def feedback(y, k=k):
            return k * s * shapes[kind]((np.asarray(y) - m) / s)

        with np.errstate(over="ignore", invalid="ignore"):  # a too strong loop diverges: halve and retry
            y = simulate_hammerstein_feedback(v, fmap, feedback, linear)
        if np.all(np.isfinite(y)) and np.max(np.abs(y - m)) < 20 * s:
            return y, f"feedback {kind} strength {k * abs(linear.dc_gain):.2f}"
        strength *= 0.5
    raise RuntimeError("no stable feedback strength found")


def _parallel_block(rng, linear: LinearModel) -> tuple[LinearModel, str]:
    """A first-order path whose pole differs clearly from the Hammerstein branch's poles."""
    slowest = float(np.max(np.abs(linear.poles)))
    if rng.random() < 0.5 or slowest > 0.85:
        pole = rng.uniform(0.0, 0.35)
        delay = int(rng.integers(0, 2))
        label = f"fast path pole {pole:.2f} delay {delay}"
    else:
        pole = rng.uniform(max(slowest + 0.06, 0.9), 0.97)
        delay = 1
        label = f"slow path pole {pole:.2f}"
    return LinearModel(np.concatenate([np.zeros(delay), [1.0 - pole]]), [1.0, -pole]), label


def _output_map(rng, x: np.ndarray):
    """A static sensor map after the linear block."""
    w, m, s = _normalised(x)
    kind = str(rng.choice(["saturation", "two_sided_saturation", "dead_zone", "abs", "compressive", "polynomial"]))
    if kind == "saturation":
        level = np.quantile(w, rng.uniform(0.7, 0.88))
        top = rng.random() < 0.5
        z = np.minimum(w, level) if top else -np.minimum(-w, level)
        label = f"one-sided clip at {level:.2f} std"
    elif kind == "two_sided_saturation":
        lo, hi = np.quantile(w, rng.uniform(0.08, 0.2)), np.quantile(w, rng.uniform(0.8, 0.92))
        z, label = np.clip(w, lo, hi), f"clip [{lo:.2f}, {hi:.2f}] std"
    elif kind == "dead_zone":
        centre, half = rng.uniform(-0.3, 0.3), rng.uniform(0.25, 0.6)
        z = np.where(w > centre + half, w - half, np.where(w < centre - half, w + half, centre))
        label = f"dead zone half-width {half:.2f} std"
    elif kind == "abs":  # a rectifier off the middle of the signal (at the median the input-output
        # correlation of every order-one statistic vanishes and no Hammerstein start sees it)
        centre = np.quantile(w, rng.uniform(0.2, 0.4) if rng.random() < 0.5 else rng.uniform(0.6, 0.8))
        z, label = np.abs(w - centre), f"|x - {centre:.2f}|"
    elif kind == "compressive":
        gamma = rng.uniform(0.35, 0.65)
        z, label = np.sign(w) * np.abs(w) ** gamma, f"sign(x)|x|^{gamma:.2f}"
    else:
        beta = rng.uniform(0.2, 0.45) * rng.choice([-1, 1])
        z, label = w + beta * w**2, f"x{beta:+.2f}x^2"
    return m + s * z, f"output {label}"


def _time_varying(rng, linear: LinearModel, u: np.ndarray):
    """A step in the gain or the poles, or a gain drift over the whole record."""
    n = u.size - PREROLL
    kind = str(rng.choice(["gain_step", "pole_step", "gain_drift", "late_step"]))
    switch = PREROLL + int((rng.uniform(0.72, 0.8) if kind == "late_step" else rng.uniform(0.25, 0.6)) * n)
    if kind in ("gain_step", "late_step"):
        factor = rng.uniform(0.5, 0.75) if rng.random() < 0.5 else rng.uniform(1.35, 1.8)
        gain = np.where(np.arange(u.size) < switch, 1.0, factor)
        return linear.simulate(gain * u), f"{kind} x{factor:.2f} at {switch - PREROLL}"
    if kind == "gain_drift":
        total = rng.uniform(0.35, 0.7) * rng.choice([-1, 1])
        gain = 1.0 + total * np.clip(np.arange(u.size) - PREROLL, 0, None) / n
        return linear.simulate(gain * u), f"gain drift {total:+.2f} over the record"
    factor = rng.uniform(1.8, 3.0) if rng.random() < 0.5 else rng.uniform(0.35, 0.55)
    poles = linear.poles
    moved = np.abs(poles) ** (1.0 / factor) * np.exp(1j * np.angle(poles) / factor)
    second = LinearModel.from_zeros_poles(linear.zeros, moved, linear.dc_gain)
    return _switched(linear, second, u, switch), f"time constants x{factor:.2f} at {switch - PREROLL}"


def _extra_dynamics(rng, bandwidth: float) -> tuple[LinearModel, str]:
    """A unit-DC-gain factor with modes the nominal order cannot hold: a resonance inside the
    input's band, or a slow creep mode."""
    if rng.random() < 0.6:
        radius, angle = rng.uniform(0.85, 0.96), rng.uniform(0.25, min(2.2, 0.8 * bandwidth))
        weight = rng.uniform(0.3, 0.7)
        den = np.real(np.poly([radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]))
        resonance = LinearModel([np.sum(den)], den)
        b = (1 - weight) * den + weight * np.concatenate([resonance.b, [0.0, 0.0]])
        return LinearModel(b, den), f"resonance r={radius:.2f} angle={angle:.2f} weight {weight:.2f}"
    pole, weight = rng.uniform(0.9, 0.97), rng.uniform(0.35, 0.6)
    b = (1 - weight) * np.array([1.0, -pole]) + weight * np.array([1.0 - pole, 0.0])
    return LinearModel(b, [1.0, -pole]), f"slow mode pole {pole:.3f} weight {weight:.2f}"


# --------------------------------------------------------------------------- entry points


def generate_case(cause: str, seed: int, n: int = 4000) -> GeneratedCase:
    """One record of ``n`` samples with the hidden ``cause`` (one of ``CAUSES``)."""
    if cause not in CAUSES:
        raise ValueError(f"unknown cause {cause!r}")
    rng = np.random.default_rng([seed, CAUSES.index(cause)])
    order = int(rng.integers(2, 4))
    linear = random_linear_block(rng, order)
    v, input_kind, bandwidth = random_input(rng, n + PREROLL)
    names = STRONG_NONLINEARITIES if cause in ("parallel_path", "input_dynamics") else NONLINEARITIES
    shape, shape_label = random_nonlinearity(rng, names)
    centre, scale = float(np.mean(v)), float(np.std(v))

    def fmap(x):
        return scale * shape((np.asarray(x) - centre) / scale)

    if cause == "input_dynamics":
        clean, reference, nominal, effect = _input_dynamics(rng, linear, fmap, v, bandwidth, order)
    else:
        clean, nominal, effect = _effect(cause, rng, linear, fmap, v, bandwidth, order)
        reference = linear.simulate(fmap(v))
    effect_size = float(np.sqrt(np.mean((clean - reference)[PREROLL:] ** 2)))
    clean = clean[PREROLL:] + rng.uniform(-1.0, 1.0) * np.std(clean)
    level = rng.uniform(0.01, 0.05)
    noise_std = level * float(np.std(clean))
    if cause != "none":  # the effect stays visible: its size is at least 2.5 noise standard deviations
        noise_std = min(noise_std, 0.4 * effect_size)
        level = noise_std / float(np.std(clean))
    noise, noise_kind = _noise(rng, n, noise_std)
    poles = ", ".join(f"{p.real:.2f}{p.imag:+.2f}j" if abs(p.imag) > 1e-9 else f"{p.real:.2f}" for p in linear.poles)
    description = (f"{cause}: {effect}; G poles [{poles}], F {shape_label}, input {input_kind}, "
                   f"noise {100 * level:.1f} % {noise_kind}")
    return GeneratedCase(cause, v[PREROLL:], clean + noise, nominal, seed, description)


def generate_cases(seeds, causes=CAUSES, n: int = 4000) -> list[GeneratedCase]:
    return [generate_case(cause, seed, n) for seed in seeds for cause in causes]
