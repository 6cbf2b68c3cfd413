"""The one definition of every parameter (name, type, default, unit, range, description).

The offline API keywords (:func:`mkf_ros.estimate`), the ROS parameter declarations of the
nodes, the commented YAML in ``config/`` and the ``mkf`` CLI flags are all generated from
:data:`PARAMS`, so they cannot drift apart. ``scope`` says who uses a parameter: ``filter``
parameters reach the core filter (and therefore every front end); ``node`` parameters only
concern the ROS node.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Param:
    """Definition of one parameter."""

    name: str
    type: type  # bool, int, float, str or list (of floats)
    default: Any
    description: str
    unit: str = ""
    choices: tuple[str, ...] | None = None
    range: tuple[float, float] | None = None  # inclusive
    scope: str = "filter"  # "filter" or "node"
    group: str = "filter"
    length: int | None = None  # for lists
    read_only: bool = False

    def doc(self) -> str:
        """One line: description, unit, range or choices (used by YAML, ROS and CLI help)."""
        parts = [self.description]
        if self.unit:
            parts.append(f"[{self.unit}]")
        if self.choices:
            parts.append("one of: " + ", ".join(self.choices))
        if self.range:
            parts.append(f"range {_fmt(self.range[0])} .. {_fmt(self.range[1])}")
        return " ".join(parts)

    def validate(self, value: Any) -> Any:
        """Return ``value`` coerced to the parameter's type, or raise a one-line ValueError."""
        n = self.name
        if self.type is bool:
            # numpy's booleans too (a numpy bool from an array is a bool)
            if isinstance(value, (bool, np.bool_)):
                return bool(value)
            if isinstance(value, str) and value.lower() in ("true", "false"):
                return value.lower() == "true"
            raise ValueError(f"{n} must be true or false, got {value!r}")
        if self.type is str:
            if not isinstance(value, str):
                raise ValueError(f"{n} must be a string, got {value!r}")
            v = value.strip().lower() if self.choices else value  # frame ids keep their case
            if self.choices and v not in self.choices:
                raise ValueError(f"{n} must be one of {', '.join(self.choices)}, got {value!r}")
            return v
        if self.type in (int, float):
            if isinstance(value, (bool, np.bool_)):  # float(True) is 1.0: not a number here
                raise ValueError(f"{n} must be a number, got {value!r}")
            if not isinstance(value, (int, float)):
                try:
                    value = float(value) if self.type is float else int(value)
                except (TypeError, ValueError):
                    raise ValueError(f"{n} must be a number, got {value!r}") from None
            num = self.type(value)
            if not math.isfinite(num):
                raise ValueError(f"{n} must be finite, got {value!r}")
            if self.range and not (self.range[0] <= num <= self.range[1]):
                raise ValueError(
                    f"{n} must be in [{_fmt(self.range[0])}, {_fmt(self.range[1])}]"
                    f"{' ' + self.unit if self.unit else ''}, got {value!r}"
                )
            return num
        if self.type is list:
            # a string is iterable, but "123" is not [1, 2, 3]; nor is True a number
            if isinstance(value, (str, bytes)) or any(
                    isinstance(x, (bool, np.bool_, str, bytes)) for x in _iter(value)):
                raise ValueError(f"{n} must be a list of numbers, got {value!r}")
            try:
                vals = [float(x) for x in value]
            except (TypeError, ValueError):
                raise ValueError(f"{n} must be a list of numbers, got {value!r}") from None
            if self.length is not None and len(vals) != self.length:
                raise ValueError(f"{n} must have {self.length} elements, got {len(vals)}")
            if not all(math.isfinite(x) for x in vals):
                raise ValueError(f"{n} must contain finite numbers, got {value!r}")
            if self.range and not all(self.range[0] <= x <= self.range[1] for x in vals):
                raise ValueError(
                    f"{n} elements must be in [{_fmt(self.range[0])}, {_fmt(self.range[1])}], "
                    f"got {value!r}"
                )
            return vals
        raise TypeError(f"unsupported parameter type {self.type}")  # pragma: no cover


def _iter(value: Any) -> list:
    """The elements of ``value`` if it is a sequence (else none: float() judges it)."""
    try:
        return list(value)
    except TypeError:
        return []


