"""Foxglove's own TypeScript libraries as independent checkers (``test/js``, pinned by its
lockfile, installed by ``.ci/run`` with ``npm ci``); a test that needs them is skipped, saying why,
where Node.js or the packages are missing."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

CHECKERS = Path(__file__).resolve().parent / "js"


def run_checker(script: str, *args: str, timeout: float = 120) -> tuple[int, dict]:
    """(exit code, the JSON it printed) of ``node test/js/SCRIPT ARGS``."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node.js is not installed: Foxglove's TypeScript libraries cannot run")
    if not (CHECKERS / "node_modules" / "@mcap" / "core").is_dir():
        pytest.skip("test/js is not installed (npm ci --prefix test/js, as .ci/run does)")
    done = subprocess.run([node, str(CHECKERS / script), *args], capture_output=True, text=True, timeout=timeout)
    try:
        return done.returncode, json.loads(done.stdout)
    except json.JSONDecodeError:
        raise AssertionError(f"{script} printed no report: {done.stderr[-2000:]}") from None
