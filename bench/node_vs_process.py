"""The ``estimator`` node against ``mkf process`` on real bags: the same computation?

    ./run bench node_vs_process BAG_DIR [--only GLOB] [--algorithm A ...] [--set NAME=VALUE ...]

e.g. ``./run bench node_vs_process ../shared/eval-data/ros-bags`` (the ROS 1 bags described in
that folder's README; not in this repository and never used by the tests).

For every bag in BAG_DIR (``*.bag``, ``*.mcap``, rosbag2 folders), for each algorithm (default
MEKF) without the magnetometer (6D) and, where the bag has a ``sensor_msgs/MagneticField`` topic,
with it (9D):

1. :func:`mkf_ros.bags.process.process_bag` (what ``mkf process`` runs) on the bag, its IMU
   topic the bag's one ``sensor_msgs/Imu`` topic, into a throw-away output bag;
2. the same messages (the IMU topic, plus the magnetometer topic in 9D: the topics
   ``process_bag`` reads; ``--all-topics``: the magnetometer in 6D too), read back with the
   project's reader (ROS 1 → CDR), deserialised to rclpy messages and published in recording
   order to an in-process ``estimator`` node with the same parameters, one message at a time
   (each taken before the next is published, so the executor cannot reorder the two
   subscriptions), its ``imu/data`` recorded;
3. per output, the node's message against the process tool's estimate for the same input
   message: orientation (x, y, z, w) and orientation covariance compared bit for bit; the
   node's stream counters against the process run's.

Columns: ``in`` messages published (IMU + magnetometer), ``out`` outputs compared (node /
process), ``identical`` outputs whose orientation and covariance are bit-identical, ``max |Δq|``
/ ``max |Δcov|`` over the others, ``first diff`` the index of the first differing output (and
its input IMU message), ``ties`` IMU/magnetometer messages of equal log time (where the
recording order and ``process_bag``'s merge rule — magnetometer first — could disagree),
``counters`` equal or the names that differ. Exit code 0 if every run is identical, 1 if not,
2 for bad arguments.
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import random
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

# every process that may start rclpy: discovery on this host only, a domain of its own
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 101)))
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="mkf_ros-bench-log-"))

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from ros_bags import only_topic, parse_set  # noqa: E402  (the ROS-bag bench's readers)

ALGORITHMS = ("mekf", "mukf")


@dataclass
class Result:
    bag: str
    label: str
    n_in: int
    n_node: int
    n_proc: int
    identical: int
    max_dq: float
    max_dcov: float
    first_diff: str
    ties: int
    counters: str
    seconds: float

    @property
    def same(self) -> bool:
        return (self.n_node == self.n_proc and self.identical == self.n_proc
                and self.counters == "equal")


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def _bags(folder: Path, only: str | None) -> list[Path]:
    found = sorted(p for p in folder.iterdir()
                   if p.suffix in (".bag", ".mcap", ".db3")
                   or (p.is_dir() and (p / "metadata.yaml").is_file()))
    return [p for p in found if only is None or fnmatch.fnmatch(p.name, only)]


def _topic(path: Path, msgtype: str) -> str | None:
    from mkf_ros.bags import BagReader

    with BagReader(path) as br:
        return only_topic(br, msgtype)


def _ties(path: Path, imu_topic: str, mag_topic: str) -> int:
    """IMU messages whose log time equals a magnetometer message's."""
    from mkf_ros.bags import BagReader

    with BagReader(path) as br:
        b = br.read([imu_topic, mag_topic])
    return int(np.isin(b[imu_topic].log_ns, b[mag_topic].log_ns).sum())


