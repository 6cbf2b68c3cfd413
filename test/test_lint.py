"""ruff (configuration: ruff.toml) finds nothing in mkf_ros/, test/ and bench/, so that CI fails on
a lint finding as it does on a failing test.

ruff is a hard dependency of the test environment (requirements/dev.txt): if it is missing, the
subprocess fails and so does this test.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ("mkf_ros", "test", "bench")


def test_ruff_is_clean() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise",
         *CHECKED],
        cwd=ROOT, capture_output=True, text=True, timeout=240)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"ruff check {' '.join(CHECKED)} failed:\n{out}"
    assert "All checks passed" in out, out


def test_ruff_reports_a_finding(tmp_path: Path) -> None:
    """The check above can fail: the same command, on a file with an unused import, exits
    non-zero and names it (so that a passing run means a clean tree, not a broken linter)."""
    bad = tmp_path / "bad.py"
    bad.write_text("import os\n")
    proc = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--config",
         str(ROOT / "ruff.toml"), "--output-format", "concise", str(bad)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "F401" in proc.stdout, proc.stdout + proc.stderr
