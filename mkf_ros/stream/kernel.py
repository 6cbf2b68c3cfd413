"""Compiled event loop of :class:`mkf_ros.stream.adapter.StreamAdapter`: every time and input rule.

The adapter's rules (see :mod:`mkf_ros.stream` for what they are) are implemented once, here,
as kernels over a merged sequence of IMU and magnetometer events. The per-message methods
(``on_imu``, ``on_mag``) run a one-event sequence through :func:`run_events`; the batch entry
(``process``) runs a whole recording through it. Only resets leave the compiled loop: the
kernel stops at the event that needs one, Python resets the filter (new state) and the loop
resumes, so both paths share every rule, bit for bit.

Records (one definition each, below): the adapter's node parameters (:data:`NODE`), its time
state with the magnetometer samples held for the IMU stream and, with split input, the
accelerometer samples held for the gyro stream (:data:`STREAM`; rows ``stamp, v`` in stamp
order, equal stamps in arrival order), its own counters (:data:`ADAPTER_COUNTER_RECORD`), the
events (:data:`EVENT`) and the outputs, one per IMU (gyro) message (:data:`OUTPUT`, flags
``OF_*``). The filter's records travel together as a :class:`FilterRecords`, the adapter's as
a :class:`StreamRecords`.

Every function that runs a filter step is inlined into :func:`run_events` (numba IR), so that
the filter's compiled code is linked into one kernel here: numba links (and re-optimises) a
callee's machine code into every compiled function that calls it, directly or not (measured:
each such function cost another 8–10 s of compile time).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.filter import (
    ACC,
    GYR,
    MAG,
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    YAW_VAR_UNKNOWN,
    bias,
    bias_variance,
    classify_reading,
    count_reading,
    gap_count,
    gravity,
    heading_fixed,
    is_initialized,
    kernels_at,
    max_dt,
    rate,
    rate_covariance,
    run_step,
    uses_mag,
)
from mkf_ros.core.quaternion import q_from_rotvec, qmul, rotate_inv, rotmat, t3
from mkf_ros.core.smoother import recorded_step

#: Out-of-order IMU samples in a row after which the stream is taken to have jumped back.
MAX_BACKWARDS = 10
#: Magnetometer (and, split input, accelerometer) samples held while waiting for the IMU
#: (gyro) stream to reach their stamps, per sensor.
MAX_PENDING_MAG = 32
#: Smallest time step of an internal magnetometer-only filter step (the MUKF cannot
#: factorise its sigma points with zero process noise at dt = 0).
MIN_STEP = 1e-9
#: A magnetometer stamp this close to an IMU stamp is fused in the same filter step.
SAME_STAMP = 1e-6
#: Rows of a held-samples table: one more than it keeps (a sample is inserted, then the oldest
#: dropped).
PEND_ROWS = MAX_PENDING_MAG + 1
NAN3 = (np.nan, np.nan, np.nan)

#: The adapter's own counters (the filter's are synced separately).
ADAPTER_COUNTERS = (
    "imu_received", "imu_duplicate", "imu_out_of_order", "imu_bad_stamp",
    "gyr_missing", "gyr_invalid", "acc_missing", "acc_invalid", "acc_implausible",
    "mag_received", "mag_unused", "mag_missing", "mag_invalid", "mag_too_old", "mag_ahead",
    "mag_overflow", "mag_fused", "output_nonfinite", "resets", "resets_time_jump",
    "acc_received", "acc_too_old", "acc_ahead", "acc_overflow", "acc_fused",
)
ADAPTER_COUNTER_RECORD = np.dtype([(name, np.int64) for name in ADAPTER_COUNTERS])

#: The node parameters as the rules read them (the filter's own are in its configuration).
NODE = np.dtype(
    [
        ("constant_dt", np.float64),
        ("time_jump_threshold", np.float64),
        ("acc_magnitude_tolerance", np.float64),
        ("mag_max_delay", np.float64),
        ("acc_max_delay", np.float64),
        ("orientation_stddev", np.float64),
        ("av_source", np.int64),  # angular_velocity_source, index in AV_SOURCES
        ("remove_gravity_vector", np.bool_),
        ("split", np.bool_),  # input_mode split
        ("has_offset", np.bool_),  # a yaw offset / declination turns the output
        ("q_offset", np.float64, 4),  # that turn about world up, in world axes
        ("R_offset", np.float64, (3, 3)),  # its rotation matrix
        ("up_world", np.float64, 3),  # world up in world_frame axes
    ],
    align=True,
)
#: ``angular_velocity_source`` choices, in ``av_source`` code order.
AV_SOURCES = ("input", "bias_corrected", "estimate")
AV_INPUT, AV_BIAS_CORRECTED, AV_ESTIMATE = 0, 1, 2

#: The adapter's time state: filter time and whether it is set, heading lost in a gap,
#: out-of-order run, the held samples (these, cleared by a reset: :data:`RESET_FIELDS`),
#: latest magnitudes/offset/stamps, time-step statistics, and whether a usable gyro reading
#: that is not exactly zero, and a usable accelerometer reading, ever arrived (input checks).
STREAM = np.dtype(
    [
        ("t", np.float64),  # the filter's time (s)
        ("valid", np.bool_),  # the first IMU sample has set it
        ("yaw_lost", np.bool_),  # a gap: heading unknown until the magnetometer fixes it
        ("backwards", np.int64),  # out-of-order IMU samples in a row
        ("n_mag", np.int64),  # magnetometer samples held
        ("n_acc", np.int64),  # accelerometer samples held (split input)
        ("mag_held", np.float64, (PEND_ROWS, 4)),  # rows: stamp, field
        ("acc_held", np.float64, (PEND_ROWS, 4)),  # rows: stamp, specific force
        ("acc_norm", np.float64),  # latest finite accelerometer magnitude (m/s²)
        ("mag_norm", np.float64),  # latest finite magnetometer magnitude
        ("mag_offset", np.float64),  # latest magnetometer stamp − filter time (s)
        ("last_imu", np.float64),  # latest stamps (s)
        ("last_mag", np.float64),
        ("last_acc", np.float64),
        ("dt_n", np.int64),  # IMU time steps since the statistics were read ...
        ("dt_min", np.float64),
        ("dt_sum", np.float64),
        ("dt_max", np.float64),
        ("gyr_seen", np.bool_),
        ("acc_seen", np.bool_),
        ("resume", np.bool_),  # the next IMU event is the same sample again, after a reset
    ],
    align=True,
)
#: :data:`STREAM` fields a reset clears.
RESET_FIELDS = ("t", "valid", "yaw_lost", "backwards", "n_mag", "n_acc")

#: One input event: stamp, the gyro / magnetometer / (split input) accelerometer vector, the
#: accelerometer of an IMU message, kind (``EV_*``) and output row (IMU events).
EVENT = np.dtype([("stamp", np.float64), ("v", np.float64, 3), ("a", np.float64, 3),
                  ("kind", np.int64), ("row", np.int64)])
EV_IMU, EV_MAG, EV_ACC = 0, 1, 2  # EV_ACC: split input, an accelerometer sample in v

#: One output per IMU (gyro) message; ``present``: published, and which optional fields are
#: present (an absent one is NaN).
OUTPUT = np.dtype([("present", np.int64), ("q", np.float64, 4), ("cov", np.float64, (3, 3)),
                   ("w", np.float64, 3), ("wcov", np.float64, (3, 3)), ("wadd", np.float64, 3),
                   ("lin", np.float64, 3), ("omega", np.float64, 3), ("bias", np.float64, 3),
                   ("bstd", np.float64, 3), ("slot", np.int64)])
#: ``OF_YAW_LOST``: published with the heading lost in a gap (yaw variance raised to
#: YAW_VAR_UNKNOWN); ``slot``: the smoother's record of this output's filter step (-1: not
#: recording).
OF_PUB, OF_W, OF_WCOV, OF_WADD, OF_LIN, OF_HEADING, OF_YAW_LOST = 1, 2, 4, 8, 16, 32, 64


def float_slice(dtype: np.dtype, name: str) -> slice:
    """Where field ``name`` of a record of 8-byte fields lies in the record viewed as float64
    values (``array.view(np.float64)``)."""
    assert dtype.fields is not None
    sub, offset = dtype.fields[name][:2]
    return slice(offset // 8, offset // 8 + sub.itemsize // 8)

#: The filter's records (:meth:`mkf_ros.core.filter.AttitudeFilter.kernel_arrays`, element
#: ``[0]`` of each: configuration, state, counters, scratch), its compiled kernels, and the
#: smoother's recording (:func:`filter_step`): the slots
#: (:data:`~mkf_ros.core.smoother.RECORD`) and ``rn = [slots filled, 1 if out of room, limit,
#: base]``: :func:`run_events` returns ``R_FULL`` after the event that filled ``limit`` slots
#: (0: no limit); ``base`` is the global number of ``rec[0]`` (outputs name global slots).
FilterRecords = namedtuple("FilterRecords", ("c", "s", "k", "w", "kern", "rec", "rn"))
#: The adapter's records: node parameters, time state, counters.
StreamRecords = namedtuple("StreamRecords", ("p", "t", "a"))

# the outcome of one IMU event: nothing published, published, or a reset request; run_events
# returns R_DONE or the reset request with the index of the event it stopped at
_NONE, _OUT, R_TIME_JUMP, R_NONFINITE = 0, 1, 2, 3
#: run_events stopped after an event that filled the smoother's recording up to its limit
#: (call again from ``k`` once the recording has room)
R_FULL = 4
#: Filter steps one event can make (an IMU event: every held magnetometer and accelerometer
#: sample, then its own): room the smoother's recording keeps beyond its limit.
MAX_STEPS_PER_EVENT = 2 * PEND_ROWS + 1
R_DONE = 0


@jit
def norm3(v: np.ndarray) -> float:
    """Euclidean norm without overflow or underflow (like ``math.hypot``)."""
    m = max(abs(v[0]), abs(v[1]), abs(v[2]))
    if m == 0.0 or not np.isfinite(m):
        return m
    x, y, z = v[0] / m, v[1] / m, v[2] / m
    return m * np.sqrt(x * x + y * y + z * z)


@jit
def input_class(a: np.record, v: np.ndarray, sensor: int, is_vector: bool,
                limit: float) -> int:
    """0 if ``v`` is a usable reading, 1 missing (no reading), 2 invalid; counted. The
    filter's own rule, :func:`~mkf_ros.core.filter.classify_reading` with its plausibility
    limits (``limit``: a gyro faster than :data:`~mkf_ros.core.filter.MAX_GYRO_RATE` is
    invalid, etc.)."""
    cls = classify_reading((v[0], v[1], v[2]), is_vector, limit)
    count_reading(a, cls, sensor)
    return cls


@jit
def rotate_back(v: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """``Exp(−θ) v = R(q(θ))ᵀ v``: a world-fixed vector seen after the body turned by ``θ``."""
    th = norm3(rotvec)
    if not 1e-12 < th < 1e3:  # no rotation, or a diverged rate: leave the vector as it is
        return v
    return rotate_inv(q_from_rotvec(rotvec), v)


@jit
def covariance_rows(c: np.ndarray, stddev: float, add: np.ndarray) -> None:
    """Published covariances from the input's, in place (rows of 9, see
    :func:`mkf_ros.stream.rep145.covariance_out`); ``add`` has one row per row of ``c``, one for
    all, or none."""
    for i in range(c.shape[0]):
        row = c[i]
        if row[0] == -1.0 or not np.isfinite(row.sum()):
            row[:] = 0.0
        if not row.any():
            if stddev <= 0.0:
                continue
            row[0] = row[4] = row[8] = stddev * stddev
        if add.shape[0]:
            row += add[i if add.shape[0] > 1 else 0]


# --- magnetometer (split input: accelerometer) samples held for the IMU (gyro) stream --------
# ``t.mag_held`` holds magnetometer samples (count ``t.n_mag``), ``t.acc_held`` accelerometer
# samples (count ``t.n_acc``); ``is_acc`` selects the sensor in the functions below.


@jit
def _held(t: np.record, is_acc: bool) -> tuple[np.ndarray, int]:
    """The held samples of a sensor and their count."""
    return (t.acc_held, t.n_acc) if is_acc else (t.mag_held, t.n_mag)


@jit
def _set_count(t: np.record, is_acc: bool, n: int) -> None:
    if is_acc:
        t.n_acc = n
    else:
        t.n_mag = n


@jit
def _pop_front(t: np.record, k: int, is_acc: bool) -> None:
    """Drop the ``k`` oldest held samples of a sensor."""
    buf, n = _held(t, is_acc)
    for i in range(n - k):
        for j in range(4):
            buf[i, j] = buf[i + k, j]
    _set_count(t, is_acc, n - k)


@jit
def _count_dropped(a: np.record, is_acc: bool, n: int, why: int) -> None:
    """Count ``n`` samples of a sensor dropped: too old (0), ahead (1), overflow (2)."""
    if why == 0:
        if is_acc:
            a.acc_too_old += n
        else:
            a.mag_too_old += n
    elif why == 1:
        if is_acc:
            a.acc_ahead += n
        else:
            a.mag_ahead += n
    elif is_acc:
        a.acc_overflow += n
    else:
        a.mag_overflow += n


@jit
def hold(t: np.record, a: np.record, stamp: float, m: np.ndarray, is_acc: bool) -> None:
    """Insert a sample in stamp order (after equal stamps); the oldest goes on overflow."""
    buf, n = _held(t, is_acc)
    i = n
    while i > 0 and buf[i - 1, 0] > stamp:
        for j in range(4):
            buf[i, j] = buf[i - 1, j]
        i -= 1
    buf[i, 0] = stamp
    for j in range(3):
        buf[i, 1 + j] = m[j]
    _set_count(t, is_acc, n + 1)
    if n + 1 > MAX_PENDING_MAG:
        _pop_front(t, 1, is_acc)
        _count_dropped(a, is_acc, 1, 2)


@jit_inline
def filter_step(f: FilterRecords, dt: float, gyr: tuple, acc: tuple, mag: tuple) -> None:
    """One filter step; with the configuration's ``record_posterior`` (the smoother's forward
    pass, ``mkf process --smooth``) recorded into the next slot of ``f.rec``
    (:func:`~mkf_ros.core.smoother.recorded_step`), or, with no slot left, not recorded and
    ``f.rn[1]`` set (the caller reserves room for every event: each makes at most one step)."""
    if f.c.record_posterior:
        n = f.rn[0]
        if n < f.rec.shape[0]:
            recorded_step(f.kern, f.c, f.s, f.k, f.w, dt, gyr, acc, mag, f.rec, n)
            f.rn[0] = n + 1
            return
        f.rn[1] = 1
    run_step(f.kern, f.c, f.s, f.k, f.w, dt, gyr, acc, mag)


@jit_inline
def _filter_step(f: FilterRecords, a: np.record, dt: float, v: np.ndarray,
                 is_acc: bool) -> None:
    """One filter step with only a magnetometer (or accelerometer) sample; counted."""
    filter_step(f, dt, NAN3, t3(v) if is_acc else NAN3,
             NAN3 if is_acc else t3(v))
    if is_acc:
        a.acc_fused += 1
    else:
        a.mag_fused += 1


@jit_inline
def fuse_now(f: FilterRecords, a: np.record, v: np.ndarray, age: float, is_acc: bool) -> None:
    """Fuse a magnetometer (or accelerometer) sample at the filter's current time, rotated
    forward over its ``age`` (s): both measure a world-fixed vector in body axes."""
    if age > 0.0 and is_initialized(f.s) and np.isfinite(v[0] + v[1] + v[2]):
        w = np.empty(3)
        for i in range(3):
            w[i] = rate(f.s, i) * age
        v = rotate_back(v, w)
    _filter_step(f, a, MIN_STEP, v, is_acc)


@jit_inline
def fuse_late(f: FilterRecords, r: StreamRecords, stamp: float, m: np.ndarray,
              is_acc: bool) -> None:
    """A sample stamped at or before the filter time: fused now if recent enough
    (``mag_max_delay``, ``acc_max_delay``)."""
    age = r.t.t - stamp
    if age > (r.p.acc_max_delay if is_acc else r.p.mag_max_delay) + SAME_STAMP:
        _count_dropped(r.a, is_acc, 1, 0)
        return
    fuse_now(f, r.a, m, max(age, 0.0), is_acc)


@jit
def _first_pending(r: StreamRecords, t_new: float, tol: float, same: np.ndarray,
                   is_acc: bool) -> bool:
    """On the first IMU sample: keep the held samples ahead of it, drop the older ones but the
    latest within ``tol``, which goes in ``same`` to be fused with it (True if so)."""
    buf, n = _held(r.t, is_acc)
    n_keep = 0
    n_near = 0
    for i in range(n):
        p = buf[i, 0]
        if p > t_new + SAME_STAMP:
            n_keep += 1
        elif abs(t_new - p) <= tol:
            n_near += 1
            for j in range(3):
                same[j] = buf[i, 1 + j]
    _count_dropped(r.a, is_acc, n - n_keep - min(n_near, 1), 0)
    _pop_front(r.t, n - n_keep, is_acc)  # sorted: the kept ones are the newest
    return n_near > 0


@jit
def _drop_unplaceable(r: StreamRecords, t_new: float) -> None:
    """A gap: held samples older than the maximum delay before ``t_new`` cannot be placed."""
    for is_acc in (False, True):
        buf, n = _held(r.t, is_acc)
        x = t_new - (r.p.acc_max_delay if is_acc else r.p.mag_max_delay)
        old = 0
        while old < n and buf[old, 0] < x:
            old += 1
        _count_dropped(r.a, is_acc, old, 0)
        _pop_front(r.t, old, is_acc)


@jit_inline
def take_pending(f: FilterRecords, r: StreamRecords, t_new: float, dt: float,
                 same: np.ndarray, same_a: np.ndarray) -> int:
    """Fuse held samples stamped before ``t_new``, in stamp order (the magnetometer first at
    equal stamps), each at its own stamp; put one stamped at ``t_new`` (or, on the first IMU
    sample, the latest recent one) in ``same`` (magnetometer) / ``same_a`` (accelerometer) to
    fuse with the IMU (gyro) sample. Returns 1 if ``same`` is set, plus 2 if ``same_a`` is."""
    t = r.t
    if not t.valid:  # first sample: initialise with the latest recent samples
        res = 0
        if t.n_mag > 0 and _first_pending(r, t_new, max(r.p.mag_max_delay, SAME_STAMP), same,
                                          False):
            res |= 1
        if t.n_acc > 0 and _first_pending(r, t_new, max(r.p.acc_max_delay, SAME_STAMP),
                                          same_a, True):
            res |= 2
        return res
    if dt > max_dt(f.c):  # a gap: the held samples cannot be placed
        _drop_unplaceable(r, t_new)
    res = 0
    while True:
        m_due = t.n_mag > 0 and t.mag_held[0, 0] <= t_new + SAME_STAMP
        a_due = t.n_acc > 0 and t.acc_held[0, 0] <= t_new + SAME_STAMP
        if not (m_due or a_due):
            break
        is_acc = a_due and not (m_due and t.mag_held[0, 0] <= t.acc_held[0, 0])
        buf, _ = _held(t, is_acc)
        tm = buf[0, 0]
        v = buf[0, 1:4].copy()
        _pop_front(t, 1, is_acc)
        if abs(tm - t_new) <= SAME_STAMP:
            bit = 2 if is_acc else 1
            sm = same_a if is_acc else same
            if res & bit:
                fuse_now(f, r.a, sm.copy(), 0.0, is_acc)
            sm[:] = v
            res |= bit
        elif tm <= t.t:  # held before a reset moved the time: treat as late
            fuse_late(f, r, tm, v, is_acc)
        else:
            _filter_step(f, r.a, max(tm - t.t, MIN_STEP), v, is_acc)
            t.t = tm
    return res


# --- events ---------------------------------------------------------------------------------


@jit_inline
def fuse_untimed(f: FilterRecords, r: StreamRecords, v: np.ndarray, is_acc: bool) -> None:
    """A magnetometer or (split input) accelerometer sample when stamps are not trusted
    (``constant_dt``): fused at the current time; before the first IMU sample kept as the
    one held sample."""
    if not r.t.valid:
        buf, _ = _held(r.t, is_acc)
        buf[0, 0] = 0.0
        buf[0, 1:4] = v
        _set_count(r.t, is_acc, 1)
    else:
        fuse_now(f, r.a, v, 0.0, is_acc)


@jit_inline
def place(f: FilterRecords, r: StreamRecords, stamp: float, v: np.ndarray,
          is_acc: bool) -> None:
    """A checked, stamped magnetometer or (split input) accelerometer sample: held while ahead
    of the IMU (gyro) stream (before its first sample, the latest few), dropped when more than
    ``max_dt`` ahead, else fused now if recent enough (:func:`fuse_late`)."""
    if not r.t.valid:  # before the first IMU sample: keep the latest few
        hold(r.t, r.a, stamp, v, is_acc)
        return
    d = stamp - r.t.t
    if d > max_dt(f.c):
        _count_dropped(r.a, is_acc, 1, 1)
    elif d > SAME_STAMP:
        hold(r.t, r.a, stamp, v, is_acc)
    else:
        fuse_late(f, r, stamp, v, is_acc)


@jit_inline
def mag_event(f: FilterRecords, r: StreamRecords, stamp: float, mag: np.ndarray) -> None:
    """One magnetometer sample: fused now (late), held (ahead of the IMU) or dropped."""
    a, t = r.a, r.t
    a.mag_received += 1
    if not uses_mag(f.c):
        a.mag_unused += 1
        return
    if input_class(a, mag, MAG, True, MAX_MAG) != 0:
        return
    m = mag.copy()
    # hard/soft-iron calibration (mag_bias_*, mag_soft_iron) is applied by the core filter
    norm = norm3(m)
    t.mag_norm = norm
    if not 0.0 < norm < np.inf:
        a.mag_invalid += 1
        return
    # the raw field goes to the filter: it calibrates it and checks its magnitude
    t.last_mag = stamp
    if r.p.constant_dt > 0.0:  # stamps are not trusted: fuse at the current time
        fuse_untimed(f, r, m, False)
        return
    if not np.isfinite(stamp):
        a.mag_invalid += 1
        return
    if t.valid:
        t.mag_offset = stamp - t.t
    place(f, r, stamp, m, False)


@jit_inline
def acc_event(f: FilterRecords, r: StreamRecords, stamp: float, acc: np.ndarray) -> None:
    """One accelerometer sample of split input (its own stream, ``input_mode`` split): like a
    magnetometer sample, held until the gyro stream reaches its stamp and fused there (with
    the gyro sample of the same stamp), fused at once if up to ``acc_max_delay`` late (rotated
    forward by the estimated rate), dropped if older. The same checks as the accelerometer of
    a combined message: a missing, invalid or implausible sample is counted and not fused."""
    a, t = r.a, r.t
    a.acc_received += 1
    if input_class(a, acc, ACC, True, MAX_ACC_G * gravity(f.c)) != 0:
        return
    norm = norm3(acc)
    t.acc_norm = norm
    if abs(norm / gravity(f.c) - 1.0) > r.p.acc_magnitude_tolerance:
        a.acc_implausible += 1
        return
    t.acc_seen = True
    v = acc.copy()
    if r.p.constant_dt > 0.0:  # stamps are not trusted: fuse at the current time
        fuse_untimed(f, r, v, True)
        return
    if not np.isfinite(stamp) or stamp == 0.0:
        a.acc_invalid += 1
        return
    t.last_acc = stamp
    place(f, r, stamp, v, True)


@jit
def _imu_time(r: StreamRecords, stamp: float, resume: bool) -> tuple[int, float, float]:
    """The time rules of an IMU sample: ``(status, t_new, dt)``, status ``_OUT`` to go on,
    ``_NONE`` to drop the sample (bad stamp, duplicate, out of order; counted) or a reset
    request ``R_TIME_JUMP``."""
    a, t, p = r.a, r.t, r.p
    if not resume:
        a.imu_received += 1
    if p.constant_dt > 0.0:
        dt = p.constant_dt if t.valid else 0.0
        return _OUT, (t.t + dt if t.valid else 0.0), dt
    if not np.isfinite(stamp) or stamp == 0.0:
        a.imu_bad_stamp += 1
        return _NONE, 0.0, 0.0
    dt = 0.0
    if t.valid:
        dt = stamp - t.t
        if dt <= 0.0:
            if dt == 0.0:
                a.imu_duplicate += 1
                return _NONE, 0.0, 0.0
            t.backwards += 1
            if -dt <= p.time_jump_threshold and t.backwards < MAX_BACKWARDS:
                a.imu_out_of_order += 1
                return _NONE, 0.0, 0.0
            a.resets_time_jump += 1
            return R_TIME_JUMP, 0.0, 0.0  # Python resets; the sample comes back with resume
    return _OUT, stamp, dt


@jit
def _imu_inputs(f: FilterRecords, r: StreamRecords, gyr: np.ndarray,
                acc: np.ndarray) -> tuple[bool, bool, bool]:
    """The input checks of an IMU sample: ``(has_g, has_a_in, has_a)``, a usable gyro, a usable
    accelerometer reading, and one that passed the plausibility of its magnitude
    (``acc_magnitude_tolerance``); counted."""
    a, t = r.a, r.t
    has_g = input_class(a, gyr, GYR, False, MAX_GYRO_RATE) == 0
    if has_g and (gyr[0] != 0.0 or gyr[1] != 0.0 or gyr[2] != 0.0):
        t.gyr_seen = True
    a_cls = 1 if r.p.split else input_class(a, acc, ACC, True, MAX_ACC_G * gravity(f.c))
    has_a_in = a_cls == 0
    has_a = has_a_in
    if has_a:
        norm = norm3(acc)
        t.acc_norm = norm
        if abs(norm / gravity(f.c) - 1.0) > r.p.acc_magnitude_tolerance:
            a.acc_implausible += 1
            has_a = False
        else:
            t.acc_seen = True
    return has_g, has_a_in, has_a


@jit
def _dt_stats(t: np.record, dt: float) -> None:
    """The IMU time steps' statistics (diagnostics)."""
    if t.valid and dt > 0.0:
        t.dt_n += 1
        t.dt_min = min(t.dt_min, dt)
        t.dt_sum += dt
        t.dt_max = max(t.dt_max, dt)


