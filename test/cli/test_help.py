"""Every command's ``--help`` works: ``mkf``, each ``mkf`` subcommand, the ``estimator`` and
the ``player`` executables, each run as its own process (as a user types it). A bare ``%`` in
a parameter's description once made argparse die formatting ``mkf process --help``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from mkf_ros.bags.process import stream_param_names
from mkf_ros.cli.main import COMMANDS
from mkf_ros.core.params import PARAMS, filter_params

BIN = Path(sys.executable).parent


def _help(exe: str, *args: str) -> str:
    path = BIN / exe
    assert path.is_file(), f"console script {path} not installed"
    r = subprocess.run([str(path), *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"{exe} {' '.join(args)}: exit {r.returncode}\n{r.stderr}"
    assert "Traceback" not in r.stderr, r.stderr
    return r.stdout


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def test_mkf_help_lists_every_command() -> None:
    out = _help("mkf", "--help")
    assert all(c in out for c in COMMANDS)


#: subcommand → the parameters whose flags its help must show
FLAGS = {"process": stream_param_names, "demo": lambda: [p.name for p in filter_params()]}


@pytest.mark.parametrize(("command", "opt"),
                         [(c, "--help") for c in sorted(COMMANDS)] + [("process", "-h")])
def test_every_subcommand_help(command: str, opt: str) -> None:
    out = _help("mkf", command, opt)
    assert out.startswith("usage: mkf " + command)
    names = FLAGS.get(command, list)()
    missing = [n for n in names if _flag(n) not in out]
    assert not missing, f"mkf {command} --help lacks {missing}"
    if command == "process":  # the '%' texts themselves come through
        assert "differs by 10-25 % from place to place" in " ".join(out.split())


def test_estimator_help_names_every_parameter() -> None:
    out = _help("estimator", "--help")
    missing = [p.name for p in PARAMS if p.name not in out]
    assert not missing, f"estimator --help lacks {missing}"


def test_estimator_lifecycle_help() -> None:
    out = _help("estimator_lifecycle", "--help")
    assert "usage: estimator_lifecycle" in out and "change_state" in out
    missing = [p.name for p in PARAMS if p.name not in out]
    assert not missing, f"estimator_lifecycle --help lacks {missing}"


def test_player_help_names_every_parameter() -> None:
    from mkf_ros.ros.player_node import PARAMS as PLAYER_PARAMS

    out = _help("player", "--help")
    missing = [n for n in PLAYER_PARAMS if n not in out]
    assert not missing, f"player --help lacks {missing}"
