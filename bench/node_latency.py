"""Benchmark of the ``estimator`` node as a separate process (not a test).

Three processes: a publisher (IMU at each rate of the ladder + magnetometer at 100 Hz, header
stamps = wall clock at publish), the estimator (the installed console script, reliable input
QoS via ``qos_overrides``), and a recorder subscribed to ``imu/data``. For each rate it reports
messages lost (IMU published − ``imu/data`` received), the latency publish → estimator →
recorder (median, p99), and the CPU of the estimator process (from /proc, during the window).

    ./run bench node_latency                     # ladder 200, 1000, 2000, 3000, 4000 Hz
    .venv/bin/python bench/node_latency.py --rates 200 1000 --seconds 10 --algorithm mukf

The maximum sustained rate is the highest rate of the ladder with zero loss, the achieved
publish rate within 2 % of the target and p99 latency below 20 ms.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# every process that may start rclpy: discovery on this host only, a domain of its own
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 101)))
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="mkf_ros-bench-log-"))

HERE = Path(__file__).resolve()
CLK_TCK = os.sysconf("SC_CLK_TCK")


# --------------------------------------------------------------------------- child roles
def _ros_init() -> None:
    import rclpy

    rclpy.init()


def role_publish(rate: float, seconds: float, mag_rate: float) -> None:
    """Publish IMU (+ magnetometer) paced to ``rate``; print a JSON summary."""
    import numpy as np
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu, MagneticField

    from mkf_ros.sim import simulate

    _ros_init()
    node = Node("bench_publisher")
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Imu, "imu/data_raw", qos)
    pub_mag = node.create_publisher(MagneticField, "imu/mag", qos)
    end = time.monotonic() + 60
    while (pub.get_subscription_count() == 0 or pub_mag.get_subscription_count() == 0):
        assert time.monotonic() < end, "the estimator never subscribed"
        time.sleep(0.01)
    time.sleep(0.5)
    rec = simulate("slow_rotation", duration=10.0, rate=200.0, seed=1)
    n_rec = len(rec.t)
    imu, mag = Imu(), MagneticField()
    imu.header.frame_id = mag.header.frame_id = "imu_link"
    n = int(rate * seconds)
    mag_every = max(1, round(rate / mag_rate))
    n_mag = 0
    period = 1.0 / rate
    t_start_ns = time.time_ns()
    t0 = time.monotonic()
    for k in range(n):
        target = t0 + k * period
        ahead = target - time.monotonic()
        if ahead > 0.0005:
            time.sleep(ahead)
        i = k % n_rec
        now = time.time_ns()
        imu.header.stamp.sec, imu.header.stamp.nanosec = divmod(now, 1_000_000_000)
        g, a = rec.gyr[i], rec.acc[i]
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = map(float, g)
        imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = map(
            float, a)
        pub.publish(imu)
        if k % mag_every == mag_every // 2:
            mag.header.stamp = imu.header.stamp
            m = rec.mag[i]
            mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z = map(float, m)
            pub_mag.publish(mag)
            n_mag += 1
    elapsed = time.monotonic() - t0
    t_end_ns = time.time_ns()
    time.sleep(1.0)  # let the reliable writer deliver the tail
    print(json.dumps(dict(start_ns=t_start_ns, end_ns=t_end_ns, n_imu=n, n_mag=n_mag,
                          achieved=n / elapsed)), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    del np


def role_record(out: str) -> None:
    """Record (stamp, receive time) of every imu/data message until SIGINT; save .npy."""
    import numpy as np
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu

    _ros_init()
    node = Node("bench_recorder")
    rows: list[tuple[int, int]] = []
    append = rows.append

    def on_msg(m: Imu) -> None:
        append((m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, time.time_ns()))

    node.create_subscription(Imu, "imu/data", on_msg,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    print("recorder ready", flush=True)
    # the C++ EventsExecutor (spin_once loop): the recorder must not be the bottleneck
    from rclpy.experimental import EventsExecutor

    ex = EventsExecutor()
    ex.add_node(node)
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        while ex.context.ok():
            ex.spin_once(timeout_sec=0.2)
    np.save(out, np.array(rows, dtype=np.int64).reshape(-1, 2))
    rclpy.try_shutdown()


# --------------------------------------------------------------------------- orchestration
def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime + stime


def estimator_cmd(args: argparse.Namespace) -> list[str]:
    exe = Path(sys.executable).parent / "estimator"
    base = [str(exe)] if exe.is_file() else [sys.executable, "-m", "mkf_ros.ros.estimator_node"]
    base.append(f"--executor={args.executor}")
    params = {
        "use_mag": "true", "algorithm": args.algorithm, "diagnostics_period": "1.0",
        "qos_overrides./imu/data_raw.subscription.reliability": args.qos,
        "qos_overrides./imu/mag.subscription.reliability": args.qos,
        # 1 s at 1 kHz: a stall of the process (other jobs on the machine) must not overflow
        # the reader's history, which drops the oldest samples even with reliable QoS
        "qos_overrides./imu/data_raw.subscription.depth": str(args.depth),
        "qos_overrides./imu/mag.subscription.depth": str(args.depth),
    }
    return base + ["--ros-args"] + [x for k, v in params.items() for x in ("-p", f"{k}:={v}")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[200, 1000, 2000, 3000, 4000])
    ap.add_argument("--seconds", type=float, default=5.0, help="per rate")
    ap.add_argument("--mag-rate", type=float, default=100.0)
    ap.add_argument("--algorithm", choices=("mekf", "mukf"), default="mekf")
    ap.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                    help="estimator input QoS (default input QoS of the node: best_effort)")
    ap.add_argument("--depth", type=int, default=1000, help="estimator input queue depth")
    ap.add_argument("--nice", type=int, default=0,
                    help="niceness of the three processes (negative needs root): measure on a "
                         "machine that other jobs keep busy")
    ap.add_argument("--executor", choices=("events", "single"), default="events")
    ap.add_argument("_role", nargs="?", help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._role == "_publish":
        role_publish(args.rate, args.seconds, args.mag_rate)
        return 0
    if args._role == "_record":
        role_record(args.out)
        return 0

    import numpy as np

    if args.nice:
        os.nice(args.nice)  # inherited by the three child processes
    env = dict(os.environ)
    tmp = Path(tempfile.mkdtemp(prefix="mkf_ros-bench-"))
    print(f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}, nice {args.nice}; "
          f"estimator: {args.algorithm}, use_mag, input QoS {args.qos} depth {args.depth}, "
          f"{args.executor} executor",
          flush=True)
    est = subprocess.Popen(estimator_cmd(args), env=env, stdout=subprocess.DEVNULL,
                           stderr=open(tmp / "estimator.log", "w"))  # noqa: SIM115
    rec_file = tmp / "rec.npy"
    recorder = subprocess.Popen([sys.executable, str(HERE), "_record", "--out", str(rec_file)],
                                env=env, stdout=subprocess.PIPE, text=True)
    assert recorder.stdout is not None
    recorder.stdout.readline()
    # the estimator is up when it logs where it listens (kernels loaded)
    t_end = time.monotonic() + 300
    while "listening on" not in (tmp / "estimator.log").read_text():
        if est.poll() is not None or time.monotonic() > t_end:
            print((tmp / "estimator.log").read_text(), file=sys.stderr)
            return 1
        time.sleep(0.2)
    phases = []
    try:
        # warm-up, not reported: discovery of the reliable endpoints, first-call costs
        subprocess.run([sys.executable, str(HERE), "_publish", "--rate", "100", "--seconds",
                        "1", "--mag-rate", str(args.mag_rate)], env=env, capture_output=True,
                       timeout=120, check=True)
        for rate in args.rates:
            cpu0, w0 = cpu_seconds(est.pid), time.monotonic()
            p = subprocess.run([sys.executable, str(HERE), "_publish", "--rate", str(rate),
                                "--seconds", str(args.seconds), "--mag-rate",
                                str(args.mag_rate)], env=env, capture_output=True, text=True,
                               timeout=args.seconds * 4 + 120)
            cpu1, w1 = cpu_seconds(est.pid), time.monotonic()
            if p.returncode != 0:
                print(p.stderr, file=sys.stderr)
                return 1
            info = json.loads(p.stdout.strip().splitlines()[-1])
            # CPU over the publishing window only (the publisher's set-up is ~1.5 s of idle)
            busy_wall = args.seconds + 1.0
            info.update(rate=rate, cpu=(cpu1 - cpu0) / busy_wall * 100.0,
                        cpu_total_window=(cpu1 - cpu0) / (w1 - w0) * 100.0)
            phases.append(info)
            print(f"  {rate:.0f} Hz done", flush=True)
    finally:
        recorder.send_signal(signal.SIGINT)
        recorder.wait(timeout=60)
        est.send_signal(signal.SIGINT)
        est.wait(timeout=60)
    rows = np.load(rec_file)
    print()
    print("| IMU rate (Hz) | achieved | mag (Hz) | IMU sent | imu/data received | lost "
          "| latency median (ms) | latency p99 (ms) | estimator CPU (% of one core) |")
    print("|---|---|---|---|---|---|---|---|---|")
    best = None
    for ph in phases:
        sel = (rows[:, 0] >= ph["start_ns"]) & (rows[:, 0] <= ph["end_ns"])
        got = int(sel.sum())
        lat = (rows[sel, 1] - rows[sel, 0]) / 1e6
        lost = ph["n_imu"] - got
        med = float(np.median(lat)) if got else float("nan")
        p99 = float(np.percentile(lat, 99)) if got else float("nan")
        print(f"| {ph['rate']:.0f} | {ph['achieved']:.0f} | {args.mag_rate:.0f} | "
              f"{ph['n_imu']} | {got} | {lost} | {med:.2f} | {p99:.2f} | {ph['cpu']:.1f} |")
        if lost == 0 and ph["achieved"] >= 0.98 * ph["rate"] and p99 < 20.0:
            best = ph["rate"]
    print()
    print(f"maximum sustained IMU rate: {best:.0f} Hz" if best else "no rate sustained")
    print(f"(estimator log: {tmp / 'estimator.log'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
