"""Diagnosis of simulated servo configurations against the 7-parameter physical yardstick.

    python test/actuators_held_out.py FIRST_SEED LAST_SEED [--concatenated]

draws, per seed, a position servo (arm mass 0.05-0.5 kg, length 0.08-0.3 m, P gain 2-12 N m/rad,
a D term in half of them, torque limit 0.6-2 N m, viscous and Coulomb friction), runs 8 estimation
and 8 validation experiments of 600 samples (6 s at 100 Hz), each from rest at its own random start
and ending anywhere (``actuators.servo_runs_record``), diagnoses them given as runs (no order given)
and fits the yardstick (``fit_physical_servo``, every run simulated from its own measured start) on
the same data. ``--concatenated``: the same records without their run boundaries (one record each;
the yardstick simulated from the record's first sample), for contrast. Prints one line per
configuration and the counts. Not a test: the numbers are quoted in docs/notes/diagnosis-measurements.md."""

from __future__ import annotations

import sys
import time

import numpy as np

from hammer_ros.diagnosis.actuators import ServoArm, fit_physical_servo, physical_servo_runs, servo_runs_record
from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.split import Split


def configuration(seed: int) -> ServoArm:
    rng = np.random.default_rng([seed, 35])
    return ServoArm(mass=rng.uniform(0.05, 0.5), length=rng.uniform(0.08, 0.3), gain=rng.uniform(2.0, 12.0),
                    damping_gain=rng.choice([0.0, rng.uniform(0.02, 0.1)]), torque_limit=rng.uniform(0.6, 2.0),
                    viscous=rng.uniform(0.05, 0.3), coulomb=rng.uniform(0.01, 0.08))


def main(first: int, last: int, concatenated: bool) -> None:
    named = beaten = 0
    for seed in range(first, last + 1):
        arm = configuration(seed)
        record = servo_runs_record(arm, seed=seed)
        runs_est, runs_val = (None, None) if concatenated else (record.runs_est, record.runs_val)
        t0 = time.perf_counter()
        d = diagnose(Split(record.u_est, record.y_est, record.u_val, record.y_val, continuous=False,
                           runs_est=runs_est, runs_val=runs_val)).diagnosis
        seconds = time.perf_counter() - t0
        theta, _ = fit_physical_servo(record.u_est, record.y_est, runs=runs_est)
        reference = float(np.sqrt(np.mean((physical_servo_runs(theta, record.u_val, record.y_val, runs_val)
                                           - record.y_val) ** 2)))
        extended = d.extended.rms if d.extended is not None else d.baseline.rms
        named += d.cause == "output_feedback"
        beaten += extended <= reference
        print(f"seed {seed}: m {arm.mass:.2f} l {arm.length:.2f} K {arm.gain:.1f} Kd {arm.damping_gain:.2f} "
              f"T {arm.torque_limit:.2f}: {d.cause} ({d.confidence:.2f}) extended {extended:.4f} rad, yardstick "
              f"{reference:.4f}, baseline {d.baseline.rms:.4f}, {seconds:.1f} s"
              + ("" if d.cause == "output_feedback" and extended <= reference else "  <--"), flush=True)
    total = last - first + 1
    print(f"{'concatenated' if concatenated else 'runs'}: output_feedback {named}/{total}, "
          f"at most the yardstick's RMSE {beaten}/{total}")


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), "--concatenated" in sys.argv[3:])
