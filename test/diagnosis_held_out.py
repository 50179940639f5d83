"""Diagnosis on cases drawn unlike the generators' own: other linear blocks (poles -0.5..0.96,
angles up to 2.2 rad, gains 0.2-5, non-minimum-phase zeros, one extra sample of delay in a
third of them) and other input maps, with the generators' effects and noise.

    python test/diagnosis_held_out.py FIRST_SEED LAST_SEED [SAMPLES]

prints one line per case (a miss marked ``<--``) and the count named right. Not a test: the
numbers are quoted in the README."""

from __future__ import annotations

import sys
import time

import numpy as np

from hammer_ros.diagnosis import generators
from hammer_ros.diagnosis.causes import CAUSES
from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.split import split_record
from hammer_ros.identification.linear import LinearModel

generators_nonlinearity = generators.random_nonlinearity


def linear_block(rng: np.random.Generator, order: int) -> LinearModel:
    poles: list[complex] = []
    if order >= 2 and rng.random() < 0.6:
        radius, angle = rng.uniform(0.5, 0.95), rng.uniform(0.1, 2.2)
        poles += [radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]
    poles += list(rng.uniform(-0.5, 0.96, order - len(poles)))
    zeros = [rng.choice([rng.uniform(-0.9, 0.9), rng.uniform(1.3, 2.5)])] if order >= 2 and rng.random() < 0.5 else []
    model = LinearModel.from_zeros_poles(zeros, poles, rng.uniform(0.2, 5.0) * rng.choice([-1.0, 1.0]))
    if rng.random() < 0.35:  # one more sample of delay
        model = LinearModel(np.concatenate([[0.0], model.b]), model.a)
    return model


def nonlinearity(rng: np.random.Generator, names=generators.NONLINEARITIES):
    kind = str(rng.choice(["cubic", "asymmetric_saturation", "sine", "coulomb", "staircase", "generators"]))
    if kind == "cubic":
        return (lambda z: z**3 + 0.2 * z), "z^3 + 0.2z"
    if kind == "asymmetric_saturation":
        lo, hi, k = rng.uniform(0.3, 0.8), rng.uniform(1.0, 2.0), rng.uniform(0.3, 0.7)
        return (lambda z: np.where(z > 0, np.minimum(z, hi), k * np.maximum(z, -lo))), "asymmetric saturation"
    if kind == "sine":
        return (lambda z: np.sin(1.2 * z)), "sin(1.2z)"
    if kind == "coulomb":
        c = rng.uniform(0.2, 0.5)
        return (lambda z: z - c * np.tanh(z / 0.1)), f"z - {c:.2f} sign z"
    if kind == "staircase":
        return (lambda z: z + np.sin(2 * np.pi * z) / (4 * np.pi)), "staircase"
    return generators_nonlinearity(rng, names)


def main(first: int, last: int, samples: int = 4000) -> None:
    generators.random_linear_block = linear_block
    generators.random_nonlinearity = nonlinearity
    right = total = 0
    for seed in range(first, last):
        for cause in CAUSES:
            try:
                case = generators.generate_case(cause, seed, samples)
            except RuntimeError:  # no stable feedback strength
                continue
            started = time.perf_counter()
            d = diagnose(split_record(case.v, case.y), case.order).diagnosis
            ok = d.cause == cause and (cause == "none" or d.gain >= 1.15)
            right += d.cause == cause
            total += 1
            gain = "-" if d.gain is None else f"{d.gain:.3f}"
            print(f"{seed:5d} {cause:21s} -> {d.cause:21s} gain {gain:>7s} {time.perf_counter() - started:5.1f} s"
                  f"{'' if ok else '  <--'}  {case.description}", flush=True)
    print(f"{right}/{total} named right")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
