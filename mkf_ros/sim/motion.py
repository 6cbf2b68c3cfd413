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
product of the ``substeps·N`` small rotations is a blocked prefix product (one small compiled
kernel, :mod:`mkf_ros.sim._integrate`).

A recording is generated in chunks (:class:`SimStream`), so its length is not bounded by memory:
a scenario makes its random draws when it is set up (long runs of them handed out chunk by
chunk, :class:`Draws`) and returns a function of a chunk's time range; the integrator carries its
state from chunk to chunk. The result does not depend on the chunk size, and :func:`simulate`
(the chunks concatenated) gives the arrays the whole-recording simulator always gave.

Everything a scorer needs is returned: the true attitude, rate and bias per sample, the true
sampling instants next to the (possibly jittered or jumping) stamps, the linear acceleration and
the magnetic disturbance, and in ``meta['intervals']`` the time intervals of each disturbance
(``acc_disturbed``, ``mag_disturbed``, ``dropout``, ``mag_dropout``, ``gimbal_lock``).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from mkf_ros.core.quaternion import q_exp_np, rotmat_np

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


class Integrator:
    """``q_{k+1} = q_k ⊗ q_ω(ω_k, dt)`` (exact for piecewise-constant ω) over a recording of
    ``m`` rates fed in consecutive chunks (:meth:`advance`), keeping the attitude after every
    ``every``-th step. A blocked prefix product (blocks of ``√m`` steps: products inside the
    block, then the block's start attitude times them, renormalised), computed by the compiled
    kernel :func:`mkf_ros.sim._integrate.integrate_chunk`; the result does not depend on the
    chunks."""

    def __init__(self, q0: np.ndarray, m: int, dt: float, every: int = 1) -> None:
        q0 = np.asarray(q0, dtype=float)
        self.head = q0 / np.linalg.norm(q0)  #: attitude at the start of the current block
        self.start = self.head.copy()  #: the attitude before the first step
        self.prefix = np.array([1.0, 0.0, 0.0, 0.0])  #: product inside the current block
        self.block = max(1, math.isqrt(m))
        self.m, self.dt, self.every = m, dt, every
        self.done = 0  #: steps integrated so far

    def advance(self, omega: np.ndarray) -> np.ndarray:
        """Integrate the next ``len(omega)`` rates; the attitudes after each step ``j``
        (counted from the start of the recording) with ``(j + 1) % every == 0``, (K, 4)."""
        from mkf_ros.sim._integrate import integrate_chunk

        f = omega.shape[0]
        if self.done + f > self.m:
            raise ValueError(f"{self.done + f} rates for a recording of {self.m}")
        out = np.empty(((self.done + f) // self.every - self.done // self.every, 4))
        dq = q_exp_np(omega * self.dt) if f else np.empty((0, 4))
        k = integrate_chunk(np.ascontiguousarray(dq), self.done, self.block, self.every,
                            self.head, self.prefix, out)
        assert k == out.shape[0]
        self.done += f
        return out


def integrate(q0: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Attitudes on a grid: ``q_{k+1} = q_k ⊗ q_ω(ω_k, dt)`` (exact for piecewise-constant ω).

    Returns ``(M + 1, 4)`` for ``M`` rates (one :class:`Integrator` chunk)."""
    q0 = np.asarray(q0, dtype=float)
    m = omega.shape[0]
    if m == 0:
        return q0[None, :].copy()
    it = Integrator(q0, m, dt)
    return np.concatenate([it.start[None, :], it.advance(np.asarray(omega, dtype=float))])


# ------------------------------------------------------------------ scenario machinery


class Draws:
    """A long run of random draws a scenario makes (``normal`` or ``uniform`` of ``shape``,
    its first axis along the recording), handed out in order, chunk by chunk (:meth:`take`),
    from a copy of the generator. The scenario's generator is moved past the whole run at once
    (drawn and discarded in blocks), so what it draws afterwards (and the sensor noise) is what
    one draw of the whole array would have left: chunked draws equal the whole-array draw
    because both distributions fill arrays element by element in C order."""

    _BLOCK = 1 << 20

    def __init__(self, rng: np.random.Generator, kind: str, a: float, b: float,
                 shape: tuple[int, ...]) -> None:
        if kind not in ("normal", "uniform"):
            raise ValueError(f"unknown distribution {kind!r}")
        self.kind, self.a, self.b, self.shape = kind, a, b, shape
        self.rng = np.random.Generator(type(rng.bit_generator)())
        self.rng.bit_generator.state = rng.bit_generator.state
        self.left = shape[0]
        skip_draws(rng, kind, math.prod(shape))

    def take(self, rows: int) -> np.ndarray:
        """The next ``rows`` rows of the run."""
        if rows > self.left:
            raise ValueError(f"{rows} rows asked of a run with {self.left} left")
        self.left -= rows
        size = (rows, *self.shape[1:])
        if self.kind == "normal":
            return self.rng.normal(self.a, self.b, size)
        return self.rng.uniform(self.a, self.b, size)


def skip_draws(rng: np.random.Generator, kind: str, count: int) -> None:
    """Move ``rng`` past ``count`` draws of ``kind`` (``normal``: one standard normal each,
    whatever loc and scale; ``uniform``: one double each), in blocks of bounded memory."""
    buf = np.empty(min(count, Draws._BLOCK))
    while count > 0:
        k = min(count, buf.size)
        if kind == "normal":
            rng.standard_normal(out=buf[:k])
        else:
            rng.random(out=buf[:k])
        count -= k


@dataclass
class Chunk:
    """One stretch of a recording, what a scenario's chunk function fills in: samples ``i0 ..
    i1 - 1`` at the true instants ``t`` and the fine rate grid ``j0 .. j1 - 1`` at ``t_fine``."""

    i0: int
    i1: int
    t: np.ndarray
    j0: int
    j1: int
    t_fine: np.ndarray
    omega_fine: np.ndarray | None = None  #: (j1 - j0, 3) body rate on t_fine (required)
    lin_acc: np.ndarray | None = None  #: (K, 3) ENU linear acceleration at t
    #: (K, 3) linear acceleration in body axes at t, on top of ``lin_acc`` (a sensor away from
    #: the point the body turns about: α × r + ω × (ω × r))
    lin_acc_body: np.ndarray | None = None
    mag_dist: np.ndarray | None = None  #: (K, 3) ENU field disturbance at t
    mag_body: np.ndarray | None = None  #: (K, 3) field added in body axes (a magnet on it)
    bias: np.ndarray | None = None  #: (K, 3) extra gyro bias at t
    drop: np.ndarray | None = None  #: (K,) bool: sample not delivered at all
    mag_drop: np.ndarray | None = None  #: (K,) bool: no magnetometer sample
    stamps: np.ndarray | None = None  #: (K,) stamps if they differ from t
    #: interval kinds whose intervals are the runs of these (K,) masks (merged over chunks)
    runs: dict[str, np.ndarray] = field(default_factory=dict)


ChunkFn = Callable[[Chunk], None]


@dataclass
class Context:
    """What a scenario sees when it is set up: the random generator (its draws in a fixed
    order), the recording's size (``n`` samples at ``rate``, ``m`` steps of ``fine_dt`` on the
    rate grid) and its parameters. It makes its random draws here (long runs through
    :meth:`draws`) and fills in the metadata; the function it returns fills each :class:`Chunk`
    and may depend on nothing but the chunk's range and what was set up."""

    rng: np.random.Generator
    n: int
    m: int
    rate: float
    fine_dt: float
    duration: float
    args: dict[str, Any]
    level_start: bool = False  #: start level (random heading) when q0 is not given
    intervals: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def draws(self, kind: str, a: float, b: float, shape: tuple[int, ...]) -> Draws:
        """``rng.normal(a, b, shape)`` or ``rng.uniform(a, b, shape)`` handed out by chunks."""
        return Draws(self.rng, kind, a, b, shape)


@dataclass(frozen=True)
class Scenario:
    """A named scenario: a description, its parameters (defaults) and the function that sets it
    up (:class:`Context`) and returns its chunk function."""

    name: str
    description: str
    fill: Callable[[Context], ChunkFn]
    params: dict[str, Any] = field(default_factory=dict)


class _Pulses:
    """Rate pulses ``vec · (1 − cos 2πτ)``, τ = (t − t0)/length ∈ [0, 1), added in order: a
    smooth rate pulse whose integral over the pulse is ``vec · length``."""

    def __init__(self) -> None:
        self.items: list[tuple[float, float, np.ndarray]] = []
        self._ends: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, t0: float, length: float, vec: np.ndarray) -> None:
        self.items.append((t0, length, vec))
        self._ends = None

    def apply(self, w: np.ndarray, t: np.ndarray) -> None:
        """Add the pulses to the rates ``w`` on the sorted grid ``t`` (in place)."""
        if not t.size or not self.items:
            return
        if self._ends is None:
            self._ends = (np.array([p[0] for p in self.items]),
                          np.array([p[0] + p[1] for p in self.items]))
        t0s, t1s = self._ends
        near = np.flatnonzero((t0s <= t[-1]) & (t1s > t[0]))
        for i in near.tolist():
            t0, length, vec = self.items[i]
            a, b = np.searchsorted(t, [t0, t0 + length])
            tau = (t[a:b] - t0) / length
            w[a:b] += (1.0 - np.cos(2.0 * np.pi * tau))[:, None] * vec


class _SlowRates:
    """Smooth rotation about all three axes (≤ ~0.6 rad/s · scale), reaching large tilts."""

    def __init__(self, rng: np.random.Generator, scale: float = 1.0) -> None:
        self.f = np.array([0.05, 0.07, 0.09])
        self.a = np.array([0.5, 0.4, 0.6]) * scale
        self.ph = rng.uniform(0, 2 * np.pi, 3)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return self.a * np.sin(2 * np.pi * self.f * t[:, None] + self.ph)

    def derivative(self, t: np.ndarray) -> np.ndarray:
        """The angular acceleration of these rates at ``t``."""
        return self.a * 2 * np.pi * self.f * np.cos(2 * np.pi * self.f * t[:, None] + self.ph)


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


def _cumsum(steps: np.ndarray, last: np.ndarray | None) -> np.ndarray:
    """Running sum of ``steps`` (K, 3) along axis 0 continuing from ``last`` (the sum so far;
    None at the start), in the order of one ``np.cumsum`` over the whole run."""
    if last is None:
        return np.cumsum(steps, axis=0)
    return np.cumsum(np.concatenate([last[None, :], steps]), axis=0)[1:]


def _static(c: Context) -> ChunkFn:
    def chunk(ch: Chunk) -> None:
        ch.omega_fine = np.zeros((ch.t_fine.size, 3))
    return chunk


def _slow_rotation(c: Context) -> ChunkFn:
    slow = _SlowRates(c.rng)

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
    return chunk


def _wiener(c: Context) -> ChunkFn:
    steps = c.draws("normal", 0.0, float(np.sqrt(c.args["q_omega_psd"] * c.fine_dt)), (c.m, 3))
    last: list[np.ndarray | None] = [None]

    def chunk(ch: Chunk) -> None:
        w = _cumsum(steps.take(ch.t_fine.size), last[0])
        if w.size:
            last[0] = w[-1].copy()
        ch.omega_fine = w
    return chunk


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


def _sweep(c: Context) -> ChunkFn:
    """Raised-cosine rotations of :data:`SWEEP` at mean rate ``sweep_rate`` (°/s), with a
    ``hold`` between them; the cycle repeats until the end."""
    rate = np.radians(c.args["sweep_rate"])
    hold = c.args["hold"]
    pulses = _Pulses()
    t0 = hold
    segments = []
    while t0 < c.duration:
        for axis, ang, label in SWEEP:
            u = np.asarray(axis, float) / np.linalg.norm(axis)
            th = np.radians(ang)
            T = max(0.5, abs(th) / rate)
            pulses.add(t0, T, (th / T) * u)
            segments.append((float(t0), float(t0 + T), label))
            t0 += T + hold
    c.level_start = True
    c.extra["segments"] = segments

    def chunk(ch: Chunk) -> None:
        w = np.zeros((ch.t_fine.size, 3))
        pulses.apply(w, ch.t_fine)
        ch.omega_fine = w
    return chunk


def _fast_rotation(c: Context) -> ChunkFn:
    """Spins about random axes peaking at ``max_rate`` rad/s, on top of slow motion."""
    slow = _SlowRates(c.rng)
    pulses = _Pulses()
    t0 = 0.5
    while t0 < c.duration:
        T = c.rng.uniform(0.3, 1.0)
        u = c.rng.normal(size=3)
        u /= np.linalg.norm(u)
        peak = c.args["max_rate"] * c.rng.uniform(0.5, 1.0)
        pulses.add(t0, T, 0.5 * peak * u)
        c.intervals.setdefault("fast", []).append((float(t0), float(t0 + T)))
        t0 += T + c.rng.uniform(0.3, 1.0)

    def chunk(ch: Chunk) -> None:
        w = slow(ch.t_fine)
        pulses.apply(w, ch.t_fine)
        ch.omega_fine = w
    return chunk


def _vibration(c: Context) -> ChunkFn:
    """Slow motion plus angular and linear vibration (sums of sines at ``vib_freq`` ·
    (1, 1.37, 1.81) Hz), like an IMU on a running engine."""
    f = c.args["vib_freq"] * np.array([1.0, 1.37, 1.81])
    ph = c.rng.uniform(0, 2 * np.pi, (2, 3))
    slow = _SlowRates(c.rng)
    c.intervals["acc_disturbed"] = [(0.0, c.duration)]

    def chunk(ch: Chunk) -> None:
        w = slow(ch.t_fine)
        w += c.args["vib_rate"] * np.sin(2 * np.pi * f * ch.t_fine[:, None] + ph[0])
        ch.omega_fine = w
        ch.lin_acc = c.args["vib_acc"] * np.sin(2 * np.pi * f[::-1] * ch.t[:, None] + ph[1])
    return chunk


def _gyro_bias(c: Context) -> ChunkFn:
    """A large constant gyro bias (``bias``, rad/s) on slow motion."""
    slow = _SlowRates(c.rng)

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        ch.bias = np.broadcast_to(np.asarray(c.args["bias"], float), (ch.t.size, 3)).copy()
    return chunk


def _bias_drift(c: Context) -> ChunkFn:
    """Gyro bias as a random walk (``bias_walk`` rad/s/√s) plus a slow warm-up drift of
    ``bias_ramp`` rad/s per axis over the recording, on slow motion."""
    slow = _SlowRates(c.rng)
    dt = 1.0 / c.rate
    steps = c.draws("normal", 0.0, c.args["bias_walk"] * np.sqrt(dt), (c.n, 3))
    last: list[np.ndarray | None] = [None]

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        walk = _cumsum(steps.take(ch.t.size), last[0])
        if walk.size:
            last[0] = walk[-1].copy()
        ramp = np.asarray(c.args["bias_ramp"], float) * (
            1.0 - np.exp(-ch.t / (0.3 * c.duration)))[:, None]
        ch.bias = walk + ramp
    return chunk


def _mag_disturbance(c: Context) -> ChunkFn:
    """A local field change (``mag_dist`` T, horizontal, east) over the middle fifth of the
    recording, with smooth 0.5 s edges, on slow motion."""
    slow = _SlowRates(c.rng)
    a, b = 0.4 * c.duration, 0.6 * c.duration
    edge = min(0.5, 0.25 * (b - a))
    c.intervals["mag_disturbed"] = [(float(a), float(b))]

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        s = np.clip(np.minimum((ch.t - a) / edge, (b - ch.t) / edge), 0.0, 1.0)
        s = 0.5 - 0.5 * np.cos(np.pi * s)
        ch.mag_dist = s[:, None] * np.array([c.args["mag_dist"], 0.0, 0.0])
    return chunk


def _mag_field_change(c: Context) -> ChunkFn:
    """The undisturbed field changes for good at ``change_at`` of the recording (another room,
    a rebar floor: indoors 10–25 % in magnitude and some degrees of dip), with a smooth 2 s
    edge, on slow motion: ``mag_change`` (T, ENU) is added from then on. The default, north
    and up components only, keeps north and turns the default Earth field (50 µT, dip 60°)
    into 40 µT at dip 70°."""
    slow = _SlowRates(c.rng)
    a = c.args["change_at"] * c.duration
    c.intervals["mag_changed"] = [(float(a), c.duration)]
    change = np.asarray(c.args["mag_change"], float)

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        s = np.clip((ch.t - a) / 2.0, 0.0, 1.0)
        ch.mag_dist = (0.5 - 0.5 * np.cos(np.pi * s))[:, None] * change
    return chunk


def _accel_bursts(c: Context) -> ChunkFn:
    """Translational acceleration bursts (one full sine period each, so the velocity returns to
    zero) in random directions, peaking at ``acc_peak`` g, on slow motion."""
    slow = _SlowRates(c.rng)
    ivs = _bursts(c.rng, c.duration, 0.5, c.args["burst_every"], (0.3, 1.0))
    bursts = []
    for a, b in ivs:
        u = c.rng.normal(size=3)
        u /= np.linalg.norm(u)
        peak = c.args["acc_peak"] * GRAVITY * c.rng.uniform(0.5, 1.0)
        bursts.append((a, b, u, peak))
    c.intervals["acc_disturbed"] = ivs

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        acc = np.zeros((ch.t.size, 3))
        for a, b, u, peak in bursts:
            if ch.t.size and (a > ch.t[-1] + 1.0 or b < ch.t[0] - 1.0):
                continue  # τ outside [0, 1] on the whole chunk
            tau = (ch.t - a) / (b - a)
            inside = (tau >= 0) & (tau <= 1)
            acc[inside] += peak * np.sin(2 * np.pi * tau[inside])[:, None] * u
        ch.lin_acc = acc
    return chunk


def _shaking(c: Context) -> ChunkFn:
    """Sustained shaking (the motion that drags a raw accelerometer off, like BROAD's fast
    translation): two stretches of a quarter of the recording each in which the body is shaken back
    and forth at ``shake_freq`` Hz with peaks up to ``shake_acc`` g along a direction that changes
    every second (whole periods of a velocity oscillating about zero), while it also rocks about all
    axes (up to ``shake_rate`` rad/s at the same frequency); slow motion in between."""
    slow = _SlowRates(c.rng, 0.5)
    f = c.args["shake_freq"]
    ivs = [(0.15 * c.duration, 0.4 * c.duration), (0.55 * c.duration, 0.8 * c.duration)]
    shakes = []
    for a, b in ivs:
        t0 = a
        while t0 + 1.0 <= b:
            u = c.rng.normal(size=3)
            u /= np.linalg.norm(u)
            v = c.rng.normal(size=3)
            v /= np.linalg.norm(v)
            peak = c.args["shake_acc"] * GRAVITY * c.rng.uniform(0.5, 1.0)
            rock = c.args["shake_rate"] * c.rng.uniform(0.5, 1.0)
            shakes.append((t0, u, v, peak, rock))
            t0 += 1.0
    c.intervals["acc_disturbed"] = [(float(a), float(b)) for a, b in ivs]

    def chunk(ch: Chunk) -> None:
        w = slow(ch.t_fine)
        acc = np.zeros((ch.t.size, 3))
        lo = min(ch.t[0] if ch.t.size else np.inf, ch.t_fine[0] if ch.t_fine.size else np.inf)
        hi = max(ch.t[-1] if ch.t.size else -np.inf,
                 ch.t_fine[-1] if ch.t_fine.size else -np.inf)
        for t0, u, v, peak, rock in shakes:
            if t0 > hi or t0 + 1.0 <= lo:
                continue  # [t0, t0 + 1) misses the chunk
            inside = (ch.t >= t0) & (ch.t < t0 + 1.0)  # velocity (peak/ω) sin(ωt): mean zero
            acc[inside] += peak * np.cos(2 * np.pi * f * (ch.t[inside] - t0))[:, None] * u
            fin = (ch.t_fine >= t0) & (ch.t_fine < t0 + 1.0)
            w[fin] += (rock * np.sin(2 * np.pi * f * (ch.t_fine[fin] - t0)))[:, None] * v
        ch.omega_fine = w
        ch.lin_acc = acc
    return chunk


def _running(c: Context) -> ChunkFn:
    """Running with the sensor in a trouser pocket: the thigh swings about the hip at the
    stride frequency ``stride_freq`` Hz by ±``swing`` rad, the sensor ``lever`` m from the hip
    (its centripetal and tangential acceleration, up to several g, always along the same body
    axes), the hip bounces up and down at each step (``bounce`` g peak at twice the stride
    frequency), and the body turns slowly on top. Minutes of it: no quiet phase in which the
    accelerometer sees gravity alone."""
    slow = _SlowRates(c.rng, 0.3)
    axis = c.rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    r = c.rng.normal(size=3)
    r -= axis * (r @ axis)  # the lever across the swing axis
    r *= c.args["lever"] / np.linalg.norm(r)
    w0 = 2 * np.pi * c.args["stride_freq"]
    amp = c.args["swing"]
    c.intervals["acc_disturbed"] = [(0.0, c.duration)]

    def rates(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ph = w0 * t[:, None]
        w = slow(t) + amp * w0 * np.cos(ph) * axis
        dw = slow.derivative(t) - amp * w0 * w0 * np.sin(ph) * axis
        return w, dw

    def chunk(ch: Chunk) -> None:
        ch.omega_fine, _ = rates(ch.t_fine)
        w, dw = rates(ch.t)
        ch.lin_acc_body = np.cross(dw, r) + np.cross(w, np.cross(w, r))
        acc = np.zeros((ch.t.size, 3))
        acc[:, 2] = c.args["bounce"] * GRAVITY * np.cos(2 * w0 * ch.t)
        ch.lin_acc = acc
    return chunk


def _laps(c: Context) -> ChunkFn:
    """Laps at speed (a vehicle, a runner on a track): level, moving forward along the body's x
    axis at ``speed`` m/s, a straight of ``straight`` s, then a half turn to the left over
    ``turn_time`` s (the yaw rate a smooth pulse, up to ``2π/turn_time`` rad/s), and again. In a
    turn the body feels the centripetal acceleration ``v Ω`` along its y axis, across gravity,
    for as long as the turn lasts: an acceleration that points the same way in the body for
    seconds, which no low-pass of the accelerometer averages out."""
    c.level_start = True
    v, s0, tt = c.args["speed"], c.args["straight"], c.args["turn_time"]
    period = s0 + tt
    c.intervals["turning"] = [(k * period + s0, (k + 1) * period)
                              for k in range(int(c.duration // period))]

    def yaw_rate(t: np.ndarray) -> np.ndarray:
        tau = np.mod(t, period) - s0
        return np.where(tau > 0.0, (np.pi / tt) * (1.0 - np.cos(2.0 * np.pi * tau / tt)), 0.0)

    def chunk(ch: Chunk) -> None:
        w = np.zeros((ch.t_fine.size, 3))
        w[:, 2] = yaw_rate(ch.t_fine)
        ch.omega_fine = w
        a = np.zeros((ch.t.size, 3))
        a[:, 1] = v * yaw_rate(ch.t)
        ch.lin_acc_body = a
    return chunk


def _slow_turn(c: Context) -> ChunkFn:
    """Level, at rest for ``rest`` s, then a steady turn about the vertical at ``turn_rate``
    rad/s (a robot turning slowly: a turn rest detection must not take for a bias) with a linear
    vibration of ``vib_acc`` m/s² (a rolling robot; 0 = a perfectly smooth turn, which no IMU can
    tell from a gyro bias)."""
    c.level_start = True
    shake = (c.draws("normal", 0.0, c.args["vib_acc"], (c.n, 3))
             if c.args["vib_acc"] > 0 else None)
    c.intervals["turning"] = [(float(c.args["rest"]), c.duration)]

    def chunk(ch: Chunk) -> None:
        w = np.zeros((ch.t_fine.size, 3))
        w[ch.t_fine >= c.args["rest"], 2] = c.args["turn_rate"]
        ch.omega_fine = w
        if shake is not None:
            moving = (ch.t >= c.args["rest"])[:, None]
            ch.lin_acc = moving * shake.take(ch.t.size)
    return chunk


def _mag_attached(c: Context) -> ChunkFn:
    """A magnet attached to the body (a disturbance the magnetometer checks must refuse, like
    BROAD's attached-magnet trials): a constant field ``mag_offset`` (T, body axes; hundreds of µT
    at 1 cm) from 0.3 to 0.7 of the recording, on slow motion: it turns with the body, so the
    measured north swings."""
    slow = _SlowRates(c.rng)
    a, b = 0.3 * c.duration, 0.7 * c.duration
    c.intervals["mag_disturbed"] = [(float(a), float(b))]

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        on = ((ch.t >= a) & (ch.t < b))[:, None]
        ch.mag_body = on * np.asarray(c.args["mag_offset"], float)
    return chunk


def _dropouts(c: Context) -> ChunkFn:
    """Lost messages on slow motion: a short gap (5 samples), a long one (``gap`` s, longer than
    the filters' default ``max_dt``), and a magnetometer outage of 2 s."""
    slow = _SlowRates(c.rng)
    d = c.duration
    dt = 1.0 / c.rate
    ivs = [(0.25 * d, 0.25 * d + 5 * dt), (0.5 * d, 0.5 * d + c.args["gap"])]
    ma, mb = 0.7 * d, min(0.7 * d + 2.0, d)
    # intervals span the true times of the missing samples (runs of the masks, over the chunks)
    c.intervals["dropout"] = []
    c.intervals["mag_dropout"] = []

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        drop = np.zeros(ch.t.size, dtype=bool)
        for a, b in ivs:
            drop |= (ch.t > a) & (ch.t < b + 0.5 * dt)
        ch.drop = drop
        ch.mag_drop = (ch.t >= ma) & (ch.t < mb)
        ch.runs["dropout"] = drop
        ch.runs["mag_dropout"] = ch.mag_drop
    return chunk


def _jitter(c: Context) -> ChunkFn:
    """Stamps off the true sampling instants by up to ± ``jitter`` sample periods (uniform;
    below 0.5 they stay increasing), on slow motion."""
    slow = _SlowRates(c.rng)
    j = c.args["jitter"] / c.rate
    offsets = c.draws("uniform", -j, j, (c.n,))

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        ch.stamps = ch.t + offsets.take(ch.t.size)
    return chunk


def _first_at_or_after(x: float, n: int, dt: float) -> int:
    """``np.searchsorted(np.arange(n) * dt, x)`` without the array: the first sample index
    whose instant ``i · dt`` is not before ``x`` (``n`` if none)."""
    k = min(max(math.ceil(x / dt), 0), n) if math.isfinite(x / dt) else (0 if x < 0 else n)
    while k > 0 and (k - 1) * dt >= x:
        k -= 1
    while k < n and k * dt < x:
        k += 1
    return k


def _time_jump(c: Context) -> ChunkFn:
    """Stamps jump back by ``jump`` s at ``jump_at`` · duration (a clock reset or a bag loop),
    then run on; the motion (slow) does not notice."""
    slow = _SlowRates(c.rng)
    dt = 1.0 / c.rate
    k = _first_at_or_after(c.args["jump_at"] * c.duration, c.n, dt)
    jump = c.args["jump"]
    if 0 < k < c.n:
        c.extra["time_jumps"] = [(k, float((k - 1) * dt), float(k * dt - jump))]

    def chunk(ch: Chunk) -> None:
        ch.omega_fine = slow(ch.t_fine)
        stamps = ch.t.copy()
        stamps[max(k - ch.i0, 0):] -= jump
        ch.stamps = stamps
    return chunk


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
    Scenario("mag_field_change", "the undisturbed field's magnitude and dip change for good "
             "(another room)", _mag_field_change,
             {"change_at": 0.25, "mag_change": (0.0, -11.32e-6, 5.71e-6)}),
    Scenario("accel_bursts", "translational acceleration bursts up to acc_peak g",
             _accel_bursts, {"acc_peak": 3.0, "burst_every": 3.0}),
    Scenario("shaking", "sustained shaking up to shake_acc g with rocking up to shake_rate "
             "rad/s", _shaking, {"shake_acc": 10.0, "shake_freq": 4.0, "shake_rate": 6.0}),
    Scenario("running", "running with the sensor in a pocket: the thigh's swing (its "
             "centripetal acceleration along fixed body axes) and the steps' bounce, for minutes",
             _running, {"stride_freq": 1.4, "swing": 0.6, "lever": 0.35, "bounce": 1.5}),
    Scenario("laps", "laps at speed: straights and half turns, the turns' centripetal "
             "acceleration across gravity", _laps,
             {"speed": 3.0, "straight": 4.0, "turn_time": 3.0}),
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


class _Runs:
    """Maximal runs of a per-sample mask fed chunk by chunk, as (t_first, t_last) pairs
    appended to ``out`` (what :func:`_intervals_where` gives for the whole mask)."""

    def __init__(self, out: list[tuple[float, float]]) -> None:
        self.out = out
        self.open: tuple[float, float] | None = None

    def add(self, t: np.ndarray, mask: np.ndarray) -> None:
        if not mask.size:
            return
        runs = _intervals_where(t, mask)
        if self.open is not None:
            if mask[0]:
                runs[0] = (self.open[0], runs[0][1])
            else:
                self.out.append(self.open)
            self.open = None
        if mask[-1]:
            self.open = runs.pop()
        self.out.extend(runs)

    def close(self) -> None:
        if self.open is not None:
            self.out.append(self.open)
            self.open = None


#: Rate-grid steps per chunk that :class:`SimStream` aims at by default (~30 MB of arrays).
CHUNK_FINE_STEPS = 1 << 18
#: At most this many samples per chunk by default.
CHUNK_SAMPLES = 8192


@dataclass(frozen=True)
class Sensors:
    """The simulated sensors of a :class:`SimStream`: white noise per sample of the gyro (rad/s),
    the accelerometer (m/s²) and the magnetometer (T); a constant gyro bias added to the
    scenario's (rad/s); the Earth field in ENU (T); the magnetometer's own rate (Hz; NaN rows
    between its samples; None: one with every IMU sample)."""

    gyro_noise: float = 0.01
    acc_noise: float = 0.05
    mag_noise: float = 0.5e-6
    gyro_bias: object = (0.0, 0.0, 0.0)
    mag_field: np.ndarray = field(default_factory=lambda: MAG_FIELD_ENU)
    mag_rate: float | None = None


#: The keywords of :class:`SimStream` and :func:`simulate` that describe the sensors.
SENSOR_ARGS = frozenset(f.name for f in fields(Sensors))


class SimStream:
    """A synthetic recording of ``duration`` s at ``rate`` Hz generated chunk by chunk in bounded
    memory. ``q0`` is the initial attitude (default: random, uniform on S³; level with a random
    heading for ``sweep``); the other keywords are the sensors' (the fields of :class:`Sensors`:
    noise, a constant gyro bias added to the scenario's, the Earth field, the magnetometer's
    rate) and the scenario's own parameters (``SCENARIOS[name].params``); ``chunk``: samples per
    chunk, default ~2¹⁸ steps of the rate
    grid and at most :data:`CHUNK_SAMPLES`. Iterating yields :class:`SimData` chunks in time
    order (dropped samples removed, so a chunk may be empty) whose concatenation is
    :func:`simulate`'s result, whatever the chunk size. Every chunk shares :attr:`meta`, which
    is complete (the truth intervals found on the way, e.g. ``gimbal_lock``) once the iteration
    has ended. One pass only: the random draws are consumed."""

    def __init__(
        self,
        scenario: str = "slow_rotation",
        *,
        duration: float = 20.0,
        rate: float = 100.0,
        seed: int = 0,
        substeps: int = 100,
        q0: np.ndarray | None = None,
        chunk: int | None = None,
        **kwargs: Any,
    ) -> None:
        sensors = Sensors(**{k: kwargs.pop(k) for k in list(kwargs) if k in SENSOR_ARGS})
        scenario_args = kwargs
        gyro_noise, acc_noise, mag_noise = sensors.gyro_noise, sensors.acc_noise, sensors.mag_noise
        gyro_bias, mag_field, mag_rate = sensors.gyro_bias, sensors.mag_field, sensors.mag_rate
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
        if chunk is not None and chunk < 1:
            raise ValueError(f"chunk must be at least 1 sample, got {chunk!r}")
        rng = np.random.default_rng(seed)
        self.n = n = round(duration * rate) + 1  #: samples (before dropped ones are removed)
        self.dt = dt = 1.0 / rate
        self.substeps = substeps
        self.fine_dt = fine_dt = dt / substeps
        self.m = m = (n - 1) * substeps  #: steps of the rate grid
        q0_random = rng.normal(size=4)
        # the scenario sees a grid of at least two steps (its draws are sized by it)
        ctx = Context(rng=rng, n=n, m=m if m > 1 else 2, rate=rate, fine_dt=fine_dt,
                      duration=duration, args=dict(sc.params, **scenario_args))
        self._fill = sc.fill(ctx)
        if q0 is None:
            q0 = q0_random
            if ctx.level_start:
                yaw = np.arctan2(q0_random[0], q0_random[1])
                q0 = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        self.q0 = np.asarray(q0, dtype=float) / np.linalg.norm(q0)
        # the noise of each sensor is drawn after everything above, gyro, then accelerometer,
        # then magnetometer, each (n, 3) at once: three generators at those three positions
        self._noise = []
        for _ in range(3):
            g = np.random.Generator(type(rng.bit_generator)())
            g.bit_generator.state = rng.bit_generator.state
            self._noise.append(g)
            skip_draws(rng, "normal", 3 * n)
        self.gyro_noise, self.acc_noise, self.mag_noise = gyro_noise, acc_noise, mag_noise
        self.gyro_bias = np.asarray(gyro_bias, dtype=float)
        self.mag_field = np.asarray(mag_field, float)
        self.mag_rate = mag_rate
        self.duration = duration
        self.rate = rate
        if chunk is None:
            chunk = max(1, min(CHUNK_SAMPLES, CHUNK_FINE_STEPS // substeps))
        self.chunk = chunk
        self.meta: dict[str, Any] = dict(
            scenario=scenario, rate=rate, seed=seed, duration=duration,
            mag_field=self.mag_field, mag_rate=mag_rate, gyro_noise=gyro_noise,
            acc_noise=acc_noise, mag_noise=mag_noise, description=sc.description,
            params=dict(ctx.args), intervals=dict(ctx.intervals), **ctx.extra)
        self._used = False

    def __len__(self) -> int:
        """Samples before dropped ones are removed."""
        return self.n

    def _mag_keep(self, i0: int, i1: int) -> np.ndarray:
        """(i1 - i0,) bool: the samples of ``i0 .. i1 - 1`` on the magnetometer's grid, as
        ``round(arange(0, duration, 1 / mag_rate) · rate)`` (its values in that range)."""
        assert self.mag_rate is not None
        step = 1.0 / self.mag_rate
        count = math.ceil(self.duration / step)  # len(np.arange(0, duration, step))
        per = step * self.rate  # samples per magnetometer sample (≥ 1 in practice)
        k0 = max(0, math.floor((i0 - 1) / per) - 2)
        k1 = min(count, math.ceil((i1 + 1) / per) + 2)
        idx = np.round(np.arange(k0, k1) * step * self.rate).astype(int)
        idx = idx[(idx >= i0) & (idx < i1)]
        keep = np.zeros(i1 - i0, dtype=bool)
        keep[idx - i0] = True
        return keep

    def __iter__(self) -> Iterator[SimData]:
        if self._used:
            raise RuntimeError("a SimStream is iterated once (make a new one)")
        self._used = True
        n, S, K = self.n, self.substeps, self.chunk
        integ = Integrator(self.q0, self.m, self.fine_dt, every=S) if self.m else None
        runs = {k: _Runs(v) for k, v in self.meta["intervals"].items()}
        lock = _Runs([])
        up = np.array([0.0, 0.0, GRAVITY])
        ng, na, nm = self._noise
        # the first chunk holds sample 0 too: its rate is the first one of the grid
        bounds = [0, *range(min(n, K + 1), n, K), n]
        for i0, i1 in itertools.pairwise(bounds):
            j0, j1 = max(i0 - 1, 0) * S, (i1 - 1) * S
            t = np.arange(i0, i1) * self.dt
            ch = Chunk(i0=i0, i1=i1, t=t, j0=j0, j1=j1,
                       t_fine=np.arange(j0, j1) * self.fine_dt)
            self._fill(ch)
            assert ch.omega_fine is not None, f"scenario {self.meta['scenario']} set no rate"
            w = ch.omega_fine
            k = i1 - i0
            if integ is None:  # one sample: no steps
                quat = self.q0[None, :].copy()
                omega = np.zeros((k, 3))
            else:
                quat = integ.advance(np.ascontiguousarray(w))
                # what the gyro reports: the mean rate over the sample interval that ends at
                # its stamp (a MEMS gyro's anti-alias filter and decimation; at t=0 the first
                # rate)
                mean = w.reshape(-1, S, 3).mean(axis=1)
                if i0 == 0:
                    quat = np.concatenate([integ.start[None, :], quat])
                    omega = np.vstack([w[:1], mean])
                else:
                    omega = mean
            R = rotmat_np(quat)
            bias = np.broadcast_to(self.gyro_bias, (k, 3)).copy()
            if ch.bias is not None:
                bias = bias + ch.bias
            lin_acc = np.zeros((k, 3)) if ch.lin_acc is None else ch.lin_acc
            mag_dist = np.zeros((k, 3)) if ch.mag_dist is None else ch.mag_dist
            gyr = omega + bias + ng.normal(0, self.gyro_noise, (k, 3))
            if ch.lin_acc_body is not None:  # into the world frame: one model, lin_acc
                lin_acc = lin_acc + np.einsum("nij,nj->ni", R, ch.lin_acc_body)
            acc = np.einsum("nji,nj->ni", R, up + lin_acc) + na.normal(0, self.acc_noise, (k, 3))
            mag = np.einsum("nji,nj->ni", R, self.mag_field + mag_dist) + \
                nm.normal(0, self.mag_noise, (k, 3))
            mag_body = np.zeros((k, 3)) if ch.mag_body is None else ch.mag_body
            mag = mag + mag_body
            if self.mag_rate is not None:
                mag[~self._mag_keep(i0, i1)] = np.nan
            if ch.mag_drop is not None:
                mag[ch.mag_drop] = np.nan
            stamps = t.copy() if ch.stamps is None else ch.stamps
            for kind, mask in ch.runs.items():
                runs[kind].add(t, mask)
            pitch_lock = np.abs(pitch_deg(quat)) > 80.0
            if pitch_lock.any() or lock.open is not None:
                lock.add(t, pitch_lock)
                if lock.out or lock.open is not None:
                    self.meta["intervals"].setdefault("gimbal_lock", lock.out)
            sd = SimData(t=stamps, gyr=gyr, acc=acc, mag=mag, quat=quat, omega=omega, bias=bias,
                         meta=self.meta, t_true=t, lin_acc=lin_acc, mag_dist=mag_dist,
                         mag_body=mag_body)
            yield sd if ch.drop is None else _select(sd, ~ch.drop)
        for r in runs.values():
            r.close()
        lock.close()


def simulate(scenario: str = "slow_rotation", **kwargs: Any) -> SimData:
    """Synthesise a recording (see the module doc), the arguments those of :class:`SimStream`
    (``duration``, ``rate``, ``seed``, noise, ``gyro_bias``, ``mag_field``, ``mag_rate``,
    ``q0``, ``chunk`` and the scenario's own parameters, ``SCENARIOS[name].params``). The
    whole recording in memory: the stream's chunks concatenated (``chunk`` does not change the
    result); for long recordings iterate a :class:`SimStream`."""
    stream = SimStream(scenario, **kwargs)
    return concat(list(stream), stream.meta)


_FIELDS = ("t", "gyr", "acc", "mag", "quat", "omega", "bias", "t_true", "lin_acc", "mag_dist",
           "mag_body")


def concat(chunks: list[SimData], meta: dict[str, Any]) -> SimData:
    """One :class:`SimData` of consecutive chunks (with ``meta``)."""
    if not chunks:
        raise ValueError("no chunks")
    return SimData(meta=meta, **{k: np.concatenate([getattr(c, k) for c in chunks])
                                 for k in _FIELDS})


def _select(sd: SimData, keep: np.ndarray) -> SimData:
    """The rows of ``sd`` where ``keep`` is true (dropped messages vanish entirely)."""
    return SimData(meta=sd.meta, **{k: getattr(sd, k)[keep] for k in _FIELDS})
