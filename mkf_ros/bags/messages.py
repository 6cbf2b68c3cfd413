"""The messages of ``mkf process``: a window of decoded IMU and magnetometer messages through
the :class:`~mkf_ros.stream.adapter.StreamAdapter` (the node's conversions and rules), the
``imu/data`` fields it publishes (:class:`Outputs`) and those messages encoded, the input's
header kept."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.bags.reader import BagError
from mkf_ros.stream import rep145


@dataclass
class Outputs:
    """The estimates, one row per published ``imu/data`` message: the orientation in the
    library's vocabulary (``quat``, ``cov``, as :class:`mkf_ros.api.EstimateResult`), the other
    fields as the message carries them (``*_covariance``: its row-major 9-vectors)."""

    index: np.ndarray  #: (M,) index of the input IMU message
    quat: np.ndarray  #: (M, 4) [w, x, y, z], sensor → world_frame
    cov: np.ndarray  #: (M, 3, 3) orientation covariance, rad², world axes
    angular_velocity: np.ndarray  #: (M, 3) rad/s
    angular_velocity_covariance: np.ndarray  #: (M, 9)
    linear_acceleration: np.ndarray  #: (M, 3) m/s²
    linear_acceleration_covariance: np.ndarray  #: (M, 9)
    #: (M,) bool, published with the heading lost in a gap (the node's yaw variance rule)
    yaw_lost: np.ndarray
    #: (M,) int, the smoother's slot of each output (``--smooth``; -1 otherwise)
    slot: np.ndarray


@dataclass
class Chunk:
    """One window of the bag's output: its ``imu/data`` messages (encoded) with their outputs,
    log times and stamps, its ground truth and the input messages copied with it; written as
    it comes, or once smoothed (:class:`~mkf_ros.bags.smoothing.Smoothing`)."""

    outs: Outputs  #: the filter's outputs (published form); ``slot``: global slots
    encoded: np.ndarray | list[bytes]  #: the output messages with the filter's orientation
    out_log: np.ndarray
    out_stamp: np.ndarray
    log_s: np.ndarray
    truth: Any  #: the window's ground truth (decoded) or None
    truth_log: np.ndarray | None
    copies: list[tuple[Any, np.ndarray, Any]]  #: (connection, log times, messages)



def decode(raws: np.ndarray | list[bytes], layout: cdr.Layout, topic: str,
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
    w_ok = ~np.isnan(res.angular_velocity[:, 0])
    a_ok = ~np.isnan(res.linear_acceleration[:, 0])
    w_cov = rep145.published_covariances(w_ok, res.angular_velocity_cov, av_in[i],
                                         float(node_params["angular_velocity_stddev"]),
                                         res.angular_velocity_cov_add)
    a_cov = rep145.published_covariances(a_ok, None, la_in[i],
                                         float(node_params["linear_acceleration_stddev"]))
    return Outputs(index=i, quat=res.quat, cov=res.cov,
                   angular_velocity=np.where(w_ok[:, None], res.angular_velocity, 0.0),
                   angular_velocity_covariance=w_cov,
                   linear_acceleration=np.where(a_ok[:, None], res.linear_acceleration, 0.0),
                   linear_acceleration_covariance=a_cov, yaw_lost=res.yaw_lost, slot=res.slot)


def encode_outputs(imu: cdr.Decoded, batch: Any, out: Outputs) -> np.ndarray | list[bytes]:
    """``imu/data`` messages: the input messages with the estimate written in (header kept)."""
    if len(out.index) == 0:
        return []
    q = out.quat
    values = dict(orientation=np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]]),
                  orientation_covariance=out.cov.reshape(-1, 9),
                  angular_velocity=out.angular_velocity,
                  angular_velocity_covariance=out.angular_velocity_covariance,
                  linear_acceleration=out.linear_acceleration,
                  linear_acceleration_covariance=out.linear_acceleration_covariance)
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
