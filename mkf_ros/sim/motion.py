"""Synthetic IMU recordings with ground truth.

A scenario produces the true body rate ``ω`` on a fine time grid, and optionally a linear
acceleration, a local magnetic disturbance, a gyro bias history, dropped samples and distorted
time stamps. :func:`simulate` integrates the attitude ``q`` (body → ENU), samples ideal sensors at
the requested rate and adds noise:

* gyro ``ω_m = ω + b + n_g``;
* accelerometer ``a_m = R(q)ᵀ (g·up + a_lin) + n_a`` (specific force, +g up at rest, REP-145);
* magnetometer ``m_m = R(q)ᵀ (m_E + d) + n_m`` in tesla (``d``: a local disturbance).

The attitude is integrated exactly for a piecewise-constant rate (docs/math.md §1.3) on ``substeps``
sub-intervals per sample, as in the paper's study (§7.2: rate updated first, then used). The
product of the ``substeps·N`` small rotations is a blocked prefix product in NumPy (no compiled
kernel, so the simulator never touches the filters' kernel cache).

Everything a scorer needs is returned: the true attitude, rate and bias per sample, the true
sampling instants next to the (possibly jittered or jumping) stamps, the linear acceleration and
the magnetic disturbance, and in ``meta['intervals']`` the time intervals of each disturbance
(``acc_disturbed``, ``mag_disturbed``, ``dropout``, ``mag_dropout``, ``gimbal_lock``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mkf_ros.core.quaternion import qmul_np, rotmat_np

GRAVITY = 9.80665
#: Earth field used by default: 50 µT with a 60° dip (north and down), ENU, tesla.
MAG_FIELD_ENU = 50e-6 * np.array([0.0, np.cos(np.radians(60)), -np.sin(np.radians(60))])


@dataclass
class SimData:
    """A synthetic recording: sensor arrays and the ground truth, one row per sample."""

    t: np.ndarray  #: (N,) s, the stamps a driver would write (jitter/jumps included)
    gyr: np.ndarray  #: (N, 3) rad/s
    acc: np.ndarray  #: (N, 3) m/s²
    mag: np.ndarray  #: (N, 3) T (NaN rows where the magnetometer has no sample)
    quat: np.ndarray  #: (N, 4) true orientation, body → ENU, [w, x, y, z]
    omega: np.ndarray  #: (N, 3) true body rate, rad/s
    bias: np.ndarray  #: (N, 3) true gyro bias, rad/s
    meta: dict = field(default_factory=dict)
    t_true: np.ndarray | None = None  #: (N,) s, true sampling instants (strictly increasing)
    lin_acc: np.ndarray | None = None  #: (N, 3) true linear acceleration, ENU, m/s²
    mag_dist: np.ndarray | None = None  #: (N, 3) local magnetic disturbance, ENU, T
    mag_body: np.ndarray | None = None  #: (N, 3) field carried by the body (a magnet), body, T

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def mag_valid(self) -> np.ndarray:
        """(N,) bool: rows that carry a magnetometer sample."""
        return ~np.isnan(self.mag).any(axis=1)

    def mask(self, kind: str, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: samples whose true time lies in an interval of ``kind`` (see
        ``meta['intervals']``), widened by ``margin`` seconds on both sides."""
        t = self.t if self.t_true is None else self.t_true
        m = np.zeros(t.shape, dtype=bool)
        for a, b in self.meta.get("intervals", {}).get(kind, []):
            m |= (t >= a - margin) & (t <= b + margin)
        return m


# ------------------------------------------------------------------ attitude integration


def q_exp(rotvec: np.ndarray) -> np.ndarray:
    """Quaternions of rotation vectors (..., 3) → (..., 4): ``[cos(θ/2), sin(θ/2) u]``."""
    rotvec = np.asarray(rotvec, dtype=float)
    th = np.atleast_1d(np.sqrt(np.einsum("...i,...i->...", rotvec, rotvec)))
    out = np.empty((*th.shape, 4))
    out[..., 0] = np.cos(0.5 * th)
    # sin(θ/2)/θ, with its series near 0
    small = th < 1e-6
    k = np.sin(0.5 * th) / np.where(small, 1.0, th)
    k[small] = 0.5 - th[small] ** 2 / 48.0
    out[..., 1:] = k[..., None] * rotvec
    return out.reshape((*rotvec.shape[:-1], 4))