def run_case(ctx: Any, path: Path, imu_topic: str, mag_topic: str | None, params: dict[str, Any],
             tmp: Path, all_topics: bool = False) -> Result:
    from rosharness import Harness, bag_messages, output_arrays, send_one_by_one
    from sensor_msgs.msg import Imu

    from mkf_ros.bags.process import process_bag

    t0 = time.monotonic()
    use_mag = bool(params["use_mag"])
    r = process_bag(path, tmp / "out.mcap", params, imu_topic=imu_topic,
                    mag_topic=mag_topic if use_mag else None, truth_topic=None, overwrite=True,
                    keep_outputs=True)
    o = r.outputs
    assert o is not None
    topics = [imu_topic, mag_topic] if (use_mag or all_topics) and mag_topic else [imu_topic]
    msgs = bag_messages(path, topics)
    imus = [m for m in msgs if isinstance(m, Imu)]
    h = Harness(ctx, params)
    try:
        send_one_by_one(h, msgs, timeout=30.0)
        st, q_node, cov_node = output_arrays(h.out)
        node_counters = h.est.stream.counters
    finally:
        h.close()
    in_st, _, _ = output_arrays([imus[i] for i in o.index.tolist()])
    n = min(len(st), len(o.index))
    same_row = ((st[:n] == in_st[:n])
                & (_bits(q_node[:n]) == _bits(o.quat[:n])).all(1)
                & (_bits(cov_node[:n]) == _bits(o.cov[:n].reshape(-1, 9))).all(1))
    diff = np.flatnonzero(~same_row)
    dq = np.abs(q_node[:n] - o.quat[:n])[diff]
    dc = np.abs(cov_node[:n] - o.cov[:n].reshape(-1, 9))[diff]
    first = (f"{diff[0]} (IMU msg {o.index[diff[0]]})" if len(diff) else
             "—" if len(st) == len(o.index) else f"{n} (count)")
    bad = sorted(k for k in set(node_counters) | set(r.counters)
                 if node_counters.get(k) != r.counters.get(k))
    counters = "equal" if not bad else ", ".join(
        f"{k} {node_counters.get(k)}≠{r.counters.get(k)}" for k in bad)
    ties = _ties(path, imu_topic, mag_topic) if len(topics) == 2 and mag_topic else 0
    label = f"{params['algorithm']} {'9D' if use_mag else '6D'}"
    if len(topics) == 2 and not use_mag:
        label += " + mag published"
    return Result(path.name, label, len(msgs),
                  len(st), len(o.index), int(same_row.sum()),
                  float(np.nanmax(dq)) if dq.size else 0.0,
                  float(np.nanmax(dc)) if dc.size else 0.0, first, ties, counters,
                  time.monotonic() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(formatter_class=argparse.RawDescriptionHelpFormatter,
                                 description=(__doc__ or "").replace("``", ""))
    ap.add_argument("folder", type=Path, metavar="BAG_DIR", help="folder with bags")
    ap.add_argument("--only", metavar="GLOB", help="only the bags whose file name matches")
    ap.add_argument("--algorithm", choices=ALGORITHMS, nargs="+", default=["mekf"],
                    help="filters to run (default mekf)")
    ap.add_argument("--all-topics", action="store_true",
                    help="6D: publish the magnetometer topic to the node too (what mkf play "
                         "and a live sensor send; process_bag does not read it in 6D)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="override a parameter for every run (repeatable)")
    args = ap.parse_args(argv)
    if not args.folder.is_dir():
        print(f"node_vs_process: {args.folder} is not a folder", file=sys.stderr)
        return 2
    try:
        overrides = parse_set(args.set)
    except ValueError as e:
        print(f"node_vs_process: {e}", file=sys.stderr)
        return 2
    bags = _bags(args.folder, args.only)
    if not bags:
        print(f"node_vs_process: no bags in {args.folder}", file=sys.stderr)
        return 2

    import rclpy
    from rclpy.context import Context

    from mkf_ros.bags import BagError, cdr

    sys.path.insert(0, str(ROOT / "test" / "ros"))  # the node test harness
    ctx = Context()
    rclpy.init(context=ctx)
    results: list[Result] = []
    print("| bag | run | in | out node / process | identical | max abs Δq | max abs Δcov | "
          "first diff | ties | counters | s |")
    print("|---|---|---:|---:|---:|---:|---:|---|---:|---|---:|", flush=True)
    try:
        with tempfile.TemporaryDirectory(prefix="mkf-nvp-") as td:
            for path in bags:
                try:
                    imu = _topic(path, cdr.IMU.msgtype)
                    mag = _topic(path, cdr.MAGNETIC_FIELD.msgtype)
                except BagError as e:
                    print(f"| {path.name} | {e} |")
                    continue
                if imu is None:
                    print(f"| {path.name} | no sensor_msgs/Imu topic |")
                    continue
                for alg in args.algorithm:
                    for use_mag in ([False, True] if mag else [False]):
                        params = {**overrides, "algorithm": alg, "use_mag": use_mag}
                        res = run_case(ctx, path, imu, mag, params, Path(td),
                                       args.all_topics)
                        results.append(res)
                        print(f"| {res.bag} | {res.label} | {res.n_in} | {res.n_node} / "
                              f"{res.n_proc} | {res.identical} | "
                              f"{res.max_dq:.3g} | {res.max_dcov:.3g} | {res.first_diff} | "
                              f"{res.ties} | {res.counters} | {res.seconds:.0f} |", flush=True)
    finally:
        rclpy.try_shutdown(context=ctx)
    bad = [r for r in results if not r.same]
    print(f"\n{len(results) - len(bad)} of {len(results)} runs bit-identical"
          + (": differ: " + ", ".join(f"{r.bag} {r.label}" for r in bad) if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