def _fmt(x: float) -> str:
    return f"{x:g}"


#: The paper's filters, then the seed report's baselines (mkf_ros.core.baselines,
#: docs/baselines.md).
ALGORITHMS = ("mekf", "mukf", "euler_kf", "euler_ukf", "madgwick")
#: The baselines among them (no smoother; their kernels compiled on first use,
#: :mod:`mkf_ros.kernels`).
BASELINE_ALGORITHMS = ALGORITHMS[2:]
WORLD_FRAMES = ("enu", "ned", "nwu")
#: The smoother's forms (``estimate(smooth=...)``, ``mkf process --smooth``, docs/math.md §11):
#: the forward RTS smoother, or it fused with the same smoother run over the reversed recording
#: (§11.5).
SMOOTH_MODES = ("rts", "two-way")

_P = Param
PARAMS: tuple[Param, ...] = (
    # --- filter and chart (docs/math.md §5, §6, §2) -----------------------------------------------
    _P("algorithm", str, "mekf", "Filter: Manifold EKF (§5) or Manifold UKF (§6); baselines "
       "(docs/baselines.md): Euler-angle KF, Euler-angle UKF, Madgwick", choices=ALGORITHMS),
    _P("chart", str, "rp", "Chart of the error state: orthographic, Rodrigues parameters, "
       "modified Rodrigues parameters, rotation vector (§2)", choices=("o", "rp", "mrp", "rv")),
    _P("chart_update", bool, True, "Move the covariance to the chart of the updated estimate "
       "(paper eq. 47b); false = the classic reset"),
    _P("mukf_w0", float, 1.0 / 25.0, "MUKF weight of the central sigma point W_0 (§6)",
       unit="1", range=(1e-3, 0.99)),
    _P("mukf_noise_scaling", str, "integrated", "MUKF angular-velocity noise (§8 item 3): "
       "'consistent' grows the rate variance by Q_w*dt; 'published' by Q_w*dt^2 as in the "
       "paper's figures; 'integrated' (extension) also rotates each step with the mean rate of "
       "the Wiener process, giving the attitude the MEKF's Q_w*dt^3/3 and an honest covariance",
       choices=("consistent", "published", "integrated")),
    # --- frames and sensors -----------------------------------------------------------------
    _P("world_frame", str, "enu", "World frame of the published orientation (REP-103/145)",
       choices=WORLD_FRAMES, group="frames"),
    _P("use_mag", bool, False, "Fuse the magnetometer for heading; without it yaw is relative "
       "to the start-up heading", group="frames"),
    _P("mag_reference", list, [0.0, 0.0, 0.0], "Earth field direction in the world frame "
       "(any unit); all zeros = learn it from the first magnetometer samples", length=3,
       range=(-1e6, 1e6), group="frames"),
    _P("gravity", float, 9.80665, "Magnitude of gravity, to express accelerometer noise "
       "relative to it", unit="m/s^2", range=(1.0, 100.0), group="frames"),
    # --- noise model (docs/math.md §4) ------------------------------------------------------------
    _P("gyro_noise", float, 0.01, "Gyroscope white noise per sample (sqrt of R_w)",
       unit="rad/s", range=(1e-6, 10.0), group="noise"),
    _P("acc_noise", float, 0.05, "Accelerometer white noise per sample (sqrt of R_v)",
       unit="m/s^2", range=(1e-6, 100.0), group="noise"),
    _P("acc_disturbance", float, 0.6, "Non-gravitational acceleration expected "
       "(sqrt of Q_v, external disturbance)", unit="m/s^2", range=(0.0, 100.0), group="noise"),
    _P("mag_noise", float, 0.02, "Magnetometer white noise per sample, relative to the field "
       "magnitude", unit="1", range=(1e-6, 10.0), group="noise"),
    _P("mag_disturbance", float, 0.1, "Magnetic disturbance expected, relative to the field "
       "magnitude (indoors the undisturbed field differs by 10-25 % from place to place)",
       unit="1", range=(0.0, 10.0), group="noise"),
    _P("rate_process_noise", float, 20.0, "Power spectral density Q_w of the angular "
       "acceleration driving the constant-rate model (§4.2)", unit="rad^2/s^3",
       range=(1e-9, 1e9), group="noise"),
    _P("estimate_gyro_bias", bool, True, "Estimate a gyro bias in the state (extension)",
       group="noise"),
    _P("gyro_bias_noise", float, 1e-4, "Random walk of the gyro bias (sqrt of its PSD)",
       unit="rad/s/sqrt(s)", range=(0.0, 1.0), group="noise"),
    _P("gyro_bias_stddev", float, 0.02, "Initial uncertainty of the gyro bias, the Kalman "
       "prior (a calibrated MEMS gyro: about 1 deg/s; evidence in motion moves the bias "
       "against it, a rest learns a turn-on bias up to 0.05 rad/s in seconds)",
       unit="rad/s", range=(1e-9, 1.0), group="noise"),
    # --- disturbances and calibration (extensions for real sensors) --------------------------
    _P("acc_time_constant", float, 0.8, "The accelerometer is low-passed in an almost "
       "inertial frame before it corrects the tilt (extension): two first-order stages with "
       "this time constant whose memory turns with the body by the gyro. Gravity passes "
       "however the body turns; shaking, vibration and other non-gravitational acceleration "
       "(the derivative of a bounded velocity) average out. 0 = every raw sample (the paper)",
       unit="s", range=(0.0, 100.0), group="robustness"),
    _P("acc_bias_excess", float, 0.3, "Under sustained non-gravitational acceleration "
       "(running, a vehicle) the gyro bias learns from the accelerometer at the weight "
       "1/(1 + E/e^2), E the recent excess power of the accelerometer's magnitude "
       "((|a|/g - 1)^2, low-passed over acc_time_constant) and e this value: what the "
       "low-pass leaves of that acceleration is correlated with the motion over the times the "
       "bias integrates, and a full Kalman gain on the bias would follow it (a partial-update "
       "Schmidt-Kalman filter: only the bias's gain is scaled, its covariance follows by the "
       "Joseph form); 0 = the full gain always", unit="1", range=(0.0, 100.0),
       group="robustness"),
    _P("mag_bias_gain", float, 0.3, "The magnetometer's heading update moves the gyro bias "
       "at this share of its Kalman gain (a partial-update Schmidt-Kalman filter, as "
       "acc_bias_excess; its covariance follows by the Joseph form): a magnetic disturbance "
       "correlated over mag_disturbance_time turns the heading like a gyro bias would, and a "
       "full gain on the bias follows it and then turns the heading for as long as the field "
       "is refused; 1 = the full gain", unit="1", range=(0.0, 1.0), group="robustness"),
    _P("acc_turn_speed", float, 0.0, "Forward speed of the body while it turns (a vehicle, "
       "a walking or running person): turning at the vertical rate W it feels a centripetal "
       "acceleration v*W across gravity for as long as the turn lasts, which no averaging "
       "removes; the accelerometer's disturbance variance grows by (v*W/g)^2 (W low-passed "
       "over acc_time_constant, correlated over it), so that the gyro carries the tilt through "
       "the turn. 0 = the body turns in place (a handheld sensor); a person walking or "
       "running: 1.5-3 (phones carried by two people: 2 lowers each one's tilt error by an "
       "eighth, docs/real_data.md); a car: its speed",
       unit="m/s", range=(0.0, 100.0), group="robustness"),
    _P("acc_disturbance_time", float, 0.1, "Correlation time of the non-gravitational "
       "acceleration left in the fused accelerometer: its per-sample variance is "
       "acc_disturbance^2 * max(1, time/dt), so that its information per second does not grow "
       "with the sample rate; 0 = independent per sample (the paper)", unit="s",
       range=(0.0, 100.0), group="noise"),
    _P("acc_alignment_error", float, 0.0175, "Misalignment and calibration error of the "
       "accelerometer's axes against the body's (constant and unobservable: no filter "
       "averages it out); added to the published tilt variance only (default 1 deg)",
       unit="rad", range=(0.0, 0.5), group="noise"),
    _P("gyro_scale_error", float, 0.013, "Relative scale and axis-alignment error of the "
       "gyroscope: attitude noise (error * |w|)^2 * dt per step for the net rotation (the rate "
       "low-passed over acc_time_constant) and 0.3 of it for the rest (a swing back and forth "
       "turns the error one way and back), so that the covariance grows while the body turns; "
       "it also widens the magnetometer consistency test; 0 = off "
       "(the paper)", unit="1", range=(0.0, 1.0), group="noise"),
    _P("acc_mode", str, "tilt", "'tilt': the accelerometer corrects roll and pitch only and can "
       "never move heading or the vertical rate and bias (extension: gravity carries no heading "
       "information); 'vector': the paper's full vector measurement",
       choices=("tilt", "vector"), group="robustness"),
    _P("mag_mode", str, "heading", "'heading': the magnetometer corrects heading only and can "
       "never tilt the estimate (extension); 'vector': the paper's full vector measurement",
       choices=("heading", "vector"), group="robustness"),
    _P("mag_time_constant", float, 1.0, "Memory of the magnetometer consistency test: the "
       "field is low-passed in the same almost inertial frame as the accelerometer; a magnet on "
       "the body or a field that changes along the path disagrees with it", unit="s",
       range=(1e-3, 100.0), group="robustness"),
    _P("mag_consistency_tolerance", float, 0.15, "Magnetometer samples that differ from that "
       "low-passed field by more than this fraction of the field (plus the gyro scale error "
       "over the rotation in its memory) are not fused", unit="1", range=(0.0, 1000.0),
       group="robustness"),
    _P("mag_disturbance_time", float, 3.0, "Correlation time of the magnetometer's heading "
       "error (calibration, the local field: indoors it changes over metres, seconds at "
       "walking speed): the heading variance per sample is the noise's times max(1, time/dt); "
       "0 = independent per sample", unit="s", range=(0.0, 100.0),
       group="noise"),
    _P("mag_norm_tolerance", float, 0.1, "Magnetometer samples whose magnitude differs from the "
       "learned field by more than this fraction are not fused", unit="1", range=(0.0, 1000.0),
       group="robustness"),
    _P("mag_new_time", float, 10.0, "A field of another magnitude than the learned one "
       "(another room, a rebar floor, the start of a recording near metal) that stays "
       "consistent with the gyro and with itself for this long while the body turns becomes "
       "the new reference; 0 = never", unit="s", range=(0.0, 3600.0), group="robustness"),
    _P("mag_new_first_time", float, 2.0, "As mag_new_time for the first new field since the "
       "start: the reference learned from the first samples is the least trusted", unit="s",
       range=(0.0, 3600.0), group="robustness"),
    _P("rest_detection", bool, True, "Detect rest and fuse a zero angular velocity, which "
       "sharpens the gyro bias (never the attitude): the gyro and the accelerometer steady "
       "within the thresholds of their 0.5 s low-pass, and the low-passed rate explained by "
       "the bias estimate (chi-square), for rest_time", group="robustness"),
    _P("rest_gyro_threshold", float, 0.035, "Rest: the gyro within this of its low-pass",
       unit="rad/s", range=(0.0, 10.0), group="robustness"),
    _P("rest_acc_threshold", float, 0.2, "Rest: the accelerometer within this of its low-pass",
       unit="m/s^2", range=(0.0, 100.0), group="robustness"),
    _P("rest_time", float, 1.0, "Rest: the conditions held for this long", unit="s",
       range=(0.0, 3600.0), group="robustness"),
    _P("rest_rate_stddev", float, 0.005, "Standard deviation of the zero-rate measurement at "
       "rest", unit="rad/s", range=(1e-6, 1.0), group="robustness"),
    _P("mag_bias_x", float, 0.0, "Hard-iron offset subtracted from the magnetometer x reading "
       "(same unit as the magnetometer: T for ROS)", unit="mag unit", range=(-1e6, 1e6),
       group="calibration"),
    _P("mag_bias_y", float, 0.0, "Hard-iron offset subtracted from the magnetometer y reading",
       unit="mag unit", range=(-1e6, 1e6), group="calibration"),
    _P("mag_bias_z", float, 0.0, "Hard-iron offset subtracted from the magnetometer z reading",
       unit="mag unit", range=(-1e6, 1e6), group="calibration"),
    _P("mag_soft_iron", list, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "Soft-iron "
       "matrix S (row-major) applied after the hard-iron offset: m = S (m_raw - bias)",
       length=9, range=(-1e6, 1e6), group="calibration"),
    # --- baselines (docs/baselines.md): used only by algorithm euler_kf, euler_ukf, madgwick ------
    _P("madgwick_beta", float, 0.041, "Madgwick gain beta: gyro error as the magnitude of a "
       "quaternion derivative (Madgwick 2010 recommends 0.041 for 9D, 0.033 for 6D; "
       "imu_filter_madgwick's 'gain' defaults to 0.1)", unit="rad/s", range=(0.0, 10.0),
       group="baselines"),
    _P("madgwick_stddev", float, 0.05, "Madgwick has no covariance: this fixed standard "
       "deviation is published about each world axis (in 6D the heading's grows from it with "
       "the integrated gyro noise)", unit="rad", range=(1e-4, 3.15), group="baselines"),
    _P("gimbal_lock_pitch", float, 1.3963, "Euler-angle baselines: samples whose estimated "
       "|pitch| exceeds this are counted as gimbal_lock (near +-90 deg the Euler-rate matrix "
       "is singular; default 80 deg)", unit="rad", range=(0.0, 1.5708), group="baselines"),
    # --- initialisation and time -------------------------------------------------------------
    _P("init_mode", str, "align", "'align': closed-form attitude from the first accelerometer "
       "(+ magnetometer) sample; 'paper': identity with P0 = 100 I as in the paper's study",
       choices=("align", "paper"), group="time"),
    _P("max_dt", float, 0.5, "A gap between samples longer than this re-aligns roll and pitch "
       "(and heading with a magnetometer) instead of integrating the rate across it (a step "
       "below 1e-9 s is a repeated instant)",
       unit="s", range=(1e-4, 3600.0), group="time"),
    # ============================================================================================
    # scope "node": the streaming front end (mkf_ros.stream) and the ROS node only. Names follow
    # imu_filter_madgwick where the meaning is the same (drop-in). Owned by the estimator node.
    # ============================================================================================
    # --- node: input and time -------------------------------------------------------------------
    _P("constant_dt", float, 0.0, "Time step used for every IMU sample instead of the header "
       "stamps; 0 = use the stamps (imu_filter_madgwick name); below 1e-9 s a step is a "
       "repeated instant (no prediction)", unit="s", range=(0.0, 10.0),
       scope="node", group="node: input and time"),
    _P("time_jump_threshold", float, 1.0, "An IMU stamp this much older than the previous one "
       "(bag loop, clock reset) resets the filter; smaller steps back are dropped as out of "
       "order (10 in a row also reset)", unit="s", range=(0.0, 1e6), scope="node",
       group="node: input and time"),
    _P("mag_max_delay", float, 0.1, "A magnetometer sample up to this much older than the "
       "latest IMU sample is still fused (rotated forward by the estimated rate); older ones "
       "are dropped", unit="s", range=(0.0, 10.0), scope="node", group="node: input and time"),
    _P("input_mode", str, "imu", "'imu': one sensor_msgs/Imu stream carrying the gyro and the "
       "accelerometer in every message (imu/data_raw); 'split': separate accelerometer and "
       "gyroscope streams of sensor_msgs/Imu (imu/accel and imu/gyro; Intel RealSense "
       "accel/sample and gyro/sample, each message's other vector ignored): the gyro drives "
       "the prediction and the output (one message per gyro message, with its header), each "
       "accelerometer sample is fused at its own stamp", choices=("imu", "split"),
       scope="node", group="node: input and time", read_only=True),
    _P("acc_max_delay", float, 0.1, "Split input: an accelerometer sample up to this much "
       "older than the latest gyro sample is still fused (rotated forward by the estimated "
       "rate); older ones are dropped", unit="s", range=(0.0, 10.0), scope="node",
       group="node: input and time"),
    _P("acc_magnitude_tolerance", float, 0.5, "Plausibility check before the filter: "
       "accelerometer samples whose magnitude differs from gravity by more than this fraction "
       "(gravity removed? units of g?) never reach the filter, not even to initialise; the "
       "filter weighs the rest by their magnitude's distance from gravity", unit="1",
       range=(0.01, 1000.0), scope="node", group="node: input and time"),
    # --- node: output -----------------------------------------------------------------------------
    _P("angular_velocity_source", str, "input", "angular_velocity published in imu/data: the "
       "input gyro as received, the input minus the estimated gyro bias, or the filter's "
       "rate estimate", choices=("input", "bias_corrected", "estimate"), scope="node",
       group="node: output"),
    _P("orientation_stddev", float, 0.0, "If > 0, publish this fixed orientation_covariance "
       "diagonal instead of the filter's propagated covariance (0 = the filter's, recommended)",
       unit="rad", range=(0.0, 3.15), scope="node", group="node: output"),
    _P("angular_velocity_stddev", float, 0.0, "Fills angular_velocity_covariance (diagonal) "
       "when the input leaves it unknown (all zeros); 0 = copy the input as is (REP-145)",
       unit="rad/s", range=(0.0, 100.0), scope="node", group="node: output"),
    _P("linear_acceleration_stddev", float, 0.0, "Fills linear_acceleration_covariance "
       "(diagonal) when the input leaves it unknown (all zeros); 0 = copy the input as is "
       "(REP-145)", unit="m/s^2", range=(0.0, 1000.0), scope="node", group="node: output"),
    _P("remove_gravity_vector", bool, False, "Subtract the estimated gravity from "
       "linear_acceleration (default: pass the specific force through, REP-145)",
       scope="node", group="node: output"),
    _P("yaw_offset", float, 0.0, "Rotation about the world's up axis (counter-clockwise seen "
       "from above) added to the published heading, message and TF", unit="rad",
       range=(-6.2832, 6.2832), scope="node", group="node: output"),
    _P("declination", float, 0.0, "Magnetic declination (positive east); subtracted from the "
       "heading so that it refers to true north, message and TF", unit="rad",
       range=(-3.1416, 3.1416), scope="node", group="node: output"),
    _P("publish_debug_topics", bool, False, "Also publish imu/rpy/filtered (roll, pitch, yaw "
       "in rad) and imu/gyro_bias (geometry_msgs/Vector3Stamped)", scope="node",
       group="node: output"),
    # --- node: TF ---------------------------------------------------------------------------------
    _P("publish_tf", bool, False, "Broadcast the orientation as a TF fixed_frame -> IMU frame "
       "(rotation only; needs tf2_ros)", scope="node", group="node: tf"),
    _P("fixed_frame", str, "odom", "Parent frame of the TF (imu_filter_madgwick default)",
       scope="node", group="node: tf"),
    _P("reverse_tf", bool, False, "Broadcast IMU frame -> fixed_frame (the inverse) instead",
       scope="node", group="node: tf"),
    # --- node: diagnostics ------------------------------------------------------------------------
    _P("diagnostics_period", float, 1.0, "Period of the /diagnostics status; 0 = off",
       unit="s", range=(0.0, 3600.0), scope="node", group="node: diagnostics"),
    _P("input_timeout", float, 5.0, "Diagnostics warn (naming the topic) when no message has "
       "arrived on an expected input for this long", unit="s", range=(0.1, 3600.0),
       scope="node", group="node: diagnostics"),
)

