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
