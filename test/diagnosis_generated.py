"""The generated suite of docs/notes/diagnosis-measurements.md: every cause on seeds FIRST..LAST (4000 samples,
70/30 split, the nominal order), diagnosed in two processes.

    python test/diagnosis_generated.py FIRST_SEED LAST_SEED

prints one line per miss, the count named right per cause and the median / largest time per
record. Not a test (the suite's test runs seeds 0-5: test_diagnosis.py); its numbers are quoted in
docs/notes/diagnosis-measurements.md."""

from __future__ import annotations

import multiprocessing
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from hammer_ros.diagnosis.causes import CAUSES
from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.generators import generate_case
from hammer_ros.diagnosis.split import split_record


def _run(cause: str, seed: int) -> tuple[str, int, str, float | None, float, str]:
    case = generate_case(cause, seed)
    t0 = time.perf_counter()
    d = diagnose(split_record(case.v, case.y), case.order).diagnosis
    return cause, seed, d.cause, d.gain, time.perf_counter() - t0, case.description


def main(first: int, last: int) -> None:
    jobs = [(cause, seed) for seed in range(first, last + 1) for cause in CAUSES]
    right, total, seconds = Counter(), Counter(), []
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        for cause, seed, named, gain, spent, description in pool.map(_run, *zip(*jobs)):
            total[cause] += 1
            right[cause] += named == cause
            seconds.append(spent)
            if named != cause:
                print(f"seed {seed}: {description} -> {named} (gain {gain})", flush=True)
    for cause in CAUSES:
        print(f"{cause}: {right[cause]}/{total[cause]}")
    print(f"{sum(right.values())} of {sum(total.values())} named right; median {np.median(seconds):.1f} s, "
          f"at most {np.max(seconds):.1f} s per record")


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]))
