"""Launch the mkf_ros ``estimator`` with the package's commented parameter file.

    ros2 launch mkf_ros estimator.launch.py
    ros2 launch mkf_ros estimator.launch.py namespace:=imu_front params_file:=/path/my.yaml \\
        imu_topic:=/camera/imu use_sim_time:=true

The topics are relative (imu/data_raw, imu/mag -> imu/data), so ``namespace`` moves all of
them; the ``*_topic`` arguments remap them one by one. For a drop-in replacement of
imu_filter_madgwick keep the default topics and set ``use_mag`` and ``world_frame`` in the
parameter file (both default to the safer false / enu).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("mkf_ros"), "config", "estimator.yaml")
    args = [
        DeclareLaunchArgument("params_file", default_value=config,
                              description="parameter file (top-level key: the node name)"),
        DeclareLaunchArgument("node_name", default_value="estimator"),
        DeclareLaunchArgument("namespace", default_value=""),
        DeclareLaunchArgument("use_sim_time", default_value="false"),
        DeclareLaunchArgument("imu_topic", default_value="imu/data_raw"),
        DeclareLaunchArgument("mag_topic", default_value="imu/mag"),
        DeclareLaunchArgument("output_topic", default_value="imu/data"),
    ]
    node = Node(
        package="mkf_ros",
        executable="estimator",
        name=LaunchConfiguration("node_name"),
        namespace=LaunchConfiguration("namespace"),
        parameters=[
            LaunchConfiguration("params_file"),
            {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"),
                                            value_type=bool)},
        ],
        remappings=[
            ("imu/data_raw", LaunchConfiguration("imu_topic")),
            ("imu/mag", LaunchConfiguration("mag_topic")),
            ("imu/data", LaunchConfiguration("output_topic")),
        ],
        output="screen",
        emulate_tty=True,
    )
    return LaunchDescription([*args, node])