@jit_inline
def imu_event(f: FilterRecords, r: StreamRecords, stamp: float, gyr: np.ndarray,
              acc: np.ndarray, o: np.record) -> int:
    """One IMU sample (split input: a gyro sample; its accelerometer field is ignored): time
    rules, input checks, held magnetometer (and accelerometer) samples, filter step, output.
    Returns ``_OUT`` (``o`` written), ``_NONE``, or a reset request ``R_*``; with
    ``r.t.resume`` the same sample again after a time-jump reset (already counted). A reading
    that is not usable goes to the filter as missing (all NaN)."""
    o.present = 0
    t = r.t
    status, t_new, dt = _imu_time(r, stamp, t.resume)
    t.resume = False
    if status != _OUT:
        return status
    t.backwards = 0
    t.last_imu = stamp
    has_g, has_a_in, has_a = _imu_inputs(f, r, gyr, acc)
    _dt_stats(t, dt)
    mag = np.empty(3)
    a_in = t3(acc) if has_a else NAN3
    # the call is skipped when nothing is held, as it mostly is (it costs ~0.4 µs)
    has_m = False
    a_held = False
    if t.n_mag > 0 or t.n_acc > 0:
        a_same = np.empty(3)
        res = take_pending(f, r, t_new, dt, mag, a_same)
        has_m = (res & 1) > 0
        if res & 2:
            a_in = t3(a_same)
            a_held = True
    gaps = gap_count(f.k)
    dt_step = dt if not t.valid or r.p.constant_dt > 0.0 else t_new - t.t
    filter_step(f, dt_step, t3(gyr) if has_g else NAN3, a_in,
             t3(mag) if has_m else NAN3)
    if gap_count(f.k) != gaps:
        t.yaw_lost = True
    if has_m:
        r.a.mag_fused += 1
    if a_held:
        r.a.acc_fused += 1
    t.t = t_new
    t.valid = True
    res = output(f, r, gyr, has_g, acc, has_a_in, o)
    o.slot = f.rn[3] + f.rn[0] - 1 if f.c.record_posterior else -1
    return res


