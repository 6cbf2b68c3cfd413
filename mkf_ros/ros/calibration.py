"""The estimator node's calibration services and their parameters (docs/math.md §10).

* ``~/calibrate_gyro`` (std_srvs/Trigger): collects ``gyro_calibration_duration`` seconds of IMU
  samples (by their stamps), returns only when done, refuses when the sensor moved, and applies
  the bias as ``gyro_offset_x/y/z`` (subtracted from every gyro sample before the filter);
* ``~/calibrate_mag/start`` and ``~/calibrate_mag/finish`` (std_srvs/Trigger): collect raw
  magnetometer samples while the user turns the sensor, then fit the hard and soft iron
  (:func:`mkf_ros.core.magcal.fit_ellipsoid`) and apply them as ``mag_bias_x/y/z`` and
  ``mag_soft_iron``.

Both apply their result through the node's own parameters, so a parameter dump saves it.

The services are served by a helper node (hidden name ``_<node>_calibration``, no global ROS
arguments) spun by its own executor thread, under the estimator's private names (``~/...``
resolves to ``/<ns>/<node>/...``): ``~/calibrate_gyro`` waits for IMU messages that the
estimator's executor delivers, and that works with every executor the node runs under (the
EventsExecutor runs neither coroutine service callbacks nor two callbacks at once).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from mkf_ros.core.params import Param

_G = "node: calibration"
#: Parameters of the calibration services (node scope, declared by the estimator node only).
CALIBRATION_PARAMS: tuple[Param, ...] = (
    Param("gyro_calibration_duration", float, 2.0, "~/calibrate_gyro: how long to collect "
          "gyro samples at rest (by their stamps)", unit="s", range=(0.05, 600.0), scope="node",
          group=_G),
    Param("gyro_calibration_max_gyro_stddev", float, 0.02, "~/calibrate_gyro refuses when a "
          "gyro axis varies by more than this (RMS) over the window: the sensor moved",
          unit="rad/s", range=(1e-6, 10.0), scope="node", group=_G),
    Param("gyro_calibration_max_acc_stddev", float, 0.2, "~/calibrate_gyro refuses when an "
          "accelerometer axis varies by more than this (RMS) over the window: the sensor moved",
          unit="m/s^2", range=(1e-6, 100.0), scope="node", group=_G),
    Param("gyro_offset_x", float, 0.0, "Gyro offset subtracted from the x reading before the "
          "filter (set by ~/calibrate_gyro)", unit="rad/s", range=(-10.0, 10.0), scope="node",
          group=_G),
    Param("gyro_offset_y", float, 0.0, "Gyro offset subtracted from the y reading",
          unit="rad/s", range=(-10.0, 10.0), scope="node", group=_G),
    Param("gyro_offset_z", float, 0.0, "Gyro offset subtracted from the z reading",
          unit="rad/s", range=(-10.0, 10.0), scope="node", group=_G),
    Param("mag_calibration_soft_iron", bool, True, "~/calibrate_mag/finish fits the soft-iron "
          "matrix too (false: the hard-iron offset only, for a magnet on the body or partial "
          "coverage)", scope="node", group=_G),
    Param("mag_calibration_min_coverage", float, 0.25, "~/calibrate_mag/finish refuses a fit "
          "whose calibrated directions cover less than this fraction of the sphere", unit="1",
          range=(0.0, 1.0), scope="node", group=_G),
)
BY_NAME: dict[str, Param] = {p.name: p for p in CALIBRATION_PARAMS}
GYRO_OFFSETS = ("gyro_offset_x", "gyro_offset_y", "gyro_offset_z")
#: ~/calibrate_mag keeps at most this many samples (about 30 min at 100 Hz).
MAX_MAG_SAMPLES = 200_000


class GyroWindow:
    """IMU samples collected for ``~/calibrate_gyro`` until their stamps span ``duration``."""

    def __init__(self, duration: float) -> None:
        self.duration = duration
        self.gyr: list[np.ndarray] = []
        self.acc: list[np.ndarray] = []
        self.t0: float | None = None
        self.last: float | None = None
        self.done = threading.Event()

    def add(self, stamp: float, gyr: Any, acc: Any) -> None:
        """One IMU sample (raw gyro; ``acc`` None in split input, see :meth:`add_acc`)."""
        if self.done.is_set():
            return
        if self.last is not None and stamp < self.last:  # time went back: start again
            self.gyr.clear()
            self.acc.clear()
            self.t0 = None
        if self.t0 is None:
            self.t0 = stamp
        self.last = stamp
        self.gyr.append(np.array(gyr, dtype=float))
        if acc is not None:
            self.acc.append(np.array(acc, dtype=float))
        if stamp - self.t0 >= self.duration:
            self.done.set()

    def add_acc(self, acc: Any) -> None:
        if not self.done.is_set() and self.t0 is not None:
            self.acc.append(np.array(acc, dtype=float))


#: s, the longest wait of the service thread's executor (a safety net: close() wakes it)
SPIN_TIMEOUT = 2.0


class ServiceThread:
    """A helper node serving services under ``owner``'s private names from its own thread."""

    def __init__(self, owner: Node) -> None:
        self._owner_name = owner.get_fully_qualified_name()
        self.node = rclpy.create_node(
            f"_{owner.get_name()}_calibration", namespace=owner.get_namespace(),
            context=owner.context, use_global_arguments=False,
            start_parameter_services=False, enable_rosout=False)
        self._executor = SingleThreadedExecutor(context=owner.context)
        self._executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"{owner.get_name()}-services",
                                        daemon=True)
        self._thread.start()

    def service(self, srv_type: Any, private_name: str,
                callback: Callable[[Any, Any], Any]) -> Any:
        """``srv_type`` at ``~/private_name`` of the owner node."""
        return self.node.create_service(srv_type, f"{self._owner_name}/{private_name}",
                                        callback)

    def _spin(self) -> None:
        # a request, close() (wake) or the context's shutdown ends each wait: no polling (the
        # Python executor rebuilds its wait set on every turn: polling at 10 Hz cost this
        # thread 0.7 % of a core, measured with bench/node_latency at 1 kHz)
        while not self._stop.is_set() and self._executor.context.ok():
            try:
                self._executor.spin_once(timeout_sec=SPIN_TIMEOUT)
            except Exception:  # context shut down under us
                if self._executor.context.ok() and not self._stop.is_set():
                    raise
                return

    def close(self) -> None:
        self._stop.set()
        self._executor.wake()
        self._thread.join(timeout=5.0)
        self._executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
