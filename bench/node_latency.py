"""Benchmark of the ``estimator`` node against the floor of any Python node (not a test).

Two subjects, each in a ROS domain of its own with its own publisher and recorder processes:

* ``estimator``: the installed console script (MEKF, ``use_mag``, default parameters but the
  input QoS: reliable via ``qos_overrides``, so that a loss is a loss);
* ``stand-in``: an rclpy node that does nothing but republish the bytes of every
  ``imu/data_raw`` message on ``imu/data`` — the same input and output QoS (and the same
  ``qos_overrides``), a raw subscription to ``imu/mag`` that does nothing, the same
  EventsExecutor loop. It is the floor of a Python node doing this job: what rclpy and
  Fast DDS cost per message.

The publisher sends serialized ``sensor_msgs/Imu`` at each rate (header stamp = wall clock at
publish) plus ``MagneticField`` at ``--mag-rate``; the recorder takes ``imu/data`` raw. The
phases are interleaved — for each repetition, each rate, the two subjects one after the
other (the order alternating) — so that the machine's load falls on both alike; each subject
runs on CPU 1, its publisher and recorder on CPU 0 (``--no-pin``: where the scheduler puts
them, which moves the figures by up to a factor of two from run to run). Per phase:
messages lost (IMU published − ``imu/data`` received), latency publish → subject → recorder,
and the CPU of the subject process (the scheduler's run time of all its threads, from /proc,
over the publishing window and a 0.3 s tail). The table gives each subject's mean CPU and the ratio
estimator / stand-in (the mean of the per-repetition ratios, and their range).

    ./run bench node_latency                        # 1 and 4 kHz, 3 repetitions of 5 s
    ./run bench node_latency --rates 1000 --reps 10 --seconds 3
    ./run bench node_latency --subjects estimator --rates 200 1000 2000 3000 4000
    ./run bench node_latency --estimator-cmd "OTHER/.venv/bin/estimator"   # another build
    ./run bench node_latency --callback             # the callback's parts, one process
    ./run bench node_latency --estimator-part parse # the node with its callback cut after a step
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import shlex
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO, Any

# every process that may start rclpy: discovery on this host only, log files in a temp dir
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="mkf_ros-bench-log-"))

HERE = Path(__file__).resolve()
CLK_TCK = os.sysconf("SC_CLK_TCK")
SUBJECTS = ("estimator", "stand-in")
TAIL = 0.3  # s after the last message: the subject's CPU window includes its tail
_STAMP = struct.Struct("<iI")  # header.stamp after the 4-byte CDR encapsulation


# --------------------------------------------------------------------------- child roles
def _qos(depth: int, reliable: bool) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)


#: the stand-in's QoS, checked against the estimator's (mkf_ros.ros.qos) by the orchestrator:
#: the stand-in itself imports nothing of mkf_ros (a plain rclpy node)
STANDIN_INPUT_QOS = dict(depth=200, reliable=False)
STANDIN_OUTPUT_QOS = dict(depth=100, reliable=True)


def role_standin() -> None:
    """The stand-in republisher (see the module docstring)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rclpy.qos_overriding_options import QoSOverridingOptions
    from sensor_msgs.msg import Imu, MagneticField

    rclpy.init()
    node = Node("estimator")
    opts = QoSOverridingOptions.with_default_policies
    pub = node.create_publisher(Imu, "imu/data", _qos(**STANDIN_OUTPUT_QOS),
                                qos_overriding_options=opts())
    node.create_subscription(Imu, "imu/data_raw", pub.publish, _qos(**STANDIN_INPUT_QOS),
                             qos_overriding_options=opts(), raw=True)
    node.create_subscription(MagneticField, "imu/mag", lambda data: None,
                             _qos(**STANDIN_INPUT_QOS), qos_overriding_options=opts(), raw=True)
    ex = EventsExecutor()
    ex.add_node(node)
    print("listening on", flush=True)
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        while ex.context.ok():
            ex.spin_once(timeout_sec=0.2)
    rclpy.try_shutdown()