def integrate(q0: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Attitudes on a grid: ``q_{k+1} = q_k ⊗ q_ω(ω_k, dt)`` (exact for piecewise-constant ω).

    Returns ``(M + 1, 4)`` for ``M`` rates. A blocked prefix product: ``√M`` vectorised passes
    inside blocks, then one pass over the block totals.
    """
    q0 = np.asarray(q0, dtype=float)
    m = omega.shape[0]
    if m == 0:
        return q0[None, :].copy()
    b = max(1, math.isqrt(m))
    nb = -(-m // b)
    dq = np.zeros((nb * b, 4))
    dq[:, 0] = 1.0
    dq[:m] = q_exp(omega * dt)
    # component-major layout (4, b, nb): every pass below works on contiguous rows
    c = np.ascontiguousarray(dq.reshape(nb, b, 4).transpose(2, 1, 0))
    w, x, y, z = c
    for j in range(1, b):  # prefix products inside each block, all blocks at once
        pw, px, py, pz = w[j - 1], x[j - 1], y[j - 1], z[j - 1]
        qw, qx, qy, qz = w[j].copy(), x[j].copy(), y[j].copy(), z[j].copy()
        w[j] = pw * qw - px * qx - py * qy - pz * qz
        x[j] = pw * qx + px * qw + py * qz - pz * qy
        y[j] = pw * qy + py * qw + pz * qx - px * qz
        z[j] = pw * qz + pz * qw + px * qy - py * qx
    heads = np.empty((nb, 4))  # attitude at the start of each block (scalar loop)
    pw, px, py, pz = (q0 / np.linalg.norm(q0)).tolist()
    for i, (qw, qx, qy, qz) in enumerate(c[:, -1, :].T.tolist()):
        heads[i] = pw, px, py, pz
        pw, px, py, pz = (pw * qw - px * qx - py * qy - pz * qz,
                          pw * qx + px * qw + py * qz - pz * qy,
                          pw * qy + py * qw + pz * qx - px * qz,
                          pw * qz + pz * qw + px * qy - py * qx)
        s = 1.0 / math.sqrt(pw * pw + px * px + py * py + pz * pz)
        pw, px, py, pz = pw * s, px * s, py * s, pz * s
    out = qmul_np(heads[:, None, :], c.transpose(2, 1, 0)).reshape(-1, 4)[:m]
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return np.concatenate([heads[:1], out])


# ------------------------------------------------------------------ scenario machinery


@dataclass
class Context:
    """What a scenario sees and fills in. ``t_fine`` is the rate grid; ``t`` the sample grid."""

    rng: np.random.Generator
    t_fine: np.ndarray
    t: np.ndarray
    rate: float
    duration: float
    args: dict[str, Any]
    omega_fine: np.ndarray | None = None  #: (M, 3) body rate on t_fine (required)
    lin_acc: np.ndarray | None = None  #: (N, 3) ENU linear acceleration at t
    mag_dist: np.ndarray | None = None  #: (N, 3) ENU field disturbance at t
    mag_body: np.ndarray | None = None  #: (N, 3) field added in body axes (a magnet on it)
    bias: np.ndarray | None = None  #: (N, 3) extra gyro bias at t
    drop: np.ndarray | None = None  #: (N,) bool: sample not delivered at all
    mag_drop: np.ndarray | None = None  #: (N,) bool: no magnetometer sample
    stamps: np.ndarray | None = None  #: (N,) stamps if they differ from t
    level_start: bool = False  #: start level (random heading) when q0 is not given
    intervals: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Scenario:
    """A named scenario: a description, its parameters (defaults) and the function."""

    name: str
    description: str
    fill: Callable[[Context], None]
    params: dict[str, Any] = field(default_factory=dict)


def _add_pulse(w: np.ndarray, t: np.ndarray, t0: float, length: float,
               vec: np.ndarray) -> None:
    """Add ``vec · (1 − cos 2πτ)``, τ = (t − t0)/length ∈ [0, 1), to ``w`` (in place): a smooth
    rate pulse whose integral over the pulse is ``vec · length``."""
    a, b = np.searchsorted(t, [t0, t0 + length])
    tau = (t[a:b] - t0) / length
    w[a:b] += (1.0 - np.cos(2.0 * np.pi * tau))[:, None] * vec


def _slow_rates(rng: np.random.Generator, t: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Smooth rotation about all three axes (≤ ~0.6 rad/s · scale), reaching large tilts."""
    f = np.array([0.05, 0.07, 0.09])
    a = np.array([0.5, 0.4, 0.6]) * scale
    ph = rng.uniform(0, 2 * np.pi, 3)
    return a * np.sin(2 * np.pi * f * t[:, None] + ph)


def _bursts(rng: np.random.Generator, duration: float, start: float, every: float,
            length: tuple[float, float]) -> list[tuple[float, float]]:
    """Non-overlapping intervals starting after ``start``, about one per ``every`` seconds."""
    out: list[tuple[float, float]] = []
    t0 = start
    while True:
        t0 += rng.uniform(0.5, 1.5) * every
        ln = rng.uniform(*length)
        if t0 + ln > duration - 0.5:
            return out
        out.append((float(t0), float(t0 + ln)))
        t0 += ln


def _static(c: Context) -> None:
    c.omega_fine = np.zeros((c.t_fine.size, 3))


def _slow_rotation(c: Context) -> None:
    c.omega_fine = _slow_rates(c.rng, c.t_fine)


def _wiener(c: Context) -> None:
    dt = c.t_fine[1] - c.t_fine[0] if c.t_fine.size > 1 else 1.0 / c.rate
    steps = c.rng.normal(0.0, np.sqrt(c.args["q_omega_psd"] * dt), size=(c.t_fine.size, 3))
    c.omega_fine = np.cumsum(steps, axis=0)


#: (body axis, angle °, label) of one sweep cycle: full turns about x, y, z, then into both
#: gimbal-lock attitudes (pitch ±90°) and a turn about the body axis while there.
SWEEP = (
    ((1, 0, 0), 360.0, "roll 360"),
    ((0, 1, 0), 360.0, "pitch 360"),
    ((0, 0, 1), 360.0, "yaw 360"),
    ((0, 1, 0), -90.0, "pitch to +90 (gimbal lock)"),
    ((1, 0, 0), 90.0, "turn about the vertical body x at +90"),
    ((0, 1, 0), 90.0, "back to level"),
    ((0, 1, 0), 90.0, "pitch to -90 (gimbal lock)"),
    ((1, 0, 0), -120.0, "turn about the vertical body x at -90"),
    ((0, 1, 0), -90.0, "back to level"),
    ((1, 1, 1), 360.0, "turn about the diagonal"),
)


def _sweep(c: Context) -> None:
    """Raised-cosine rotations of :data:`SWEEP` at mean rate ``sweep_rate`` (°/s), with a
    ``hold`` between them; the cycle repeats until the end."""
    rate = np.radians(c.args["sweep_rate"])
    hold = c.args["hold"]
    w = np.zeros((c.t_fine.size, 3))
    t0 = hold
    segments = []
    while t0 < c.duration:
        for axis, ang, label in SWEEP:
            u = np.asarray(axis, float) / np.linalg.norm(axis)
            th = np.radians(ang)
            T = max(0.5, abs(th) / rate)
            _add_pulse(w, c.t_fine, t0, T, (th / T) * u)
            segments.append((float(t0), float(t0 + T), label))
            t0 += T + hold
    c.omega_fine = w
    c.level_start = True
    c.extra["segments"] = segments


def _fast_rotation(c: Context) -> None:
    """Spins about random axes peaking at ``max_rate`` rad/s, on top of slow motion."""
    w = _slow_rates(c.rng, c.t_fine)
    t0 = 0.5
    while t0 < c.duration:
        T = c.rng.uniform(0.3, 1.0)
        u = c.rng.normal(size=3)
        u /= np.linalg.norm(u)
        peak = c.args["max_rate"] * c.rng.uniform(0.5, 1.0)
        _add_pulse(w, c.t_fine, t0, T, 0.5 * peak * u)
        c.intervals.setdefault("fast", []).append((float(t0), float(t0 + T)))
        t0 += T + c.rng.uniform(0.3, 1.0)
    c.omega_fine = w


def _vibration(c: Context) -> None:
    """Slow motion plus angular and linear vibration (sums of sines at ``vib_freq`` ·
    (1, 1.37, 1.81) Hz), like an IMU on a running engine."""
    f = c.args["vib_freq"] * np.array([1.0, 1.37, 1.81])
    ph = c.rng.uniform(0, 2 * np.pi, (2, 3))
    w = _slow_rates(c.rng, c.t_fine)
    w += c.args["vib_rate"] * np.sin(2 * np.pi * f * c.t_fine[:, None] + ph[0])
    c.omega_fine = w
    c.lin_acc = c.args["vib_acc"] * np.sin(2 * np.pi * f[::-1] * c.t[:, None] + ph[1])
    c.intervals["acc_disturbed"] = [(0.0, c.duration)]


def _gyro_bias(c: Context) -> None:
    """A large constant gyro bias (``bias``, rad/s) on slow motion."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    c.bias = np.broadcast_to(np.asarray(c.args["bias"], float), (c.t.size, 3)).copy()


def _bias_drift(c: Context) -> None:
    """Gyro bias as a random walk (``bias_walk`` rad/s/√s) plus a slow warm-up drift of
    ``bias_ramp`` rad/s per axis over the recording, on slow motion."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    dt = 1.0 / c.rate
    walk = np.cumsum(c.rng.normal(0.0, c.args["bias_walk"] * np.sqrt(dt), (c.t.size, 3)), 0)
    ramp = np.asarray(c.args["bias_ramp"], float) * (1.0 - np.exp(-c.t / (0.3 * c.duration)))[
        :, None]
    c.bias = walk + ramp


def _mag_disturbance(c: Context) -> None:
    """A local field change (``mag_dist`` T, horizontal, east) over the middle fifth of the
    recording, with smooth 0.5 s edges, on slow motion."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    a, b = 0.4 * c.duration, 0.6 * c.duration
    edge = min(0.5, 0.25 * (b - a))
    s = np.clip(np.minimum((c.t - a) / edge, (b - c.t) / edge), 0.0, 1.0)
    s = 0.5 - 0.5 * np.cos(np.pi * s)
    c.mag_dist = s[:, None] * np.array([c.args["mag_dist"], 0.0, 0.0])
    c.intervals["mag_disturbed"] = [(float(a), float(b))]


def _accel_bursts(c: Context) -> None:
    """Translational acceleration bursts (one full sine period each, so the velocity returns to
    zero) in random directions, peaking at ``acc_peak`` g, on slow motion."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    acc = np.zeros((c.t.size, 3))
    ivs = _bursts(c.rng, c.duration, 0.5, c.args["burst_every"], (0.3, 1.0))
    for a, b in ivs:
        u = c.rng.normal(size=3)
        u /= np.linalg.norm(u)
        peak = c.args["acc_peak"] * GRAVITY * c.rng.uniform(0.5, 1.0)
        tau = (c.t - a) / (b - a)
        inside = (tau >= 0) & (tau <= 1)
        acc[inside] += peak * np.sin(2 * np.pi * tau[inside])[:, None] * u
    c.lin_acc = acc
    c.intervals["acc_disturbed"] = ivs


def _shaking(c: Context) -> None:
    """Sustained shaking (the motion that drags a raw accelerometer off, like BROAD's fast
    translation): two stretches of a quarter of the recording each in which the body is shaken back
    and forth at ``shake_freq`` Hz with peaks up to ``shake_acc`` g along a direction that changes
    every second (whole periods of a velocity oscillating about zero), while it also rocks about all
    axes (up to ``shake_rate`` rad/s at the same frequency); slow motion in between."""
    w = _slow_rates(c.rng, c.t_fine, 0.5)
    acc = np.zeros((c.t.size, 3))
    f = c.args["shake_freq"]
    ivs = [(0.15 * c.duration, 0.4 * c.duration), (0.55 * c.duration, 0.8 * c.duration)]
    for a, b in ivs:
        t0 = a
        while t0 + 1.0 <= b:
            u = c.rng.normal(size=3)
            u /= np.linalg.norm(u)
            v = c.rng.normal(size=3)
            v /= np.linalg.norm(v)
            peak = c.args["shake_acc"] * GRAVITY * c.rng.uniform(0.5, 1.0)
            inside = (c.t >= t0) & (c.t < t0 + 1.0)  # velocity (peak/ω) sin(ωt): mean zero
            acc[inside] += peak * np.cos(2 * np.pi * f * (c.t[inside] - t0))[:, None] * u
            fin = (c.t_fine >= t0) & (c.t_fine < t0 + 1.0)
            w[fin] += (c.args["shake_rate"] * c.rng.uniform(0.5, 1.0)
                       * np.sin(2 * np.pi * f * (c.t_fine[fin] - t0)))[:, None] * v
            t0 += 1.0
    c.omega_fine = w
    c.lin_acc = acc
    c.intervals["acc_disturbed"] = [(float(a), float(b)) for a, b in ivs]


def _slow_turn(c: Context) -> None:
    """Level, at rest for ``rest`` s, then a steady turn about the vertical at ``turn_rate``
    rad/s (a robot turning slowly: a turn rest detection must not take for a bias) with a linear
    vibration of ``vib_acc`` m/s² (a rolling robot; 0 = a perfectly smooth turn, which no IMU can
    tell from a gyro bias)."""
    c.level_start = True
    w = np.zeros((c.t_fine.size, 3))
    w[c.t_fine >= c.args["rest"], 2] = c.args["turn_rate"]
    c.omega_fine = w
    if c.args["vib_acc"] > 0:
        moving = (c.t >= c.args["rest"])[:, None]
        c.lin_acc = moving * c.rng.normal(0.0, c.args["vib_acc"], (c.t.size, 3))
    c.intervals["turning"] = [(float(c.args["rest"]), c.duration)]


def _mag_attached(c: Context) -> None:
    """A magnet attached to the body (a disturbance the magnetometer checks must refuse, like
    BROAD's attached-magnet trials): a constant field ``mag_offset`` (T, body axes; hundreds of µT
    at 1 cm) from 0.3 to 0.7 of the recording, on slow motion: it turns with the body, so the
    measured north swings."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    a, b = 0.3 * c.duration, 0.7 * c.duration
    on = ((c.t >= a) & (c.t < b))[:, None]
    c.mag_body = on * np.asarray(c.args["mag_offset"], float)
    c.intervals["mag_disturbed"] = [(float(a), float(b))]


def _dropouts(c: Context) -> None:
    """Lost messages on slow motion: a short gap (5 samples), a long one (``gap`` s, longer than
    the filters' default ``max_dt``), and a magnetometer outage of 2 s."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    n, d = c.t.size, c.duration
    drop = np.zeros(n, dtype=bool)
    dt = 1.0 / c.rate
    ivs = [(0.25 * d, 0.25 * d + 5 * dt), (0.5 * d, 0.5 * d + c.args["gap"])]
    for a, b in ivs:
        drop |= (c.t > a) & (c.t < b + 0.5 * dt)
    c.drop = drop
    ma, mb = 0.7 * d, min(0.7 * d + 2.0, d)
    c.mag_drop = (c.t >= ma) & (c.t < mb)
    # intervals span the true times of the missing samples
    c.intervals["dropout"] = _intervals_where(c.t, drop)
    c.intervals["mag_dropout"] = _intervals_where(c.t, c.mag_drop)


def _jitter(c: Context) -> None:
    """Stamps off the true sampling instants by up to ± ``jitter`` sample periods (uniform;
    below 0.5 they stay increasing), on slow motion."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    j = c.args["jitter"] / c.rate
    c.stamps = c.t + c.rng.uniform(-j, j, c.t.size)


def _time_jump(c: Context) -> None:
    """Stamps jump back by ``jump`` s at ``jump_at`` · duration (a clock reset or a bag loop),
    then run on; the motion (slow) does not notice."""
    c.omega_fine = _slow_rates(c.rng, c.t_fine)
    k = int(np.searchsorted(c.t, c.args["jump_at"] * c.duration))
    stamps = c.t.copy()
    stamps[k:] -= c.args["jump"]
    c.stamps = stamps
    if 0 < k < c.t.size:
        c.extra["time_jumps"] = [(k, float(stamps[k - 1]), float(stamps[k]))]


def _register(*scenarios: Scenario) -> dict[str, Scenario]:
    return {s.name: s for s in scenarios}


SCENARIOS: dict[str, Scenario] = _register(
    Scenario("static", "at rest", _static),
    Scenario("slow_rotation", "smooth rotation about all axes (≤ 0.6 rad/s), large tilts",
             _slow_rotation),
    Scenario("wiener", "the paper's study: body rate a Wiener process (PSD q_omega_psd)",
             _wiener, {"q_omega_psd": 1.0}),
    Scenario("sweep", "full turns about x, y, z and the diagonal, and both gimbal-lock "
             "attitudes (pitch ±90°)", _sweep, {"sweep_rate": 90.0, "hold": 0.5}),
    Scenario("fast_rotation", "spins about random axes up to max_rate rad/s", _fast_rotation,
             {"max_rate": 15.0}),
    Scenario("vibration", "angular and linear vibration on slow motion", _vibration,
             {"vib_freq": 23.0, "vib_rate": 0.3, "vib_acc": 3.0}),
    Scenario("gyro_bias", "large constant gyro bias", _gyro_bias,
             {"bias": (0.02, -0.03, 0.015)}),
    Scenario("bias_drift", "gyro bias random walk plus warm-up drift", _bias_drift,
             {"bias_walk": 1e-3, "bias_ramp": (0.01, -0.008, 0.012)}),
    Scenario("mag_disturbance", "a local magnetic field change over the middle fifth",
             _mag_disturbance, {"mag_dist": 25e-6}),
    Scenario("accel_bursts", "translational acceleration bursts up to acc_peak g",
             _accel_bursts, {"acc_peak": 3.0, "burst_every": 3.0}),
    Scenario("shaking", "sustained shaking up to shake_acc g with rocking up to shake_rate "
             "rad/s", _shaking, {"shake_acc": 10.0, "shake_freq": 4.0, "shake_rate": 6.0}),
    Scenario("slow_turn", "level rest, then a steady slow turn about the vertical", _slow_turn,
             {"turn_rate": 0.04, "rest": 5.0, "vib_acc": 0.0}),
    Scenario("mag_attached", "a magnet attached to the body over the middle of the recording",
             _mag_attached, {"mag_offset": (150e-6, -80e-6, 60e-6)}),
    Scenario("dropouts", "lost IMU messages (short and long gap) and a magnetometer outage",
             _dropouts, {"gap": 1.0}),
    Scenario("jitter", "time stamps jitter around the true sampling instants", _jitter,
             {"jitter": 0.3}),
    Scenario("time_jump", "time stamps jump back mid-recording", _time_jump,
             {"jump": 2.0, "jump_at": 0.5}),
)


def _intervals_where(t: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """Maximal runs of ``mask`` as (t_first, t_last) pairs."""
    if not mask.any():
        return []
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends, strict=True)]


def pitch_deg(quat: np.ndarray) -> np.ndarray:
    """Pitch (°) of body → ENU quaternions: elevation of the body x axis above the horizon."""
    R = rotmat_np(quat)
    return np.degrees(np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0)))


def simulate(
    scenario: str = "slow_rotation",
    *,
    duration: float = 20.0,
    rate: float = 100.0,
    seed: int = 0,
    substeps: int = 100,
    gyro_noise: float = 0.01,
    acc_noise: float = 0.05,
    mag_noise: float = 0.5e-6,
    gyro_bias: object = (0.0, 0.0, 0.0),
    mag_field: np.ndarray = MAG_FIELD_ENU,
    mag_rate: float | None = None,
    q0: np.ndarray | None = None,
    **scenario_args: Any,
) -> SimData:
    """Synthesise a recording of ``duration`` s at ``rate`` Hz (see the module doc).

    ``q0`` is the initial attitude (default: random, uniform on S³; level with a random heading
    for ``sweep``); ``gyro_bias`` a constant bias added to the scenario's; ``mag_field`` the
    Earth field in ENU (T); ``mag_rate`` (Hz) makes the magnetometer slower (NaN rows between its
    samples). ``scenario_args`` are the scenario's own parameters (``SCENARIOS[name].params``).
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    sc = SCENARIOS[scenario]
    unknown = set(scenario_args) - set(sc.params)
    if unknown:
        known = ", ".join(sc.params) or "none"
        raise ValueError(f"scenario {scenario!r} has no parameter {sorted(unknown)[0]!r} "
                         f"(its parameters: {known})")
    if not (rate > 0 and duration > 0 and substeps >= 1):
        raise ValueError("rate, duration and substeps must be positive")
    if mag_rate is not None and not mag_rate > 0:
        raise ValueError(f"mag_rate must be positive, got {mag_rate!r}")
    rng = np.random.default_rng(seed)
    n = round(duration * rate) + 1
    dt = 1.0 / rate
    fine_dt = dt / substeps
    t_fine = np.arange((n - 1) * substeps) * fine_dt
    q0_random = rng.normal(size=4)
    t = np.arange(n) * dt
    ctx = Context(rng=rng, t_fine=t_fine if t_fine.size > 1 else np.array([0.0, fine_dt]),
                  t=t, rate=rate, duration=duration, args=dict(sc.params, **scenario_args))
    sc.fill(ctx)
    assert ctx.omega_fine is not None, f"scenario {scenario} set no rate"
    if q0 is None:
        q0 = q0_random
        if ctx.level_start:
            yaw = np.arctan2(q0_random[0], q0_random[1])
            q0 = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    q0 = np.asarray(q0, dtype=float) / np.linalg.norm(q0)
    w_fine = ctx.omega_fine[: t_fine.size]
    q_fine = integrate(q0, np.ascontiguousarray(w_fine), fine_dt)
    quat = q_fine[::substeps]
    # what the gyro reports: the mean rate over the sample interval that ends at its stamp
    # (a MEMS gyro's anti-alias filter and decimation; at t=0 the first rate)
    if w_fine.size:
        m = (n - 1) * substeps
        mean = w_fine[:m].reshape(n - 1, substeps, 3).mean(axis=1)
        omega = np.vstack([w_fine[:1], mean])
    else:
        omega = np.zeros((n, 3))
    R = rotmat_np(quat)
    bias = np.broadcast_to(np.asarray(gyro_bias, dtype=float), (n, 3)).copy()
    if ctx.bias is not None:
        bias = bias + ctx.bias
    lin_acc = np.zeros((n, 3)) if ctx.lin_acc is None else ctx.lin_acc
    mag_dist = np.zeros((n, 3)) if ctx.mag_dist is None else ctx.mag_dist
    gyr = omega + bias + rng.normal(0, gyro_noise, (n, 3))
    up = np.array([0.0, 0.0, GRAVITY])
    acc = np.einsum("nji,nj->ni", R, up + lin_acc) + rng.normal(0, acc_noise, (n, 3))
    mag = np.einsum("nji,nj->ni", R, np.asarray(mag_field, float) + mag_dist) + \
        rng.normal(0, mag_noise, (n, 3))
    mag_body = np.zeros((n, 3)) if ctx.mag_body is None else ctx.mag_body
    mag = mag + mag_body
    if mag_rate is not None:
        keep = np.zeros(n, dtype=bool)
        keep[np.unique(np.round(np.arange(0, duration, 1.0 / mag_rate) * rate).astype(int))] = True
        mag[~keep[:n]] = np.nan
    if ctx.mag_drop is not None:
        mag[ctx.mag_drop] = np.nan
    stamps = t.copy() if ctx.stamps is None else ctx.stamps
    intervals = dict(ctx.intervals)
    lock = np.abs(pitch_deg(quat)) > 80.0
    if lock.any():
        intervals["gimbal_lock"] = _intervals_where(t, lock)
    meta: dict[str, Any] = dict(scenario=scenario, rate=rate, seed=seed, duration=duration,
                                mag_field=np.asarray(mag_field, float), mag_rate=mag_rate,
                                gyro_noise=gyro_noise, acc_noise=acc_noise, mag_noise=mag_noise,
                                description=sc.description, params=dict(ctx.args),
                                intervals=intervals, **ctx.extra)
    sd = SimData(t=stamps, gyr=gyr, acc=acc, mag=mag, quat=quat, omega=omega, bias=bias,
                 meta=meta, t_true=t, lin_acc=lin_acc, mag_dist=mag_dist, mag_body=mag_body)
    if ctx.drop is not None:
        sd = _select(sd, ~ctx.drop)
    return sd


def _select(sd: SimData, keep: np.ndarray) -> SimData:
    """The rows of ``sd`` where ``keep`` is true (dropped messages vanish entirely)."""
    arrays = {k: getattr(sd, k)[keep] for k in ("t", "gyr", "acc", "mag", "quat", "omega",
                                                 "bias", "t_true", "lin_acc", "mag_dist",
                                                 "mag_body")}
    return SimData(meta=sd.meta, **arrays)
