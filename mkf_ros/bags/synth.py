"""Synthetic recordings as ROS 2 messages: ``imu/data_raw`` (sensor_msgs/Imu without
orientation), ``imu/mag`` (sensor_msgs/MagneticField, tesla) and the true orientation on
``imu/ground_truth`` (geometry_msgs/QuaternionStamped, same stamps as the IMU), as bags
(``mkf synth``) or as the message stream the ``player`` node publishes.

Stamps are ``start + SimData.t`` (jitter and jumps included); log (receive) times are
``start + SimData.t_true``, which always increase.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.bags.writer import BagWriter
from mkf_ros.sim import SimData, SimStream

#: 2024-01-01T00:00:00Z: default start of synthetic bags (reproducible bytes)
DEFAULT_START_NS = 1_704_067_200 * 1_000_000_000
TOPICS = {"imu": "/imu/data_raw", "mag": "/imu/mag", "truth": "/imu/ground_truth",
          "accel": "/imu/accel", "gyro": "/imu/gyro"}
#: custom_data key under which a synthetic bag records how it was made (JSON)
CUSTOM_KEY = "mkf_ros.synth"


@dataclass
class Stream:
    """One topic of a synthetic recording."""

    topic: str
    msgtype: str
    log_ns: np.ndarray  #: (N,) int64
    rows: np.ndarray  #: (N, L) uint8 CDR messages


def _ns(t: np.ndarray, start_ns: int) -> np.ndarray:
    return start_ns + np.round(np.asarray(t) * 1e9).astype(np.int64)


def sim_streams(sim: SimData, *, start_ns: int = DEFAULT_START_NS, frame_id: str = "imu_link",
                topics: dict[str, str] | None = None) -> dict[str, Stream]:
    """The IMU, magnetometer and ground-truth streams of ``sim`` (keys ``imu``, ``mag``,
    ``truth``). Covariances: the simulated noise variances on the diagonals;
    ``orientation_covariance[0] = -1`` (no orientation in ``imu/data_raw``, REP-145)."""
    names = dict(TOPICS, **(topics or {}))
    meta = sim.meta
    stamps = _ns(sim.t, start_ns)
    logs = _ns(sim.t if sim.t_true is None else sim.t_true, start_ns)
    eye = np.eye(3).reshape(9)
    imu = cdr.encode(
        cdr.IMU, stamps, frame_id,
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=sim.gyr,
        angular_velocity_covariance=eye * meta.get("gyro_noise", 0.0) ** 2,
        linear_acceleration=sim.acc,
        linear_acceleration_covariance=eye * meta.get("acc_noise", 0.0) ** 2,
    )
    ok = sim.mag_valid
    mag = cdr.encode(cdr.MAGNETIC_FIELD, stamps[ok], frame_id, magnetic_field=sim.mag[ok],
                     magnetic_field_covariance=eye * meta.get("mag_noise", 0.0) ** 2)
    q = sim.quat
    truth = cdr.encode(cdr.QUATERNION_STAMPED, stamps, frame_id,
                       quaternion=np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]]))
    return {
        "imu": Stream(names["imu"], cdr.IMU.msgtype, logs, imu),
        "mag": Stream(names["mag"], cdr.MAGNETIC_FIELD.msgtype, logs[ok], mag),
        "truth": Stream(names["truth"], cdr.QUATERNION_STAMPED.msgtype, logs, truth),
    }


def split_imu(imu: Stream, accel_every: int, accel_topic: str = TOPICS["accel"],
              gyro_topic: str = TOPICS["gyro"], offset: int = 0) -> tuple[Stream, Stream]:
    """The accelerometer and gyroscope streams a RealSense-like driver publishes from one
    combined ``sensor_msgs/Imu`` stream: every ``accel_every``-th message (from the first)
    with its angular velocity zeroed on ``accel_topic``, every message with its linear
    acceleration zeroed on ``gyro_topic`` (stamps, log times and covariances kept).
    ``offset``: messages of the stream before ``imu`` (a chunk of it), counted for the
    every-``accel_every``-th choice."""
    if accel_every < 1:
        raise ValueError(f"accel_every must be >= 1, got {accel_every}")
    first = -offset % accel_every
    acc_rows = imu.rows[first::accel_every].copy()
    cdr.set_fields(acc_rows, cdr.IMU, angular_velocity=0.0)
    gyr_rows = imu.rows.copy()
    cdr.set_fields(gyr_rows, cdr.IMU, linear_acceleration=0.0)
    return (Stream(accel_topic, cdr.IMU.msgtype, imu.log_ns[first::accel_every], acc_rows),
            Stream(gyro_topic, cdr.IMU.msgtype, imu.log_ns, gyr_rows))


def interleave(streams: list[Stream]) -> tuple[np.ndarray, np.ndarray, list[bytes]]:
    """All messages in log-time order (ties keep the list order): (stream index, log ns,
    raw bytes)."""
    idx = np.concatenate([np.full(len(s.log_ns), i) for i, s in enumerate(streams)])
    t = np.concatenate([s.log_ns for s in streams])
    raws = [r for s in streams for r in cdr.split_rows(s.rows)]
    order = np.lexsort((idx, t))
    return idx[order], t[order], [raws[i] for i in order.tolist()]


def describe(sim: SimData | SimStream) -> dict[str, Any]:
    """JSON-able record of how a synthetic recording was made (scenario, parameters, truth
    intervals), stored in the bag's ``custom_data``."""
    m = sim.meta
    keep = ("scenario", "rate", "seed", "duration", "mag_rate", "gyro_noise", "acc_noise",
            "mag_noise", "params", "intervals", "time_jumps")
    out = {k: m[k] for k in keep if k in m}
    out["mag_field"] = [float(x) for x in np.asarray(m.get("mag_field", []))]
    return json.loads(json.dumps(out, default=_jsonable))


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return str(x)


