"""The ``estimator`` node: MEKF/MUKF attitude from ``imu/data_raw`` (+ ``imu/mag``) to ``imu/data``.

A drop-in replacement for imu_filter_madgwick (same topics, same names for the parameters that
mean the same thing) and a thin rclpy wrapper around :class:`mkf_ros.stream.adapter.StreamAdapter`,
which holds every rule about time and input.

Topics (relative names: remap ``imu:=...`` to move them together, REP-145):

* subscribes ``imu/data_raw`` (sensor_msgs/Imu) and ``imu/mag`` (sensor_msgs/MagneticField,
  tesla), best-effort, keep last 50 (matches reliable and best-effort publishers); both are
  overridable with ``qos_overrides.<topic>.subscription.*``. The magnetometer is fused
  asynchronously and never gates the IMU;
* publishes ``imu/data`` (sensor_msgs/Imu, reliable, keep last 100) once initialised, one
  message per accepted IMU message, with its header; ``/diagnostics`` (DiagnosticArray);
  ``imu/rpy/filtered`` and ``imu/gyro_bias`` with ``publish_debug_topics``; TF with
  ``publish_tf`` when tf2_ros is importable;
* services ``~/reset``, ``~/calibrate_gyro``, ``~/calibrate_mag/start`` and
  ``~/calibrate_mag/finish`` (std_srvs/Trigger; the calibrations: :mod:`.calibration`,
  docs/math.md §10).

Every parameter of :data:`mkf_ros.core.params.PARAMS` is declared and can be changed at run
time through SetParameters (``ros2 param set``): validated in the on-set callback (a rejected
value leaves everything as it was and the caller sees the reason) and applied atomically,
between two messages, in the post-set callback.

Speed: the hot path uses no rclpy message objects (raw CDR in and out, :mod:`.rawmsg`), and the
console script spins with the C++ EventsExecutor in a ``spin_once`` loop (``--executor=single``
for rclpy's SingleThreadedExecutor, which alone costs ~0.3 ms of CPU per message here).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockChange, ClockType, JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.serialization import deserialize_message
from rclpy.timer import Timer
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import Imu, MagneticField
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from mkf_ros.core.params import BY_NAME, PARAMS
from mkf_ros.core.quaternion import qconj_np
from mkf_ros.ros import calibration, convert, rawmsg
from mkf_ros.ros.diagnostics import DiagnosticsTracker, Snapshot
from mkf_ros.ros.parameters import (
    UnknownParameter,
    declare_all,
    declare_calibration,
    to_double,
    unknown_overrides,
)
from mkf_ros.stream.adapter import (
    INPUT_CHECK_MESSAGES,
    StreamAdapter,
    carries_orientation,
    orientation_note,
)


def input_qos() -> QoSProfile:
    """Sensor-data policies (best effort, volatile) with a deeper queue than the profile's 5
    (200: 0.2 s at 1 kHz), so that a burst, or the node being descheduled on a busy machine,
    does not drop samples. A new object per call: QoS overrides modify it in place."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                      reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def output_qos() -> QoSProfile:
    """Reliable, keep last 100 (what rviz, rosbag and robot_localization expect)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class ParameterError(Exception):
    """An invalid start-up parameter (reported as one line; the node does not start)."""


class EstimatorNode(Node):
    """The attitude estimator node (see the module docstring)."""

    #: whether the node is managed (:class:`mkf_ros.ros.lifecycle.EstimatorLifecycleNode`)
    MANAGED = False

    def __init__(self, node_name: str = "estimator", *, warm: bool = True,
                 **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self._lock = threading.Lock()
        self._t_start = time.monotonic()
        self._configured = False
        self._active = not self.MANAGED  #: a managed node processes input only when active
        self._cal_services: calibration.ServiceThread | None = None
        self._timer: Timer | None = None
        self._warm = warm
        try:
            values = declare_all(self)
            self.stream = StreamAdapter(values)
            self._cal = declare_calibration(self)
        except (ValueError, InvalidParameterValueException, InvalidParameterTypeException,
                ParameterException) as e:
            msg = " ".join(str(e).split())
            self.destroy_node()
            raise ParameterError(f"invalid parameter: {msg}") from None
        self.add_pre_set_parameters_callback(self._pre_set)
        self.add_on_set_parameters_callback(self._on_set)
        self.add_post_set_parameters_callback(self._post_set)
        if not self.MANAGED:
            self._configure()

    def _current_values(self) -> dict[str, Any]:
        """The node's current parameter values (filter, node and calibration)."""
        names = [p.name for p in PARAMS] + [p.name for p in calibration.CALIBRATION_PARAMS]
        return {p.name: p.value for p in self.get_parameters(names)}

    def _configure(self) -> None:
        """Everything but the parameters: the filter from the current parameter values, the
        publishers, subscriptions, services and timers (the lifecycle's configure)."""
        log = self.get_logger()
        values = self._current_values()
        self._cal = {k: v for k, v in values.items() if k in calibration.BY_NAME}
        with self._lock:
            self.stream = StreamAdapter({k: v for k, v in values.items() if k in BY_NAME})
        if self._warm:
            from mkf_ros.kernels import FIRST_COMPILE_TIME, warmup

            log.info("loading the filter kernels (compiled at install time; where that step "
                     f"did not run, the first start compiles them: {FIRST_COMPILE_TIME})...")
            t0 = time.monotonic()

            warmup(("stream",))  # the node runs the streaming kernels only
            log.info(f"filter kernels ready in {time.monotonic() - t0:.1f} s")

        # counters and state owned by the node (the adapter has the rest)
        self._published = 0
        self.received_imu = self.received_mag = 0  #: messages taken from each subscription
        self._exceptions = 0
        self._last_exception = ""
        self._last_imu_wall: float | None = None
        self._last_mag_wall: float | None = None
        self._frame_id = ""
        self._warned: set[str] = set()
        self._ori_checks = INPUT_CHECK_MESSAGES  # IMU messages left to check for an orientation
        self._carries_orientation = False
        self._out = Imu()
        self._encoder = rawmsg.ImuEncoder()

        qos_opts = QoSOverridingOptions.with_default_policies
        self._pub = self._make_output_publisher()
        # input_mode split: the gyro drives the stream (and the output), the accelerometer is
        # fused at its own stamps (RealSense: -r imu/gyro:=camera/gyro/sample
        # -r imu/accel:=camera/accel/sample)
        split = self.stream.split
        self._sub_imu = self.create_subscription(Imu, "imu/gyro" if split else "imu/data_raw",
                                                 self._on_imu, input_qos(),
                                                 qos_overriding_options=qos_opts(), raw=True)
        self.received_acc = 0  #: split input: messages taken from imu/accel
        self._sub_acc = (self.create_subscription(Imu, "imu/accel", self._on_accel,
                                                  input_qos(), raw=True,
                                                  qos_overriding_options=qos_opts())
                         if split else None)
        self._sub_mag = self.create_subscription(MagneticField, "imu/mag", self._on_mag,
                                                 input_qos(), qos_overriding_options=qos_opts(),
                                                 raw=True)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diag = DiagnosticsTracker(f"{self.get_name()}: attitude estimator")
        self._srv_reset = self.create_service(Trigger, "~/reset", self._on_reset)
        # calibrations (docs/math.md §10): served from their own thread (see .calibration)
        self._set_gyro_offset()
        self._gyro_window: calibration.GyroWindow | None = None
        self._mag_samples: list[np.ndarray] | None = None
        services = self._cal_services = calibration.ServiceThread(self)
        services.service(Trigger, "calibrate_gyro", self._on_calibrate_gyro)
        services.service(Trigger, "calibrate_mag/start", self._on_calibrate_mag_start)
        services.service(Trigger, "calibrate_mag/finish", self._on_calibrate_mag_finish)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = None
        # a ROS-time jump back (bag loop with /clock) or a switch to/from sim time resets
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True),
            post_callback=self._on_time_jump)
        self._tf: Any = None  # a tf2_ros.TransformBroadcaster once publish_tf is on
        self._rpy_pub: Publisher | None = None
        self._bias_pub: Publisher | None = None
        self._configured = True
        self._apply_node_side_effects()

        for name, hint in unknown_overrides(self).items():
            log.warning(f"ignoring unknown parameter {name!r}: {hint}")
        p = self.stream.params
        log.info(
            f"{p['algorithm']} on chart {p['chart']}, world frame {p['world_frame']}, "
            f"use_mag {str(p['use_mag']).lower()}; listening on {self._sub_imu.topic_name} and "
            f"{self._sub_mag.topic_name}, publishing {self._pub.topic_name}")

    def _make_output_publisher(self) -> Publisher:
        """``imu/data`` (a lifecycle publisher in the managed node)."""
        return self.create_publisher(Imu, "imu/data", output_qos(),
                                     qos_overriding_options=QoSOverridingOptions
                                     .with_default_policies())

    def _destroy_output_publisher(self, pub: Publisher) -> None:
        self.destroy_publisher(pub)

    def _teardown(self) -> None:
        """Undo :meth:`_configure` (the lifecycle's cleanup and shutdown)."""
        if not self._configured:
            return
        self._configured = False
        if self._cal_services is not None:
            self._cal_services.close()
            self._cal_services = None
        for t in (self._timer,):
            if t is not None:
                self.destroy_timer(t)
        self._timer = None
        self._jump_handle.unregister()
        for sub in (self._sub_imu, self._sub_acc, self._sub_mag):
            if sub is not None:
                self.destroy_subscription(sub)
        self._destroy_output_publisher(self._pub)
        for pub in (self._diag_pub, self._rpy_pub, self._bias_pub):
            if pub is not None:
                self.destroy_publisher(pub)
        self._rpy_pub = self._bias_pub = None
        self.destroy_service(self._srv_reset)
        self._tf = None

    # --- parameters ----------------------------------------------------------------------------
    def _pre_set(self, params: list[Parameter]) -> list[Parameter]:
        """Accept integers for floating-point parameters (``ros2 param set x max_dt 1``);
        refuse an unknown name with a reason naming it (:class:`UnknownParameter`)."""
        for p in params:
            if not self.has_parameter(p.name):
                raise UnknownParameter(p.name)
        return [to_double(p) for p in params]

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        """Validate only, no side effects: the reason reaches the SetParameters caller."""
        changes = {p.name: p.value for p in params if p.name in BY_NAME}
        try:
            for p in params:
                if p.name in calibration.BY_NAME:
                    calibration.BY_NAME[p.name].validate(p.value)
            if changes:
                with self._lock:
                    self.stream.validate(changes)
        except ValueError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _post_set(self, params: list[Parameter]) -> None:
        """Apply accepted changes atomically (between two messages)."""
        cal = {p.name: calibration.BY_NAME[p.name].validate(p.value) for p in params
               if p.name in calibration.BY_NAME}
        if cal:
            with self._lock:
                self._cal.update(cal)
                self._set_gyro_offset()
            self.get_logger().info("parameters changed: " + ", ".join(
                f"{k}={v!r}" for k, v in cal.items()))
        changes = {p.name: p.value for p in params if p.name in BY_NAME}
        if not changes:
            return
        try:
            with self._lock:
                self.stream.set_params(**changes)
        except Exception as e:  # validated already: would be a bug; never kill the node
            self._count_exception(e, "applying parameters")
            return
        self._apply_node_side_effects(changes)
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{k}={v!r}" for k, v in changes.items()))

    def _apply_node_side_effects(self, changes: dict[str, Any] | None = None) -> None:
        self._p = p = self.stream.params
        if not self._configured:
            return  # applied by the lifecycle's configure
        if changes is None or "diagnostics_period" in changes:
            self._make_timer()
        if p["publish_tf"] and self._tf is None:
            try:
                import tf2_ros  # optional: no pip wheel; present on a real ROS install
            except ImportError:
                self._warn_once("tf", "publish_tf is true but tf2_ros cannot be imported "
                                "(install ros-jazzy-tf2-ros); not publishing TF")
            else:
                self._tf = tf2_ros.TransformBroadcaster(self)
        if p["publish_debug_topics"] and self._rpy_pub is None:
            self._rpy_pub = self.create_publisher(Vector3Stamped, "imu/rpy/filtered", 10)
            self._bias_pub = self.create_publisher(Vector3Stamped, "imu/gyro_bias", 10)

    def _make_timer(self) -> None:
        if self._timer is not None:
            self.destroy_timer(self._timer)
        period = float(self.stream.params["diagnostics_period"]) or 1.0
        self._timer = self.create_timer(period, self._on_timer, clock=self._steady)

    # --- callbacks -----------------------------------------------------------------------------
    def _on_imu(self, data: bytes) -> None:
        """Serialized Imu in (``raw=True``), serialized Imu out: no message objects on the
        fast path (see :mod:`mkf_ros.ros.rawmsg`)."""
        if not self._active:
            return  # a managed node that is not active takes no input
        self.received_imu += 1
        try:
            self._last_imu_wall = time.monotonic()
            h = rawmsg.parse(data, rawmsg.IMU_DOUBLES)
            if h is None:  # not little-endian CDR: message objects
                self._on_imu_msg(deserialize_message(data, Imu))
                return
            if self._ori_checks:
                self._check_orientation(h.d[rawmsg.Q:rawmsg.Q + 4], h.d[rawmsg.QC])
            gyr, acc = rawmsg.imu_views(h)  # copied into the adapter's event record
            p = self._p
            extras = (self._tf is not None and p["publish_tf"]) or (
                self._rpy_pub is not None and p["publish_debug_topics"])
            with self._lock:
                gyr = self._gyro_input(h.stamp, gyr, acc)
                # no StreamOutput on this path: the output record straight into the bytes
                flags = self.stream.step_imu(h.stamp, gyr, acc)
                if not flags:
                    return
                payload = self._encoder.encode_values(
                    h, self.stream.output_values, flags, p["angular_velocity_stddev"],
                    p["linear_acceleration_stddev"])
                out = self.stream.last_output() if extras else None
            self._frame_id = h.frame_id
            self._pub.publish(payload)
            self._published += 1
            if out is not None:
                self._extras(Header(stamp=Time(sec=h.sec, nanosec=h.nanosec),
                                    frame_id=h.frame_id), out, p)
        except Exception as e:
            self._count_exception(e, "imu callback")

    def _on_imu_msg(self, msg: Imu) -> None:
        """The same with message objects (inputs that are not little-endian CDR)."""
        stamp, gyr, acc = convert.imu_to_arrays(msg)
        if self._ori_checks:
            o = msg.orientation
            self._check_orientation((o.x, o.y, o.z, o.w), msg.orientation_covariance[0])
        p = self._p
        with self._lock:
            gyr = self._gyro_input(stamp, gyr, acc)
            out = self.stream.on_imu(stamp, gyr, acc)
            if out is None:
                return
            convert.fill_imu(self._out, msg, out, p["angular_velocity_stddev"],
                             p["linear_acceleration_stddev"])
        self._frame_id = msg.header.frame_id
        self._pub.publish(self._out)
        self._published += 1
        self._extras(msg.header, out, p)

    def _check_orientation(self, quat_xyzw: Any, cov0: float) -> None:
        """One of the first IMU messages: does it carry an orientation (an estimator's output
        subscribed as raw data)? Logged once, and in /diagnostics from then on."""
        self._ori_checks -= 1
        if not self._carries_orientation and carries_orientation(quat_xyzw, cov0):
            self._carries_orientation = True
            self._warn_once("input-orientation", orientation_note(self._sub_imu.topic_name))

    def _input_problems(self) -> dict[str, str]:
        """Input that cannot give an orientation (see :meth:`StreamAdapter.input_problems`),
        by kind; call with the lock held."""
        acc = self._sub_acc.topic_name if self._sub_acc is not None else ""
        out = self.stream.input_problems(self._sub_imu.topic_name, acc)
        if self._carries_orientation:
            out["orientation"] = orientation_note(self._sub_imu.topic_name)
        return out

    def _on_accel(self, data: bytes) -> None:
        """Split input: one accelerometer message (its angular velocity ignored)."""
        if not self._active:
            return
        self.received_acc += 1
        try:
            h = rawmsg.parse(data, rawmsg.IMU_DOUBLES)
            if h is None:
                stamp, _, acc = convert.imu_to_arrays(deserialize_message(data, Imu))
            else:
                stamp, acc = h.stamp, rawmsg.imu_arrays(h)[1]
            with self._lock:
                if self._gyro_window is not None:
                    self._gyro_window.add_acc(acc)
                self.stream.on_accel(stamp, acc)
        except Exception as e:
            self._count_exception(e, "accelerometer callback")

    def _on_mag(self, data: bytes) -> None:
        if not self._active:
            return
        self.received_mag += 1
        try:
            self._last_mag_wall = time.monotonic()
            h = rawmsg.parse(data, rawmsg.MAG_DOUBLES)
            if h is None:
                stamp, m = convert.mag_to_array(deserialize_message(data, MagneticField))
            else:
                stamp, m = h.stamp, h.d[0:3]
            with self._lock:
                if self._mag_samples is not None and len(self._mag_samples) < \
                        calibration.MAX_MAG_SAMPLES:
                    self._mag_samples.append(np.array(m, dtype=float))
                self.stream.on_mag(stamp, m)
        except Exception as e:
            self._count_exception(e, "magnetometer callback")

    def _extras(self, header: Header, out: Any, p: dict[str, Any]) -> None:
        """TF and debug topics (message objects; only when enabled)."""
        if self._tf is not None and p["publish_tf"]:
            self._send_tf(self._tf, header, out.quat_wxyz, p)
        rpy_pub, bias_pub = self._rpy_pub, self._bias_pub  # created together
        if rpy_pub is not None and bias_pub is not None and p["publish_debug_topics"]:
            self._send_debug(rpy_pub, bias_pub, header, out)

    def _send_tf(self, tf: Any, header: Header, q: Any, p: dict[str, Any]) -> None:
        child = header.frame_id
        if not child:
            self._warn_once("tf-frame", "publish_tf: the IMU messages have no frame_id; "
                            "not publishing TF")
            return
        if p["reverse_tf"]:
            t = convert.transform(header.stamp, child, p["fixed_frame"], qconj_np(q))
        else:
            t = convert.transform(header.stamp, p["fixed_frame"], child, q)
        tf.sendTransform(t)

    def _send_debug(self, rpy_pub: Publisher, bias_pub: Publisher, header: Header,
                    out: Any) -> None:
        r = Vector3Stamped(header=header)
        r.vector.x, r.vector.y, r.vector.z = convert.rpy(out.quat_wxyz)
        rpy_pub.publish(r)
        b = Vector3Stamped(header=header)
        convert.set_vec(b.vector, out.bias)
        bias_pub.publish(b)

    # --- calibrations (docs/math.md §10; served from the ServiceThread) ------------------------
    def _set_gyro_offset(self) -> None:
        """``gyro_offset_*`` from the calibration parameters. Call with the lock held."""
        self._gyro_offset = np.array([self._cal[n] for n in calibration.GYRO_OFFSETS])
        self._gyro_offset_set = bool(self._gyro_offset.any())  # tested per message

    def _gyro_input(self, stamp: float, gyr: Any, acc: Any) -> Any:
        """The gyro sample for the filter: the raw one to a running ``~/calibrate_gyro``, minus
        ``gyro_offset_*`` to the filter. Call with the lock held."""
        if self._gyro_window is not None:
            self._gyro_window.add(stamp, gyr, None if self.stream.split else acc)
        if self._gyro_offset_set:
            return np.asarray(gyr, dtype=float) - self._gyro_offset
        return gyr

    def _on_calibrate_gyro(self, request: Trigger.Request, response: Trigger.Response
                           ) -> Trigger.Response:
        """Collect ``gyro_calibration_duration`` s of IMU samples (stamps), return when done;
        apply the mean gyro as ``gyro_offset_*`` unless the sensor moved (docs/math.md §10.2)."""
        from mkf_ros.core.gyrocal import rest_bias

        with self._lock:
            if not self._active:
                response.success = False
                response.message = "the node is not active: no IMU input to calibrate from"
                return response
            if self._gyro_window is not None:
                response.success = False
                response.message = "a gyro calibration is already running"
                return response
            duration = float(self._cal["gyro_calibration_duration"])
            window = self._gyro_window = calibration.GyroWindow(duration)
            wait = duration + float(self.stream.params["input_timeout"])
        self.get_logger().info(f"gyro calibration: collecting {duration:g} s at rest")
        complete = window.done.wait(timeout=wait)
        with self._lock:
            self._gyro_window = None
        try:
            if not complete:
                raise ValueError(f"gyro calibration: {duration:g} s of IMU data did not arrive on "
                                 f"{self._sub_imu.topic_name} within {wait:g} s")
            acc = np.array(window.acc) if window.acc else None
            res = rest_bias(np.array(window.gyr), acc,
                            max_gyro_stddev=self._cal["gyro_calibration_max_gyro_stddev"],
                            max_acc_stddev=self._cal["gyro_calibration_max_acc_stddev"])
            result = self.set_parameters([
                Parameter(n, Parameter.Type.DOUBLE, float(v))
                for n, v in zip(calibration.GYRO_OFFSETS, res.bias, strict=True)])
            refused = [r.reason for r in result if not r.successful]
            if refused:
                raise ValueError("gyro calibration not applied: " + "; ".join(refused))
        except ValueError as e:
            response.success = False
            response.message = str(e)
            self.get_logger().warning(response.message)
            return response
        response.success = True
        response.message = f"{res.summary()}; applied as gyro_offset_x/y/z"
        self.get_logger().info(response.message)
        return response

    def _on_calibrate_mag_start(self, request: Trigger.Request, response: Trigger.Response
                                ) -> Trigger.Response:
        with self._lock:
            restarted = self._mag_samples is not None
            self._mag_samples = []
        response.success = True
        response.message = (f"{'restarted' if restarted else 'started'} collecting "
                            f"{self._sub_mag.topic_name}: turn the sensor through every "
                            "orientation, then call calibrate_mag/finish")
        self.get_logger().info("magnetometer calibration: " + response.message)
        return response

    def _on_calibrate_mag_finish(self, request: Trigger.Request, response: Trigger.Response
                                 ) -> Trigger.Response:
        """Fit the collected samples (docs/math.md §10.1) and apply ``mag_bias_*`` and
        ``mag_soft_iron``; the filter then re-initialises (its learned field was the old
        calibration's)."""
        from mkf_ros.core.magcal import fit_ellipsoid

        with self._lock:
            samples, self._mag_samples = self._mag_samples, None
        try:
            if samples is None:
                raise ValueError("no magnetometer calibration running: call "
                                 "calibrate_mag/start first")
            cal = fit_ellipsoid(np.array(samples).reshape(-1, 3),
                                soft_iron=self._cal["mag_calibration_soft_iron"],
                                min_coverage=self._cal["mag_calibration_min_coverage"])
            values = cal.params()
            result = self.set_parameters_atomically([
                Parameter(k, value=v) for k, v in values.items()])
            if not result.successful:
                raise ValueError(f"magnetometer calibration not applied: {result.reason}")
        except ValueError as e:
            response.success = False
            response.message = str(e)
            self.get_logger().warning(response.message)
            return response
        with self._lock:
            self.stream.reset("magnetometer calibration applied")
        response.success = True
        response.message = ("; ".join(cal.summary().splitlines())
                            + "; applied as mag_bias_x/y/z, mag_soft_iron (filter re-initialised)")
        self.get_logger().info(response.message)
        return response

    def destroy_node(self) -> None:
        services = getattr(self, "_cal_services", None)
        if services is not None:
            services.close()
            self._cal_services = None
        super().destroy_node()

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        with self._lock:
            self.stream.reset("reset service")
        self.get_logger().info("reset requested: re-initialising from the next samples")
        response.success = True
        response.message = "filter reset; re-initialising from the next accelerometer sample"
        return response

    def _on_time_jump(self, jump: TimeJump) -> None:
        try:
            if jump.clock_change in (ClockChange.ROS_TIME_ACTIVATED,
                                     ClockChange.ROS_TIME_DEACTIVATED):
                why = "ROS time source changed (use_sim_time)"
            else:
                why = f"ROS time jumped back by {-jump.delta.nanoseconds * 1e-9:.3f} s"
            with self._lock:
                if self.stream.time is None:
                    return  # nothing to forget
                self.stream.reset(why)
            self.get_logger().info(f"{why}: filter reset")
        except Exception as e:
            self._count_exception(e, "time jump callback")

    def _on_timer(self) -> None:
        if not self._active:
            return
        try:
            now = time.monotonic()
            self._check_silence(now)
            with self._lock:
                problems = self._input_problems()
            for kind, text in problems.items():  # in the log once, in /diagnostics always
                self._warn_once(f"input-{kind}", text)
            if self.stream.params["diagnostics_period"] > 0:
                arr = DiagnosticArray()
                arr.header.stamp = self.get_clock().now().to_msg()
                arr.status = [self._diag.status(self.snapshot(now))]
                self._diag_pub.publish(arr)
        except Exception as e:
            self._count_exception(e, "diagnostics timer")

    def snapshot(self, now: float | None = None) -> Snapshot:
        """The node's state for diagnostics (and tests)."""
        with self._lock:
            s = self.stream
            f = s.filter
            return Snapshot(
                now=time.monotonic() if now is None else now, start=self._t_start,
                imu_topic=self._sub_imu.topic_name, mag_topic=self._sub_mag.topic_name,
                params=s.params, counters=s.all_counters(), published=self._published,
                exceptions=self._exceptions, last_exception=self._last_exception,
                last_imu=self._last_imu_wall, last_mag=self._last_mag_wall,
                initialized=f.initialized, heading_initialized=f.heading_initialized,
                cov=f.covariance if f.initialized else None, bias=f.bias,
                bias_stddev=f.bias_stddev, acc_norm=s.acc_norm, mag_norm=s.mag_norm,
                mag_offset=s.mag_offset, dt_stats=s.pop_dt_stats(),
                last_reset_reason=s.last_reset_reason, frame_id=self._frame_id,
                input_problems=self._input_problems())

    def _check_silence(self, now: float) -> None:
        """Log (not only diagnose) a silent input, once per silence."""
        timeout = self.stream.params["input_timeout"]
        for key, last, topic, needed in (
            ("imu", self._last_imu_wall, self._sub_imu.topic_name, True),
            ("mag", self._last_mag_wall, self._sub_mag.topic_name,
             self.stream.params["use_mag"]),
        ):
            silent = now - (last if last is not None else self._t_start)
            if needed and silent > timeout:
                kind = "Imu" if key == "imu" else "MagneticField"
                self._warn_once(f"silent-{key}-{last}", f"no data on {topic} for {silent:.0f} s "
                                f"(sensor_msgs/{kind}; driver running? topic remapped? QoS "
                                "compatible?)")

    # --- helpers -------------------------------------------------------------------------------
    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def _count_exception(self, e: BaseException, where: str) -> None:
        self._exceptions += 1
        self._last_exception = f"{where}: {type(e).__name__}: {e}"
        self.get_logger().error(self._last_exception, throttle_duration_sec=5.0)


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
  publishes   imu/data (sensor_msgs/Imu), /diagnostics; imu/rpy/filtered, imu/gyro_bias
              with publish_debug_topics; TF with publish_tf
  services    ~/reset, ~/calibrate_gyro (collects gyro_calibration_duration s at rest, applies
              gyro_offset_*), ~/calibrate_mag/start and ~/calibrate_mag/finish (fits and
              applies mag_bias_*, mag_soft_iron), all std_srvs/Trigger
examples:
  estimator --ros-args -p use_mag:=true -p world_frame:=ned
  estimator --ros-args -r __ns:=/imu_front -r imu/data_raw:=/camera/imu
  estimator --ros-args --params-file config/estimator.yaml
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
    kind = os.environ.get("MKF_ROS_EXECUTOR", DEFAULT_EXECUTOR)
    for a in plain:
        if a.startswith("--executor="):
            kind = a.split("=", 1)[1]
        else:
            print(f"{prog}: error: unknown argument {a!r} (ROS arguments go after "
                  "--ros-args; see --help)", file=sys.stderr)
            return 2
    if kind not in EXECUTORS:
        print(f"{prog}: error: executor must be one of {', '.join(EXECUTORS)}, "
              f"got {kind!r}", file=sys.stderr)
        return 2
    rclpy.init(args=args)
    executor = node = None
    code = 0
    try:
        executor = make_executor(kind)
        node = (node_class or EstimatorNode)()
        executor.add_node(node)
        node.get_logger().info(f"spinning with the {kind} executor")
        spin(executor)
    except ParameterError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # SIGTERM during start-up: the context is already shut down; nothing to report
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
