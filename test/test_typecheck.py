"""The type checker over mkf_ros/ (configuration: setup.cfg [mypy]) is clean.

mypy is a hard dependency of the test environment (requirements/dev.txt): if it is missing, the
subprocess fails and so does this test.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_mypy_is_clean_over_the_package(tmp_path_factory: pytest.TempPathFactory) -> None:
    cache = tmp_path_factory.mktemp("mypy-cache")
    proc = subprocess.run(
        [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "setup.cfg"),
         "--cache-dir", str(cache), "mkf_ros"],
        cwd=ROOT, capture_output=True, text=True, timeout=240)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"mypy mkf_ros failed (exit {proc.returncode}):\n{out}"
    # the run really checked the package (not, e.g., an empty file list)
    assert "Success: no issues found in" in out, out
