"""The ``estimator`` node: MEKF/MUKF attitude from ``imu/data_raw`` (+ ``imu/mag``) to ``imu/data``.

A drop-in replacement for imu_filter_madgwick (same topics, same names for the parameters that
mean the same thing; the differences: docs/migrating.md) and a thin rclpy wrapper around
:class:`mkf_ros.stream.adapter.StreamAdapter`, which holds every rule about time and input.
This module holds the node: its parameters, callbacks and diagnostics; beside it are its
calibration services (:mod:`.calibration`) and its console entry point
(:mod:`.estimator_main`: usage, executor, ``main``).

Topics (relative names: remap ``imu:=...`` to move them together, REP-145):

* subscribes ``imu/data_raw`` (sensor_msgs/Imu) and ``imu/mag`` (sensor_msgs/MagneticField,
  tesla), best-effort, keep last 200 (matches reliable and best-effort publishers); both are
  overridable with ``qos_overrides.<topic>.subscription.*``. The magnetometer is fused
  asynchronously and never gates the IMU. A message whose header stamp is zero (a driver that
  does not stamp) takes its receive time (the node's clock) as its stamp, in the filter and
  in the output, with one warning;
* publishes ``imu/data`` (sensor_msgs/Imu, reliable, keep last 100) once initialised, one
  message per accepted IMU message, with its header; ``/diagnostics`` (DiagnosticArray);
  with ``publish_debug_topics`` ``imu/rpy/filtered``, ``imu/rpy/raw`` (roll, pitch, yaw
  from the accelerometer and the magnetometer alone; with ``use_mag``), ``imu/gyro_bias``
  (geometry_msgs/Vector3Stamped) and ``imu/steady_state`` (std_msgs/Bool: the rest
  detector); TF with ``publish_tf`` when tf2_ros is importable;
* services ``~/reset``, ``~/calibrate_gyro``, ``~/calibrate_mag/start`` and
  ``~/calibrate_mag/finish`` (std_srvs/Trigger; the calibrations: :mod:`.calibration`,
  docs/math.md §10).

Every parameter of :data:`mkf_ros.core.params.PARAMS` is declared and can be changed at run
time through SetParameters (``ros2 param set``): validated in the on-set callback (a rejected
value leaves everything as it was and the caller sees the reason) and applied atomically,
between two messages, in the post-set callback. Parameters that would be ignored are named
at start-up (:func:`~mkf_ros.ros.parameters.unknown_overrides`,
:func:`~mkf_ros.ros.parameters.foreign_filter_rules`).

Speed: the hot path uses no rclpy message objects (raw CDR in and out, :mod:`.rawmsg`), and the
console script spins with the C++ EventsExecutor (docs/estimator.md, Executor and CPU).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
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
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.timer import Timer
from sensor_msgs.msg import Imu, MagneticField
from std_msgs.msg import Bool, Header
from std_srvs.srv import Trigger

from mkf_ros.core.params import BY_NAME, PARAMS
from mkf_ros.core.quaternion import qconj_np
from mkf_ros.core.state import COUNTER_NAMES
from mkf_ros.ros import calibration, convert, rawmsg
from mkf_ros.ros.diagnostics import DiagnosticsTracker, Snapshot
from mkf_ros.ros.parameters import (
    UnknownParameter,
    declare_all,
    declare_calibration,
    foreign_filter_rules,
    to_double,
    unknown_overrides,
)
from mkf_ros.ros.qos import input_qos, output_qos
from mkf_ros.stream.adapter import (
    INPUT_CHECK_MESSAGES,
    StreamAdapter,
    StreamOutput,
    carries_orientation,
    orientation_note,
)
from mkf_ros.stream.kernel import OF_WADD

_REST_UPDATES = COUNTER_NAMES.index("rest_updates")


class ParameterError(Exception):
    """An invalid start-up parameter (reported as one line; the node does not start)."""


class EstimatorNode(Node):
    """The attitude estimator node (see the module docstring).

    ``argv``: the command line whose ROS arguments the node was started with (default
    ``sys.argv``), searched for parameters addressed to another IMU filter's node name."""

    #: whether the node is managed (:class:`mkf_ros.ros.lifecycle.EstimatorLifecycleNode`)
    MANAGED = False

    def __init__(self, node_name: str = "estimator", *, warm: bool = True,
                 argv: Sequence[str] | None = None, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self._lock = threading.Lock()
        self._t_start = time.monotonic()
        self._configured = False
        self._active = not self.MANAGED  #: a managed node processes input only when active
        self._calib: calibration.CalibrationServices | None = None
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
        ros_args = [*(sys.argv if argv is None else argv), *(node_kwargs.get("cli_args") or [])]
        for text in foreign_filter_rules(ros_args, self.get_name(), self.get_namespace()):
            self.get_logger().warning(text)
        self.add_pre_set_parameters_callback(self._pre_set)
        self.add_on_set_parameters_callback(self._on_set)
        self.add_post_set_parameters_callback(self._post_set)
        if not self.MANAGED:
            self._configure()

    def _current_values(self) -> dict[str, Any]:
        """The node's current parameter values (filter, node and calibration)."""
        names = [p.name for p in PARAMS] + [p.name for p in calibration.CALIBRATION_PARAMS]
        return {p.name: p.value for p in self.get_parameters(names)}

    # --- configure / teardown ------------------------------------------------------------------
    def _configure(self) -> None:
        """Everything but the parameters: the filter from the current parameter values, the
        publishers, subscriptions, services and timers (the lifecycle's configure)."""
        values = self._current_values()
        self._cal = {k: v for k, v in values.items() if k in calibration.BY_NAME}
        with self._lock:
            self.stream = StreamAdapter({k: v for k, v in values.items() if k in BY_NAME})
        if self._warm:
            self._load_kernels()
        self._reset_node_state()
        self._make_endpoints()
        self._configured = True
        self._apply_node_side_effects()
        log = self.get_logger()
        for name, hint in unknown_overrides(self).items():
            log.warning(f"ignoring unknown parameter {name!r}: {hint}")
        p = self.stream.params
        log.info(
            f"{p['algorithm']} on chart {p['chart']}, world frame {p['world_frame']}, "
            f"use_mag {str(p['use_mag']).lower()}; listening on {self._sub_imu.topic_name} and "
            f"{self._sub_mag.topic_name}, publishing {self._pub.topic_name}")

    def _load_kernels(self, switch_to: str | None = None) -> None:
        """The streaming kernels (the node runs no others) of the configured algorithm at
        start, or of ``switch_to`` when the parameter changes to an algorithm the install did
        not compile (its own kernels are compiled on its first use, then cached)."""
        from mkf_ros.kernels import (
            FIRST_COMPILE_TIME,
            FIRST_USE_COMPILE_TIME,
            INSTALLED_ALGORITHMS,
            warmup,
        )

        log = self.get_logger()
        algo = switch_to or self.stream.params["algorithm"]
        installed = algo in INSTALLED_ALGORITHMS
        if switch_to is not None and installed:
            return  # loaded at start
        if switch_to is None:
            log.info("loading the filter kernels (compiled at install time; where that step "
                     f"did not run, the first start compiles them: {FIRST_COMPILE_TIME})...")
        if not installed:
            log.info(f"loading the kernels of algorithm {algo} (compiled on its first use: "
                     f"{FIRST_USE_COMPILE_TIME}, then cached)...")
        t0 = time.monotonic()
        warmup(("stream",), algorithms=(algo,))
        log.info(f"filter kernels ready in {time.monotonic() - t0:.1f} s")

    def _reset_node_state(self) -> None:
        """The counters and state owned by the node (the adapter has the rest)."""
        self._published = 0
        self.received_imu = self.received_mag = 0  #: messages taken from each subscription
        self.received_acc = 0  #: split input: messages taken from imu/accel
        self._exceptions = 0
        self._last_exception = ""
        self._last_imu_wall: float | None = None
        self._last_mag_wall: float | None = None
        self._last_imu_data: bytes | None = None  # the latest IMU message (frame_id)
        self._warned: set[str] = set()
        #: messages whose zero header stamp was replaced by the receive time, by input
        self.stamped_on_receipt = {"imu": 0, "acc": 0, "mag": 0}
        self._ori_checks = INPUT_CHECK_MESSAGES  # IMU messages left to check for an orientation
        self._carries_orientation = False
        self._out = Imu()
        self._encoder = rawmsg.ImuEncoder()
        self._tf: Any = None  # a tf2_ros.TransformBroadcaster once publish_tf is on
        self._debug: dict[str, Publisher] = {}  # publish_debug_topics: name -> publisher
        self._raw_rpy: StreamAdapter | None = None  # imu/rpy/raw's closed-form alignment
        self._last_mag: np.ndarray | None = None  # for imu/rpy/raw

    def _make_endpoints(self) -> None:
        """Publishers, subscriptions, services, the calibration services, the time-jump
        callback (the diagnostics timer follows the parameters: _apply_node_side_effects)."""
        qos_opts = QoSOverridingOptions.with_default_policies
        self._pub = self._make_output_publisher()
        # input_mode split: the gyro drives the stream (and the output), the accelerometer is
        # fused at its own stamps (RealSense: -r imu/gyro:=camera/gyro/sample
        # -r imu/accel:=camera/accel/sample)
        split = self.stream.split
        self._sub_imu = self.create_subscription(Imu, "imu/gyro" if split else "imu/data_raw",
                                                 self._on_imu, input_qos(),
                                                 qos_overriding_options=qos_opts(), raw=True)
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
        self._calib = calibration.CalibrationServices(self, self._sub_imu.topic_name,
                                                      self._sub_mag.topic_name)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = None
        # a ROS-time jump back (bag loop with /clock) or a switch to/from sim time resets
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True),
            post_callback=self._on_time_jump)

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
        if self._calib is not None:
            self._calib.close()
            self._calib = None
        if self._timer is not None:
            self.destroy_timer(self._timer)
        self._timer = None
        self._jump_handle.unregister()
        for sub in (self._sub_imu, self._sub_acc, self._sub_mag):
            if sub is not None:
                self.destroy_subscription(sub)
        self._destroy_output_publisher(self._pub)
        for pub in (self._diag_pub, *self._debug.values()):
            self.destroy_publisher(pub)
        self._debug = {}
        self.destroy_service(self._srv_reset)
        self._tf = None

    def destroy_node(self) -> None:
        calib = getattr(self, "_calib", None)
        if calib is not None:
            calib.close()
            self._calib = None
        super().destroy_node()

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
                if self._calib is not None:
                    self._calib.update_offset()
            self._log_changes(cal)
        changes = {p.name: p.value for p in params if p.name in BY_NAME}
        if not changes:
            return
        try:
            if "algorithm" in changes:
                self._load_kernels(changes["algorithm"])
            with self._lock:
                self.stream.set_params(**changes)
        except Exception as e:  # validated already: would be a bug; never kill the node
            self._count_exception(e, "applying parameters")
            return
        self._apply_node_side_effects(changes)
        self._log_changes(changes)

    def _log_changes(self, changes: dict[str, Any]) -> None:
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{k}={v!r}" for k, v in changes.items()))

    def _apply_node_side_effects(self, changes: dict[str, Any] | None = None) -> None:
        """What the node parameters change outside the adapter: the diagnostics timer, the TF
        broadcaster, the debug publishers."""
        self._p = p = self.stream.params
        self._extras_on = False
        self._stddevs = (p["angular_velocity_stddev"], p["linear_acceleration_stddev"])
        if not self._configured:
            return  # applied by the lifecycle's configure
        if changes is None or "diagnostics_period" in changes:
            self._make_timer()
        if p["publish_tf"] and self._tf is None:
            try:
                import tf2_ros  # a real ROS install has it (package.xml); no pip wheel
            except ImportError:
                self._warn_once("tf", "publish_tf is true but tf2_ros cannot be imported "
                                "(install ros-jazzy-tf2-ros); not publishing TF")
            else:
                self._tf = tf2_ros.TransformBroadcaster(self)
        if p["publish_debug_topics"] and not self._debug:
            self._debug = {
                "rpy": self.create_publisher(Vector3Stamped, "imu/rpy/filtered", 10),
                "rpy_raw": self.create_publisher(Vector3Stamped, "imu/rpy/raw", 10),
                "bias": self.create_publisher(Vector3Stamped, "imu/gyro_bias", 10),
                "steady": self.create_publisher(Bool, "imu/steady_state", 10),
            }
        self._raw_rpy = None  # rebuilt from the current parameters when next needed
        # read per message: whether TF or debug topics go out, the REP-145 fill values
        self._extras_on = bool((p["publish_tf"] and self._tf is not None)
                               or (p["publish_debug_topics"] and self._debug))
        self._stddevs = (p["angular_velocity_stddev"], p["linear_acceleration_stddev"])

    def _make_timer(self) -> None:
        if self._timer is not None:
            self.destroy_timer(self._timer)
        period = float(self.stream.params["diagnostics_period"]) or 1.0
        self._timer = self.create_timer(period, self._on_timer, clock=self._steady)

    # --- callbacks -----------------------------------------------------------------------------
    def _receive_time(self, kind: str, topic: str) -> tuple[int, int]:
        """``(sec, nanosec)`` now, for a message without a stamp (zero); warns once."""
        self.stamped_on_receipt[kind] += 1
        self._warn_once(f"stamp-{kind}", f"the messages on {topic} have a zero header stamp "
                        "(the driver does not stamp them): using their receive time (this "
                        "node's clock) as their stamp, in the filter and in the header of "
                        "what is published for them")
        sec, nsec = divmod(self.get_clock().now().nanoseconds, 1_000_000_000)
        return sec, nsec

    def _on_imu(self, data: bytes) -> None:
        """Serialized Imu in (``raw=True``), serialized Imu out: no message objects and no
        numpy on the fast path (see :mod:`mkf_ros.ros.rawmsg`)."""
        if not self._active:
            return  # a managed node that is not active takes no input
        self.received_imu += 1
        try:
            self._last_imu_wall = time.monotonic()
            m = rawmsg.unpack_imu(data)
            if m is None:  # not little-endian CDR: message objects
                self._on_imu_msg(deserialize_message(data, Imu))
                return
            sec, nsec, off, gyr, acc = m
            prefix = None
            if sec == 0 and nsec == 0:
                sec, nsec = self._receive_time("imu", self._sub_imu.topic_name)
                prefix = rawmsg.restamped_prefix(data, off, sec, nsec)
            if self._ori_checks:
                d = rawmsg.doubles(data, off)
                self._check_orientation(d[rawmsg.Q:rawmsg.Q + 4], d[rawmsg.QC])
            self._last_imu_data = data
            stamp = sec + nsec * 1e-9
            extras = self._extras_on
            with self._lock:
                stream, calib = self.stream, self._calib
                if calib is not None and (calib.window is not None or calib.offset_set):
                    gyr = calib.gyro_input(stamp, gyr, acc, stream.split)
                rest0 = stream.filter.counters[_REST_UPDATES] if extras else 0
                rawmsg.pack_imu_event(stream.imu_event_bytes, stamp, gyr, acc)
                flags = stream.run_imu_event()
                if not flags:
                    return
                payload = self._encode(data, off, flags, sec, nsec, prefix)
                if extras:
                    out = stream.last_output()
                    at_rest = bool(stream.filter.counters[_REST_UPDATES] > rest0)
            self._pub.publish(payload)
            self._published += 1
            if extras:
                self._extras(Header(stamp=Time(sec=sec, nanosec=nsec),
                                    frame_id=rawmsg.frame_id(data)), out, self._p, acc, at_rest)
        except Exception as e:
            self._count_exception(e, "imu callback")

    def _encode(self, data: bytes, off: int, flags: int, sec: int, nsec: int,
                prefix: bytes | None) -> bytes:
        """``imu/data``'s bytes for the estimate in the adapter's output record (lock held)."""
        av_sd, la_sd = self._stddevs
        if flags & OF_WADD:  # the bias-corrected rate: its covariance changes every sample
            h = rawmsg.RawHeader(data, rawmsg.IMU_DOUBLES)
            if prefix is not None:
                h.restamp(sec, nsec)
            return self._encoder.encode_values(h, self.stream.output_values, flags, av_sd,
                                               la_sd)
        return self._encoder.encode_record(data, off, self.stream.output_bytes, flags, av_sd,
                                           la_sd, prefix)

    def _on_imu_msg(self, msg: Imu) -> None:
        """The same with message objects (inputs that are not little-endian CDR)."""
        if msg.header.stamp.sec == 0 and msg.header.stamp.nanosec == 0:
            sec, nsec = self._receive_time("imu", self._sub_imu.topic_name)
            msg.header.stamp = Time(sec=sec, nanosec=nsec)
        stamp, gyr, acc = convert.imu_to_arrays(msg)
        if self._ori_checks:
            o = msg.orientation
            self._check_orientation((o.x, o.y, o.z, o.w), msg.orientation_covariance[0])
        p = self._p
        with self._lock:
            if self._calib is not None:
                gyr = self._calib.gyro_input(stamp, gyr, acc, self.stream.split)
            rest0 = self.stream.filter.counters[_REST_UPDATES]
            out = self.stream.on_imu(stamp, gyr, acc)
            if out is None:
                return
            at_rest = bool(self.stream.filter.counters[_REST_UPDATES] > rest0)
            convert.fill_imu(self._out, msg, out, p["angular_velocity_stddev"],
                             p["linear_acceleration_stddev"])
        self._last_imu_data = serialize_message(msg.header)  # its frame_id, for diagnostics
        self._pub.publish(self._out)
        self._published += 1
        self._extras(msg.header, out, p, acc, at_rest)

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
                msg = deserialize_message(data, Imu)
                stamp, _, acc = convert.imu_to_arrays(msg)
            else:
                stamp, acc = h.stamp, rawmsg.imu_arrays(h)[1]
            if stamp == 0.0:
                sec, nsec = self._receive_time("acc", self._sub_acc.topic_name
                                               if self._sub_acc is not None else "imu/accel")
                stamp = sec + nsec * 1e-9
            with self._lock:
                if self._calib is not None:
                    self._calib.add_accel(acc)
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
            if stamp == 0.0:
                sec, nsec = self._receive_time("mag", self._sub_mag.topic_name)
                stamp = sec + nsec * 1e-9
            with self._lock:
                if self._calib is not None:
                    self._calib.add_mag(m)
                if self._debug:
                    self._last_mag = np.array(m, dtype=float)
                self.stream.on_mag(stamp, m)
        except Exception as e:
            self._count_exception(e, "magnetometer callback")

    # --- TF and debug topics (message objects; only when enabled) ------------------------------
    def _extras(self, header: Header, out: StreamOutput, p: dict[str, Any], acc: Any,
                at_rest: bool) -> None:
        if self._tf is not None and p["publish_tf"]:
            self._send_tf(self._tf, header, out.quat, p)
        if self._debug and p["publish_debug_topics"]:
            self._send_debug(header, out, p, acc, at_rest)

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

    def _send_debug(self, header: Header, out: StreamOutput, p: dict[str, Any], acc: Any,
                    at_rest: bool) -> None:
        """``imu/rpy/filtered``, ``imu/rpy/raw`` (with ``use_mag``, once a magnetometer sample
        came), ``imu/gyro_bias``, ``imu/steady_state``."""
        pubs = self._debug
        r = Vector3Stamped(header=header)
        r.vector.x, r.vector.y, r.vector.z = convert.rpy(out.quat)
        pubs["rpy"].publish(r)
        q_raw = self._raw_orientation(header, acc) if p["use_mag"] else None
        if q_raw is not None:
            r = Vector3Stamped(header=header)
            r.vector.x, r.vector.y, r.vector.z = convert.rpy(q_raw)
            pubs["rpy_raw"].publish(r)
        b = Vector3Stamped(header=header)
        convert.set_vec(b.vector, out.bias)
        pubs["bias"].publish(b)
        pubs["steady"].publish(Bool(data=at_rest))

    def _raw_orientation(self, header: Header, acc: Any) -> np.ndarray | None:
        """The orientation from this accelerometer sample and the latest magnetometer sample
        alone, as ``imu/data`` would publish it (world frame, yaw offset, calibration): the
        filter's closed-form alignment of a fresh filter (docs/math.md, initialisation).
        None without both readings or when they give no orientation (free fall, implausible
        magnitude, field along gravity)."""
        m = self._last_mag
        if acc is None or m is None:
            return None
        if self._raw_rpy is None:
            self._raw_rpy = StreamAdapter({**self.stream.params, "algorithm": "mekf",
                                           "input_mode": "imu", "constant_dt": 0.0})
        s = self._raw_rpy
        s.reset("imu/rpy/raw")
        t = header.stamp.sec + header.stamp.nanosec * 1e-9
        s.on_mag(t, m)
        est = s.on_imu(t, (0.0, 0.0, 0.0), acc)
        if est is None or not est.heading_initialized:
            return None
        return est.quat

    # --- services, time, diagnostics -----------------------------------------------------------
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
            extra = {f"stamped on receipt ({k})": str(v)
                     for k, v in self.stamped_on_receipt.items() if v}
            return Snapshot(
                now=time.monotonic() if now is None else now, start=self._t_start,
                imu_topic=self._sub_imu.topic_name, mag_topic=self._sub_mag.topic_name,
                params=s.params, counters=s.all_counters(), published=self._published,
                exceptions=self._exceptions, last_exception=self._last_exception,
                last_imu=self._last_imu_wall, last_mag=self._last_mag_wall,
                initialized=f.initialized, heading_initialized=f.heading_initialized,
                cov=f.covariance if f.initialized else None, bias=f.bias,
                bias_stddev=f.bias_std, acc_norm=s.acc_norm, mag_norm=s.mag_norm,
                mag_offset=s.mag_offset, dt_stats=s.pop_dt_stats(),
                last_reset_reason=s.last_reset_reason, frame_id=self._frame_id(),
                extra=extra, input_problems=self._input_problems())

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
    def _frame_id(self) -> str:
        """The frame_id of the latest IMU message (decoded when asked, not per message)."""
        data = self._last_imu_data
        return "" if data is None else rawmsg.frame_id(data)

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def _count_exception(self, e: BaseException, where: str) -> None:
        self._exceptions += 1
        self._last_exception = f"{where}: {type(e).__name__}: {e}"
        self.get_logger().error(self._last_exception, throttle_duration_sec=5.0)
