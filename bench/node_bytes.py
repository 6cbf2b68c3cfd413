"""Does the ``estimator`` node publish the same ``imu/data`` bytes as another version of it?
(A check for a change to the node's per-message path; not a test: it takes real bags.)

The node of this checkout and the node of ``--reference`` (another checkout, or ``git archive``
of a branch, unpacked: its ``mkf_ros`` is imported from there, each version in a process of its
own) are fed the same serialized messages through their subscription callbacks, in one process
each, without DDS: the IMU and magnetometer messages of ROS 1 bags (read with rosbags, written
as ROS 2 CDR with every field of the recording), with edge cases inserted (duplicates, messages
out of order, a time jump back, zero stamps, big-endian and truncated and empty messages,
not-reported and non-finite fields), under a few parameter sets, with parameters changed while
the messages flow. Compared, per bag and parameter set: every ``imu/data`` payload, byte for
byte (a zero stamp takes a receive time both versions get from the same counter), the
exceptions counted (their one-line text), the adapter's counters, the messages received and
published, and the latest frame_id.

    ./run bench node_bytes /work/shared/eval-data/ros-bags --reference /tmp/main-src
    (git archive main | tar -x -C /tmp/main-src)
"""

from __future__ import annotations

import argparse
import os
import pickle
import random
import struct
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 101)))
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="mkf_ros-bench-log-"))

#: (bag, IMU topic, magnetometer topic) of the ros-bags folder (its README)
BAGS = (("phidgets_imu_upside_down.bag", "/imu/data_raw", "/imu/mag"),
        ("ardrone_imu.bag", "/ardrone/imu", "/ardrone/mag"),
        ("sparkfun_razor.bag", "/imu/data_raw", "/imu/mag"),
        ("rl_test2.bag", "/imu/data", None))
CONFIGS: dict[str, dict[str, Any]] = {
    "default, use_mag": {"use_mag": True},
    "bias_corrected, stddevs": {"use_mag": True, "angular_velocity_source": "bias_corrected",
                                "angular_velocity_stddev": 0.02,
                                "linear_acceleration_stddev": 0.3},
    "estimate, no gravity, NED, yaw offset": {
        "angular_velocity_source": "estimate", "remove_gravity_vector": True,
        "yaw_offset": 0.4, "world_frame": "ned"},
    "mukf, orientation_stddev, constant_dt": {"algorithm": "mukf", "use_mag": True,
                                              "orientation_stddev": 0.1,
                                              "constant_dt": 0.004},
}
#: parameters set while the messages flow (at these message indices)
LIVE: dict[int, dict[str, Any]] = {
    1500: {"angular_velocity_stddev": 0.05},
    4500: {"angular_velocity_source": "estimate"},
    7000: {"linear_acceleration_stddev": 0.7, "angular_velocity_source": "input"}}
_STAMP = struct.Struct("<iI")


def bag_messages(path: Path, imu_topic: str, mag_topic: str | None) -> list[tuple[str, bytes]]:
    """``("imu" | "mag", CDR bytes)`` of a ROS 1 bag's IMU and magnetometer messages."""
    from rclpy.serialization import serialize_message
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import Imu, MagneticField

    out = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as r:
        conns = [c for c in r.connections if c.topic in (imu_topic, mag_topic)]
        for c, _, raw in r.messages(connections=conns):
            m = r.deserialize(raw, c.msgtype)
            if c.topic == imu_topic:
                x: Any = Imu()
                o = m.orientation
                x.orientation.x, x.orientation.y, x.orientation.z, x.orientation.w = (
                    o.x, o.y, o.z, o.w)
                for f in ("angular_velocity", "linear_acceleration"):
                    v, w = getattr(m, f), getattr(x, f)
                    w.x, w.y, w.z = v.x, v.y, v.z
                for f in ("orientation_covariance", "angular_velocity_covariance",
                          "linear_acceleration_covariance"):
                    setattr(x, f, [float(v) for v in getattr(m, f)])
            else:
                x = MagneticField()
                v = m.magnetic_field if hasattr(m, "magnetic_field") else m.vector
                x.magnetic_field.x, x.magnetic_field.y, x.magnetic_field.z = v.x, v.y, v.z
            x.header.stamp.sec, x.header.stamp.nanosec = m.header.stamp.sec, m.header.stamp.nanosec
            x.header.frame_id = m.header.frame_id
            out.append(("imu" if c.topic == imu_topic else "mag", serialize_message(x)))
    return out


def _restamped(d: bytes, sec: int, nsec: int) -> bytes:
    b = bytearray(d)
    _STAMP.pack_into(b, 4, sec, nsec)
    return bytes(b)


