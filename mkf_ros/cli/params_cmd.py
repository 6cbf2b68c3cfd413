"""``mkf params``: print every parameter as commented YAML or as a Markdown table."""

from __future__ import annotations

import argparse

from mkf_ros.core.params import BY_NAME, Param

HELP = "print the parameters (commented YAML for --params-file, or a Markdown table)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--format", choices=("yaml", "markdown"), default="yaml")
    parser.add_argument("--node-name", default="estimator",
                        help="top-level key of the YAML (default: estimator)")


def yaml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return "[" + ", ".join(yaml_value(x) for x in v) + "]"
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return f'"{v}"'
    return str(v)


def to_yaml(params: list[Param], node_name: str) -> str:
    lines = [f"{node_name}:", "  ros__parameters:"]
    group = None
    for p in params:
        if p.group != group:
            group = p.group
            lines.append(f"    # --- {group} ---")
        lines.append(f"    # {p.doc()}")
        lines.append(f"    {p.name}: {yaml_value(p.default)}")
    return "\n".join(lines) + "\n"


def to_markdown(params: list[Param]) -> str:
    rows = ["| parameter | type | default | unit | range / choices | description |",
            "|---|---|---|---|---|---|"]
    for p in params:
        rng = ", ".join(p.choices) if p.choices else (
            f"{p.range[0]:g} .. {p.range[1]:g}" if p.range else "")
        rows.append(f"| `{p.name}` | {p.type.__name__} | `{yaml_value(p.default)}` | {p.unit} "
                    f"| {rng} | {p.description} |")
    return "\n".join(rows) + "\n"


def run(args: argparse.Namespace) -> int:
    params = list(BY_NAME.values())
    print(to_yaml(params, args.node_name) if args.format == "yaml" else to_markdown(params),
          end="")
    return 0