@jit
def _offset(p: np.record, q: tuple, cov: np.ndarray) -> tuple:
    """The yaw offset / declination turn applied to the output, covariance in place:
    ``q ← q_off q``, ``Σ ← R Σ Rᵀ``."""
    qo = qmul(p.q_offset, np.array(q))
    R = p.R_offset
    rc = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rc[i, j] = R[i, 0] * cov[0, j] + R[i, 1] * cov[1, j] + R[i, 2] * cov[2, j]
    for i in range(3):
        for j in range(3):
            cov[i, j] = rc[i, 0] * R[j, 0] + rc[i, 1] * R[j, 1] + rc[i, 2] * R[j, 2]
    if qo[0] < 0.0:
        qo = -qo
    return (qo[0], qo[1], qo[2], qo[3])


@jit
def published(p: np.record, q: tuple, cov: np.ndarray, yaw_lost: bool) -> tuple:
    """The node's rules for an orientation and its covariance as published (``cov`` in place,
    the quaternion returned): the yaw offset / declination turn (:func:`_offset`), the yaw
    variance of an unknown heading where ``yaw_lost`` (world z is vertical in ENU, NED and
    NWU), a fixed ``orientation_stddev``. The one place of these rules: the filter's estimate
    (:func:`output`) and the smoother's (:func:`published_batch`) go through it."""
    if p.has_offset:
        q = _offset(p, q, cov)
    if yaw_lost and cov[2, 2] < YAW_VAR_UNKNOWN:
        cov[2, 2] = YAW_VAR_UNKNOWN
    sd = p.orientation_stddev
    if sd > 0.0:
        cov[:, :] = 0.0
        for i in range(3):
            cov[i, i] = sd * sd
    return q