BY_NAME: dict[str, Param] = {p.name: p for p in PARAMS}


def register(*params: Param) -> None:
    """Add parameter definitions (for front ends with scope ``node``); names must be new."""
    global PARAMS
    for p in params:
        if p.name in BY_NAME:
            raise ValueError(f"parameter {p.name!r} is defined twice")
        BY_NAME[p.name] = p
    PARAMS = tuple(BY_NAME.values())


def filter_params() -> list[Param]:
    """Definitions with scope ``filter`` (the keywords of :func:`mkf_ros.estimate`)."""
    return [p for p in BY_NAME.values() if p.scope == "filter"]


#: Former parameters, now fixed levels (the one definition of each; ``mkf_ros.core.state``
#: gives them to the kernels under the upper-case name): docs/math.md §9.3, §9.4. No real
#: recording of the benchmark depends on them; the mechanisms stay, for the hostile cases the
#: tests build. Name → (value, what it is).
REMOVED: dict[str, tuple[float, str]] = {
    "acc_gate": (16.3, "chi-square gate"),
    "mag_gate": (10.8, "chi-square gate"),
    "gyro_gate": (1e4, "chi-square gate"),
    "acc_recovery_time": (1.0, "s"),
    "mag_recovery_time": (10.0, "s"),
    "rest_bias_range": (0.05, "rad/s"),
    "acc_norm_tolerance": (0.5, "g off gravity: a raw accelerometer sample beyond it is left "
                                "out of the blend"),
}


