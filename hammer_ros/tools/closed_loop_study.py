"""The closed-loop measurement of docs/notes/methods-measurements.md: pole RSS of cls-markov and plls-hammerstein
with and without the reference as instrument (and refined), and the ``closed_loop`` verdict,
on random closed-loop records and on the same plants in open loop
(``identification.closed_loop.random_loop_pair``).

    python -m hammer_ros.tools.closed_loop_study [--runs 100] [--samples 4000] [--pi] [--refine]
        [--snr LOW HIGH] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..diagnosis.closed_loop import closed_loop_evidence
from ..identification.closed_loop import LoopRecord, random_loop_pair
from ..identification.instrumental import refinement_input
from ..identification.linear import root_rss_error
from ..identification.methods import IdentifyOptions, identify

METHODS = ("cls-markov", "plls-hammerstein")
VALIDATION = 0.3  # the closed_loop row on the last 30 % (diagnose's default validation part)


def pole_errors(record: LoopRecord, reference: np.ndarray | None, refine: bool) -> dict[str, float]:
    """method (+ ' refined') -> pole RSS against the true plant."""
    from ..identification.refinement import refine_result

    out = {}
    for method in METHODS:
        result = identify(method, record.u, record.y, IdentifyOptions(order=3, delay=1, reference=reference))
        out[method] = root_rss_error(record.linear.poles, result.poles)
        if refine:
            refined = refine_result(result, refinement_input(record.u, reference), record.y)
            out[f"{method} refined"] = root_rss_error(record.linear.poles, refined.poles)
    return out


def feedback_detected(record: LoopRecord) -> bool:
    """The ``closed_loop`` row fails on the validation part (cls-markov's residual)."""
    model = identify("cls-markov", record.u, record.y, IdentifyOptions(order=3, delay=1))
    cut = int((1.0 - VALIDATION) * record.u.size)
    return not closed_loop_evidence(record.u[cut:], (record.y - model.simulate(record.u))[cut:]).passed


def study(runs: int, samples: int, integral: bool, refine: bool, snr: tuple[float, float]) -> dict:
    errors: dict[str, dict[str, list[float]]] = {"closed": {}, "closed, reference": {}, "open": {}}
    detected = {"closed": 0, "open": 0}
    for seed in range(runs):
        closed, opened = random_loop_pair(seed, samples, snr, integral)
        for case, record, reference in (("closed", closed, None), ("closed, reference", closed, closed.r),
                                        ("open", opened, None)):
            for key, value in pole_errors(record, reference, refine).items():
                errors[case].setdefault(key, []).append(value)
        detected["closed"] += feedback_detected(closed)
        detected["open"] += feedback_detected(opened)
    return {"runs": runs, "samples": samples, "controller": "PI" if integral else "P", "snr_db": list(snr),
            "pole_rss_median": {case: {k: float(np.median(v)) for k, v in by.items()} for case, by in errors.items()},
            "closed_loop_failed_share": {k: v / runs for k, v in detected.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="closed_loop_study", description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--pi", action="store_true", help="a PI controller (default P)")
    parser.add_argument("--refine", action="store_true", help="also the refined estimates")
    parser.add_argument("--snr", type=float, nargs=2, default=(4.0, 8.0), metavar=("LOW", "HIGH"))
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    doc = study(args.runs, args.samples, args.pi, args.refine, tuple(args.snr))
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(f"{doc['runs']} runs, {doc['samples']} samples, {doc['controller']} controller, SNR {doc['snr_db']} dB")
    for case, by in doc["pole_rss_median"].items():
        print(f"  {case:18s} " + ", ".join(f"{k} {v:.3f}" for k, v in by.items()))
    print("  closed_loop failed on " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in
                                               doc["closed_loop_failed_share"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
