"""Real ROS 1 bags through ``mkf process``: does the published orientation jump without the gyro
turning, and is the published yaw variance honest?

    ./run bench ros_bags BAG_DIR [--only GLOB] [--set NAME=VALUE ...]
    ./run bench ros_bags BAG_DIR --detail BAG [--algorithm A] [--use-mag] [--at T] [--window S]

e.g. ``./run bench ros_bags ../shared/eval-data/ros-bags`` (five small public ROS 1 bags from
imu_tools and robot_localization, described in that folder's README; not in this repository and
never used by the tests). No ground truth: this checks behaviour, not accuracy.

How: every ``*.bag`` in BAG_DIR goes through :func:`mkf_ros.bags.process.process_bag` (what
``mkf process`` runs: ROS 1 → CDR reading, the node's input conversions, the
:class:`~mkf_ros.stream.adapter.StreamAdapter` time, gap and magnetometer rules) into a throw-away
output bag, with the default parameters (``--set`` overrides them; ``estimate_gyro_bias`` is on by
default), for ``algorithm`` mekf and mukf, without the magnetometer (6D) and, where the bag has a
``sensor_msgs/MagneticField`` topic, with ``use_mag`` true (9D). The IMU topic is the bag's one
``sensor_msgs/Imu`` topic. The same decoded messages also go once more through
:func:`mkf_ros.bags.messages.run_stream` (the glue ``process_bag`` uses) with an adapter that
notes after every message the filter's ``rest_updates`` counter and keeps the per-output
``heading_initialized`` flag; the script checks that this run publishes bit for bit what
``process_bag`` published.

One table row per (bag, algorithm, 6D/9D):

* ``in`` / ``out``: IMU (+ magnetometer) messages in, orientations published;
* ``max step``: the largest angle between consecutive published orientations (°);
* ``jumps``: steps the gyro does not explain by more than 5°: ``angle − |ω|·Δt > 5°``
  (:func:`mkf_ros.evaluation.metrics.unexplained_steps`; ω the input gyro of the later message, Δt
  the stamp difference), with the largest unexplained part and its time (s since the bag start).
  Excused, and shown apart as ``+N ok``: steps after a gap longer than ``max_dt`` (the filter
  re-aligns there by design), the first step with the heading fixed by the magnetometer when
  the yaw variance published just before it was ≥ 1 rad² (the filter had said "heading unknown"),
  and steps whose unexplained part is within one standard deviation, about the step's axis, of
  the orientation covariance published just before (the filter had said it was that uncertain
  about that axis, e.g. after a shake faster than its rate model follows, docs/math.md § 9.3);
* ``max yaw var``: the largest published variance about world z (rad², covariance[8], ENU);
* ``var↓``: jumps (not excused) at which the published yaw variance decreases — "the variance
  drops while the estimate jumps";
* ``pre-heading`` (9D): outputs published before the magnetometer fixed the heading (the
  adapter's ``heading_initialized``), of which before the first magnetometer message arrived,
  and the smallest yaw variance among them;
* ``tilt vs own``: where the IMU topic carries the device's own orientation (a unit quaternion
  that changes: the robot_localization bags, the AR.Drone's), the RMS and max inclination
  difference in degrees between ours and it (BROAD,
  :func:`mkf_ros.evaluation.metrics.orientation_errors`; independent of heading). A sanity check,
  not ground truth.

Then PASS/FAIL per run against: (1) no jump > 5°; (2) the yaw variance never decreases during a
jump; (3) 9D: no output with a yaw variance < 1 rad² before the magnetometer fixed the heading;
(4) the yaw variance finite and ≤ 10 rad². A uniformly unknown angle has variance π²/3 ≈ 3.29
rad², the value the adapter itself publishes after a gap: larger values are flagged ("high"),
above 10 rad² they fail (the Gaussian yaw no longer means anything). The exit code is 0 whatever
the checks say (it is a report); 2 for bad arguments.

``--detail BAG`` instead runs one bag (default MEKF 6D) and prints the messages around ``--at T``
(s since the bag start; default: its largest jump, else the start of its last rest period): input
gyro z, the rest criterion |ω − b̂| (bias-corrected input gyro; rest needs it below
``rest_gyro_threshold`` for ``rest_time``), the estimated bias z, whether a zero-rate update at
rest was made there (the filter's ``rest_updates`` counter grew), our yaw, its step and
unexplained part, the yaw variance, and the device's own yaw and the odometry if present. If the
bag has an own orientation and odometry it then characterises the raw data over 1 s windows (hop
0.5 s) — the data a rest detector has to tell apart: gyro mean per axis and about the vertical
(the mean accelerometer direction), gyro std per axis, accelerometer std per axis and norm mean,
and whether every sample of the window passes the filter's per-sample rest test with the raw gyro;
each window classed by the odometry (wheels still: |vx| < 0.01 m/s and |wz| < 0.02 rad/s; rolling:
|vx| > 0.1 m/s) and the own orientation's yaw rate (steady < 0.01 rad/s, slow turn < 0.1, turning).
The own yaw is only as independent as the device's filter: on ``rl_test2.bag`` it is the
integrated gyro (the printout compares the two over the whole bag).
"""

