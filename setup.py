"""ament_python packaging of mkf_ros.

Runtime ROS dependencies live in package.xml (rosdep / apt on a ROS machine);
ros-* PyPI wheels are for development and CI only (requirements/ros-jazzy.txt)
and must never appear in install_requires.
"""

from glob import glob

from setuptools import find_packages, setup

package_name = "mkf_ros"

setup(
    name=package_name,
    version="0.1.0",
    description="Manifold Kalman Filter (MEKF/MUKF) attitude estimation for ROS 2",
    license="Apache-2.0",
    maintainer="mkf_ros maintainers",
    maintainer_email="maintainers@users.noreply.h-seed-5101cbd9.example",
    packages=find_packages(exclude=["test*", "bench*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=[
        "setuptools",
        "numpy>=1.24",
        "numba>=0.59",
        "rosbags>=0.11,<0.12",  # mkf_ros.bags.writer extends its storage writers' internals
        "matplotlib>=3.7",
        "tqdm>=4.60",
        "pyyaml",
    ],
    extras_require={
        # `mkf study/process --scheduler tcp://HOST:8786`: work units on a Dask cluster
        # (docs/study/cluster.md); never needed by the nodes
        "cluster": ["dask[distributed]>=2024.1"],
    },
    python_requires=">=3.10",
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "mkf = mkf_ros.cli.main:main",
            "estimator = mkf_ros.ros.estimator_node:main",
            "player = mkf_ros.ros.player_node:main",
        ],
    },
)
