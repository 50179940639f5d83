"""The process environment ROS 2 needs, set before ``rclpy`` is imported.

With the Jazzy wheels from PyPI nothing is sourced, so a bare ``.venv/bin/hammer-ros node``
would look up message packages in an empty ament index, log into ``~/.ros/log`` and announce
itself on every network interface. :func:`prepare_ros_environment` fills in the missing
variables (never overriding what the user set):

- ``AMENT_PREFIX_PATH``: the interpreter prefix, where the wheels install ``share/`` (appended
  when the variable is set but does not list it);
- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: DDS stays on loopback unless the user asks for
  ``SUBNET`` (a multi-machine robot sets it explicitly);
- ``ROS_LOG_DIR``: a per-user directory under the system temp dir.

:class:`DomainLease` hands out a ROS_DOMAIN_ID that no other cooperating process on this
machine holds (an ``flock`` per id, released when the holder exits, even on a crash); the demo
and the tests use it to run private ROS graphs side by side.
"""

from __future__ import annotations

import fcntl
import os
import sys
import tempfile
from collections.abc import Mapping, MutableMapping
from pathlib import Path

# ROS_DOMAIN_IDs 1..101 map to UDP ports valid on Linux (0 is everybody's default: never leased)
DOMAIN_IDS = range(1, 102)
FAST_DISCOVERY_PROFILE = Path(__file__).resolve().parents[1] / "data" / "fastdds_fast_discovery.xml"
# set by the ROS wheels when they re-exec the interpreter: a child of this one must bootstrap itself again
BOOTSTRAP_VARIABLES = ("LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")


def _wheel_prefix() -> str | None:
    """sys.prefix when the ROS wheels installed their ament index there, else None (apt ROS)."""
    return sys.prefix if (Path(sys.prefix) / "share" / "ament_index").is_dir() else None


def prepare_ros_environment(environ: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """Fill in AMENT_PREFIX_PATH, ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_LOG_DIR where unset
    (``environ`` defaults to ``os.environ``; call before importing rclpy). Returns ``environ``."""
    env = os.environ if environ is None else environ
    prefix = _wheel_prefix()
    if prefix is not None:
        entries = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
        if prefix not in entries:
            env["AMENT_PREFIX_PATH"] = os.pathsep.join([*entries, prefix])
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if "ROS_LOG_DIR" not in env:
        log_dir = Path(tempfile.gettempdir()) / f"hammer_ros-{os.getuid()}" / "ros_log"
        log_dir.mkdir(parents=True, exist_ok=True)
        env["ROS_LOG_DIR"] = str(log_dir)
    return env


def without_bootstrap(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``environ`` (default ``os.environ``) without the ROS wheels' BOOTSTRAP_VARIABLES: the
    environment of any child process of this interpreter."""
    return {k: v for k, v in (os.environ if environ is None else environ).items() if k not in BOOTSTRAP_VARIABLES}


def child_environment(domain_id: int, log_dir: str | Path | None = None, fast_discovery: bool = True) -> dict[str, str]:
    """Environment for a ROS child process of this interpreter on a private graph: the given
    ROS_DOMAIN_ID, loopback discovery, unbuffered output, and (optionally) the fast-discovery
    FastDDS profile so restarted nodes are rediscovered in well under a second."""
    env = without_bootstrap()
    if log_dir is not None:
        env["ROS_LOG_DIR"] = str(log_dir)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    prepare_ros_environment(env)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONUNBUFFERED"] = "1"
    if fast_discovery:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FAST_DISCOVERY_PROFILE)
    return env


class DomainLease:
    """An exclusive ROS_DOMAIN_ID for this process: ``with DomainLease() as lease: lease.domain_id``.

    Ids are tried from a pid-dependent start so parallel runs rarely contend; the lock file
    ``<tmp>/hammer_ros-domains/<id>.lock`` is held with ``flock`` until :meth:`release` (or
    process exit). Raises RuntimeError when every id in DOMAIN_IDS is taken.
    """

    def __init__(self, lock_dir: str | Path | None = None) -> None:
        self._lock_dir = Path(lock_dir or Path(tempfile.gettempdir()) / "hammer_ros-domains")
        self._lock_dir.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = None
        self.domain_id = self._acquire()

    def _acquire(self) -> int:
        ids = list(DOMAIN_IDS)
        start = (os.getpid() * 7) % len(ids)
        for domain_id in ids[start:] + ids[:start]:
            fd = os.open(self._lock_dir / f"{domain_id}.lock", os.O_CREAT | os.O_RDWR, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            self._fd = fd
            return domain_id
        raise RuntimeError(f"no free ROS_DOMAIN_ID in {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1} "
                           f"(all locked in {self._lock_dir})")

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *exc) -> None:
        self.release()
