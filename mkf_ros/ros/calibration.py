"""The estimator node's calibration services and their parameters (docs/math.md §10).

* ``~/calibrate_gyro`` (std_srvs/Trigger): collects ``gyro_calibration_duration`` seconds of IMU
  samples (by their stamps), returns only when done, refuses when the sensor moved, and applies
  the bias as ``gyro_offset_x/y/z`` (subtracted from every gyro sample before the filter);
* ``~/calibrate_mag/start`` and ``~/calibrate_mag/finish`` (std_srvs/Trigger): collect raw
  magnetometer samples while the user turns the sensor, then fit the hard and soft iron
  (:func:`mkf_ros.core.magcal.fit_ellipsoid`) and apply them as ``mag_bias_x/y/z`` and
  ``mag_soft_iron``.

Both apply their result through the node's own parameters, so a parameter dump saves it.

:class:`CalibrationServices` holds the services' state (the running collections, the gyro
offset) and their callbacks; the estimator node (:mod:`mkf_ros.ros.estimator_node`) creates
it when it configures, feeds it from its callbacks, and owns the parameters.

The services are served by a helper node (hidden name ``_<node>_calibration``, no global ROS
arguments) spun by its own executor thread, under the estimator's private names (``~/...``
resolves to ``/<ns>/<node>/...``): ``~/calibrate_gyro`` waits for IMU messages that the
estimator's executor delivers, and that works with every executor the node runs under (the
EventsExecutor runs neither coroutine service callbacks nor two callbacks at once).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

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


class Estimator(Protocol):
    """What :class:`CalibrationServices` needs of the estimator node."""

    _lock: threading.Lock
    _active: bool
    _cal: dict[str, Any]  #: the calibration parameters' current values
    stream: Any  #: the node's StreamAdapter

    def get_logger(self) -> Any: ...
    def get_name(self) -> str: ...
    def get_namespace(self) -> str: ...
    def get_fully_qualified_name(self) -> str: ...
    def set_parameters(self, parameter_list: list[Parameter]) -> Any: ...
    def set_parameters_atomically(self, parameter_list: list[Parameter]) -> Any: ...
    @property
    def context(self) -> Any: ...


class CalibrationServices:
    """The three calibration services of an estimator node and their state.

    The node calls :meth:`gyro_input` for every IMU sample (lock held), :meth:`add_accel`
    and :meth:`add_mag` for every split-input accelerometer and magnetometer sample, and
    :meth:`update_offset` when the ``gyro_offset_*`` parameters change."""

    def __init__(self, node: Estimator, imu_topic: str, mag_topic: str) -> None:
        self.node = node
        self.imu_topic, self.mag_topic = imu_topic, mag_topic
        self.window: GyroWindow | None = None  #: a running ~/calibrate_gyro
        self.mag_samples: list[np.ndarray] | None = None  #: a running ~/calibrate_mag
        self.offset = np.zeros(3)
        self.offset_set = False  #: tested per message
        self.update_offset()
        self._thread = ServiceThread(node)  # type: ignore[arg-type]
        self._thread.service(Trigger, "calibrate_gyro", self.on_calibrate_gyro)
        self._thread.service(Trigger, "calibrate_mag/start", self.on_calibrate_mag_start)
        self._thread.service(Trigger, "calibrate_mag/finish", self.on_calibrate_mag_finish)

    def close(self) -> None:
        self._thread.close()

    # --- fed by the node's callbacks (lock held) -------------------------------------------
    def update_offset(self) -> None:
        """``gyro_offset_*`` from the node's calibration parameters."""
        self.offset = np.array([self.node._cal[n] for n in GYRO_OFFSETS])
        self.offset_set = bool(self.offset.any())

    def gyro_input(self, stamp: float, gyr: Any, acc: Any, split: bool) -> Any:
        """The gyro sample for the filter: the raw one to a running ``~/calibrate_gyro``,
        minus ``gyro_offset_*`` to the filter."""
        if self.window is not None:
            self.window.add(stamp, gyr, None if split else acc)
        if self.offset_set and gyr is not None:
            return np.asarray(gyr, dtype=float) - self.offset
        return gyr

    def add_accel(self, acc: Any) -> None:
        if self.window is not None:
            self.window.add_acc(acc)

    def add_mag(self, m: Any) -> None:
        if self.mag_samples is not None and len(self.mag_samples) < MAX_MAG_SAMPLES:
            self.mag_samples.append(np.array(m, dtype=float))

    # --- the services (from the service thread) --------------------------------------------
    def _refuse(self, response: Trigger.Response, text: str) -> Trigger.Response:
        response.success = False
        response.message = text
        self.node.get_logger().warning(text)
        return response

    def _done(self, response: Trigger.Response, text: str) -> Trigger.Response:
        response.success = True
        response.message = text
        self.node.get_logger().info(text)
        return response

    def on_calibrate_gyro(self, request: Trigger.Request, response: Trigger.Response
                          ) -> Trigger.Response:
        """Collect ``gyro_calibration_duration`` s of IMU samples (stamps), return when done;
        apply the mean gyro as ``gyro_offset_*`` unless the sensor moved (docs/math.md
        §10.2)."""
        from mkf_ros.core.gyrocal import rest_bias

        node, cal = self.node, self.node._cal
        with node._lock:
            if not node._active:
                response.success = False
                response.message = "the node is not active: no IMU input to calibrate from"
                return response
            if self.window is not None:
                response.success = False
                response.message = "a gyro calibration is already running"
                return response
            duration = float(cal["gyro_calibration_duration"])
            window = self.window = GyroWindow(duration)
            wait = duration + float(node.stream.params["input_timeout"])
        node.get_logger().info(f"gyro calibration: collecting {duration:g} s at rest")
        complete = window.done.wait(timeout=wait)
        with node._lock:
            self.window = None
        try:
            if not complete:
                raise ValueError(f"gyro calibration: {duration:g} s of IMU data did not arrive "
                                 f"on {self.imu_topic} within {wait:g} s")
            acc = np.array(window.acc) if window.acc else None
            res = rest_bias(np.array(window.gyr), acc,
                            max_gyro_stddev=cal["gyro_calibration_max_gyro_stddev"],
                            max_acc_stddev=cal["gyro_calibration_max_acc_stddev"])
            result = node.set_parameters([
                Parameter(n, Parameter.Type.DOUBLE, float(v))
                for n, v in zip(GYRO_OFFSETS, res.bias, strict=True)])
            refused = [r.reason for r in result if not r.successful]
            if refused:
                raise ValueError("gyro calibration not applied: " + "; ".join(refused))
        except ValueError as e:
            return self._refuse(response, str(e))
        return self._done(response, f"{res.summary()}; applied as gyro_offset_x/y/z")

    def on_calibrate_mag_start(self, request: Trigger.Request, response: Trigger.Response
                               ) -> Trigger.Response:
        with self.node._lock:
            restarted = self.mag_samples is not None
            self.mag_samples = []
        response.success = True
        response.message = (f"{'restarted' if restarted else 'started'} collecting "
                            f"{self.mag_topic}: turn the sensor through every "
                            "orientation, then call calibrate_mag/finish")
        self.node.get_logger().info("magnetometer calibration: " + response.message)
        return response

    def on_calibrate_mag_finish(self, request: Trigger.Request, response: Trigger.Response
                                ) -> Trigger.Response:
        """Fit the collected samples (docs/math.md §10.1) and apply ``mag_bias_*`` and
        ``mag_soft_iron``; the filter then re-initialises (its learned field was the old
        calibration's)."""
        from mkf_ros.core.magcal import fit_ellipsoid

        node, cal = self.node, self.node._cal
        with node._lock:
            samples, self.mag_samples = self.mag_samples, None
        try:
            if samples is None:
                raise ValueError("no magnetometer calibration running: call "
                                 "calibrate_mag/start first")
            fit = fit_ellipsoid(np.array(samples).reshape(-1, 3),
                                soft_iron=cal["mag_calibration_soft_iron"],
                                min_coverage=cal["mag_calibration_min_coverage"])
            result = node.set_parameters_atomically([
                Parameter(k, value=v) for k, v in fit.params().items()])
            if not result.successful:
                raise ValueError(f"magnetometer calibration not applied: {result.reason}")
        except ValueError as e:
            return self._refuse(response, str(e))
        with node._lock:
            node.stream.reset("magnetometer calibration applied")
        return self._done(response, "; ".join(fit.summary().splitlines())
                          + "; applied as mag_bias_x/y/z, mag_soft_iron (filter re-initialised)")