from __future__ import annotations

import argparse
import fnmatch
import math
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import BagError, BagReader, cdr
from mkf_ros.core.quaternion import qconj_np, qmul_np
from mkf_ros.evaluation.metrics import orientation_errors, step_angles, unexplained_steps
from mkf_ros.stream import rep145

ALGORITHMS = ("mekf", "mukf")
JUMP_DEG = 5.0  #: a step the gyro does not explain by more than this is a jump
SMALL_YAW_VAR = 1.0  #: rad²: below this the heading is claimed known to about ±1 rad
UNIFORM_YAW_VAR = math.pi**2 / 3.0  #: rad²: variance of an angle uniform on (−π, π]
SUSPICIOUS_YAW_VAR = 10.0  #: rad²: above this the published yaw variance fails
FAST = 5.0  #: rad/s: jumps while the gyro reads more than this are counted as "fast" too
ODOM_TYPE = "nav_msgs/msg/Odometry"


# ------------------------------------------------------------------------------- reading
@dataclass
class BagData:
    """One bag's messages, decoded once (the filter runs read it again, as a user would)."""

    path: Path
    imu_topic: str
    mag_topic: str | None
    odom_topic: str | None
    start_ns: int
    imu: cdr.Decoded
    imu_log_ns: np.ndarray
    mag: cdr.Decoded | None = None
    mag_log_ns: np.ndarray | None = None
    odom_t: np.ndarray | None = None  #: s since the bag start (log time)
    odom_vx: np.ndarray | None = None  #: m/s, twist.linear.x
    odom_wz: np.ndarray | None = None  #: rad/s, twist.angular.z

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def t(self) -> np.ndarray:
        """IMU messages: s since the bag start (log time)."""
        return (self.imu_log_ns - self.start_ns) * 1e-9

    @property
    def gyr(self) -> np.ndarray:
        return self.imu.fields["angular_velocity"]

    @property
    def acc(self) -> np.ndarray:
        return self.imu.fields["linear_acceleration"]

    @property
    def own_quat(self) -> np.ndarray | None:
        """The device's own orientation [w, x, y, z] if the IMU topic carries one (a finite unit
        quaternion that is not constant and not marked "not reported"), else None."""
        f = self.imu.fields
        q = f["orientation"]
        if rep145.not_reported(f["orientation_covariance"][:, 0]).any() or \
                not np.isfinite(q).all():
            return None
        if np.abs(np.linalg.norm(q, axis=1) - 1.0).max() > 1e-3 or np.ptp(q, axis=0).max() < 1e-6:
            return None
        return np.column_stack([q[:, 3], q[:, 0], q[:, 1], q[:, 2]])


def only_topic(br: BagReader, msgtype: str) -> str | None:
    """The bag's one topic of ``msgtype`` (None without; BagError if several)."""
    names = sorted(t for t, i in br.topics.items() if i.msgtype == msgtype)
    if len(names) > 1:
        raise BagError(f"{br.path}: several {msgtype} topics ({', '.join(names)})")
    return names[0] if names else None


def read_bag(path: Path) -> BagData:
    with BagReader(path) as br:
        imu_topic = only_topic(br, cdr.IMU.msgtype)
        if imu_topic is None:
            raise BagError(f"{path}: no {cdr.IMU.msgtype} topic")
        mag_topic = only_topic(br, cdr.MAGNETIC_FIELD.msgtype)
        odom_topic = only_topic(br, ODOM_TYPE)
        batches = br.read([t for t in (imu_topic, mag_topic, odom_topic) if t])
        start = br.start_ns
    b = batches[imu_topic]
    bd = BagData(path, imu_topic, mag_topic, odom_topic, start,
                 cdr.decode(b.data, cdr.IMU, imu_topic), b.log_ns)
    if mag_topic:
        m = batches[mag_topic]
        bd.mag, bd.mag_log_ns = cdr.decode(m.data, cdr.MAGNETIC_FIELD, mag_topic), m.log_ns
    if odom_topic:
        from rosbags.typesys import Stores, get_typestore

        ts = get_typestore(Stores.ROS2_JAZZY)
        o = batches[odom_topic]
        msgs = [ts.deserialize_cdr(raw, ODOM_TYPE) for raw in o.raws]
        bd.odom_t = (o.log_ns - start) * 1e-9
        bd.odom_vx = np.array([x.twist.twist.linear.x for x in msgs])
        bd.odom_wz = np.array([x.twist.twist.angular.z for x in msgs])
    return bd


