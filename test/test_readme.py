"""The README promises things the code must keep true."""

from __future__ import annotations

import re
from pathlib import Path

from mkf_ros.cli.params_cmd import to_markdown
from mkf_ros.core.params import BY_NAME

README = Path(__file__).resolve().parents[1] / "README.md"


def test_parameter_table_is_current() -> None:
    text = README.read_text()
    m = re.search(r"<!-- PARAMS-TABLE[^>]*-->\n(.*?)<!-- /PARAMS-TABLE -->", text, re.S)
    assert m, "README has no generated parameter table"
    assert m.group(1) == to_markdown(list(BY_NAME.values())), (
        "README parameter table is stale: regenerate with `mkf params --format markdown`")


def test_quick_start_has_the_two_commands() -> None:
    text = README.read_text()
    block = re.search(r"## Quick start.*?```bash\n(.*?)```", text, re.S)
    assert block
    cmds = [ln.split("#")[0].strip() for ln in block.group(1).splitlines() if ln.strip()]
    assert cmds == ["./run demo", "./run test"]


def test_layout_tree_matches_the_package() -> None:
    """The Development section's tree names every package and top-level module of mkf_ros (and
    every module of core/ and stream/, where the design lives), and nothing that is not there."""
    text = README.read_text()
    block = re.search(r"## Development\n+```\n(.*?)```", text, re.S)
    assert block, "README has no layout tree under ## Development"
    tree = block.group(1)
    pkg = README.parent / "mkf_ros"
    named = set(re.findall(r"mkf_ros/([\w.]+)", tree))
    for name in named - {"_kernels"}:  # _kernels: made by the install / ./run setup
        assert (pkg / name).exists(), f"README layout names mkf_ros/{name}, which does not exist"
    top = {p.name for p in pkg.iterdir()
           if (p.suffix == ".py" and p.name != "__init__.py")
           or (p.is_dir() and (p / "__init__.py").exists())}
    assert top <= named, f"README layout misses {sorted(top - named)}"
    words = set(re.findall(r"[\w]+\.py", tree))
    for sub in ("core", "stream"):
        mods = {p.name for p in (pkg / sub).glob("*.py") if p.name != "__init__.py"}
        assert mods <= words, f"README layout misses mkf_ros/{sub}/{sorted(mods - words)}"