def _serialized_stream(n: int) -> tuple[list[bytes], list[bytes]]:
    """Serialized Imu and MagneticField messages of a simulated rotation (stamps patched at
    publish)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu, MagneticField

    from mkf_ros.sim import simulate

    rec = simulate("slow_rotation", duration=n / 200.0, rate=200.0, seed=1)
    imus, mags = [], []
    for i in range(n):
        imu, mag = Imu(), MagneticField()
        imu.header.frame_id = mag.header.frame_id = "imu_link"
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = map(
            float, rec.gyr[i])
        imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = map(
            float, rec.acc[i])
        mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z = map(float, rec.mag[i])
        imus.append(serialize_message(imu))
        mags.append(serialize_message(mag))
    return imus, mags


def _stamped(buf: bytes, ns: int) -> bytes:
    b = bytearray(buf)
    _STAMP.pack_into(b, 4, *divmod(ns, 1_000_000_000))
    return bytes(b)


def role_publish() -> None:
    """Publish on command from stdin: ``run RATE SECONDS MAG_RATE`` prints ``start`` when the
    first message goes out and ``end {json}`` after the last one and a tail; ``quit``."""
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import Imu, MagneticField

    rclpy.init()
    node = Node("bench_publisher")
    pub = node.create_publisher(Imu, "imu/data_raw", _qos(1000, True))
    pub_mag = node.create_publisher(MagneticField, "imu/mag", _qos(1000, True))
    imus, mags = _serialized_stream(2000)
    end = time.monotonic() + 120
    while pub.get_subscription_count() == 0 or pub_mag.get_subscription_count() == 0:
        assert time.monotonic() < end, "the subject never subscribed"
        time.sleep(0.01)
    time.sleep(0.5)
    print("ready", flush=True)
    for line in sys.stdin:
        cmd = line.split()
        if not cmd or cmd[0] == "quit":
            break
        rate, seconds, mag_rate = map(float, cmd[1:4])
        n = int(rate * seconds)
        mag_every = max(1, round(rate / mag_rate))
        n_mag, period = 0, 1.0 / rate
        print("start", flush=True)
        t_start_ns = time.time_ns()
        t0 = time.monotonic()
        for k in range(n):
            ahead = t0 + k * period - time.monotonic()
            if ahead > 0.0005:
                time.sleep(ahead)
            now = time.time_ns()
            pub.publish(_stamped(imus[k % len(imus)], now))
            if k % mag_every == mag_every // 2:
                pub_mag.publish(_stamped(mags[k % len(mags)], now))
                n_mag += 1
        elapsed = time.monotonic() - t0
        t_end_ns = time.time_ns()
        time.sleep(TAIL)
        print("end " + json.dumps(dict(start_ns=t_start_ns, end_ns=t_end_ns, n_imu=n,
                                       n_mag=n_mag, achieved=n / elapsed)), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def role_callback(seconds: float) -> None:
    """In one process, caches warm, no subscriber: CPU per IMU message (1 kHz of a simulated
    rotation with a 100 Hz magnetometer, ``seconds`` long, best of three passes) of the
    stand-in's callback (``publish``), of the estimator's and of each part of it."""
    import numpy as np
    import rclpy
    from rclpy.parameter import Parameter

    from mkf_ros.ros import rawmsg
    from mkf_ros.ros.estimator_node import EstimatorNode

    rclpy.init()
    node = EstimatorNode(argv=[], parameter_overrides=[Parameter("use_mag", value=True)])
    n = int(1000 * seconds)
    imus, mags = _serialized_stream(n)
    t0 = time.time_ns()
    imu = [_stamped(b, t0 + k * 1_000_000) for k, b in enumerate(imus)]
    mag = {k: _stamped(mags[k], t0 + k * 1_000_000) for k in range(5, n, 10)}
    pub, stream, enc = node._pub, node.stream, node._encoder

    def passes(fn: Any) -> float:
        best = math.inf
        for _ in range(3):
            stream.reset("benchmark pass")
            c0 = time.process_time()
            for k, data in enumerate(imu):
                fn(data)
                if k in mag:
                    node._on_mag(mag[k])
            best = min(best, time.process_time() - c0)
        return best / n * 1e6

    parts = np.zeros(4)
    clock = time.perf_counter_ns

    def timed(data: bytes) -> None:  # the callback's steps, each timed (lock and checks left out)
        a = clock()
        sec, nsec, off, gyr, acc = rawmsg.unpack_imu(data)  # type: ignore[misc]
        b = clock()
        rawmsg.pack_imu_event(stream.imu_event_bytes, sec + nsec * 1e-9, gyr, acc)
        flags = stream.run_imu_event()
        c = clock()
        payload = enc.encode_record(data, off, stream.output_bytes, flags, 0.0, 0.0)
        d = clock()
        pub.publish(payload)
        parts[:] += (b - a, c - b, d - c, clock() - d)

    rows = [("the stand-in's callback: publish the input bytes", passes(pub.publish)),
            ("the estimator's callback (EstimatorNode._on_imu)", passes(node._on_imu))]
    passes(timed)
    labels = ("read the message (rawmsg.unpack_imu)",
              "the filter (pack_imu_event + StreamAdapter.run_imu_event)",
              "build imu/data (ImuEncoder.encode_record)", "publish")
    rows += [(f"  of which: {lab}", t / (3 * n) / 1e3) for lab, t in zip(labels, parts,
                                                                       strict=True)]
    print("| per IMU message (1 kHz, 100 Hz magnetometer, warm caches) | CPU (µs) |")
    print("|---|---:|")
    for lab, us in rows:
        print(f"| {lab} | {us:.1f} |")
    node.destroy_node()
    rclpy.try_shutdown()


#: ``--estimator-part``: the estimator with its IMU callback cut after this step (each part
#: includes the ones before it; the last publishes what the node publishes)
PARTS = ("republish", "parse", "filter", "encode")


def role_estimator_part(part: str) -> int:
    """The installed estimator node, but its IMU callback replaced by the first steps of its
    own (lock, counters and checks left out), up to ``part``: ``republish`` publishes the
    input bytes (the node's structure with the stand-in's callback), ``parse`` reads the
    message first (``rawmsg.unpack_imu``), ``filter`` also runs the filter step, ``encode``
    also builds and publishes ``imu/data``. The ratio to the stand-in then says what each step
    costs in a running node (caches shared with DDS's threads), not in a warm loop."""
    from mkf_ros.ros import estimator_main, rawmsg
    from mkf_ros.ros.estimator_node import EstimatorNode

    def on_imu(self: Any, data: bytes) -> None:
        if part == "republish":
            self._pub.publish(data)
            return
        sec, nsec, off, gyr, acc = rawmsg.unpack_imu(data)
        if part == "parse":
            self._pub.publish(data)
            return
        stream = self.stream
        rawmsg.pack_imu_event(stream.imu_event_bytes, sec + nsec * 1e-9, gyr, acc)
        flags = stream.run_imu_event()
        if part == "filter":
            self._pub.publish(data)
        elif flags:
            self._pub.publish(self._encode(data, off, flags, sec, nsec, None))

    EstimatorNode._on_imu = on_imu  # type: ignore[method-assign]
    argv = [a for a in sys.argv if a != "_estimator_part" and not a.startswith("--part=")]
    return estimator_main.main(argv)


def role_record(out: str) -> None:
    """Record (stamp, receive time) of every imu/data message until SIGINT; save .npy."""
    import numpy as np
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Imu

    rclpy.init()
    node = Node("bench_recorder")
    rows: list[tuple[int, int]] = []
    append, unpack = rows.append, _STAMP.unpack_from

    def on_msg(data: bytes) -> None:
        now = time.time_ns()
        sec, nsec = unpack(data, 4)
        append((sec * 1_000_000_000 + nsec, now))

    node.create_subscription(Imu, "imu/data", on_msg, _qos(1000, True), raw=True)
    print("recorder ready", flush=True)
    ex = EventsExecutor()  # the recorder must not be the bottleneck
    ex.add_node(node)
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        while ex.context.ok():
            ex.spin_once(timeout_sec=0.2)
    np.save(out, np.array(rows, dtype=np.int64).reshape(-1, 2))
    rclpy.try_shutdown()


# --------------------------------------------------------------------------- orchestration
def cpu_seconds(pid: int) -> float:
    """CPU time of a process, all its threads: the scheduler's run time of each thread
    (/proc/PID/task/*/schedstat, ns), or utime + stime (/proc/PID/stat, clock ticks) where
    schedstat is missing."""
    total = 0
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(FileNotFoundError):  # a thread that just ended
                total += int((task / "schedstat").read_text().split()[0])
        return total * 1e-9
    except (FileNotFoundError, ValueError):
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK_TCK


def subject_cmd(subject: str, args: argparse.Namespace) -> list[str]:
    params = {
        "qos_overrides./imu/data_raw.subscription.reliability": args.qos,
        "qos_overrides./imu/mag.subscription.reliability": args.qos,
        # 1 s at 1 kHz: a stall of the process (other jobs on the machine) must not overflow
        # the reader's history, which drops the oldest samples even with reliable QoS
        "qos_overrides./imu/data_raw.subscription.depth": str(args.depth),
        "qos_overrides./imu/mag.subscription.depth": str(args.depth),
    }
    if subject == "estimator" and args.estimator_part:
        base = [sys.executable, str(HERE), "_estimator_part", f"--part={args.estimator_part}",
                f"--executor={args.executor}"]
        params.update({"use_mag": "true", "algorithm": args.algorithm})
    elif subject == "estimator" and args.estimator_cmd:
        base = shlex.split(args.estimator_cmd)
        params.update({"use_mag": "true", "algorithm": args.algorithm})
    elif subject == "estimator":
        exe = Path(sys.executable).parent / "estimator"
        base = ([str(exe)] if exe.is_file()
                else [sys.executable, "-m", "mkf_ros.ros.estimator_main"])
        base.append(f"--executor={args.executor}")
        params.update({"use_mag": "true", "algorithm": args.algorithm})
    elif args.standin_cmd:
        base = shlex.split(args.standin_cmd)
        params.update({"use_mag": "true", "algorithm": args.algorithm})
    else:
        base = [sys.executable, str(HERE), "_standin"]
    return base + ["--ros-args"] + [x for k, v in params.items() for x in ("-p", f"{k}:={v}")]


#: ``--pin``: the subject on the second CPU this process may use, its publisher and recorder
#: on the first (Popen arguments; set in the child before it starts, so every thread it
#: creates inherits it)
_CPUS = sorted(os.sched_getaffinity(0))[:2]
_pinned: dict[int, dict[str, Any]] = {
    i: {"preexec_fn": lambda cpu=cpu: os.sched_setaffinity(0, {cpu})}
    for i, cpu in enumerate(_CPUS)} if len(_CPUS) == 2 else {}


class Rig:
    """One subject with its publisher and recorder, in a ROS domain of its own."""

    def __init__(self, subject: str, domain: int, args: argparse.Namespace, tmp: Path) -> None:
        self.subject, self.domain = subject, domain
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
        self.log = tmp / f"{subject}.log"
        self.rec_file = tmp / f"{subject}-rec.npy"
        pin = _pinned if args.pin else {}
        self.proc = subprocess.Popen(subject_cmd(subject, args), env=env, **pin.get(1, {}),
                                     stdout=open(self.log, "w"),  # noqa: SIM115
                                     stderr=subprocess.STDOUT)
        self.recorder = subprocess.Popen(
            [sys.executable, str(HERE), "_record", "--out", str(self.rec_file)], env=env,
            **pin.get(0, {}),
            stdout=subprocess.PIPE, text=True)
        self.env = env
        self.pin = pin
        self.pub: subprocess.Popen[str] | None = None
        self.phases: list[dict[str, Any]] = []

    def wait_ready(self) -> None:
        assert self.recorder.stdout is not None
        self.recorder.stdout.readline()
        end = time.monotonic() + 300
        while "listening on" not in self.log.read_text():
            if self.proc.poll() is not None or time.monotonic() > end:
                raise RuntimeError(f"{self.subject} did not start:\n{self.log.read_text()}")
            time.sleep(0.2)
        self.pub = subprocess.Popen([sys.executable, str(HERE), "_publish"], env=self.env,
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                    **self.pin.get(0, {}))
        assert self._line() == "ready"

    def _line(self) -> str:
        assert self.pub is not None and self.pub.stdout is not None
        line = self.pub.stdout.readline()
        if not line:
            raise RuntimeError(f"the publisher of {self.subject} ended")
        return line.strip()

    def _send(self, text: str) -> None:
        assert self.pub is not None and self.pub.stdin is not None
        stdin: IO[str] = self.pub.stdin
        stdin.write(text + "\n")
        stdin.flush()

    def start(self, rate: float, seconds: float, mag_rate: float) -> None:
        """Start publishing at ``rate`` for ``seconds``; the CPU window opens."""
        self._send(f"run {rate} {seconds} {mag_rate}")
        assert self._line() == "start"
        self._rate = rate
        self._cpu0, self._w0 = cpu_seconds(self.proc.pid), time.monotonic()

    def finish(self, keep: bool = True) -> None:
        """Wait for the end of the phase; record the subject's CPU over the window."""
        line = self._line()
        cpu1, w1 = cpu_seconds(self.proc.pid), time.monotonic()
        assert line.startswith("end "), line
        info = json.loads(line[4:])
        info.update(rate=self._rate, cpu=(cpu1 - self._cpu0) / (w1 - self._w0) * 100.0)
        if keep:
            self.phases.append(info)

    def phase(self, rate: float, seconds: float, mag_rate: float, keep: bool = True) -> None:
        self.start(rate, seconds, mag_rate)
        self.finish(keep)

    def close(self) -> Any:
        import numpy as np

        with contextlib.suppress(Exception):
            self._send("quit")
        if self.pub is not None:
            self.pub.wait(timeout=60)
        self.recorder.send_signal(signal.SIGINT)
        self.recorder.wait(timeout=60)
        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(timeout=60)
        return np.load(self.rec_file) if self.rec_file.exists() else np.zeros((0, 2), int)


def summarise(phases: list[dict[str, Any]], rows: Any, rate: float) -> dict[str, Any]:
    """Loss, latency and CPU of a subject's phases at ``rate``. A stamp received twice (another
    node in the subject's domain answering our messages) is counted in ``foreign`` and only
    its first arrival kept."""
    import numpy as np

    sel_ph = [p for p in phases if p["rate"] == rate]
    lat, lost, sent, foreign = [], 0, 0, 0
    for p in sel_ph:
        sel = rows[(rows[:, 0] >= p["start_ns"]) & (rows[:, 0] <= p["end_ns"])]
        _, first = np.unique(sel[:, 0], return_index=True)
        foreign += len(sel) - len(first)
        sel = sel[first]
        lost += p["n_imu"] - len(sel)
        sent += p["n_imu"]
        lat.append((sel[:, 1] - sel[:, 0]) / 1e6)
    lat_all = np.concatenate(lat) if lat else np.zeros(0)
    cpus = [p["cpu"] for p in sel_ph]
    return dict(sent=sent, lost=lost, cpus=cpus, cpu=float(np.mean(cpus)), foreign=foreign,
                achieved=min(p["achieved"] for p in sel_ph),
                med=float(np.median(lat_all)) if lat_all.size else float("nan"),
                p99=float(np.percentile(lat_all, 99)) if lat_all.size else float("nan"))


def quiet_domains(n: int) -> list[int]:
    """``n`` ROS domains (1–101) in which no other node is seen for a second: another run on
    this machine in the same domain would feed the subjects its messages, and answer ours."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    out: list[int] = []
    for domain in random.sample(range(1, 102), 101):
        ctx = Context()
        rclpy.init(context=ctx, domain_id=domain)
        try:
            probe = Node("bench_domain_probe", context=ctx)
            time.sleep(1.0)
            busy = [name for name, _ in probe.get_node_names_and_namespaces()
                    if name != "bench_domain_probe"]
            probe.destroy_node()
        finally:
            rclpy.try_shutdown(context=ctx)
        if not busy:
            out.append(domain)
            if len(out) == n:
                return out
    raise RuntimeError("no quiet ROS domain on this machine")


def check_standin_qos() -> None:
    """The stand-in's QoS is the estimator's (the stand-in does not import mkf_ros)."""
    from mkf_ros.ros.qos import input_qos, output_qos

    for ours, theirs in ((input_qos(), _qos(**STANDIN_INPUT_QOS)),
                         (output_qos(), _qos(**STANDIN_OUTPUT_QOS))):
        assert ours == theirs, f"stand-in QoS {theirs} differs from the estimator's {ours}"


def print_table(args: argparse.Namespace, results: dict[str, dict[float, dict[str, Any]]],
                per_rep: dict[float, list[float]]) -> None:
    print()
    print("| IMU rate (Hz) | subject | achieved (Hz) | IMU sent | lost | latency median (ms) "
          "| latency p99 (ms) | CPU per run (% of one core) | CPU mean |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rate in args.rates:
        for subject in args.subjects:
            r = results[subject][rate]
            runs = ", ".join(f"{c:.1f}" for c in r["cpus"])
            print(f"| {rate:.0f} | {subject} | {r['achieved']:.0f} | {r['sent']} | {r['lost']} "
                  f"| {r['med']:.2f} | {r['p99']:.2f} | {runs} | {r['cpu']:.1f} |")
            if r["foreign"]:
                print(f"(! {r['foreign']} messages of {subject} received twice: another node "
                      "in its domain; its CPU figures are not clean)")
    if len(args.subjects) == 2:
        print()
        print("| IMU rate (Hz) | estimator / stand-in CPU: mean of the runs' ratios | range "
              "| ratio of the mean CPUs |")
        print("|---|---|---|---|")
        for rate in args.rates:
            rs = per_rep[rate]
            whole = results["estimator"][rate]["cpu"] / results["stand-in"][rate]["cpu"]
            print(f"| {rate:.0f} | **{sum(rs) / len(rs):.2f}** | {min(rs):.2f} – {max(rs):.2f} "
                  f"| {whole:.2f} |")
    for subject in args.subjects:
        ok = [r for r in args.rates if results[subject][r]["lost"] == 0
              and results[subject][r]["achieved"] >= 0.98 * r and results[subject][r]["p99"] < 20]
        print(f"{subject}: highest rate sustained (0 lost, p99 < 20 ms): "
              + (f"{max(ok):.0f} Hz" if ok else "none"))


def run(args: argparse.Namespace) -> int:
    if args.nice:
        os.nice(args.nice)  # inherited by every child process
    check_standin_qos()
    tmp = Path(tempfile.mkdtemp(prefix="mkf_ros-bench-"))
    domains = quiet_domains(len(args.subjects))
    print(f"ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, domains {domains}; {os.cpu_count()} "
          f"cores, load average {os.getloadavg()[0]:.1f}, nice {args.nice}; estimator: "
          f"{args.algorithm}, use_mag, {args.executor} executor; input QoS {args.qos} depth "
          f"{args.depth}; {args.reps} x {args.seconds:g} s per rate and subject, interleaved"
          + (f"; the estimator's callback cut after '{args.estimator_part}'"
             if args.estimator_part else ""), flush=True)
    rigs = {s: Rig(s, d, args, tmp) for s, d in zip(args.subjects, domains, strict=True)}
    rows = {}
    try:
        for rig in rigs.values():
            rig.wait_ready()
            rig.phase(100, 1.0, args.mag_rate, keep=False)  # discovery, first-call costs
        for rep in range(args.reps):
            for rate in args.rates:
                order = list(rigs.values())
                if rep % 2:
                    order.reverse()
                if args.concurrent:  # the same machine state for both, at the same time
                    for rig in order:
                        rig.start(rate, args.seconds, args.mag_rate)
                    for rig in order:
                        rig.finish()
                    continue
                for rig in order:
                    rig.phase(rate, args.seconds, args.mag_rate)
            print(f"  repetition {rep + 1} done", flush=True)
    finally:
        for s, rig in rigs.items():
            rows[s] = rig.close()
    results = {s: {rate: summarise(rigs[s].phases, rows[s], rate) for rate in args.rates}
               for s in args.subjects}
    per_rep = {}
    if len(args.subjects) == 2:
        est, sti = (rigs[s].phases for s in SUBJECTS)
        per_rep = {rate: [e["cpu"] / s["cpu"] for e, s in zip(
            [p for p in est if p["rate"] == rate], [p for p in sti if p["rate"] == rate],
            strict=True)] for rate in args.rates}
    print_table(args, results, per_rep)
    print(f"\n(logs: {tmp})")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[1000, 4000])
    ap.add_argument("--seconds", type=float, default=5.0, help="per phase")
    ap.add_argument("--reps", type=int, default=3, help="repetitions of every phase")
    ap.add_argument("--mag-rate", type=float, default=100.0)
    ap.add_argument("--subjects", nargs="+", choices=SUBJECTS, default=list(SUBJECTS))
    ap.add_argument("--algorithm", choices=("mekf", "mukf"), default="mekf")
    ap.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                    help="input QoS of the subjects (the node's default: best_effort)")
    ap.add_argument("--depth", type=int, default=1000, help="input queue depth")
    ap.add_argument("--nice", type=int, default=0,
                    help="niceness of every process (negative needs root)")
    ap.add_argument("--executor", choices=("events", "single"), default="events")
    ap.add_argument("--callback", action="store_true",
                    help="instead: the CPU per message of the estimator's callback and its "
                    "parts, in one process with warm caches (no DDS)")
    ap.add_argument("--concurrent", action="store_true",
                    help="run the two subjects' phases at the same time (each in its own "
                    "domain) instead of one after the other: both see the same machine load")
    ap.add_argument("--pin", action=argparse.BooleanOptionalAction,
                    default=len(os.sched_getaffinity(0)) >= 2,
                    help="pin each subject to CPU 1 and its publisher and recorder to CPU 0 "
                    "(default with 2 CPUs or more: without it, which core each process lands "
                    "on moves a subject's CPU per message by a factor of two)")
    ap.add_argument("--estimator-cmd", help="run this command as the estimator instead of the "
                    "installed one (e.g. another checkout's .venv/bin/estimator); the ROS "
                    "arguments are appended")
    ap.add_argument("--estimator-part", choices=PARTS, help="run the estimator with its IMU "
                    "callback cut after this step (republish: the input bytes; parse, filter, "
                    "encode: each step of its own added): what each step costs in a running node")
    ap.add_argument("--part", choices=PARTS, help=argparse.SUPPRESS)
    ap.add_argument("--standin-cmd", help="run this command as the stand-in (an A/B comparison "
                    "of two estimators: the ratio is estimator / this); ROS arguments appended")
    ap.add_argument("_role", nargs="?", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args, _ = ap.parse_known_args()
    if args._role == "_publish":
        role_publish()
        return 0
    if args._role == "_record":
        role_record(args.out)
        return 0
    if args._role == "_standin":
        role_standin()
        return 0
    if args._role == "_estimator_part":
        return role_estimator_part(args.part)
    if args.callback:
        os.environ.setdefault("ROS_DOMAIN_ID", str(quiet_domains(1)[0]))
        role_callback(args.seconds)
        return 0
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