def with_edge_cases(msgs: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    """The messages with edge cases inserted (see the module docstring)."""
    out: list[tuple[str, bytes]] = []
    for i, (kind, d) in enumerate(msgs):
        out.append((kind, d))
        sec = _STAMP.unpack_from(d, 4)[0]
        if kind == "mag":
            extra = {3: _restamped(d, 0, 0), 5: d[:40], 7: b"\x00\x00" + d[2:], 1: b"",
                     9: _restamped(d, -2, 2_000_000_000)}  # the last: 0.0 s as a float
            out += [("mag", extra[k]) for k, m in ((3, 53), (5, 71), (7, 89), (1, 101),
                                                   (9, 97)) if i % m == k]
            continue
        j = len(out)
        cases = [(97, 5, d), (1001, 3, b""), (211, 7, b"\x00\x00" + d[2:]),
                 (313, 11, d[:120]), (313, 11, d[:10]), (401, 13, _restamped(d, 0, 0)),
                 (733, 23, _restamped(d, sec - 1, 0))]
        out += [("imu", x) for m, k, x in cases if j % m == k]
        if j % 503 == 17 or j % 577 == 19:  # a covariance marked not reported / non-finite
            b = bytearray(d)
            at = len(b) - (8 * 12 if j % 503 == 17 else 72)
            struct.pack_into("<d", b, at, -1.0 if j % 503 == 17 else float("nan"))
            out.append(("imu", bytes(b)))
        if j == 3000:  # the stamps jump back by 100 s
            out.append(("imu", _restamped(d, sec - 100, 0)))
    return out


def run_node(name: str, params: dict[str, Any], msgs: list[tuple[str, bytes]]) -> dict:
    """What one node does with ``msgs`` (see the module docstring)."""
    from rclpy.parameter import Parameter
    from rclpy.serialization import serialize_message

    from mkf_ros.ros.estimator_node import EstimatorNode

    node = EstimatorNode(f"est_{name}", argv=[],
                         parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    pubs: list[bytes] = []
    node._pub.publish = lambda p: pubs.append(p if isinstance(p, bytes)
                                              else serialize_message(p))
    if hasattr(node, "_publish_bytes"):
        node._publish_bytes = pubs.append
    ticks = iter(range(1, 1 << 62))

    class Clock:  # the receive time of a zero stamp: the same in every version
        def now(self) -> Any:
            ns = 1_700_000_000_000_000_000 + next(ticks) * 1_000_000
            return type("Now", (), {"nanoseconds": ns})()

    node.get_clock = Clock  # type: ignore[method-assign]
    errors: list[tuple[int, str]] = []
    count = node._count_exception

    def counted(e: BaseException, where: str) -> None:
        errors.append((len(pubs), f"{where}: {type(e).__name__}: {e}"))
        count(e, where)

    node._count_exception = counted  # type: ignore[method-assign]
    for i, (kind, d) in enumerate(msgs):
        if i in LIVE:
            res = node.set_parameters([Parameter(k, value=v) for k, v in LIVE[i].items()])
            assert all(r.successful for r in res), res
        (node._on_imu if kind == "imu" else node._on_mag)(d)
    result = dict(imu_data=pubs, errors=errors, counters=node.stream.all_counters(),
                  published=node._published, received=node.received_imu,
                  frame_id=node.snapshot().frame_id)
    node.destroy_node()
    return result


def role_record(bags: Path, out: str) -> None:
    import rclpy

    import mkf_ros

    rclpy.init()
    res: dict[Any, Any] = {"mkf_ros": str(Path(mkf_ros.__file__).parent)}
    for bag, imu, mag in BAGS:
        msgs = with_edge_cases(bag_messages(bags / bag, imu, mag))
        for k, (config, params) in enumerate(CONFIGS.items()):
            res[(bag, config)] = dict(run_node(f"c{k}", params, msgs), sent=len(msgs))
    rclpy.try_shutdown()
    with open(out, "wb") as f:
        pickle.dump(res, f)


def record(bags: Path, src: Path | None, out: Path) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(src), env.get("PYTHONPATH"))))
    subprocess.run([sys.executable, str(HERE), "_record", str(bags), "--out", str(out)],
                   env=env, check=True, stdout=subprocess.DEVNULL)
    with open(out, "rb") as f:
        return pickle.load(f)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bags", type=Path, help="the ros-bags folder (ROS 1 bags, its README)")
    ap.add_argument("--reference", type=Path, required=False,
                    help="the other version: a folder holding its mkf_ros package")
    ap.add_argument("_role", nargs="?", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    if len(sys.argv) > 1 and sys.argv[1] == "_record":
        args = ap.parse_args(sys.argv[2:])
        role_record(args.bags, args.out)
        return 0
    args = ap.parse_args()
    if args.reference is None or not (args.reference / "mkf_ros").is_dir():
        ap.error("--reference: a folder holding the other version's mkf_ros package")
    with tempfile.TemporaryDirectory(prefix="mkf_ros-node-bytes-") as tmp:
        ours = record(args.bags, None, Path(tmp) / "ours.pkl")
        ref = record(args.bags, args.reference, Path(tmp) / "reference.pkl")
    print(f"this checkout: {ours.pop('mkf_ros')}; reference: {ref.pop('mkf_ros')}")
    print()
    print("| bag | parameters | messages in | imu/data out | bytes out | exceptions | identical |")
    print("|---|---|---:|---:|---:|---:|---|")
    fields = ("imu_data", "errors", "counters", "published", "received", "frame_id")
    same_all = True
    for key, a in ours.items():
        b = ref[key]
        diff = [f for f in fields if a[f] != b[f]]
        same_all &= not diff
        print(f"| {key[0]} | {key[1]} | {a['sent']} | {a['published']} | "
              f"{sum(map(len, a['imu_data']))} | {len(a['errors'])} | "
              f"{'yes' if not diff else 'NO: ' + ', '.join(diff)} |")
    print()
    print("every imu/data byte, exception, counter identical" if same_all else "DIFFERENCES")
    return 0 if same_all else 1


if __name__ == "__main__":
    sys.exit(main())
