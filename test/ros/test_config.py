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
LAUNCH = REPO / "launch" / "estimator.launch.py"
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


class _LaunchConfiguration(_Recorded):
    """A stand-in for launch's LaunchConfiguration: ``perform`` reads the context (a dict of
    the launch arguments' values)."""

    def perform(self, context: dict[str, str]) -> str:
        return context[str(self.args[0])]


def _launch_stand_ins(share: Path) -> dict[str, types.ModuleType]:
    """The part of the launch API that estimator.launch.py uses (ament_index_python, launch,
    launch_ros: no wheels exist here), as modules whose classes record their arguments."""
    mods = {name: types.ModuleType(name) for name in (
        "ament_index_python", "ament_index_python.packages", "launch", "launch.actions",
        "launch.substitutions", "launch_ros", "launch_ros.actions")}
    mods["ament_index_python.packages"].get_package_share_directory = (  # type: ignore[attr-defined]
        lambda pkg: str(share / pkg))
    for mod, cls in (("launch", "LaunchDescription"), ("launch.actions", "DeclareLaunchArgument"),
                     ("launch.actions", "OpaqueFunction"), ("launch_ros.actions", "Node")):
        setattr(mods[mod], cls, type(cls, (_Recorded,), {}))
    mods["launch.substitutions"].LaunchConfiguration = _LaunchConfiguration  # type: ignore
    return mods


class Launched:
    """estimator.launch.py executed against the stand-ins: its arguments and, for given
    argument values, the node it starts."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, share: Path) -> None:
        for name, mod in _launch_stand_ins(share).items():
            monkeypatch.setitem(sys.modules, name, mod)
        self.ns: dict = {}
        exec(compile(LAUNCH.read_text(), "estimator.launch.py", "exec"), self.ns)
        entities = self.ns["generate_launch_description"]().args[0]
        self.declared = {e.args[0]: e.kwargs.get("default_value") for e in entities
                         if type(e).__name__ == "DeclareLaunchArgument"}
        (self.opaque,) = [e for e in entities if type(e).__name__ == "OpaqueFunction"]

    def node(self, **given: str) -> _Recorded:
        """The Node action for ``ros2 launch ... name:=value`` of ``given``."""
        unknown = set(given) - set(self.declared)
        assert not unknown, f"not launch arguments: {unknown}"
        (node,) = self.opaque.kwargs["function"]({**self.declared, **given})
        assert type(node).__name__ == "Node"
        return node


@pytest.mark.ros
def test_launch_file_starts_the_estimator_on_its_topics(ros_context, monkeypatch,
                                                        tmp_path) -> None:
    """The launch file, executed (against stand-ins of the launch API where ROS's launch is
    not installed), starts this package's ``estimator`` executable with the installed parameter
    file, and its topic arguments remap exactly the topics the node subscribes and publishes."""
    if importlib.util.find_spec("launch_ros") is not None:  # a real ROS install
        from launch import LaunchDescription

        ns: dict = {}
        exec(compile(LAUNCH.read_text(), "estimator.launch.py", "exec"), ns)
        assert isinstance(ns["generate_launch_description"](), LaunchDescription)
        return
    launched = Launched(monkeypatch, tmp_path)
    declared, kw = launched.declared, launched.node().kwargs
    setup = (REPO / "setup.py").read_text()
    entry = f'"{kw["executable"]} = mkf_ros.ros.estimator_main:main"'
    assert kw["package"] == "mkf_ros" and entry in setup
    # the default parameter file is the installed config/estimator.yaml (setup.py's data_files)
    assert declared["params_file"] == str(tmp_path / "mkf_ros" / "config" / "estimator.yaml")
    assert '("share/" + package_name + "/config"' in setup
    assert kw["parameters"][0].args == ("params_file",)
    assert kw["parameters"][1] == {"use_sim_time": False}  # no parameter argument given
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


def test_launch_arguments_are_the_parameters_they_name(monkeypatch, tmp_path) -> None:
    """Each parameter argument of the launch file is a parameter of the node, of its type,
    described with its default (imu_tools #180 asks for use_mag, publish_tf, world_frame,
    publish_debug_topics)."""
    launched = Launched(monkeypatch, tmp_path)
    args = launched.ns["PARAMETER_ARGUMENTS"]
    names = {name for name, _, _ in args}
    assert {"use_mag", "publish_tf", "world_frame", "publish_debug_topics"} <= names
    for name, kind, doc in args:
        p = BY_NAME[name]
        assert p.type is kind, name
        default = str(p.default).lower() if kind is bool else f"{p.default:g}" \
            if kind is float else p.default
        assert f"default {default})" in doc, (name, doc)
        assert launched.declared[name] == ""


@pytest.mark.ros
def test_launch_arguments_override_the_file_through_the_node(ros_context, monkeypatch,
                                                             tmp_path) -> None:
    """``ros2 launch mkf_ros estimator.launch.py use_mag:=true world_frame:=ned ...``: the node
    started with the launch file's parameters (the file, then the given arguments) has them;
    what is not given keeps the file's value."""
    launched = Launched(monkeypatch, tmp_path)
    kw = launched.node(use_mag="true", world_frame="ned", publish_tf="True",
                       constant_dt="0.005", fixed_frame="base_link").kwargs
    overrides = kw["parameters"][1]
    assert overrides == {"use_sim_time": False, "use_mag": True, "world_frame": "ned",
                         "publish_tf": True, "constant_dt": 0.005, "fixed_frame": "base_link"}
    f = tmp_path / "file.yaml"
    f.write_text("/**:\n  ros__parameters:\n    use_mag: false\n    max_dt: 2.0\n")
    node = EstimatorNode("launched", context=ros_context, warm=False,
                         cli_args=["--ros-args", "--params-file", str(f)],
                         parameter_overrides=[Parameter(k, value=v)
                                              for k, v in overrides.items()])
    try:
        p = node.stream.params
        assert (p["use_mag"], p["world_frame"], p["publish_tf"], p["constant_dt"],
                p["fixed_frame"], p["max_dt"]) == (True, "ned", True, 0.005, "base_link", 2.0)
    finally:
        node.destroy_node()
    with pytest.raises(ValueError, match="launch argument use_mag: expected true or false"):
        launched.node(use_mag="yes")


def test_docs_parameter_table_is_generated() -> None:
    text = DOCS.read_text()
    begin, end = "<!-- params:begin -->\n", "<!-- params:end -->"
    assert begin in text and end in text
    table = text.split(begin, 1)[1].split(end, 1)[0]
    assert table == to_markdown(list(BY_NAME.values())), (
        "docs/estimator.md parameter table is stale; regenerate: mkf params --format markdown")
