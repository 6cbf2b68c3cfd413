"""The README promises things the code must keep true."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _section(title: str) -> str:
    m = re.search(rf"^## {re.escape(title)}.*?$(.*?)(?=^## |\Z)", README.read_text(), re.S | re.M)
    assert m, f"README has no section '## {title}'"
    return m.group(1)


def test_quick_start_has_the_two_commands() -> None:
    block = re.search(r"```bash\n(.*?)```", _section("Quick start"), re.S)
    assert block
    cmds = [ln.split("#")[0].strip() for ln in block.group(1).splitlines() if ln.strip()]
    assert cmds == ["./run demo", "./run test"]
    run = (ROOT / "run").read_text()
    for verb in ("demo", "test"):  # what ./run dispatches on
        assert re.search(rf"^\s*{verb}\)", run, re.M), f"./run has no '{verb}' command"


def test_the_results_table_comes_with_the_command_that_makes_it() -> None:
    """One results table, right after the one command that prints it: a bench script that
    exists, given a folder for every dataset the table has columns for; the peers' versions
    in the table are the ones the benchmark installs (requirements/bench.txt)."""
    sec = _section("Results")
    cmds = re.findall(r"```bash\n(.*?)```", sec, re.S)
    assert len(cmds) == 1, "the Results section has one command"
    cmd = cmds[0].split("#")[0].split()
    assert cmd[:3] == ["./run", "bench", "real_data"]
    assert (ROOT / "bench" / "real_data.py").is_file()
    tables = re.findall(r"^\|.*\|$(?:\n^\|.*\|$)+", sec, re.M)
    assert len(tables) == 1, "the Results section has one table"
    header = tables[0].splitlines()[0]
    for column, folder in (("BROAD", "broad"), ("RepoIMU", "repoimu/TStick"),
                           ("ESE650", "ese650"), ("tyrex", "tyrex")):
        assert column in header
        assert any(arg.endswith("/" + folder) for arg in cmd), f"no {folder} folder in {cmd}"
    pins = dict(re.findall(r"^([\w-]+)==([\w.]+)$", (ROOT / "requirements" / "bench.txt")
                           .read_text(), re.M))
    quoted = re.findall(r"`(vqf|imufusion|ahrs)` ([\d.]+)", tables[0])
    assert {name for name, _v in quoted} == {"vqf", "imufusion", "ahrs"}
    for name, version in quoted:
        assert pins[name] == version, f"README quotes {name} {version}, the bench pins {pins[name]}"


def test_the_readme_is_short() -> None:
    """What it is, the two commands, one results table, links: a few hundred lines at most."""
    assert len(README.read_text().splitlines()) <= 300
