"""Console entry point of the ``estimator`` node: usage, the executor, ``main``.

``ros2 run mkf_ros estimator [--executor=events|single] [--ros-args ...]`` (setup.py's console
script ``estimator``; ``estimator_lifecycle`` runs the managed node through the same
:func:`main`). The node itself: :mod:`mkf_ros.ros.estimator_node`.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.utilities import remove_ros_args

from mkf_ros.core.params import PARAMS
from mkf_ros.ros import calibration
from mkf_ros.ros.estimator_node import EstimatorNode, ParameterError
from mkf_ros.ros.signals import ends_on_signal

#: ``single``: rclpy's SingleThreadedExecutor (rebuilds its wait set in Python for every
#: message: ~0.3 ms of CPU per message here); ``events``: the C++ EventsExecutor of rclpy
#: 7.1 (Jazzy), driven by a ``spin_once`` loop because its ``spin()`` does not return after
#: shutdown. See docs/estimator.md (performance) for measurements.
EXECUTORS = ("events", "single")
DEFAULT_EXECUTOR = "events"


def make_executor(kind: str) -> Any:
    """The executor of the console script (``--executor=events|single``)."""
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    return SingleThreadedExecutor()


def spin(executor: Any) -> None:
    """Spin until the context shuts down (SIGINT, SIGTERM)."""
    if isinstance(executor, SingleThreadedExecutor):
        executor.spin()
        return
    while executor.context.ok():
        executor.spin_once(timeout_sec=0.2)


USAGE = """\
usage: estimator [--executor=events|single] [--ros-args [-p NAME:=VALUE] [--params-file FILE]
                 [-r FROM:=TO] ...]

MEKF/MUKF attitude estimator (mkf_ros), a drop-in replacement for imu_filter_madgwick.
  subscribes  imu/data_raw (sensor_msgs/Imu), imu/mag (sensor_msgs/MagneticField, tesla)
  publishes   imu/data (sensor_msgs/Imu), /diagnostics; with publish_debug_topics
              imu/rpy/filtered, imu/rpy/raw (accelerometer + magnetometer alone, with
              use_mag), imu/gyro_bias (geometry_msgs/Vector3Stamped) and imu/steady_state
              (std_msgs/Bool, the rest detector); TF with publish_tf
  services    ~/reset, ~/calibrate_gyro (collects gyro_calibration_duration s at rest, applies
              gyro_offset_*), ~/calibrate_mag/start and ~/calibrate_mag/finish (fits and
              applies mag_bias_*, mag_soft_iron), all std_srvs/Trigger
examples:
  estimator --ros-args -p use_mag:=true -p world_frame:=ned
  estimator --ros-args -r __ns:=/imu_front -r imu/data_raw:=/camera/imu
  estimator --ros-args --params-file config/estimator.yaml
  estimator --ros-args -r __node:=imu_filter --params-file imu_filter_madgwick.yaml
switching from imu_filter_madgwick: docs/migrating.md
parameters (units, ranges, defaults): mkf params --format markdown
--executor (or $MKF_ROS_EXECUTOR): events (default; ~5x less CPU per message) or single
(rclpy's SingleThreadedExecutor)"""


def parameter_help() -> str:
    """The ROS parameters with their defaults and units, generated from PARAMS (descriptions,
    ranges and choices: ``mkf params``)."""
    lines = ["parameters (-p NAME:=VALUE; descriptions and ranges: mkf params):"]
    for p in (*PARAMS, *calibration.CALIBRATION_PARAMS):
        unit = f" [{p.unit}]" if p.unit else ""
        choices = f" ({'|'.join(p.choices)})" if p.choices else ""
        ro = " (read-only: start-up only)" if p.read_only else ""
        lines.append(f"  {p.name:<32} {p.default!r}{unit}{choices}{ro}")
    return "\n".join(lines)


def _executor_kind(plain: list[str], prog: str) -> str | None:
    """The executor named by ``--executor=`` (or $MKF_ROS_EXECUTOR); None after printing the
    error for anything else on the command line."""
    kind = os.environ.get("MKF_ROS_EXECUTOR", DEFAULT_EXECUTOR)
    for a in plain:
        if a.startswith("--executor="):
            kind = a.split("=", 1)[1]
        else:
            print(f"{prog}: error: unknown argument {a!r} (ROS arguments go after "
                  "--ros-args; see --help)", file=sys.stderr)
            return None
    if kind not in EXECUTORS:
        print(f"{prog}: error: executor must be one of {', '.join(EXECUTORS)}, "
              f"got {kind!r}", file=sys.stderr)
        return None
    return kind


def main(argv: Sequence[str] | None = None, *, node_class: type[EstimatorNode] | None = None,
         prog: str = "estimator", usage: str = USAGE) -> int:
    """Console script ``estimator`` (``ros2 run mkf_ros estimator [--ros-args ...]``); with
    ``node_class`` another node (the managed ``estimator_lifecycle``)."""
    args = list(sys.argv if argv is None else argv)
    plain = remove_ros_args(args)[1:]
    if any(a in ("-h", "--help") for a in plain):
        print(usage)
        print(parameter_help())
        return 0
    kind = _executor_kind(plain, prog)
    if kind is None:
        return 2
    rclpy.init(args=args)
    executor = node = None
    code = 0
    try:
        with ends_on_signal(rclpy.get_default_context()):
            executor = make_executor(kind)
            node = (node_class or EstimatorNode)(argv=args)
            executor.add_node(node)
            node.get_logger().info(f"spinning with the {kind} executor")
            spin(executor)
    except ParameterError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        code = 2
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