def write_bag(sim: SimData | SimStream, path: str | Path, storage: str = "mcap", *,
              start_ns: int = DEFAULT_START_NS, frame_id: str = "imu_link",
              overwrite: bool = False, topics: dict[str, str] | None = None,
              compress: bool = False, split_accel: int = 0) -> dict[str, int]:
    """Write ``sim`` to a new bag (atomically); returns the message count per topic.
    ``sim`` is a whole recording or a :class:`~mkf_ros.sim.SimStream`, written chunk by chunk
    in bounded memory (the same messages). ``split_accel`` > 0: instead of ``imu/data_raw``,
    separate accelerometer (``imu/accel``, every ``split_accel``-th sample) and gyroscope
    (``imu/gyro``) topics, as :func:`split_imu` (RealSense-like; process with ``input_mode``
    split)."""
    names = dict(TOPICS, **(topics or {}))
    if split_accel < 0:
        raise ValueError(f"split_accel must be >= 0, got {split_accel}")
    if split_accel:
        keys = ["accel", "gyro", "mag", "truth"]
        # at equal times: magnetometer, accelerometer, gyro (held, then fused with the gyro)
        write_order = [2, 0, 1, 3]
    else:
        keys = ["imu", "mag", "truth"]
        # at equal times the magnetometer goes first: the estimator then holds it and fuses
        # it with the IMU sample of that stamp (a first sample initialises with its heading)
        write_order = [1, 0, 2]
    types = {"imu": cdr.IMU.msgtype, "accel": cdr.IMU.msgtype, "gyro": cdr.IMU.msgtype,
             "mag": cdr.MAGNETIC_FIELD.msgtype, "truth": cdr.QUATERNION_STAMPED.msgtype}
    counts = dict.fromkeys((names[k] for k in keys), 0)
    imu_done = 0
    with BagWriter(path, storage, overwrite=overwrite, compress=compress) as w:
        conns = [w.add_topic(names[k], types[k]) for k in keys]
        ids = np.array([conns[i].id for i in write_order])
        for chunk in ([sim] if isinstance(sim, SimData) else sim):
            streams = sim_streams(chunk, start_ns=start_ns, frame_id=frame_id, topics=topics)
            if split_accel:
                acc, gyr = split_imu(streams["imu"], split_accel, names["accel"],
                                     names["gyro"], offset=imu_done)
                order = [acc, gyr, streams["mag"], streams["truth"]]
            else:
                order = [streams["imu"], streams["mag"], streams["truth"]]
            imu_done += len(streams["imu"].log_ns)
            which, t, raws = interleave([order[i] for i in write_order])
            w.write_batch(ids[which], t, raws)
            for s in order:
                counts[s.topic] += len(s.log_ns)
        # after the last chunk: the truth intervals found on the way are complete
        w._w.set_custom_data(CUSTOM_KEY, json.dumps(describe(sim)))
    return counts


def read_description(bag_path: str | Path) -> dict[str, Any] | None:
    """The ``custom_data`` record :func:`write_bag` left in a rosbag2 directory, if any."""
    meta = Path(bag_path) / "metadata.yaml"
    if not meta.is_file():
        return None
    try:
        import yaml

        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        text = (info.get("custom_data") or {}).get(CUSTOM_KEY)
        return json.loads(text) if text else None
    except Exception:
        return None