def removed_hint(name: str) -> str:
    """What replaced a removed parameter, in a few words."""
    value, what = REMOVED[name]
    level = f"{what} of {value:g}" if what.endswith("gate") else f"{value:g} {what}"
    return f"a fixed {level} (mkf_ros.core.state.{name.upper()})"


def unknown_parameter(name: str, known: Iterable[str]) -> str:
    """One short line for an unknown parameter name: a removed one and what replaced it, or
    the closest known names, and where the full list is (not all ~60 names in one line)."""
    if name in REMOVED:
        return f"filter parameter {name!r} was removed: {removed_hint(name)}"
    close = difflib.get_close_matches(str(name), list(known), n=3, cutoff=0.6)
    hint = f" (did you mean {' or '.join(map(repr, close))}?)" if close else ""
    return (f"unknown filter parameter {name!r}{hint}; the parameters are listed in "
            f"docs/estimator.md and mkf_ros.core.params.PARAMS")


def mag_reference_direction(v: Iterable[float]) -> np.ndarray | None:
    """The unit field direction that a ``mag_reference`` gives (in its world frame), or None
    for all zeros (learn it from the first magnetometer samples): any non-zero vector, however
    small, scaled to its largest component before it is normalised (its squared length would
    underflow to 0 below ~1e-154)."""
    ref = np.asarray(list(v), dtype=float)
    if not np.any(ref):
        return None
    ref = ref / np.abs(ref).max()
    return ref / np.linalg.norm(ref)


