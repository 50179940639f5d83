"""A sample fleet: small MCAP bags of a few simulated robots' joints, one bag per joint and day.

    .venv/bin/python -m hammer_ros.fleet.sample_fleet OUT_DIR [--robots R] [--joints J] [--days D]
        [--drift-day N] [--dead-zone-day N] [--damage K]

Every joint is a Hammerstein plant: F = a saturation at 2 input standard deviations (optionally
after a dead zone), then a 2nd-order linear block (one zero, relative degree 1) whose poles and
gain depend on the joint. Each bag holds ``SAMPLES`` samples at ``RATE`` Hz: ``/cmd`` (Gaussian
white command) and ``/response`` (plant output + 1 % noise), both std_msgs/msg/Float64MultiArray of
``BATCH`` samples (log time = time of the last sample); ``msg_config/sample_fleet.yaml`` maps them.
The faults: robot_01/joint2's static gain drops by ``DRIFT_PER_DAY`` per day from ``--drift-day``
(a wearing gearbox), and robot_02/joint1 (robot_01/joint3 with one robot) grows a dead zone of
``DEAD_ZONE_PER_DAY`` per day from ``--dead-zone-day`` (days count from 1). Layout:
``OUT/robot_RR/jointJ/YYYY-MM-DD.mcap`` plus ``OUT/manifest.csv`` (path, robot, joint, date).
``--damage K`` zero-fills the first 4 KiB of K bags (a disk error: those bags cannot be read).
"""

from __future__ import annotations

import argparse
import csv
import datetime
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..identification.linear import LinearModel
from ..identification.simulate import add_noise, simulate_hammerstein
from ..io.bag_writer import ResultWriter

START = datetime.datetime(2026, 11, 1, 6, 0, tzinfo=datetime.timezone.utc)
RATE = 100.0  # Hz
SAMPLES = 3000  # per bag (30 s)
BATCH = 10  # samples per message
INPUT_STD = 0.5
SATURATION = 2 * INPUT_STD
DRIFT_PER_DAY = 0.06  # relative static gain lost per day
DEAD_ZONE_PER_DAY = 0.08  # dead zone half-width grown per day (input units)
NOISE = 0.01  # relative output noise


@dataclass(frozen=True)
class JointSpec:
    """One simulated joint and its faults (days count from 1; None: healthy)."""

    robot: str
    joint: str
    poles: tuple[complex, ...]
    zeros: tuple[complex, ...]
    gain: float
    drift_day: int | None = None
    dead_zone_day: int | None = None

    @property
    def group(self) -> str:
        return f"{self.robot}/{self.joint}"

    def gain_on(self, day: int) -> float:
        """Static gain of the linear block on ``day``."""
        if self.drift_day is None or day < self.drift_day:
            return self.gain
        return self.gain * (1.0 - DRIFT_PER_DAY * (day - self.drift_day + 1))

    def dead_zone_on(self, day: int) -> float:
        """Dead-zone half-width on ``day`` (0: none)."""
        if self.dead_zone_day is None or day < self.dead_zone_day:
            return 0.0
        return DEAD_ZONE_PER_DAY * (day - self.dead_zone_day + 1)

    def linear(self, day: int) -> LinearModel:
        return LinearModel.from_zeros_poles(list(self.zeros), list(self.poles), dc_gain=self.gain_on(day))

    def nonlinearity(self, v: np.ndarray, day: int) -> np.ndarray:
        width = self.dead_zone_on(day)
        dead = np.sign(v) * np.maximum(np.abs(v) - width, 0.0)
        return np.clip(dead, -SATURATION, SATURATION)


@dataclass(frozen=True)
class SampleBag:
    path: Path
    joint: JointSpec
    day: int
    date: str
    damaged: bool


POLES = ((0.9 + 0.1j, 0.9 - 0.1j), (0.8, 0.6), (0.85 + 0.2j, 0.85 - 0.2j), (0.7, 0.5))


