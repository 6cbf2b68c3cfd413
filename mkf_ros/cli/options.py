"""CLI flags generated from the single parameter definition (:mod:`mkf_ros.core.params`)."""

from __future__ import annotations

import argparse
from typing import Any

from mkf_ros.core.params import Param, filter_params


def flag(p: Param) -> str:
    return "--" + p.name.replace("_", "-")


def add_filter_options(parser: argparse.ArgumentParser) -> None:
    """One ``--name`` flag per filter parameter; unset flags keep the parameter's default."""
    g = parser.add_argument_group("filter parameters")
    for p in filter_params():
        kw: dict[str, Any] = dict(default=None, dest=p.name,
                                  help=f"{p.doc()} (default: {p.default})".replace("%", "%%"))
        if p.type is bool:
            g.add_argument(flag(p), action=argparse.BooleanOptionalAction, **kw)
        elif p.type is list:
            g.add_argument(flag(p), type=float, nargs=p.length or "+", metavar="X", **kw)
        elif p.choices:
            g.add_argument(flag(p), choices=p.choices, **kw)
        else:
            g.add_argument(flag(p), type=p.type, metavar=p.unit.upper() or "X", **kw)


def filter_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The filter parameters the user set explicitly on the command line."""
    return {p.name: getattr(args, p.name) for p in filter_params()
            if getattr(args, p.name, None) is not None}
