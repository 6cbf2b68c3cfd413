"""config/estimator.yaml, launch/estimator.launch.py and docs/estimator.md stay generated from
the single parameter definition."""

from __future__ import annotations

import importlib.util
import sys
import types
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


class _Recorded:
    """A stand-in for a launch action or substitution: keeps its arguments."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self.args, self.kwargs = args, kwargs


def _launch_stand_ins(share: Path) -> dict[str, types.ModuleType]:
    """The part of the launch API that estimator.launch.py uses (ament_index_python, launch,
    launch_ros: no wheels exist here), as modules whose classes record their arguments."""
    mods = {name: types.ModuleType(name) for name in (
        "ament_index_python", "ament_index_python.packages", "launch", "launch.actions",
        "launch.substitutions", "launch_ros", "launch_ros.actions",
        "launch_ros.parameter_descriptions")}
    mods["ament_index_python.packages"].get_package_share_directory = (  # type: ignore[attr-defined]
        lambda pkg: str(share / pkg))
    for mod, cls in (("launch", "LaunchDescription"), ("launch.actions", "DeclareLaunchArgument"),
                     ("launch.substitutions", "LaunchConfiguration"),
                     ("launch_ros.actions", "Node"),
                     ("launch_ros.parameter_descriptions", "ParameterValue")):
        setattr(mods[mod], cls, type(cls, (_Recorded,), {}))
    return mods


@pytest.mark.ros
def test_launch_file_starts_the_estimator_on_its_topics(ros_context, monkeypatch,
                                                        tmp_path) -> None:
    """The launch file, executed (against stand-ins of the launch API where ROS's launch is
    not installed), starts this package's ``estimator`` executable with the installed parameter
    file, and its topic arguments remap exactly the topics the node subscribes and publishes."""
    src = (REPO / "launch" / "estimator.launch.py").read_text()
    have_launch = importlib.util.find_spec("launch_ros") is not None
    if not have_launch:
        for name, mod in _launch_stand_ins(tmp_path).items():
            monkeypatch.setitem(sys.modules, name, mod)
    ns: dict = {}
    exec(compile(src, "estimator.launch.py", "exec"), ns)
    ld = ns["generate_launch_description"]()
    if have_launch:  # a real ROS install: the real objects
        from launch import LaunchDescription
        from launch_ros.actions import Node

        assert isinstance(ld, LaunchDescription)
        assert any(isinstance(e, Node) for e in ld.entities)
        return
    entities = ld.args[0]
    declared = {e.args[0]: e.kwargs.get("default_value") for e in entities
                if type(e).__name__ == "DeclareLaunchArgument"}
    (node,) = [e for e in entities if type(e).__name__ == "Node"]
    kw = node.kwargs
    setup = (REPO / "setup.py").read_text()
    entry = f'"{kw["executable"]} = mkf_ros.ros.estimator_main:main"'
    assert kw["package"] == "mkf_ros" and entry in setup
    # the default parameter file is the installed config/estimator.yaml (setup.py's data_files)
    assert declared["params_file"] == str(tmp_path / "mkf_ros" / "config" / "estimator.yaml")
    assert '("share/" + package_name + "/config"' in setup
    assert kw["parameters"][0].args == ("params_file",)
    # every remapped topic is one of the node's, and each topic argument defaults to its own
    remapped = {src_topic: cfg.args[0] for src_topic, cfg in kw["remappings"]}
    est = EstimatorNode("launch_check", context=ros_context, warm=False)
    try:
        topics = {t.lstrip("/") for t, _ in est.get_topic_names_and_types()} | {
            s.topic_name.lstrip("/") for s in est.subscriptions} | {
            p.topic_name.lstrip("/") for p in est.publishers}
    finally:
        est.destroy_node()
    for topic, arg in remapped.items():
        assert topic in topics, f"the launch file remaps {topic!r}, which the node does not use"
        assert declared[arg] == topic
    assert {"imu/data_raw", "imu/mag", "imu/data"} <= set(remapped)


def test_docs_parameter_table_is_generated() -> None:
    text = DOCS.read_text()
    begin, end = "<!-- params:begin -->\n", "<!-- params:end -->"
    assert begin in text and end in text
    table = text.split(begin, 1)[1].split(end, 1)[0]
    assert table == to_markdown(list(BY_NAME.values())), (
        "docs/estimator.md parameter table is stale; regenerate: mkf params --format markdown")