@jit
def published_batch(npar: np.ndarray, quat: np.ndarray, cov: np.ndarray,
                    yaw_lost: np.ndarray) -> None:
    """:func:`published` of every row, in place: ``quat`` (M, 4) ``[w, x, y, z]``, ``cov``
    (M, 3, 3), ``yaw_lost`` (M,); ``npar`` the node's parameter record array."""
    p = npar[0]
    for k in range(quat.shape[0]):
        q = published(p, (quat[k, 0], quat[k, 1], quat[k, 2], quat[k, 3]), cov[k],
                      yaw_lost[k])
        for i in range(4):
            quat[k, i] = q[i]


@jit
def _optional_fields(f: FilterRecords, r: StreamRecords, g: np.ndarray, has_g: bool,
                     acc: np.ndarray, has_a: bool, q: tuple, o: np.record) -> int:
    """The output's optional fields per the node parameters (angular velocity and its
    covariance, linear acceleration with or without gravity); returns their flags."""
    s, p = f.s, r.p
    flags = 0
    o.w[:] = np.nan  # absent unless written below
    o.wcov[:, :] = np.nan
    o.wadd[:] = np.nan
    o.lin[:] = np.nan
    if p.av_source == AV_ESTIMATE:
        flags |= OF_W | OF_WCOV
        for i in range(3):
            o.w[i] = rate(s, i)
            for j in range(3):
                o.wcov[i, j] = rate_covariance(s, i, j)
    elif has_g:
        flags |= OF_W
        for i in range(3):
            o.w[i] = g[i] - bias(s, i) if p.av_source == AV_BIAS_CORRECTED else g[i]
        if p.av_source == AV_BIAS_CORRECTED:
            flags |= OF_WADD
            for i in range(3):
                o.wadd[i] = o.bstd[i] * o.bstd[i]
    if has_a:
        flags |= OF_LIN
        for i in range(3):
            o.lin[i] = acc[i]
        if p.remove_gravity_vector:
            Rq = rotmat(np.array(q))
            up = p.up_world
            for i in range(3):
                up_b = Rq[0, i] * up[0] + Rq[1, i] * up[1] + Rq[2, i] * up[2]
                o.lin[i] = acc[i] - gravity(f.c) * up_b
    return flags


