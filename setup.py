"""hammer_ros: ament_python package, also pip-installable.

`pip install .` installs the numerical core, the CLI and the MCAP tools.
`pip install .[ros]` adds the pinned ROS 2 Jazzy wheels from PyPI (for machines without an
apt ROS install; a sourced ROS 2 Jazzy workspace provides rclpy and the messages instead).
Exact versions used by CI and `make setup` are pinned in requirements/*.txt.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "hammer_ros"

ROS_JAZZY_WHEELS = [
    "ros-jazzy-rclpy[fastrtps]==7.1.6",
    "ros-jazzy-std-msgs==5.3.6",
    "ros-jazzy-sensor-msgs==5.3.6",
    "ros-jazzy-geometry-msgs==5.3.6",
    "ros-jazzy-diagnostic-msgs==5.3.6",
    "ros-jazzy-visualization-msgs==5.3.6",
    "ros-jazzy-builtin-interfaces==2.0.3",
    "ros-jazzy-rcl-interfaces==2.0.3",
    "ros-jazzy-lifecycle-msgs==2.0.3",
    "ros-jazzy-std-srvs==5.3.6",
    "foxglove-sdk==0.30.3",  # in-process Foxglove WebSocket server of the node (foxglove_port)
]

# hammer-ros fleet: one Dask task per bag; fleet.parquet through pyarrow
FLEET = ["dask[distributed]==2026.8.0", "pyarrow==26.0.1"]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["data/*", "data/**/*", "dashboard/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/msg_config", glob("msg_config/*.yaml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "pyyaml>=6.0",
        "matplotlib>=3.7",
        "mcap>=1.1",
        "mcap-ros2-support>=0.5",
        "zstandard>=0.19",  # zstd-compressed rosbag2 files and messages
        "numba>=0.60",  # compiled sample-by-sample simulators (a pure-numpy fallback exists)
    ],
    extras_require={
        "ros": ROS_JAZZY_WHEELS,
        "fleet": FLEET,
        "test": [
            "pytest>=7",
            "pytest-xdist>=3.5",  # the suite on both cores (make test)
            "rosbags>=0.10",
            "ruff>=0.4",
            "colcon-common-extensions>=0.3",
            "websockets>=12",  # a Foxglove protocol client in the tests
        ],
    },
    zip_safe=True,
    maintainer="hammer_ros developers",
    maintainer_email="dev@hammer-ros.invalid",
    description="Online Hammerstein system identification for ROS 2 (live topics and MCAP bags).",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "hammer-ros = hammer_ros.cli:main",
            "hammer_ros_node = hammer_ros.ros.node:main",
        ],
    },
)
