"""Launch the mkf_ros ``estimator`` with the package's commented parameter file.

    ros2 launch mkf_ros estimator.launch.py
    ros2 launch mkf_ros estimator.launch.py use_mag:=true world_frame:=ned publish_tf:=true
    ros2 launch mkf_ros estimator.launch.py namespace:=imu_front params_file:=/path/my.yaml \\
        imu_topic:=/camera/imu use_sim_time:=true
    ros2 launch mkf_ros estimator.launch.py node_name:=imu_filter \\
        params_file:=/path/imu_filter_madgwick.yaml        # a madgwick file keyed imu_filter:

The topics are relative (imu/data_raw, imu/mag -> imu/data), so ``namespace`` moves all of
them; the ``*_topic`` arguments remap them one by one. The parameter arguments below
(``use_mag``, ``world_frame``, ``publish_tf``, ...) override the parameter file when given
and leave its value when not (empty default). Switching from imu_filter_madgwick:
docs/migrating.md.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from mkf_ros.core.params import BY_NAME

#: The common parameters offered as launch arguments (imu_tools #180). Their type, description
#: and default are those of mkf_ros.core.params.PARAMS, the one definition.
PARAMETER_NAMES = ("use_mag", "world_frame", "publish_tf", "fixed_frame", "reverse_tf",
                   "publish_debug_topics", "constant_dt", "algorithm", "declination",
                   "yaw_offset", "orientation_stddev", "remove_gravity_vector", "input_mode")


def _described(name: str) -> tuple[str, type, str]:
    """``(name, type, description with its default)`` of a parameter, from PARAMS."""
    p = BY_NAME[name]
    default = str(p.default).lower() if p.type is bool else (
        f"{p.default:g}" if p.type is float else p.default)
    return name, p.type, f"{p.description} (default {default})"


PARAMETER_ARGUMENTS = tuple(_described(n) for n in PARAMETER_NAMES)


def _value(name: str, text: str):
    """A launch argument's text as the parameter's value: true/false for a boolean, else the
    parameter's own check (PARAMS)."""
    if name == "use_sim_time" or BY_NAME[name].type is bool:
        if text.strip().lower() not in ("true", "false"):
            raise ValueError(f"launch argument {name}: expected true or false, got {text!r}")
        return text.strip().lower() == "true"
    return BY_NAME[name].validate(text)


def _node(context, *args, **kwargs):
    """The node, with the parameter arguments that were given on top of the file."""
    overrides = {"use_sim_time": _value(
        "use_sim_time", LaunchConfiguration("use_sim_time").perform(context))}
    for name in PARAMETER_NAMES:
        text = LaunchConfiguration(name).perform(context)
        if text != "":
            overrides[name] = _value(name, text)
    return [Node(
        package="mkf_ros",
        executable="estimator",
        name=LaunchConfiguration("node_name"),
        namespace=LaunchConfiguration("namespace"),
        parameters=[LaunchConfiguration("params_file"), overrides],
        remappings=[
            ("imu/data_raw", LaunchConfiguration("imu_topic")),
            ("imu/mag", LaunchConfiguration("mag_topic")),
            ("imu/data", LaunchConfiguration("output_topic")),
        ],
        output="screen",
        emulate_tty=True,
    )]


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("mkf_ros"), "config", "estimator.yaml")
    args = [
        DeclareLaunchArgument("params_file", default_value=config,
                              description="parameter file (top-level key: the node name, "
                              "or /** for any)"),
        DeclareLaunchArgument("node_name", default_value="estimator",
                              description="imu_filter: read a madgwick file keyed imu_filter:"),
        DeclareLaunchArgument("namespace", default_value=""),
        DeclareLaunchArgument("use_sim_time", default_value="false"),
        DeclareLaunchArgument("imu_topic", default_value="imu/data_raw"),
        DeclareLaunchArgument("mag_topic", default_value="imu/mag"),
        DeclareLaunchArgument("output_topic", default_value="imu/data"),
    ]
    args += [DeclareLaunchArgument(name, default_value="",
                                   description=f"{doc}; empty: the parameter file's value")
             for name, _, doc in PARAMETER_ARGUMENTS]
    return LaunchDescription([*args, OpaqueFunction(function=_node)])