def sample_joints(robots: int = 2, joints: int = 2, drift_day: int | None = 4,
                  dead_zone_day: int | None = 5) -> list[JointSpec]:
    """``robots`` x ``joints`` joints; robot_01/joint2 drifts, robot_02/joint1 (or, with one robot,
    robot_01/joint3 when it exists) grows a dead zone (None: that fault nowhere)."""
    specs = []
    for r in range(1, robots + 1):
        for j in range(1, joints + 1):
            robot, joint = f"robot_{r:02d}", f"joint{j}"
            drift = drift_day if (r, j) == (1, 2) else None
            dead = dead_zone_day if (r, j) == ((2, 1) if robots > 1 else (1, 3)) else None
            specs.append(JointSpec(robot, joint, POLES[(j - 1) % len(POLES)], (-0.5,), 1.0 + 0.25 * (j - 1),
                                   drift_day=drift, dead_zone_day=dead))
    return specs


def record(spec: JointSpec, day: int, seed: int, samples: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """(command, measured response) of ``spec`` on ``day``."""
    v = INPUT_STD * np.random.default_rng(seed).standard_normal(samples)
    y = simulate_hammerstein(v, lambda x: spec.nonlinearity(x, day), spec.linear(day))
    return v, add_noise(y, NOISE, seed=seed + 1)


def write_bag(path: Path, v: np.ndarray, y: np.ndarray, start_ns: int) -> None:
    """``/cmd`` and ``/response`` as Float64MultiArray of BATCH samples at RATE Hz."""
    path.parent.mkdir(parents=True, exist_ok=True)
    layout = {"dim": [{"label": "samples", "size": BATCH, "stride": BATCH}], "data_offset": 0}
    with ResultWriter(path) as out:
        for k in range(BATCH - 1, v.size, BATCH):
            stamp = start_ns + round(k * 1e9 / RATE)
            for topic, x in (("/cmd", v), ("/response", y)):
                out.write(topic, "std_msgs/msg/Float64MultiArray",
                          {"layout": layout, "data": x[k + 1 - BATCH : k + 1].tolist()}, stamp)


def damage(path: Path) -> None:
    """Zero-fill the first 4 KiB (the header and schemas are gone: the bag cannot be read)."""
    with open(path, "r+b") as f:
        f.write(bytes(min(4096, path.stat().st_size)))


def write_sample_fleet(out: str | Path, joints: Sequence[JointSpec], days: int, damaged: int = 0,
                       samples: int = SAMPLES, seed: int = 0) -> list[SampleBag]:
    """Write one bag per joint and day (and ``manifest.csv``); ``damaged`` bags (spread over the
    fleet, never a group's first day) are zero-filled at the start. Returns the bags written."""
    out = Path(out)
    bags = []
    for g, spec in enumerate(joints):
        for day in range(1, days + 1):
            start = START + datetime.timedelta(days=day - 1, minutes=7 * g)
            path = out / spec.robot / spec.joint / f"{start.date().isoformat()}.mcap"
            v, y = record(spec, day, seed=seed + 1000 * g + 2 * day, samples=samples)
            write_bag(path, v, y, int(start.timestamp()) * 1_000_000_000)
            bags.append(SampleBag(path, spec, day, start.date().isoformat(), False))
    if damaged:
        later = [i for i, b in enumerate(bags) if b.day > 1]
        for i in np.linspace(0, len(later) - 1, damaged).round().astype(int)[:damaged]:
            b = bags[later[i]]
            damage(b.path)
            bags[later[i]] = SampleBag(b.path, b.joint, b.day, b.date, True)
    with open(out / "manifest.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["path", "robot", "joint", "date"])
        for b in bags:
            writer.writerow([b.path.relative_to(out).as_posix(), b.joint.robot, b.joint.joint, b.date])
    return bags


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hammer_ros.fleet.sample_fleet", description=__doc__.split("\n")[0])
    parser.add_argument("out", metavar="OUT_DIR")
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--joints", type=int, default=2)
    parser.add_argument("--days", type=int, default=8)
    parser.add_argument("--drift-day", type=int, default=4)
    parser.add_argument("--dead-zone-day", type=int, default=5)
    parser.add_argument("--damage", type=int, default=0, help="bags to zero-fill at the start")
    args = parser.parse_args(argv)
    bags = write_sample_fleet(args.out, sample_joints(args.robots, args.joints, args.drift_day, args.dead_zone_day),
                              args.days, args.damage)
    print(f"{len(bags)} bags in {args.out} ({sum(b.damaged for b in bags)} damaged), manifest {args.out}/manifest.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
