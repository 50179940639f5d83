"""The package builds with colcon as an ament_python package (node in lib/hammer_ros)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from hammer_ros.ros.environment import without_bootstrap

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def test_package_xml_declares_runtime_dependencies():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    deps = {e.text for e in root.iter("exec_depend")}
    assert {"rclpy", "std_msgs", "sensor_msgs", "diagnostic_msgs", "python3-numpy", "python3-scipy"} <= deps
    assert root.find("export/build_type").text == "ament_python"


@pytest.mark.skipif(not (BIN / "colcon").exists(), reason="colcon not installed in this environment")
def test_colcon_build_installs_the_node(tmp_path):
    src = tmp_path / "src" / "hammer_ros"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".venv", ".git", "build", "install", "log",
                                                             "__pycache__", "*.egg-info", "bags"))
    env = without_bootstrap()
    env.update(AMENT_PREFIX_PATH=str(BIN.parent), PATH=f"{BIN}:{env.get('PATH', '')}")
    proc = subprocess.run([str(BIN / "colcon"), "build", "--packages-select", "hammer_ros"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    install = tmp_path / "install" / "hammer_ros"
    assert (install / "lib" / "hammer_ros" / "hammer_ros_node").exists()
    assert (install / "share" / "hammer_ros" / "package.xml").exists()
    assert (install / "share" / "ament_index" / "resource_index" / "packages" / "hammer_ros").exists()
