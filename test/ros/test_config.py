"""config/estimator.yaml, launch/estimator.launch.py and docs/estimator.md stay generated from
the single parameter definition."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from mkf_ros.cli.params_cmd import to_markdown, to_yaml
from mkf_ros.core.params import BY_NAME, PARAMS
from mkf_ros.ros.estimator_node import EstimatorNode

REPO = Path(__file__).resolve().parents[2]
YAML = REPO / "config" / "estimator.yaml"
DOCS = REPO / "docs" / "estimator.md"
REGEN = "mkf params --format yaml --node-name '/**' > config/estimator.yaml"


def test_yaml_is_generated() -> None:
    assert YAML.read_text() == to_yaml(list(BY_NAME.values()), "/**"), (
        f"config/estimator.yaml is stale; regenerate: {REGEN}")


@pytest.mark.ros
def test_yaml_loads_in_the_node(ros_context) -> None:
    """rcl parses the file (any node name) and every parameter gets its default."""
    node = EstimatorNode("any_name", context=ros_context, warm=False,
                         cli_args=["--ros-args", "--params-file", str(YAML)])
    try:
        for p in PARAMS:
            got = node.get_parameter(p.name)
            assert got.type_ != Parameter.Type.NOT_SET
            assert got.value == p.default, p.name
        assert node.stream.params == {p.name: p.default for p in PARAMS}
    finally:
        node.destroy_node()


def test_launch_file() -> None:
    src = (REPO / "launch" / "estimator.launch.py").read_text()
    tree = ast.parse(src)
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description"
               for n in tree.body)
    assert '"estimator.yaml"' in src and 'executable="estimator"' in src
    compile(src, "estimator.launch.py", "exec")
    pytest.importorskip("launch_ros")  # no wheel here: runs on a real ROS install only
    from launch import LaunchDescription
    from launch_ros.actions import Node

    ns: dict = {}
    exec(compile(src, "estimator.launch.py", "exec"), ns)
    ld = ns["generate_launch_description"]()
    assert isinstance(ld, LaunchDescription)
    assert any(isinstance(e, Node) for e in ld.entities)


def test_docs_parameter_table_is_generated() -> None:
    text = DOCS.read_text()
    begin, end = "<!-- params:begin -->\n", "<!-- params:end -->"
    assert begin in text and end in text
    table = text.split(begin, 1)[1].split(end, 1)[0]
    assert table == to_markdown(list(BY_NAME.values())), (
        "docs/estimator.md parameter table is stale; regenerate: mkf params --format markdown")