@jit
def output(f: FilterRecords, r: StreamRecords, g: np.ndarray, has_g: bool, a: np.ndarray,
           has_a: bool, o: np.record) -> int:
    """The estimate as published (``o``, an :data:`OUTPUT` record): nothing before
    initialisation, never NaN (a non-finite estimate asks for a reset), then the output
    options."""
    s, t, p = f.s, r.t, r.p
    if not is_initialized(s):
        return _NONE
    qt, ct = f.kern.output(f.c, s)
    cov = np.empty((3, 3))
    tot = qt[0] + qt[1] + qt[2] + qt[3]
    for i in range(3):
        for j in range(3):
            cov[i, j] = ct[i][j]
    tot += cov.sum()
    for i in range(3):
        tot += rate(s, i) + bias(s, i)
    if not np.isfinite(tot):
        r.a.output_nonfinite += 1
        return R_NONFINITE
    heading = heading_fixed(f.c, s)
    if t.yaw_lost and heading:
        t.yaw_lost = False
    q = published(p, qt, cov, t.yaw_lost)
    for i in range(4):
        o.q[i] = q[i]
    for i in range(3):
        for j in range(3):
            o.cov[i, j] = cov[i, j]
        o.omega[i] = rate(s, i)
        o.bias[i] = bias(s, i)
        o.bstd[i] = np.sqrt(bias_variance(f.c, s, i))
    flags = OF_PUB | (OF_HEADING if heading else 0) | (OF_YAW_LOST if t.yaw_lost else 0)
    o.present = flags | _optional_fields(f, r, g, has_g, a, has_a, q, o)
    return _OUT


