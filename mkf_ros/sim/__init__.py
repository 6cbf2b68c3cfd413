"""Motion and sensor models with ground truth (no ROS): synthetic IMU streams for tests,
demos, the player node and the paper's simulation study."""

from mkf_ros.sim.motion import SCENARIOS, SimData, simulate

__all__ = ["SCENARIOS", "SimData", "simulate"]
