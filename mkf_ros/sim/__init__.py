"""Motion and sensor models with ground truth (no ROS): synthetic IMU streams for tests,
demos, the player node, ``mkf synth`` and the paper's simulation study."""

from mkf_ros.sim.motion import MAG_FIELD_ENU, SCENARIOS, Scenario, SimData, SimStream, simulate

__all__ = ["MAG_FIELD_ENU", "SCENARIOS", "Scenario", "SimData", "SimStream", "simulate"]
