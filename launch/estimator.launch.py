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

#: The common parameters offered as launch arguments: (name, type, what it does). Their
#: definitions (default, range, unit) are mkf_ros.core.params.PARAMS; test/ros/test_config.py
#: checks that each one is a parameter of that type.
PARAMETER_ARGUMENTS = (
    ("use_mag", bool, "fuse imu/mag for heading (default false)"),
    ("world_frame", str, "enu, ned or nwu (default enu)"),
    ("publish_tf", bool, "broadcast fixed_frame -> IMU frame (default false)"),
    ("fixed_frame", str, "parent frame of the TF (default odom)"),
    ("reverse_tf", bool, "broadcast IMU frame -> fixed_frame instead (default false)"),
    ("publish_debug_topics", bool,
     "imu/rpy/filtered, imu/rpy/raw, imu/gyro_bias, imu/steady_state (default false)"),
    ("constant_dt", float, "time step for every sample instead of the stamps, s (default 0)"),
    ("algorithm", str, "mekf, mukf, euler_kf, euler_ukf or madgwick (default mekf)"),
    ("declination", float, "magnetic declination, rad, positive east (default 0)"),
    ("yaw_offset", float, "added to the published heading, rad (default 0)"),
    ("orientation_stddev", float,
     "> 0: a fixed orientation_covariance diagonal, rad; 0: the filter's (default 0)"),
    ("remove_gravity_vector", bool, "subtract gravity from linear_acceleration (default false)"),
    ("input_mode", str, "imu, or split for separate imu/gyro and imu/accel (default imu)"),
)


def _value(name: str, kind: type, text: str):
    """A launch argument's text as the parameter's type (the node checks the value)."""
    if kind is bool:
        if text.strip().lower() not in ("true", "false"):
            raise ValueError(f"launch argument {name}: expected true or false, got {text!r}")
        return text.strip().lower() == "true"
    return kind(text)


def _node(context, *args, **kwargs):
    """The node, with the parameter arguments that were given on top of the file."""
    overrides = {"use_sim_time": _value(
        "use_sim_time", bool, LaunchConfiguration("use_sim_time").perform(context))}
    for name, kind, _ in PARAMETER_ARGUMENTS:
        text = LaunchConfiguration(name).perform(context)
        if text != "":
            overrides[name] = _value(name, kind, text)
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
