"""Offline estimation over a bag, without DDS: what ``mkf process`` runs.

The IMU and magnetometer messages are fed, in the order they were recorded, to the same
:class:`mkf_ros.stream.adapter.StreamAdapter` the ``estimator`` node wraps, with the node's
conversions: a field whose covariance[0] is -1 is "not reported"; the output ``imu/data`` message
keeps the input's header, carries the filter's orientation and covariance, and fills the angular
velocity and linear acceleration like the node (``mkf_ros.ros.convert.fill_imu``). So a bag
processed here and the same bag replayed through the node give the same messages.

Bulk work (reading, decoding, encoding, writing) is vectorised (see :mod:`mkf_ros.bags.cdr`);
the adapter runs the whole recording in compiled code (:meth:`StreamAdapter.process`, in chunks
for the progress bar), with the results of the node's message-by-message calls.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.bags.reader import BagError, BagReader, normalize_topic
from mkf_ros.bags.writer import BagWriter
from mkf_ros.stream import rep145


@dataclass
class Outputs:
    """The estimates, one row per published ``imu/data`` message."""

    index: np.ndarray  #: (M,) index of the input IMU message
    quat: np.ndarray  #: (M, 4) [w, x, y, z], sensor → world_frame
    cov: np.ndarray  #: (M, 9) orientation covariance, rad², world axes
    angvel: np.ndarray  #: (M, 3)
    angvel_cov: np.ndarray  #: (M, 9)
    linacc: np.ndarray  #: (M, 3)
    linacc_cov: np.ndarray  #: (M, 9)


@dataclass
class Scores:
    """Orientation errors against the ground truth (BROAD metric), degrees."""

    t: np.ndarray  #: (K,) s since the first IMU message (log time)
    q_est: np.ndarray  #: (K, 4)
    q_true: np.ndarray  #: (K, 4) in the estimate's world frame
    errors: dict[str, np.ndarray]  #: total / heading / inclination (rad), (K,)
    rmse: dict[str, float]  #: degrees
    heading_aligned: bool  #: True: no magnetometer, heading aligned once at the start
    skipped: int  #: outputs without a matching ground-truth message
    windows: dict[str, dict[str, float]] = field(default_factory=dict)  #: RMSE per interval kind


@dataclass
class ProcessResult:
    out: Path
    imu_topic: str
    mag_topic: str | None
    n_imu: int
    n_mag: int
    n_out: int
    params: dict[str, Any]
    counters: dict[str, int]
    timings: dict[str, float]
    outputs: Outputs
    stamps: np.ndarray  #: (M,) s, output stamps
    log_s: np.ndarray  #: (M,) s since the bag start, output log times
    scores: Scores | None
    notes: list[str]
    accel_topic: str | None = None  #: split input: the accelerometer topic (imu_topic: gyro)
    n_accel: int = 0


def _decode(raws: np.ndarray | list[bytes], layout: cdr.Layout, topic: str,
            path: Path) -> cdr.Decoded:
    try:
        return cdr.decode(raws, layout, topic)
    except cdr.CdrError as e:
        raise BagError(f"{path}: {e}") from None


def run_stream(adapter: Any, imu: cdr.Decoded, imu_log: np.ndarray, mag: cdr.Decoded | None,
               mag_log: np.ndarray | None, node_params: Mapping[str, Any],
               progress: Callable[[int], object] | None = None, accel: cdr.Decoded | None = None,
               accel_log: np.ndarray | None = None) -> Outputs:
    """Run ``adapter`` over the messages in recording order (by log time, the magnetometer
    first at equal times, as ``mkf synth`` writes); the ``imu/data`` fields it publishes.
    Split input (``accel`` given, ``input_mode`` split): ``imu`` is the gyro stream (its
    linear acceleration ignored) and ``accel`` the accelerometer stream (its angular velocity
    ignored), each message fused at its own stamp."""
    def seconds(stamp_ns: np.ndarray) -> np.ndarray:  # as the node: sec + nanosec · 1e-9
        return stamp_ns // 1_000_000_000 + (stamp_ns % 1_000_000_000) * 1e-9

    f = imu.fields
    av_in = f["angular_velocity_covariance"]
    la_in = f["linear_acceleration_covariance"]
    gyr = rep145.input_rows(f["angular_velocity"], av_in[:, 0])
    a_st = None
    if accel is not None:
        fa = accel.fields
        acc = rep145.input_rows(fa["linear_acceleration"],
                                fa["linear_acceleration_covariance"][:, 0])
        a_st = seconds(accel.stamp_ns)
    else:
        acc = rep145.input_rows(f["linear_acceleration"], la_in[:, 0])
    m_st = m_val = None
    if mag is not None and mag_log is not None and len(mag_log):
        m_st, m_val = seconds(mag.stamp_ns), mag.fields["magnetic_field"]
    res = adapter.process(seconds(imu.stamp_ns), gyr, acc, m_st, m_val, imu_arrival=imu_log,
                          mag_arrival=mag_log, acc_stamp=a_st, acc_arrival=accel_log,
                          progress=progress)
    i = res.index
    m = len(i)
    w_ok = ~np.isnan(res.angular_velocity[:, 0])
    a_ok = ~np.isnan(res.linear_acceleration[:, 0])
    w_cov = rep145.published_covariances(w_ok, res.angular_velocity_cov, av_in[i],
                                         float(node_params["angular_velocity_stddev"]),
                                         res.angular_velocity_cov_add)
    a_cov = rep145.published_covariances(a_ok, None, la_in[i],
                                         float(node_params["linear_acceleration_stddev"]))
    return Outputs(index=i, quat=res.quat_wxyz, cov=res.orientation_cov.reshape(m, 9),
                   angvel=np.where(w_ok[:, None], res.angular_velocity, 0.0), angvel_cov=w_cov,
                   linacc=np.where(a_ok[:, None], res.linear_acceleration, 0.0),
                   linacc_cov=a_cov)


def encode_outputs(imu: cdr.Decoded, batch: Any, out: Outputs) -> np.ndarray | list[bytes]:
    """``imu/data`` messages: the input messages with the estimate written in (header kept)."""
    q = out.quat
    values = dict(orientation=np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]]),
                  orientation_covariance=out.cov, angular_velocity=out.angvel,
                  angular_velocity_covariance=out.angvel_cov, linear_acceleration=out.linacc,
                  linear_acceleration_covariance=out.linacc_cov)
    if imu.rows is not None:
        rows = imu.rows[out.index].copy()
        cdr.set_fields(rows, cdr.IMU, **values)
        return rows
    res: list[bytes] = []  # several frame_id lengths: patch each message
    raws = batch.raws
    for j, i in enumerate(out.index.tolist()):
        row = np.frombuffer(raws[i], np.uint8)[None, :].copy()
        cdr.set_fields(row, cdr.IMU, **{k: v[j] for k, v in values.items()})
        res.append(row.tobytes())
    return res


def _match_truth(stamps_ns: np.ndarray, log_ns: np.ndarray, truth: cdr.Decoded,
                 truth_log: np.ndarray) -> np.ndarray:
    """Index of the ground-truth message for each output (-1: none): equal stamp, and among
    equal stamps (stamps that jump back repeat) the closest log time."""
    res = np.full(len(stamps_ns), -1, dtype=np.int64)
    if len(truth_log) == 0:
        return res
    order = np.lexsort((truth_log, truth.stamp_ns))
    ts = truth.stamp_ns[order]
    lo = np.searchsorted(ts, stamps_ns, "left")
    hi = np.searchsorted(ts, stamps_ns, "right")
    one = hi - lo == 1
    res[one] = order[lo[one]]
    for k in np.flatnonzero(hi - lo > 1).tolist():
        cand = order[lo[k]:hi[k]]
        res[k] = cand[np.argmin(np.abs(truth_log[cand] - log_ns[k]))]
    return res


def score(q_est: np.ndarray, q_true_enu: np.ndarray, t: np.ndarray, world_frame: str,
          use_mag: bool, intervals: Mapping[str, list] | None = None,
          skip: float = 0.0) -> Scores:
    """BROAD errors of ``q_est`` (world_frame) against ENU truth. Without a magnetometer the
    heading is unobservable: the estimate is then rotated about the world up axis once, so that
    its heading matches the truth at the first sample (a constant alignment)."""
    from mkf_ros.core.frames import FROM_ENU
    from mkf_ros.core.quaternion import qconj_np, qmul_np
    from mkf_ros.evaluation.metrics import orientation_errors, rmse_deg

    q_true = qmul_np(FROM_ENU[world_frame], q_true_enu)
    q_est = np.asarray(q_est, float)
    aligned = False
    if not use_mag and len(q_est):
        e = qmul_np(q_true[0], qconj_np(q_est[0]))  # world-frame error at the start
        up = {"enu": 3, "nwu": 3, "ned": 3}[world_frame]
        ang = 2.0 * math.atan2(e[up], e[0])  # its twist about the world z axis
        qz = np.zeros(4)
        qz[0], qz[up] = math.cos(ang / 2), math.sin(ang / 2)
        q_est = qmul_np(qz, q_est)
        aligned = True
    err = orientation_errors(q_est, q_true)
    keep = t >= (t[0] + skip if len(t) else 0.0)
    rmse = {k: rmse_deg(v[keep]) if keep.any() else math.nan for k, v in err.items()}
    windows: dict[str, dict[str, float]] = {}
    for kind, ivs in (intervals or {}).items():
        inside = np.zeros(len(t), dtype=bool)
        for a, b in ivs:
            inside |= (t >= a) & (t <= b)
        inside &= keep
        if inside.any():
            windows[kind] = {k: rmse_deg(v[inside]) for k, v in err.items()}
    return Scores(t=t, q_est=q_est, q_true=q_true, errors=err, rmse=rmse,
                  heading_aligned=aligned, skipped=0, windows=windows)


def stream_param_names() -> list[str]:
    """Parameters that matter offline: the filter's and the node's input/time/output ones."""
    from mkf_ros.core.params import PARAMS

    return [p.name for p in PARAMS
            if p.scope == "filter" or (p.group in ("node: input and time", "node: output")
                                       and p.name != "publish_debug_topics")]


def process_bag(bag: str | Path, out: str | Path, params: Mapping[str, Any] | None = None, *,
                imu_topic: str | None = None, mag_topic: str | None = None,
                accel_topic: str | None = None, gyro_topic: str | None = None,
                truth_topic: str | None = "imu/ground_truth", output_topic: str = "imu/data",
                storage: str = "mcap", overwrite: bool = False, copy_input: bool = False,
                skip: float = 0.0, progress: Any = None) -> ProcessResult:
    """Run the estimator over ``bag`` and write ``out`` (see the module docstring).

    ``params``: filter and node parameters by name (ValueError if invalid). ``progress``: a
    factory ``(description, total) -> callable(increment)`` or None. Raises :class:`BagError`
    for unusable input; the output bag is written only if everything succeeded.

    Topics: ``imu_topic`` None finds the IMU: the bag's only ``sensor_msgs/Imu`` topic, or
    ``imu/data_raw`` among several (otherwise an error lists them with their message counts);
    with ``use_mag``, ``mag_topic`` None likewise takes the only ``MagneticField`` topic (or
    ``imu/mag``). ``accel_topic`` and ``gyro_topic`` (both, and no ``imu_topic``) select split
    input (``input_mode`` split): separate accelerometer and gyro ``Imu`` streams, the output
    one message per gyro message.
    """
    from mkf_ros.bags.synth import read_description
    from mkf_ros.stream.adapter import (
        REJECTIONS,
        StreamAdapter,
        carries_orientation,
        orientation_note,
    )

    bag, out = Path(bag), Path(out)
    notes: list[str] = []
    tm: dict[str, float] = {}
    params = dict(params or {})
    if (accel_topic is None) != (gyro_topic is None):
        raise BagError("split input needs both --accel-topic and --gyro-topic (separate "
                       "accelerometer and gyroscope sensor_msgs/Imu topics)")
    split = accel_topic is not None
    if split:
        if imu_topic is not None:
            raise BagError("--imu-topic (one combined IMU topic) and --accel-topic/--gyro-topic "
                           "(split input) exclude each other")
        if params.get("input_mode", "split") != "split":
            raise BagError("--accel-topic/--gyro-topic are split input: input_mode must be "
                           "split")
        params["input_mode"] = "split"
    elif params.get("input_mode") == "split":
        raise BagError("input_mode split needs --accel-topic and --gyro-topic")
    adapter = StreamAdapter(params)
    p = adapter.params
    use_mag = bool(p["use_mag"])
    t0 = time.perf_counter()
    acc_name = None
    with BagReader(bag) as br:
        if split:
            imu_name = br.resolve(gyro_topic or "", cdr.IMU.msgtype, role="gyroscope")
            acc_name = br.resolve(accel_topic or "", cdr.IMU.msgtype, role="accelerometer")
            if acc_name == imu_name:
                raise BagError(f"--accel-topic and --gyro-topic are the same topic {imu_name}; "
                               "for one combined IMU topic use --imu-topic")
        elif imu_topic is not None:
            imu_name = br.resolve(imu_topic, cdr.IMU.msgtype, role="IMU")
        else:
            imu_name = br.discover(cdr.IMU.msgtype, role="IMU", flag="--imu-topic",
                                   preferred="imu/data_raw")
        mag_name = None
        if use_mag:
            mag_name = (br.resolve(mag_topic, cdr.MAGNETIC_FIELD.msgtype, role="magnetometer")
                        if mag_topic is not None else
                        br.discover(cdr.MAGNETIC_FIELD.msgtype, role="magnetometer",
                                    flag="--mag-topic", preferred="imu/mag"))
        elif br.of_type(cdr.MAGNETIC_FIELD.msgtype):
            notes.append(f"{', '.join(br.of_type(cdr.MAGNETIC_FIELD.msgtype))} in the bag but "
                         "use_mag is false (pass --use-mag to fuse it)")
        truth_name = None
        if truth_topic and normalize_topic(truth_topic) in br.topics:
            truth_name = br.resolve(truth_topic, cdr.QUATERNION_STAMPED.msgtype,
                                    role="ground-truth")
        want = [t for t in (imu_name, acc_name, mag_name, truth_name) if t]
        extra = list(br.topics) if copy_input else []
        read = list(dict.fromkeys(want + extra))
        tick = progress("read", br.work_total(read)) if progress else None
        batches = br.read(read, tick)
        bag_start = br.start_ns
        in_types = {t: br.topics[t].msgtype for t in extra}
    out_name = normalize_topic(output_topic)
    if copy_input and out_name in batches:
        raise BagError(f"output topic {out_name} is also in the input bag; choose another "
                       "--output-topic or drop --copy-input")
    imu_b = batches[imu_name]
    if len(imu_b) == 0:
        raise BagError(f"IMU topic {imu_name} in {bag} has no messages")
    imu = _decode(imu_b.data, cdr.IMU, imu_name, bag)
    acc = acc_b = None
    if acc_name:
        acc_b = batches[acc_name]
        acc = _decode(acc_b.data, cdr.IMU, acc_name, bag)
    mag = mag_b = None
    if mag_name:
        mag_b = batches[mag_name]
        mag = _decode(mag_b.data, cdr.MAGNETIC_FIELD, mag_name, bag)
    truth = _decode(batches[truth_name].data, cdr.QUATERNION_STAMPED, truth_name, bag) \
        if truth_name else None
    tm["read"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n_events = len(imu_b) + (len(mag_b) if mag_b else 0) + (len(acc_b) if acc_b else 0)
    tick = progress("filter", n_events) if progress else None
    outs = run_stream(adapter, imu, imu_b.log_ns, mag, mag_b.log_ns if mag_b else None, p, tick,
                      acc, acc_b.log_ns if acc_b else None)
    tm["filter"] = time.perf_counter() - t0
    found = adapter.input_problems(imu_name, acc_name or "")
    if "gyro" in found:  # an estimate of the tilt alone; said, not refused
        notes.append(found.pop("gyro"))
    problems = list(found.values())
    if not problems and len(outs.index) == 0:
        why = ", ".join(f"{v} {k}" for k, v in adapter.counters.items()
                        if v and k in (*REJECTIONS, "acc_missing", "acc_implausible"))
        problems = [f"no estimate from the {len(imu_b)} messages of {imu_name}"
                    + (f" ({why})" if why else "")]
    if problems:  # nothing to write: stop before the output bag exists
        raise BagError("; ".join(problems) + "; no output written")
    if carries_orientation(imu.fields["orientation"], imu.fields["orientation_covariance"][:, 0]):
        notes.append(orientation_note(imu_name))

    t0 = time.perf_counter()
    data = encode_outputs(imu, imu_b, outs)
    out_log = imu_b.log_ns[outs.index]
    with BagWriter(out, storage, overwrite=overwrite) as w:
        conn = w.add_topic(out_name, cdr.IMU.msgtype)
        w.write_batch(conn, out_log, data)
        for t in extra:
            c = w.add_topic(t, in_types[t])
            w.write_batch(c, batches[t].log_ns, batches[t].data)
    tm["write"] = time.perf_counter() - t0

    out_stamp = imu.stamp_ns[outs.index]
    log_s = (out_log - bag_start) * 1e-9
    scores = None
    if truth is not None and truth_name:
        m = _match_truth(out_stamp, out_log, truth, batches[truth_name].log_ns)
        ok = m >= 0
        if ok.any():
            qt = truth.fields["quaternion"][m[ok]]
            q_true = np.column_stack([qt[:, 3], qt[:, 0], qt[:, 1], qt[:, 2]])
            q_true /= np.linalg.norm(q_true, axis=1, keepdims=True)
            desc = read_description(bag) or {}
            ivs = desc.get("intervals")
            if ivs:  # synthetic intervals are in simulation time: shift to bag time
                first = (int(imu_b.log_ns[0]) - bag_start) * 1e-9
                ivs = {k: [(a + first, b + first) for a, b in v] for k, v in ivs.items()}
            scores = score(outs.quat[ok], q_true, log_s[ok], p["world_frame"], use_mag, ivs,
                           skip)
            scores.skipped = int((~ok).sum())
        else:
            notes.append(f"no {truth_name} message has the stamp of an output; not scored")
    counters = adapter.all_counters()
    return ProcessResult(out=out, imu_topic=imu_name, mag_topic=mag_name, n_imu=len(imu_b),
                         accel_topic=acc_name, n_accel=len(acc_b) if acc_b else 0,
                         n_mag=len(mag_b) if mag_b else 0, n_out=len(outs.index), params=p,
                         counters=counters, timings=tm, outputs=outs,
                         stamps=out_stamp * 1e-9, log_s=log_s, scores=scores, notes=notes)
