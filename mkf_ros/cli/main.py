"""``mkf``: the command-line front end. Each subcommand lives in its own module and is imported
only when used, so ``mkf --help`` stays fast.

A subcommand module provides ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. User errors are raised as :class:`CliError` and printed as one line,
exit code 2; no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NoReturn

#: subcommand name → module (add new subcommands here)
COMMANDS: dict[str, str] = {
    "calibrate-mag": "mkf_ros.cli.calibrate_mag",
    "demo": "mkf_ros.cli.demo",
    "params": "mkf_ros.cli.params_cmd",
    "process": "mkf_ros.cli.process",
    "study": "mkf_ros.cli.study",
    "synth": "mkf_ros.cli.synth",
}


class CliError(Exception):
    """A user error: reported as one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """argparse's own errors (an unknown flag, an invalid choice) as one line too, not after
    the usage of every flag."""

    def error(self, message: str) -> NoReturn:
        raise CliError(f"{message} (see {self.prog} --help)")


def _overview() -> str:
    lines = ["usage: mkf COMMAND [options]   (mkf COMMAND --help for details)", "", "commands:"]
    for name, mod in COMMANDS.items():
        lines.append(f"  {name:<14} {_help_of(mod)}")
    return "\n".join(lines)


def _help_of(module: str) -> str:
    try:
        return importlib.import_module(module).HELP
    except Exception as e:  # pragma: no cover - a broken module must not break the overview
        return f"(unavailable: {e})"


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_overview())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"mkf: error: unknown command {name!r}; choose from {', '.join(COMMANDS)}",
              file=sys.stderr)
        return 2
    mod = importlib.import_module(COMMANDS[name])
    parser = _Parser(prog=f"mkf {name}", description=mod.HELP)
    mod.add_arguments(parser)
    try:
        return int(mod.run(parser.parse_args(rest)) or 0)
    except CliError as e:
        print(f"mkf {name}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mkf {name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
