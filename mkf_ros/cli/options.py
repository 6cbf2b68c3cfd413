"""CLI flags generated from the single parameter definition (:mod:`mkf_ros.core.params`).

The one generator of ``--name`` flags from :class:`~mkf_ros.core.params.Param` definitions and
the one reader of the values the user set: ``mkf demo`` (the filter parameters) and
``mkf process`` (the filter's and the node's offline ones) both use it."""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from typing import Any

from mkf_ros.core.params import Param, filter_params


def flag(p: Param) -> str:
    return "--" + p.name.replace("_", "-")


def help_text(p: Param) -> str:
    """The flag's help: the definition's one-line doc and default. argparse %-formats help
    strings, so a literal ``%`` (``mag_disturbance``: "10-25 %") is escaped here."""
    return f"{p.doc()} (default: {p.default})".replace("%", "%%")


def add_param_flags(parser: argparse.ArgumentParser, params: Iterable[Param],
                    title: str) -> None:
    """One ``--name`` flag per parameter, in an argument group; unset flags stay None (the
    parameter's default applies)."""
    g = parser.add_argument_group(title)
    for p in params:
        kw: dict[str, Any] = dict(default=None, dest=p.name, help=help_text(p))
        if p.type is bool:
            g.add_argument(flag(p), action=argparse.BooleanOptionalAction, **kw)
        elif p.type is list:
            g.add_argument(flag(p), type=float, nargs=p.length or "+", metavar="X", **kw)
        elif p.choices:
            g.add_argument(flag(p), choices=p.choices, **kw)
        else:
            g.add_argument(flag(p), type=p.type, metavar=p.unit.upper() or "X", **kw)


def param_overrides(args: argparse.Namespace, params: Iterable[Param]) -> dict[str, Any]:
    """The parameters of ``params`` the user set explicitly (flags of :func:`add_param_flags`)."""
    return {p.name: getattr(args, p.name) for p in params
            if getattr(args, p.name, None) is not None}


def add_filter_options(parser: argparse.ArgumentParser) -> None:
    """One ``--name`` flag per filter parameter; unset flags keep the parameter's default."""
    add_param_flags(parser, filter_params(), "filter parameters")


def filter_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The filter parameters the user set explicitly on the command line."""
    return param_overrides(args, filter_params())
