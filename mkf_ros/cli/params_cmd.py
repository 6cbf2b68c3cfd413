"""``mkf params``: print every parameter as commented YAML or as a Markdown table."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from mkf_ros.core.params import BY_NAME, Param

HELP = "print the parameters (commented YAML for --params-file, or a Markdown table)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--format", choices=("yaml", "markdown"), default="yaml")
    parser.add_argument("--node-name", default="estimator",
                        help="top-level key of the YAML (default: estimator)")
    parser.add_argument("--update", action="store_true",
                        help="in a source checkout: rewrite every generated copy "
                             "(config/estimator.yaml and the table in docs/estimator.md)")


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


def update_generated(root: Path) -> list[Path]:
    """Regenerate the YAML and the Markdown table between its markers; returns the files."""
    params = list(BY_NAME.values())
    table = to_markdown(params)
    done = []
    cfg = root / "config" / "estimator.yaml"
    if cfg.parent.is_dir():
        cfg.write_text(to_yaml(params, "/**"))
        done.append(cfg)
    path = root / "docs" / "estimator.md"  # the table between its markers
    if path.is_file():
        new, n = re.subn(r"(<!-- params:begin -->\n)(.*?)(<!-- params:end -->)",
                         lambda m: m.group(1) + table + m.group(3), path.read_text(), flags=re.S)
        if n:
            path.write_text(new)
            done.append(path)
    return done


def run(args: argparse.Namespace) -> int:
    if args.update:
        from mkf_ros.cli.main import CliError

        root = Path(__file__).resolve().parents[2]
        if not (root / "package.xml").is_file():
            raise CliError("--update works in a source checkout (package.xml not found)")
        for path in update_generated(root):
            print(f"updated {path.relative_to(root)}")
        return 0
    params = list(BY_NAME.values())
    print(to_yaml(params, args.node_name) if args.format == "yaml" else to_markdown(params),
          end="")
    return 0
