"""Start and stop ROS child processes of this interpreter (``python -m MODULE --ros-args ...``):
the demo, the bench and the tests start the node and the simulated plant with these. No rclpy here:
the child imports it; the environment comes from ``ros.environment.child_environment``."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

STOP_TIMEOUT = 10.0  # s a child gets to exit after each signal


def ros_arguments(parameters: dict, params_file: str | Path | None = None) -> list[str]:
    """``--ros-args [--params-file FILE] -p name:=value ...`` (floats keep their decimal point, so ROS
    types them double; the ``-p`` values override the file's)."""
    args = ["--ros-args"] + (["--params-file", str(params_file)] if params_file is not None else [])
    for name, value in parameters.items():
        args += ["-p", f"{name}:={value!r}" if isinstance(value, float) else f"{name}:={value}"]
    return args


def start_ros_process(module: str, parameters: dict, env: dict, log: str | Path, *, options: Sequence[str] = (),
                      params_file: str | Path | None = None) -> subprocess.Popen:
    """``python -m module [options] --ros-args ...`` with ``env``, its stdout and stderr into ``log``."""
    with open(log, "w") as out:
        return subprocess.Popen([sys.executable, "-m", module, *options, *ros_arguments(parameters, params_file)],
                                env=env, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def stop_process(process: subprocess.Popen, signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM),
                 timeout: float = STOP_TIMEOUT) -> int:
    """Each of ``signals`` in turn while the process runs, ``timeout`` s for each, then (last resort)
    SIGKILL; returns the exit code (-9 when killed)."""
    for sig in signals:
        if process.poll() is not None:
            break
        process.send_signal(sig)
        try:
            return process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            continue
    if process.poll() is None:
        process.kill()
    return process.wait()