# ------------------------------------------------------------------------------- running
class RecordingAdapter:
    """A :class:`~mkf_ros.stream.adapter.StreamAdapter` for
    :func:`~mkf_ros.bags.messages.run_stream` that processes one message at a time
    (``chunk=1``, same results bit for bit) and notes after each IMU message the filter's
    ``rest_updates`` counter; keeps the full :class:`~mkf_ros.stream.adapter.StreamOutputs`
    (``heading_initialized``, bias, ...)."""

    def __init__(self, params: dict[str, Any]) -> None:
        from mkf_ros.stream.adapter import StreamAdapter

        self.adapter = StreamAdapter(params)
        self.params = self.adapter.params
        self.result: Any = None
        self.rest_count = np.zeros(0, dtype=np.int64)  #: (N,) rest_updates after IMU message i

    def process(self, imu_stamp: Any, *args: Any, progress: Any = None, **kw: Any) -> Any:
        a = self.adapter
        rest = np.zeros(len(imu_stamp), dtype=np.int64)

        def note(_n: int) -> None:
            c = a.counters
            if c["imu_received"]:
                rest[c["imu_received"] - 1] = c["rest_updates"]

        self.result = a.process(imu_stamp, *args, progress=note, chunk=1, **kw)
        self.rest_count = rest
        return self.result


@dataclass
class Run:
    bag: BagData
    algorithm: str
    use_mag: bool
    params: dict[str, Any]
    n_in: int
    n_out: int
    index: np.ndarray  #: (M,) IMU message of each output
    t: np.ndarray  #: (M,) s since the bag start (log time)
    stamp: np.ndarray  #: (M,) s, header stamps
    quat: np.ndarray  #: (M, 4)
    yaw_var: np.ndarray  #: (M,) rad²
    cov: np.ndarray  #: (M, 3, 3) rad², the published covariance about the world axes
    heading: np.ndarray  #: (M,) bool, heading fixed by the magnetometer
    bias: np.ndarray  #: (M, 3)
    rest: np.ndarray  #: (M,) bool, a zero-rate update at rest was made at this output
    counters: dict[str, int]
    same: bool  #: the recording run published exactly what process_bag published
    notes: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        return f"{self.algorithm} {'9D' if self.use_mag else '6D'}"


def run_case(bd: BagData, algorithm: str, use_mag: bool, overrides: dict[str, Any],
             tmp: Path) -> Run:
    from mkf_ros.bags.messages import run_stream
    from mkf_ros.bags.process import process_bag

    params = {**overrides, "algorithm": algorithm, "use_mag": use_mag}
    r = process_bag(bd.path, tmp / "out.mcap", params, imu_topic=bd.imu_topic,
                    mag_topic=bd.mag_topic or "imu/mag", truth_topic=None, overwrite=True,
                    keep_outputs=True)
    rec = RecordingAdapter(params)
    mag = bd.mag if use_mag else None
    outs = run_stream(rec, bd.imu, bd.imu_log_ns, mag, bd.mag_log_ns if use_mag else None,
                      rec.params)
    so = rec.result
    o = r.outputs
    assert o is not None and r.stamps is not None and r.log_s is not None
    same = (np.array_equal(o.index, outs.index) and np.array_equal(o.quat, outs.quat)
            and np.array_equal(o.cov, outs.cov))
    rest_count = rec.rest_count
    rest_msg = np.diff(rest_count, prepend=0) > 0
    return Run(bag=bd, algorithm=algorithm, use_mag=use_mag, params=r.params,
               n_in=r.n_imu + r.n_mag, n_out=r.n_out, index=o.index, t=r.log_s,
               stamp=r.stamps, quat=o.quat, yaw_var=o.cov[:, 2, 2],
               cov=o.cov, heading=so.heading_initialized,
               bias=so.bias, rest=rest_msg[o.index], counters=r.counters, same=same,
               notes=list(r.notes))


# ------------------------------------------------------------------------------- checks
@dataclass
class Checks:
    max_step: float  #: deg
    jumps: np.ndarray  #: output indices k (step k−1 → k) of unexcused jumps
    excused: np.ndarray  #: output indices of excused ones
    unexplained: np.ndarray  #: (M−1,) deg
    fast: np.ndarray  #: (M,) bool: the input gyro of the output or the one before > FAST
    var_drops: np.ndarray  #: output indices of jumps with a decreasing yaw variance
    max_yaw_var: float
    nonfinite: int
    pre_heading: int  #: 9D: outputs before the heading was fixed
    pre_first_mag: int  #: of those, before the first magnetometer message arrived
    pre_min_var: float  #: smallest yaw variance among them
    tilt: tuple[float, float] | None  #: RMS, max inclination difference to the own orientation


