"""``mkf``: every subcommand's ``--help`` works, and ``mkf params`` prints what a ROS parameter
file and a reader need (read back by independent parsers: PyYAML, rclpy's params-file reader,
a Markdown table split by hand)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from mkf_ros.cli import params_cmd
from mkf_ros.cli.main import COMMANDS, main
from mkf_ros.core.params import PARAMS


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_help_works(command: str, capsys: pytest.CaptureFixture) -> None:
    """``mkf COMMAND --help`` prints its usage and exits 0 (argparse expands ``%`` in help
    texts: a parameter doc with a bare ``%`` used to crash it with a TypeError)."""
    with pytest.raises(SystemExit) as ex:
        main([command, "--help"])
    assert ex.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: mkf {command}")


def test_params_yaml_is_a_params_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``mkf params --node-name N`` is a valid ``--params-file``: PyYAML and rclpy's own reader
    give one entry per parameter under ``N/ros__parameters``, each equal to its default, of its
    declared type, and the comment above each is its description."""
    from rclpy.parameter import parameter_dict_from_yaml_file, parameter_value_to_python

    assert main(["params", "--node-name", "my_estimator"]) == 0
    text = capsys.readouterr().out
    doc = yaml.safe_load(text)
    assert list(doc) == ["my_estimator"] and list(doc["my_estimator"]) == ["ros__parameters"]
    values = doc["my_estimator"]["ros__parameters"]
    assert list(values) == [p.name for p in PARAMS]
    for p in PARAMS:
        v = values[p.name]
        assert v == p.default, p.name
        assert type(v) is type(p.default), (p.name, v)
    f = tmp_path / "p.yaml"
    f.write_text(text)
    ros = parameter_dict_from_yaml_file(str(f), target_nodes=["my_estimator"])
    assert list(ros) == [p.name for p in PARAMS]
    for p in PARAMS:
        assert parameter_value_to_python(ros[p.name].value) == p.default, p.name
    lines = text.splitlines()
    for p in PARAMS:
        i = lines.index(f"    {p.name}: {params_cmd.yaml_value(p.default)}")
        assert lines[i - 1].startswith("    # ") and p.description in lines[i - 1]


def test_params_markdown_table(capsys: pytest.CaptureFixture) -> None:
    """``mkf params --format markdown``: a header, a separator and one row of six cells per
    parameter, in order, naming it, its type and its default."""
    assert main(["params", "--format", "markdown"]) == 0
    rows = capsys.readouterr().out.strip().splitlines()
    assert rows[0] == "| parameter | type | default | unit | range / choices | description |"
    assert rows[1] == "|---|---|---|---|---|---|"
    assert len(rows) == 2 + len(PARAMS)
    for p, row in zip(PARAMS, rows[2:], strict=True):
        cells = [c.strip() for c in row.strip("|").split(" | ")]
        assert len(cells) == 6, row
        assert cells[0] == f"`{p.name}`" and cells[1] == p.type.__name__
        assert cells[2] == f"`{params_cmd.yaml_value(p.default)}`"


def test_params_update_rewrites_every_generated_copy(tmp_path: Path, monkeypatch,
                                                     capsys: pytest.CaptureFixture) -> None:
    """``mkf params --update`` in a checkout rewrites config/estimator.yaml and the table
    between the markers of docs/estimator.md, and touches nothing else (README.md links to that
    table and is left as it is); outside a checkout it is one clear error line."""
    repo = Path(params_cmd.__file__).resolve().parents[2]
    root = tmp_path / "checkout"
    (root / "config").mkdir(parents=True)
    (root / "docs").mkdir()
    (root / "mkf_ros" / "cli").mkdir(parents=True)
    shutil.copy(repo / "package.xml", root / "package.xml")
    (root / "config" / "estimator.yaml").write_text("stale: 1\n")
    (root / "README.md").write_text("intro\n[parameters](docs/estimator.md#parameters)\n")
    (root / "docs" / "estimator.md").write_text("a\n<!-- params:begin -->\nold\n"
                                                "<!-- params:end -->\nb\n")
    fake = root / "mkf_ros" / "cli" / "params_cmd.py"  # run() finds the checkout from here
    monkeypatch.setattr(params_cmd, "__file__", str(fake))
    assert main(["params", "--update"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "updated config/estimator.yaml", "updated docs/estimator.md"]
    cfg = yaml.safe_load((root / "config" / "estimator.yaml").read_text())
    assert cfg["/**"]["ros__parameters"] == {p.name: p.default for p in PARAMS}
    table = params_cmd.to_markdown(PARAMS)
    assert (root / "README.md").read_text() == (
        "intro\n[parameters](docs/estimator.md#parameters)\n")
    assert (root / "docs" / "estimator.md").read_text() == (
        f"a\n<!-- params:begin -->\n{table}<!-- params:end -->\nb\n")
    (root / "package.xml").unlink()
    assert main(["params", "--update"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["mkf params: error: --update works in a source checkout "
                   "(package.xml not found)"]