@jit
def run_events(table: np.ndarray, filt: tuple, npar: np.ndarray, ts: np.ndarray,
               acnt: np.ndarray, rec: np.ndarray, rn: np.ndarray, ev: np.ndarray,
               out: np.ndarray, k0: int, k1: int) -> tuple[int, int]:
    """Events ``k0 … k1-1`` in order (the filter's compiled kernels,
    :func:`~mkf_ros.core.filter.kernel_table`, and its record arrays ``(cfg, st, cnt, work)``
    as a plain tuple: :meth:`~mkf_ros.core.filter.AttitudeFilter.kernel_arrays`, whose
    NamedTuple numba's dispatcher types more slowly at every call; the adapter's, the events
    and the outputs); returns ``(k, R_DONE)`` at the end, or the index
    and reason of an event that needs a reset (``R_TIME_JUMP``: call again from ``k`` with
    the time state's ``resume`` set; ``R_NONFINITE``: the event is done, call again from
    ``k + 1``; ``R_FULL``: the smoother's recording reached its limit, call again from ``k``
    once it has room)."""
    cfg, st, cnt, work = filt
    f = FilterRecords(cfg[0], st[0], cnt[0], work[0], kernels_at(table), rec, rn)
    r = StreamRecords(npar[0], ts[0], acnt[0])
    for k in range(k0, k1):
        e = ev[k]
        if e.kind == EV_MAG:
            mag_event(f, r, e.stamp, e.v)
        elif e.kind == EV_ACC:
            acc_event(f, r, e.stamp, e.v)
        else:
            res = imu_event(f, r, e.stamp, e.v, e.a, out[e.row])
            if res >= R_TIME_JUMP:
                return k, res
        if rn[0] >= rn[2] > 0:
            return k + 1, R_FULL
    return k1, R_DONE
