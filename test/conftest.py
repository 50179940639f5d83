"""Shared fixtures: the paper systems, and environments for real ROS 2 processes."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from hammer_ros.identification.linear import LinearModel
from hammer_ros.ros.environment import DomainLease, without_bootstrap

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent

# paper 000, sec. 4.1
G1 = LinearModel.from_zeros_poles([1.25, 0.5], [0.95, 0.245 + 0.574j, 0.245 - 0.574j], dc_gain=1.0)

@pytest.fixture
def g1() -> LinearModel:
    return G1


@pytest.fixture(scope="session")
def compiled_solve() -> None:
    """The compiled CLS solve (``cls_kernel``) loaded once per session: on a fresh checkout numba compiles
    it into its cache here (30-80 s on the loaded 2-core test machine), not inside a live test's timeout;
    the processes a test starts load it from that cache."""
    from hammer_ros.identification.correlation_least_squares import compiled_steps, correlation_functions

    v = np.random.default_rng(0).standard_normal(600)
    y = np.convolve(v, [0.0, 1.0, 0.5])[: v.size]
    compiled_steps(*correlation_functions(v, y, 66), v, y, 3, 1, 30, 3)


@pytest.fixture
def ros_env(tmp_path, compiled_solve):
    """Environment for one test's ROS processes: its own ROS_DOMAIN_ID, loopback only.

    The domain id is leased exclusively (``ros_env.DomainLease``: an flock per id), so parallel
    pytest runs, the demo and the tests of other checkouts on this machine never share a graph."""
    env = without_bootstrap()
    with DomainLease() as lease:
        env.update(
            AMENT_PREFIX_PATH=str(VENV_BIN.parent),
            ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
            ROS_DOMAIN_ID=str(lease.domain_id),
            ROS_LOG_DIR=str(tmp_path / "roslog"),
            PYTHONUNBUFFERED="1",
            FASTRTPS_DEFAULT_PROFILES_FILE=str(REPO / "hammer_ros" / "data" / "fastdds_fast_discovery.xml"),
        )
        yield env


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def tmp_dir() -> Path:
    return Path(tempfile.mkdtemp(prefix="hammer_ros_"))
