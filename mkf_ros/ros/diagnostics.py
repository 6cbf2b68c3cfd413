"""The estimator's ``/diagnostics`` status, built by hand (no diagnostic_updater wheel exists).

:class:`DiagnosticsTracker` turns a :class:`Snapshot` of the node (taken once per period) into
one ``diagnostic_msgs/DiagnosticStatus``: input rates, time-step statistics, dropped and
rejected counts with their reasons, initialisation and magnetometer state, orientation
uncertainty and covariance trace, gyro bias, and a warning that names the resolved topic when
an expected input has been silent for ``input_timeout`` seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from mkf_ros.stream.adapter import COUNTER_REASONS, GATED, REJECTIONS

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
#: A plausible Earth field magnitude range (T); outside it the unit is probably not tesla.
MAG_TESLA_RANGE = (1e-6, 1e-3)


@dataclass
class Snapshot:
    """What the node knows at one instant (wall-clock times from ``time.monotonic``)."""

    now: float
    start: float
    imu_topic: str
    mag_topic: str
    params: dict[str, Any]
    counters: dict[str, int]
    published: int = 0
    exceptions: int = 0
    last_exception: str = ""
    last_imu: float | None = None  #: wall time of the last IMU message
    last_mag: float | None = None
    initialized: bool = False
    heading_initialized: bool = False
    cov: np.ndarray | None = None  #: 3×3 about world axes, rad²
    bias: np.ndarray | None = None
    bias_stddev: np.ndarray | None = None
    acc_norm: float = math.nan
    mag_norm: float = math.nan
    mag_offset: float = math.nan
    dt_stats: tuple[int, float, float, float] = (0, math.nan, math.nan, math.nan)
    last_reset_reason: str = ""
    frame_id: str = ""
    extra: dict[str, str] = field(default_factory=dict)
    #: input that cannot give an orientation (``StreamAdapter.input_problems``; "orientation":
    #: a topic that carries one already), one line by kind
    input_problems: dict[str, str] = field(default_factory=dict)


def _fmt(x: float, spec: str = ".3g") -> str:
    return "n/a" if x is None or not math.isfinite(x) else format(x, spec)


class DiagnosticsTracker:
    """Keeps the previous snapshot's counters to report rates and per-period changes."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._prev_t: float | None = None
        self._prev: dict[str, int] = {}
        self._prev_pub = 0
        self._prev_exc = 0

    def status(self, s: Snapshot) -> DiagnosticStatus:
        dt = (s.now - self._prev_t) if self._prev_t is not None else (s.now - s.start)
        dt = max(dt, 1e-9)
        delta = {k: v - self._prev.get(k, 0) for k, v in s.counters.items()}
        pub_rate = (s.published - self._prev_pub) / dt
        new_exc = s.exceptions - self._prev_exc
        self._prev_t, self._prev = s.now, dict(s.counters)
        self._prev_pub, self._prev_exc = s.published, s.exceptions

        p = s.params
        use_mag = bool(p.get("use_mag"))
        timeout = float(p.get("input_timeout", 5.0))
        level, notes = OK, []

        def warn(msg: str, lvl: bytes = WARN) -> None:
            nonlocal level
            level = max(level, lvl)
            notes.append(msg)

        imu_silent = s.now - (s.last_imu if s.last_imu is not None else s.start)
        if imu_silent > timeout:
            what = "no data" if s.last_imu is None else "no data since a stop"
            warn(f"{what} on {s.imu_topic} for {imu_silent:.0f} s (is the driver running, "
                 f"the topic remapped, the QoS compatible?)")
        mag_silent = s.now - (s.last_mag if s.last_mag is not None else s.start)
        if use_mag and mag_silent > timeout:
            warn(f"no data on {s.mag_topic} for {mag_silent:.0f} s: use_mag is true but the "
                 "heading is not magnetometer-referenced")
        for kind, problem in s.input_problems.items():  # no accelerometer: no estimate at all
            warn(problem, ERROR if kind == "accel" else WARN)
        if delta.get("imu_received", 0) > 0 and not s.initialized:
            warn("receiving IMU data but not initialised: " + self._why_not_init(s, delta))
        dropped = {k: delta.get(k, 0) for k in REJECTIONS if delta.get(k, 0) > 0}
        for k, ref in GATED.items():  # motion, magnetic disturbances: normal in moderation
            if delta.get(k, 0) > max(delta.get(ref, 0), 1) // 2:
                dropped[k] = delta[k]
        if dropped:
            warn("dropped/rejected in the last period: "
                 + ", ".join(f"{v} {k}" for k, v in dropped.items()))
        if delta.get("resets_time_jump", 0) > 0:
            warn("reset: the IMU stamps jumped back (bag loop or clock reset)")
        if use_mag and math.isfinite(s.mag_norm) and not (
                MAG_TESLA_RANGE[0] <= s.mag_norm <= MAG_TESLA_RANGE[1]):
            warn(f"magnetometer magnitude {s.mag_norm:.3g} is not a field in tesla "
                 "(REP-145; gauss or µT?)")
        if new_exc > 0:
            warn(f"{new_exc} exception(s) in callbacks, last: {s.last_exception}", ERROR)

        if not notes:
            if not s.initialized:
                notes.append("waiting for data")
            elif use_mag and s.heading_initialized:
                notes.append("running, heading from the magnetometer")
            else:
                notes.append("running, heading relative to the start-up heading")

        st = DiagnosticStatus(level=level, name=self.name, message="; ".join(notes),
                              hardware_id=s.frame_id)
        st.values = [KeyValue(key=k, value=v) for k, v in self._values(s, delta, dt, pub_rate)]
        return st

    @staticmethod
    def _why_not_init(s: Snapshot, delta: dict[str, int]) -> str:
        g = float(s.params.get("gravity", 9.80665))
        if delta.get("imu_bad_stamp", 0):
            return "the IMU stamps are zero or invalid (fix the driver or set constant_dt)"
        if delta.get("acc_implausible", 0):
            return (f"accelerometer magnitude {_fmt(s.acc_norm)} m/s² is far from gravity "
                    f"{g:g} m/s² (gravity already removed? units of g?)")
        return "no valid accelerometer sample (NaN, zero or not reported)"

    def _values(self, s: Snapshot, delta: dict[str, int], dt: float,
                pub_rate: float) -> list[tuple[str, str]]:
        p = s.params
        use_mag = bool(p.get("use_mag"))
        if not use_mag:
            mag_state = "ignored (use_mag false)" if delta.get("mag_received") else "disabled"
        elif s.heading_initialized:
            mag_state = "fused, heading fixed"
        elif s.last_mag is None:
            mag_state = "waiting for the first sample"
        else:
            mag_state = "receiving, heading not fixed yet"
        n, lo, mean, hi = s.dt_stats
        v: list[tuple[str, str]] = [
            ("imu topic", s.imu_topic),
            ("magnetometer topic", s.mag_topic),
            ("imu rate (Hz)", _fmt(delta.get("imu_received", 0) / dt, ".1f")),
            ("magnetometer rate (Hz)", _fmt(delta.get("mag_received", 0) / dt, ".1f")),
            ("published rate (Hz)", _fmt(pub_rate, ".1f")),
            ("imu dt min/mean/max (ms)",
             f"{_fmt(lo * 1e3)} / {_fmt(mean * 1e3)} / {_fmt(hi * 1e3)}" if n else "n/a"),
            ("initialised", str(s.initialized).lower()),
            ("magnetometer", mag_state),
            ("magnetometer stamp - filter time (ms)", _fmt(s.mag_offset * 1e3, ".1f")),
            ("algorithm / chart", f"{p.get('algorithm')} / {p.get('chart')}"
                                  f"{'' if p.get('chart_update') else ' (no chart update)'}"),
            ("world frame", str(p.get("world_frame"))),
        ]
        if s.cov is not None and s.initialized:
            sd = np.degrees(np.sqrt(np.clip(np.diag(s.cov), 0.0, None)))
            v.append(("orientation stddev x/y/z, world axes (deg)",
                      " / ".join(_fmt(float(x), ".3f") for x in sd)))
            v.append(("orientation covariance trace (rad^2)", _fmt(float(np.trace(s.cov)))))
        if p.get("estimate_gyro_bias") and s.bias is not None and s.bias_stddev is not None:
            v.append(("gyro bias (rad/s)", " / ".join(_fmt(float(x), ".2e") for x in s.bias)))
            v.append(("gyro bias stddev (rad/s)",
                      " / ".join(_fmt(float(x), ".2e") for x in s.bias_stddev)))
        v.append(("accelerometer magnitude (m/s^2)", _fmt(s.acc_norm)))
        v.append(("magnetometer magnitude", _fmt(s.mag_norm)))
        for k in COUNTER_REASONS:
            v.append((k, str(s.counters.get(k, 0))))
        v.append(("published", str(s.published)))
        v.append(("callback exceptions", str(s.exceptions)))
        if s.last_exception:
            v.append(("last exception", s.last_exception))
        if s.last_reset_reason:
            v.append(("last reset", s.last_reset_reason))
        v.extend(s.extra.items())
        return v
