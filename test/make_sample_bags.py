"""Generate the sample bags in ``bags/`` from simulated Hammerstein plants (deterministic seeds).

    .venv/bin/python test/make_sample_bags.py [OUT_DIR]      # default: bags/

1. ``float64_cubic_g1.mcap`` (written with ``mcap_ros2``): paper 000's G1 after F1(v) = v + 4 v^3,
   Gaussian white command std 1/(2 pi) at 100 Hz for 60 s. ``/cmd`` std_msgs/msg/Float64 (one
   sample per message, log time = sample time); ``/response`` std_msgs/msg/Float64MultiArray with
   10 samples per message every 0.1 s (batch convention: log time = time of the LAST sample).
2. ``joint_state_saturation/`` (a rosbag2 directory with MCAP storage, written with ``rosbags``):
   saturation F(v) = clip(v, -0.6, 0.6) then a resonant 2nd-order block, Gaussian command std 0.5
   at 100 Hz for 60 s. ``/cmd`` std_msgs/msg/Float64; ``/joint_states`` sensor_msgs/msg/JointState
   (header stamp = sample time, log time 0.3-2 ms later): velocity[0] = the plant output + 1 %
   noise, position[0] its integral, effort[0] = F(v).
3. ``servo_arm/`` (a rosbag2 directory with MCAP storage, written with ``rosbags``): a position
   servo swinging a weighted arm (``hammer_ros.diagnosis.actuators.ServoArm``: P loop with a torque
   limit, gravity, viscous and Coulomb friction, encoder of 4096 counts a turn) at 100 Hz, the four
   trajectories of ``servo_trajectories`` run twice (48 s). ``/arm_controller/commands``
   std_msgs/msg/Float64MultiArray (a ros2_control forward position controller's goals for
   [shoulder_joint, elbow_joint]; the shoulder holds still); ``/joint_states`` sensor_msgs/msg/JointState
   with both named joints (header stamp = sample time, log time 0.3-2 ms later).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from hammer_ros.diagnosis.actuators import ServoArm, servo_trajectories, simulate_servo
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.simulate import add_noise, simulate_hammerstein
from hammer_ros.io.bags import ResultWriter

START_NS = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z
RATE = 100.0
SAMPLES = 6000
BATCH = 10

# paper 000, sec. 4.1
G1 = LinearModel.from_zeros_poles([1.25, 0.5], [0.95, 0.245 + 0.574j, 0.245 - 0.574j], dc_gain=1.0)
RESONANT = LinearModel.from_zeros_poles([-0.5], [0.9 + 0.3j, 0.9 - 0.3j], dc_gain=1.0)
SATURATION = 0.6


def cubic(v: np.ndarray) -> np.ndarray:
    return v + 4.0 * v * v * v  # products, not v**3: numpy's pow differs by an ulp between CPUs


def saturation(v: np.ndarray) -> np.ndarray:
    return np.clip(v, -SATURATION, SATURATION)


def stamps_ns() -> np.ndarray:
    return START_NS + np.arange(SAMPLES, dtype=np.int64) * int(1e9 / RATE)


def cubic_record(seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    v = np.random.default_rng(seed).standard_normal(SAMPLES) / (2 * np.pi)
    return v, add_noise(simulate_hammerstein(v, cubic, G1), 0.01, seed=seed + 1)


def saturation_record(seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    v = 0.5 * np.random.default_rng(seed).standard_normal(SAMPLES)
    return v, add_noise(simulate_hammerstein(v, saturation, RESONANT), 0.01, seed=seed + 1)


def write_float64_bag(path: Path) -> None:
    v, y = cubic_record()
    t = stamps_ns()
    with ResultWriter(path) as out:
        for k in range(SAMPLES):
            out.write("/cmd", "std_msgs/msg/Float64", {"data": float(v[k])}, t[k])
            if (k + 1) % BATCH == 0:
                layout = {"dim": [{"label": "samples", "size": BATCH, "stride": BATCH}], "data_offset": 0}
                out.write("/response", "std_msgs/msg/Float64MultiArray",
                          {"layout": layout, "data": y[k + 1 - BATCH : k + 1].tolist()}, t[k])


def write_joint_state_bag(path: Path, storage: str = "mcap", compression: str = "") -> None:
    """``storage``: "mcap" or "sqlite3"; ``compression``: "", "file" or "message" (zstd)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    Float64, JointState = store.types["std_msgs/msg/Float64"], store.types["sensor_msgs/msg/JointState"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    v, y = saturation_record()
    position = np.cumsum(y) / RATE
    t = stamps_ns()
    latency = np.random.default_rng(5).integers(300_000, 2_000_000, SAMPLES)
    writer = Writer(path, version=9, storage_plugin=StoragePlugin[storage.upper()])
    if compression:
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with writer:
        cmd = writer.add_connection("/cmd", Float64.__msgtype__, typestore=store)
        joints = writer.add_connection("/joint_states", JointState.__msgtype__, typestore=store)
        for k in range(SAMPLES):
            writer.write(cmd, int(t[k]), store.serialize_cdr(Float64(data=float(v[k])), Float64.__msgtype__))
            stamp = Time(sec=int(t[k] // 1_000_000_000), nanosec=int(t[k] % 1_000_000_000))
            msg = JointState(header=Header(stamp=stamp, frame_id="base_link"), name=["joint1"],
                             position=np.array([position[k]]), velocity=np.array([y[k]]),
                             effort=np.array([saturation(v[k])]))
            writer.write(joints, int(t[k] + latency[k]), store.serialize_cdr(msg, JointState.__msgtype__))


def servo_arm_record(repeats: int = 2, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(goal, measured position) of the servo arm: the four trajectories run ``repeats`` times."""
    arm = ServoArm()
    goals = [u for _ in range(repeats) for u in servo_trajectories(RATE, 6.0, 1.0, seed)]
    positions = [simulate_servo(arm, u, seed=seed + i, torque_noise=0.01) for i, u in enumerate(goals)]
    return np.concatenate(goals), np.concatenate(positions)


def write_servo_bag(path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    Commands, JointState = store.types["std_msgs/msg/Float64MultiArray"], store.types["sensor_msgs/msg/JointState"]
    Layout, Dimension = store.types["std_msgs/msg/MultiArrayLayout"], store.types["std_msgs/msg/MultiArrayDimension"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    goal, position = servo_arm_record()
    shoulder = 0.25
    t = START_NS + np.arange(goal.size, dtype=np.int64) * int(1e9 / RATE)
    latency = np.random.default_rng(7).integers(300_000, 2_000_000, goal.size)
    layout = Layout(dim=[Dimension(label="joints", size=2, stride=2)], data_offset=0)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        cmd = writer.add_connection("/arm_controller/commands", Commands.__msgtype__, typestore=store)
        joints = writer.add_connection("/joint_states", JointState.__msgtype__, typestore=store)
        for k in range(goal.size):
            command = Commands(layout=layout, data=np.array([shoulder, goal[k]]))
            writer.write(cmd, int(t[k]), store.serialize_cdr(command, Commands.__msgtype__))
            stamp = Time(sec=int(t[k] // 1_000_000_000), nanosec=int(t[k] % 1_000_000_000))
            velocity = (position[k] - position[k - 1]) * RATE if k else 0.0
            msg = JointState(header=Header(stamp=stamp, frame_id=""), name=["shoulder_joint", "elbow_joint"],
                             position=np.array([shoulder, position[k]]), velocity=np.array([0.0, velocity]),
                             effort=np.array([0.0, 0.0]))
            writer.write(joints, int(t[k] + latency[k]), store.serialize_cdr(msg, JointState.__msgtype__))


def _replace_directory(target: Path, write) -> None:
    if target.exists():
        for f in target.iterdir():
            f.unlink()
        target.rmdir()
    write(target)


def main(out_dir: str = "bags") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_float64_bag(out / "float64_cubic_g1.mcap")
    _replace_directory(out / "joint_state_saturation", write_joint_state_bag)
    _replace_directory(out / "servo_arm", write_servo_bag)


if __name__ == "__main__":
    main(*sys.argv[1:])