def _check_combination(vals: Mapping[str, Any]) -> None:
    """The rules between filter parameters (each one is valid alone): ValueError, one line."""
    if abs(np.linalg.det(np.reshape(vals["mag_soft_iron"], (3, 3)))) < 1e-12:
        raise ValueError("mag_soft_iron must be an invertible 3x3 matrix (row-major, 9 numbers)")
    if (vals["use_mag"] and vals["init_mode"] == "paper"
            and mag_reference_direction(vals["mag_reference"]) is None):
        raise ValueError("init_mode 'paper' with use_mag needs mag_reference (the paper's "
                         "filter has no alignment step to learn it)")


class FilterParams(Mapping[str, Any]):
    """Validated values of the filter parameters: a read-only mapping (``params["chart"]``,
    ``dict(params)``, ``params.values()``, ``params.items()``) with attribute access
    (``params.chart``). Immutable: :meth:`replace` makes a changed copy."""

    __slots__ = ("_values",)

    def __init__(self, overrides: Mapping[str, Any] | None = None, **kwargs: Any) -> None:
        merged = dict(overrides or {}, **kwargs)
        vals = {p.name: p.validate(p.default) for p in filter_params()}
        for k, v in merged.items():
            if k not in vals:
                raise ValueError(unknown_parameter(k, vals))
            vals[k] = BY_NAME[k].validate(v)
        _check_combination(vals)
        object.__setattr__(self, "_values", vals)

    def __getattr__(self, name: str) -> Any:  # only called for names that are not attributes
        try:
            return object.__getattribute__(self, "_values")[name]
        except KeyError:
            raise AttributeError(
                f"{type(self).__name__!r} object has no attribute {name!r}") from None

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"FilterParams is immutable; use .replace({name}=...)")

    def __getitem__(self, key: str) -> Any:
        return self._values[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"FilterParams({self._values!r})"

    def __reduce__(self) -> tuple[Any, ...]:  # pickling (process pools) through __init__
        return (FilterParams, (dict(self._values),))

    def replace(self, **changes: Any) -> FilterParams:
        """A copy with ``changes`` validated and applied."""
        return FilterParams(self._values, **changes)