def axis_variances(q: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(M−1,) rad²: the variance, about the axis of each step ``q[k−1] → q[k]`` (world frame,
    ``q[k] q[k−1]*``), of the covariance published with ``q[k−1]`` (world axes)."""
    axis = qmul_np(q[1:], qconj_np(q[:-1]))[:, 1:]
    n = np.linalg.norm(axis, axis=1, keepdims=True)
    u = np.divide(axis, n, out=np.zeros_like(axis), where=n > 0)
    return np.einsum("ki,kij,kj->k", u, cov[:-1], u)


def check(run: Run) -> Checks:
    bd = run.bag
    gyr = bd.gyr[run.index]
    unexpl = np.degrees(unexplained_steps(run.quat, run.stamp, gyr))
    steps = np.degrees(step_angles(run.quat))
    k = np.arange(1, len(run.quat))
    big = unexpl > JUMP_DEG
    gap = np.diff(run.stamp) > float(run.params["max_dt"])
    fix = run.heading[1:] & ~run.heading[:-1] & (run.yaw_var[:-1] >= SMALL_YAW_VAR)
    # within one σ about the step's axis, published just before: a correction it had announced
    announced = np.radians(unexpl) <= np.sqrt(axis_variances(run.quat, run.cov))
    ok = big & (gap | fix | announced)
    jumps = k[big & ~ok]
    drops = jumps[run.yaw_var[jumps] < run.yaw_var[jumps - 1]]
    finite = np.isfinite(run.yaw_var)
    pre = ~run.heading if run.use_mag else np.zeros(len(run.t), dtype=bool)
    first_mag = np.inf
    if run.use_mag and bd.mag_log_ns is not None and len(bd.mag_log_ns):
        first_mag = (bd.mag_log_ns[0] - bd.start_ns) * 1e-9
    tilt = None
    own = bd.own_quat
    if own is not None:
        inc = np.degrees(orientation_errors(run.quat, own[run.index])["inclination"])
        tilt = (float(np.sqrt(np.mean(inc**2))), float(inc.max()))
    rate = np.linalg.norm(np.nan_to_num(gyr), axis=1)
    fast = rate > FAST
    fast[1:] |= rate[:-1] > FAST
    return Checks(
        max_step=float(steps.max()) if len(steps) else 0.0, jumps=jumps, excused=k[ok],
        unexplained=unexpl, fast=fast, var_drops=drops,
        max_yaw_var=float(run.yaw_var[finite].max()) if finite.any() else math.nan,
        nonfinite=int((~finite).sum()), pre_heading=int(pre.sum()),
        pre_first_mag=int((pre & (run.t < first_mag)).sum()),
        pre_min_var=float(run.yaw_var[pre].min()) if pre.any() else math.nan, tilt=tilt)


def verdicts(run: Run, c: Checks) -> dict[str, str]:
    """Check name → "PASS", "FAIL ..." or "high ..." / "n/a"."""
    g = np.linalg.norm(np.nan_to_num(run.bag.gyr[run.index]), axis=1)

    def jump_text(ks: np.ndarray) -> str:
        j = int(ks[np.argmax(c.unexplained[ks - 1])])
        nf = int(c.fast[ks].sum())
        step = math.degrees(step_angles(run.quat[j - 1:j + 1])[0])
        return (f"{len(ks)}{f' ({nf} fast)' if nf else ''}, largest {c.unexplained[j - 1]:.1f}° "
                f"at t={run.t[j]:.2f} s (step {step:.1f}°, |ω| {g[j]:.2f} rad/s; yaw var "
                f"{run.yaw_var[j - 1]:.3g} → {run.yaw_var[j]:.3g} rad²)")

    v: dict[str, str] = {}
    v["no jump > 5°"] = "PASS" if not len(c.jumps) else "FAIL " + jump_text(c.jumps)
    v["no var↓ at jump"] = ("PASS" if not len(c.var_drops)
                            else "FAIL " + jump_text(c.var_drops))
    if not run.use_mag:
        v["pre-heading var ≥ 1"] = "n/a"
    else:
        small = c.pre_heading and c.pre_min_var < SMALL_YAW_VAR
        v["pre-heading var ≥ 1"] = ("PASS" if not small else
                                    f"FAIL {c.pre_heading} outputs, yaw var down to "
                                    f"{c.pre_min_var:.3g} rad²")
    if c.nonfinite or c.max_yaw_var > SUSPICIOUS_YAW_VAR:
        v["yaw var ≤ 10"] = f"FAIL max {c.max_yaw_var:.4g} rad², {c.nonfinite} non-finite"
    elif c.max_yaw_var > UNIFORM_YAW_VAR * (1 + 1e-9):
        v["yaw var ≤ 10"] = f"PASS (high: max {c.max_yaw_var:.3g} > π²/3)"
    else:
        v["yaw var ≤ 10"] = "PASS"
    return v


# ------------------------------------------------------------------------------- printing
def _code_state() -> str:
    """The commit, whether the tree has changes, and the hash of the kernel sources imported
    (:data:`mkf_ros.core._jit.KERNEL_HASH`: the filter's numbers change with them)."""
    from mkf_ros.core._jit import KERNEL_HASH

    try:
        def git(*a: str) -> str:
            return subprocess.run(["git", *a], cwd=Path(__file__).parent, capture_output=True,
                                  text=True, check=True).stdout.strip()
        dirty = git("status", "--porcelain", "--untracked-files=no")
        state = git("rev-parse", "--short", "HEAD") + (" + uncommitted changes" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        state = "unknown commit"
    return f"{state}, kernels {KERNEL_HASH}"


def _g(x: float, fmt: str = ".3g") -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def table_row(run: Run, c: Checks) -> str:
    j = f"{len(c.jumps)}"
    nf = int(c.fast[c.jumps].sum())
    if nf:
        j += f" ({nf} fast)"
    if len(c.jumps):
        i = int(c.jumps[np.argmax(c.unexplained[c.jumps - 1])])
        j += f" (max {c.unexplained[i - 1]:.1f}° @{run.t[i]:.1f}s)"
    if len(c.excused):
        j += f" +{len(c.excused)} ok"
    pre = "—"
    if run.use_mag:
        pre = (f"{c.pre_heading} ({c.pre_first_mag} before 1st mag), min var "
               f"{_g(c.pre_min_var)}" if c.pre_heading else "0")
    tilt = f"{c.tilt[0]:.2f} / {c.tilt[1]:.2f}" if c.tilt else "—"
    return (f"| {run.bag.name} | {run.label} | {run.n_in:,} | {run.n_out:,} | "
            f"{c.max_step:.1f} | {j} | {_g(c.max_yaw_var, '.4g')} | {len(c.var_drops)} | "
            f"{pre} | {tilt} |")


TABLE_HEAD = ("| bag | filter | in | out | max step ° | jumps > 5° | max yaw var rad² | var↓ "
              "| pre-heading (9D) | tilt vs own RMS / max ° |\n"
              "|---|---|---:|---:|---:|---|---:|---:|---|---|")


def parse_set(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for it in items:
        name, sep, val = it.partition("=")
        if not sep:
            raise ValueError(f"--set expects NAME=VALUE, got {it!r}")
        out[name.strip()] = val.strip()
    if out:
        from mkf_ros.stream.adapter import StreamAdapter

        StreamAdapter(out)  # validate (ValueError naming the parameter)
        out = {k: StreamAdapter(out).params[k] for k in out}
    return out


def bags_in(folder: Path, only: str | None) -> list[Path]:
    bags = sorted(folder.glob("*.bag"))
    if only:
        bags = [b for b in bags if fnmatch.fnmatch(b.name, only)]
    return bags


def main_table(folder: Path, only: str | None, overrides: dict[str, Any]) -> int:
    bags = bags_in(folder, only)
    if not bags:
        print(f"ros_bags: no *.bag in {folder}" + (f" matching {only!r}" if only else ""),
              file=sys.stderr)
        return 2
    print("# ROS 1 bags through mkf process (bench/ros_bags.py)")
    print(f"code: {_code_state()}; folder: {folder}; overrides: {overrides or 'none (defaults)'}")
    results: list[tuple[Run, Checks]] = []
    with tempfile.TemporaryDirectory(prefix="mkf-ros-bags-") as tmp:
        for path in bags:
            bd = read_bag(path)
            own = "own orientation" if bd.own_quat is not None else "no own orientation"
            print(f"\n{bd.name}: IMU {bd.imu_topic} ({len(bd.imu_log_ns):,}), magnetometer "
                  f"{bd.mag_topic or '—'}"
                  f"{f' ({len(bd.mag_log_ns):,})' if bd.mag_log_ns is not None else ''}, "
                  f"odometry {bd.odom_topic or '—'}, {own}")
            for algo in ALGORITHMS:
                for use_mag in ((False, True) if bd.mag_topic else (False,)):
                    run = run_case(bd, algo, use_mag, overrides, Path(tmp))
                    results.append((run, check(run)))
    p = results[0][0].params
    print(f"\nparameters: defaults{' + overrides' if overrides else ''} "
          f"(estimate_gyro_bias {str(p['estimate_gyro_bias']).lower()}, rest_detection "
          f"{str(p['rest_detection']).lower()}, max_dt {p['max_dt']:g} s, world_frame "
          f"{p['world_frame']})\n")
    print(TABLE_HEAD)
    for run, c in results:
        print(table_row(run, c))
    print("\nevents (counters that are not zero, besides messages received and fused):")
    skip = ("imu_received", "mag_received", "mag_fused")
    for run, _c in results:
        ev = ", ".join(f"{k} {v}" for k, v in run.counters.items() if v and k not in skip)
        print(f"  {run.bag.name} {run.label}: {ev or 'none'}")
    bad = [r for r, _c in results if not r.same]
    if bad:
        print("\nWARNING: the recording run differs from process_bag for: "
              + ", ".join(f"{r.bag.name} {r.label}" for r in bad))
    print("\n## Checks")
    fails = 0
    for run, c in results:
        for name, v in verdicts(run, c).items():
            if v == "n/a":
                continue
            fails += v.startswith("FAIL")
            print(f"{v.split()[0]:4}  {run.bag.name:30} {run.label:8} {name:20} "
                  f"{v.partition(' ')[2]}")
    n = sum(v != "n/a" for r, c in results for v in verdicts(r, c).values())
    print(f"\n{fails} FAIL of {n} checks")
    return 0


# ------------------------------------------------------------------------------- detail
def _yaw(q: np.ndarray) -> np.ndarray:
    """ZYX yaw (rad) of [w, x, y, z] quaternions, about world z."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def detail(folder: Path, bag: str, algorithm: str, use_mag: bool, at: float | None,
           window: float, overrides: dict[str, Any]) -> int:
    path = Path(bag) if Path(bag).is_file() else folder / bag
    if not path.is_file():
        print(f"ros_bags: no bag {bag} (in {folder})", file=sys.stderr)
        return 2
    bd = read_bag(path)
    if use_mag and not bd.mag_topic:
        print(f"ros_bags: {bd.name} has no magnetometer topic", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="mkf-ros-bags-") as tmp:
        run = run_case(bd, algorithm, use_mag, overrides, Path(tmp))
    c = check(run)
    p = run.params
    print(f"# {bd.name}, {run.label} (bench/ros_bags.py --detail); code: {_code_state()}")
    print(f"rest: |ω − b̂| < rest_gyro_threshold {p['rest_gyro_threshold']:g} rad/s and "
          f"| |a| − g | < rest_acc_threshold {p['rest_acc_threshold']:g} m/s² for rest_time "
          f"{p['rest_time']:g} s, then zero-rate updates (σ {p['rest_rate_stddev']:g} rad/s); "
          f"estimate_gyro_bias {str(p['estimate_gyro_bias']).lower()}")
    print(f"rest_updates {run.counters['rest_updates']} in all; "
          f"{len(c.jumps)} jump(s) > {JUMP_DEG:g}°; max yaw var {c.max_yaw_var:.4g} rad²")
    # the rest periods (zero-rate updates) of the run
    r = run.rest.astype(int)
    starts = np.flatnonzero(np.diff(r, prepend=0) > 0)
    ends = np.flatnonzero(np.diff(r, append=0) < 0)
    spans = ", ".join(f"{run.t[a]:.2f}–{run.t[b]:.2f} s" for a, b in zip(starts, ends,
                                                                         strict=True))
    print(f"zero-rate updates at rest during: {spans or 'never'}")
    if at is None:
        if len(c.jumps):
            k = int(c.jumps[np.argmax(c.unexplained[c.jumps - 1])])
            at = float(run.t[k])
            print(f"centred on the largest jump: {c.unexplained[k - 1]:.2f}° at t = {at:.3f} s")
        elif len(starts):
            at = float(run.t[starts[-1]])
            print(f"no jump; centred on the start of the last rest period, t = {at:.3f} s")
        elif len(c.unexplained):
            k = int(np.argmax(c.unexplained)) + 1
            at = float(run.t[k])
            print(f"no jump, no rest; centred on the largest unexplained step "
                  f"({c.unexplained[k - 1]:.2f}°) at t = {at:.3f} s")
        else:
            print("no output steps")
            return 0
    _detail_rows(run, c, at, window)
    if bd.own_quat is not None and bd.odom_t is not None:
        characterise(bd, p)
    return 0


def _detail_rows(run: Run, c: Checks, at: float, window: float) -> None:
    bd = run.bag
    g = bd.gyr[run.index]
    wr = np.linalg.norm(g - run.bias, axis=1)
    yaw = np.degrees(_yaw(run.quat))
    step = np.concatenate([[math.nan], np.degrees(step_angles(run.quat))])
    unex = np.concatenate([[math.nan], c.unexplained])
    own = bd.own_quat
    own_yaw = np.degrees(_yaw(own[run.index])) if own is not None else None
    cols = "t s | gyr z | |ω−b̂| | b̂ z | rest | yaw ° | step ° | unexpl ° | yaw var rad²"
    if own_yaw is not None:
        cols += " | own yaw ° | ours − own °"
    if bd.odom_t is not None:
        cols += " | odom vx | odom wz"
    print(f"\nmessages within ±{window:g} s of t = {at:.2f} s (every 5th, and every one with a "
          "rest change or a step > 1°):\n")
    print("| " + cols + " |")
    print("|" + "---:|" * (cols.count("|") + 1))
    sel = np.flatnonzero(np.abs(run.t - at) <= window)
    prev_rest = None
    for n, i in enumerate(sel):
        show = (n % 5 == 0 or run.rest[i] != prev_rest or step[i] > 1.0 or i == sel[-1])
        prev_rest = run.rest[i]
        if not show:
            continue
        row = (f"| {run.t[i]:.3f} | {g[i, 2]:+.4f} | {wr[i]:.4f} | {run.bias[i, 2]:+.4f} | "
               f"{'REST' if run.rest[i] else '-'} | {yaw[i]:+.2f} | {_g(step[i], '.2f')} | "
               f"{_g(unex[i], '+.2f')} | {run.yaw_var[i]:.4g}")
        if own_yaw is not None:
            row += f" | {own_yaw[i]:+.2f} | {_wrap_deg(yaw[i] - own_yaw[i]):+.2f}"
        if bd.odom_t is not None:
            j = int(np.clip(np.searchsorted(bd.odom_t, run.t[i]), 0, len(bd.odom_t) - 1))
            row += f" | {bd.odom_vx[j]:+.4f} | {bd.odom_wz[j]:+.4f}"
        print(row + " |")


# classes of 1 s windows for the rest-detector data: name → description
CLASSES = {
    "still, own yaw steady": "odometry |vx| < 0.01 m/s and |wz| < 0.02 rad/s throughout; own "
                             "yaw rate < 0.01 rad/s",
    "still, own yaw turning": "odometry as above, but own yaw rate ≥ 0.01 rad/s",
    "rolling, straight": "odometry |vx| > 0.1 m/s throughout; own yaw rate < 0.01 rad/s",
    "rolling, slow turn": "as above with own yaw rate 0.01–0.1 rad/s",
    "rolling, turning": "as above with own yaw rate ≥ 0.1 rad/s",
}


def windows(bd: BagData, p: dict[str, Any], length: float = 1.0,
            hop: float = 0.5) -> list[dict[str, Any]]:
    """Statistics of the raw IMU data over windows, with their class (or None). ``rest_ok``:
    the fraction of samples that pass the filter's per-sample rest test with the raw gyro
    (bias 0): |ω| < rest_gyro_threshold and | |a| − g | < rest_acc_threshold."""
    t, g, a = bd.t, bd.gyr, bd.acc
    a_norm = np.linalg.norm(a, axis=1)
    passes = ((np.linalg.norm(g, axis=1) < float(p["rest_gyro_threshold"]))
              & (np.abs(a_norm - float(p["gravity"])) < float(p["rest_acc_threshold"])))
    own = bd.own_quat
    own_yaw = np.unwrap(_yaw(own)) if own is not None else None
    res = []
    for t0 in np.arange(t[0], t[-1] - length + 1e-9, hop):
        m = (t >= t0) & (t < t0 + length)
        if m.sum() < 5:
            continue
        idx = np.flatnonzero(m)
        w: dict[str, Any] = dict(
            t0=float(t0), n=int(m.sum()), g_mean=g[m].mean(0), g_std=g[m].std(0),
            a_std=a[m].std(0), a_norm=float(a_norm[m].mean()), rest_ok=float(passes[m].mean()))
        up = a[m].mean(0)
        w["g_vert"] = float(g[m].mean(0) @ (up / np.linalg.norm(up)))  # about the vertical
        rate = math.nan
        if own_yaw is not None:
            rate = float((own_yaw[idx[-1]] - own_yaw[idx[0]]) / (t[idx[-1]] - t[idx[0]]))
        w["own_rate"] = rate
        cls = None
        if bd.odom_t is not None:
            mo = (bd.odom_t >= t0) & (bd.odom_t < t0 + length)
            vx, wz = bd.odom_vx[mo], bd.odom_wz[mo]
            w["odom_vx"] = float(vx.mean()) if mo.any() else math.nan
            w["odom_wz"] = float(wz.mean()) if mo.any() else math.nan
            if mo.any() and not math.isnan(rate):
                r = abs(rate)
                if np.abs(vx).max() < 0.01 and np.abs(wz).max() < 0.02:
                    cls = "still, own yaw steady" if r < 0.01 else "still, own yaw turning"
                elif np.abs(vx).min() > 0.1:
                    cls = ("rolling, straight" if r < 0.01 else
                           "rolling, slow turn" if r < 0.1 else "rolling, turning")
        w["cls"] = cls
        res.append(w)
    return res


def characterise(bd: BagData, p: dict[str, Any]) -> None:
    ws = windows(bd, p)
    print(f"\n## {bd.name}: raw data over 1 s windows (hop 0.5 s), for a rest detector\n")
    print("own yaw rate: of the IMU topic's own orientation (Δyaw over the window); odometry: "
          f"{bd.odom_topic} twist. gyro in rad/s, accelerometer in m/s².")
    own_yaw = np.unwrap(_yaw(bd.own_quat)) if bd.own_quat is not None else None
    st = bd.imu.stamp_ns * 1e-9
    gz_int = float(np.sum(bd.gyr[1:, 2] * np.diff(st)))
    if own_yaw is not None and bd.odom_t is not None:
        t_od = bd.odom_t
        od_int = float(np.sum(bd.odom_wz[1:] * np.diff(t_od)))
        print(f"whole bag: gyro z integrates to {math.degrees(gz_int):+.1f}°, the own yaw "
              f"changes by {math.degrees(own_yaw[-1] - own_yaw[0]):+.1f}°, the odometry wz "
              f"integrates to {math.degrees(od_int):+.1f}°")
        rolling = np.interp(bd.t, t_od, bd.odom_vx) > 0.1
        if rolling.sum() > 10:
            wz_i = np.interp(bd.t, t_od, bd.odom_wz)[rolling]
            cc = float(np.corrcoef(wz_i, bd.gyr[rolling, 2])[0, 1])
            k, c0 = np.linalg.lstsq(np.column_stack([wz_i, np.ones(len(wz_i))]),
                                    bd.gyr[rolling, 2], rcond=None)[0]
            print(f"while rolling: gyro z = {k:.3f} · odometry wz {c0:+.4f} rad/s "
                  f"(correlation {cc:.2f})")
    head = ("| window s | class | own yaw rate | odom vx | odom wz | gyr mean vertical | "
            "gyr mean x, y, z | "
            "gyr std x, y, z | acc std x, y, z | |acc| mean | rest test |\n"
            "|---|---|---:|---:|---:|---:|---|---|---|---:|---:|")

    def row(w: dict[str, Any]) -> str:
        def v3(a: np.ndarray, fmt: str) -> str:
            return ", ".join(format(float(x), fmt) for x in a)

        return (f"| {w['t0']:.1f}–{w['t0'] + 1:.1f} | {w['cls'] or '—'} | "
                f"{w['own_rate']:+.4f} | {w.get('odom_vx', math.nan):+.4f} | "
                f"{w.get('odom_wz', math.nan):+.4f} | {w['g_vert']:+.4f} | "
                f"{v3(w['g_mean'], '+.4f')} | "
                f"{v3(w['g_std'], '.4f')} | {v3(w['a_std'], '.3f')} | {w['a_norm']:.3f} | "
                f"{w['rest_ok'] * 100:.0f} % |")

    print("\nwindows with the wheels still or a slow turn (every one):\n")
    print(head)
    for w in ws:
        if w["cls"] in ("still, own yaw steady", "still, own yaw turning",
                        "rolling, slow turn"):
            print(row(w))
    print("\nper class: median [min – max] over its windows; last column: windows in which every "
          "sample passes the filter's per-sample rest test with the raw gyro (bias 0), i.e. "
          "that would start a rest period\n")
    names = ["|own yaw rate|", "|gyr mean vertical|", "|gyr mean x|", "|gyr mean y|",
             "|gyr mean z|", "gyr std x", "gyr std y", "gyr std z", "acc std x", "acc std y",
             "acc std z", "|acc| mean − g"]
    print("| class | windows | " + " | ".join(names) + " | pass rest test |")
    print("|---|---:|" + "---|" * len(names) + "---:|")
    g0 = float(p["gravity"])
    for cls in CLASSES:
        sel = [w for w in ws if w["cls"] == cls]
        if not sel:
            print(f"| {cls} | 0 |" + " — |" * (len(names) + 1))
            continue
        cols = [np.abs([w["own_rate"] for w in sel]), np.abs([w["g_vert"] for w in sel])]
        cols += [np.abs([w["g_mean"][i] for w in sel]) for i in range(3)]
        cols += [np.array([w["g_std"][i] for w in sel]) for i in range(3)]
        cols += [np.array([w["a_std"][i] for w in sel]) for i in range(3)]
        cols += [np.array([w["a_norm"] - g0 for w in sel])]
        cells = " | ".join(f"{np.median(x):.4f} [{x.min():.4f} – {x.max():.4f}]" for x in cols)
        n_rest = sum(w["rest_ok"] == 1.0 for w in sel)
        print(f"| {cls} | {len(sel)} | {cells} | {n_rest} |")
    print("\nclasses: " + "; ".join(f"{k}: {v}" for k, v in CLASSES.items()) + ". Windows "
          "that fit none (starting, stopping) are left out of the summary.")


# ------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\nHow:")[0].replace("``", ""),
        epilog="Checks per run: no jump > 5° that the gyro does not explain; the yaw variance "
               "never drops\nduring one; 9D: no yaw variance < 1 rad² before the magnetometer "
               "fixes the heading;\nyaw variance finite and ≤ 10 rad². Details: the docstring "
               "of bench/ros_bags.py.")
    ap.add_argument("folder", type=Path, metavar="BAG_DIR", help="folder with ROS 1 .bag files")
    ap.add_argument("--only", metavar="GLOB", help="only the bags whose file name matches")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="override a parameter for every run (repeatable), e.g. "
                         "--set estimate_gyro_bias=false")
    ap.add_argument("--detail", metavar="BAG", help="instead of the table: one bag (file name "
                    "in BAG_DIR, or a path) in detail around its largest jump, then its raw "
                    "data over 1 s windows if it has an own orientation and odometry")
    ap.add_argument("--algorithm", choices=ALGORITHMS, default="mekf",
                    help="--detail: the filter (default mekf)")
    ap.add_argument("--use-mag", action="store_true", help="--detail: 9D")
    ap.add_argument("--at", type=float, metavar="T",
                    help="--detail: centre (s since the bag start; default: the largest jump)")
    ap.add_argument("--window", type=float, default=1.5, metavar="S",
                    help="--detail: rows within ±S s (default 1.5)")
    args = ap.parse_args(argv)
    if not args.folder.is_dir():
        print(f"ros_bags: {args.folder} is not a folder", file=sys.stderr)
        return 2
    try:
        overrides = parse_set(args.set)
    except ValueError as e:
        print(f"ros_bags: {e}", file=sys.stderr)
        return 2
    try:
        if args.detail:
            return detail(args.folder, args.detail, args.algorithm, args.use_mag, args.at,
                          args.window, overrides)
        return main_table(args.folder, args.only, overrides)
    except BagError as e:
        print(f"ros_bags: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
