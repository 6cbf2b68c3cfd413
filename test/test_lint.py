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


#: The longest function body the package allows (lines, its docstring excluded): beyond it a
#: function does several things that want names (ruff's PLR0913 bounds the parameters, 12).
MAX_LINES = 80


def _long_functions(root: Path) -> list[str]:
    import ast

    long = []
    for path in sorted((root / "mkf_ros").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            body = node.body
            doc = (body[0].end_lineno - body[0].lineno + 1  # type: ignore[operator]
                   if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                   and isinstance(body[0].value.value, str) else 0)
            first = min([d.lineno for d in node.decorator_list] + [node.lineno])
            lines = node.end_lineno - first + 1 - doc  # type: ignore[operator]
            if lines > MAX_LINES:
                long.append(f"{path.relative_to(root)}:{node.lineno} {node.name}: {lines} lines")
    return long


def test_functions_are_short() -> None:
    """Every function of mkf_ros/ is at most MAX_LINES long, its docstring excluded."""
    long = _long_functions(ROOT)
    assert not long, f"functions over {MAX_LINES} lines:\n" + "\n".join(long)


def test_a_long_function_is_found(tmp_path: Path) -> None:
    """The check above can fail: a function of MAX_LINES + 1 lines is reported, one of
    MAX_LINES and a docstring (not counted) is not (the ``def`` line counts)."""
    pkg = tmp_path / "mkf_ros"
    pkg.mkdir()
    body = [f"    x{i} = {i}" for i in range(MAX_LINES)]
    (pkg / "m.py").write_text("def ok():\n    \"\"\"Doc\n    string.\"\"\"\n" + "\n".join(body[1:])
                              + "\n\n\ndef too_long():\n" + "\n".join(body) + "\n")
    assert _long_functions(tmp_path) == [f"mkf_ros/m.py:{MAX_LINES + 5} too_long: "
                                         f"{MAX_LINES + 1} lines"]
