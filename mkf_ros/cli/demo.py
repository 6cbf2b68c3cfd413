"""``mkf demo``: the estimator node at work, end to end, in well under a minute.

Two ROS 2 nodes in their own processes, talking over DDS exactly as on a robot: ``player``
synthesises an IMU + magnetometer stream with ground truth (``imu/data_raw``, ``imu/mag``,
``imu/ground_truth``) and ``estimator`` turns it into ``imu/data``. This process listens to
both, prints the accuracy live and at the end, and leaves a plot.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

HELP = "live demo: player and estimator nodes over DDS, accuracy against ground truth, a plot"
#: seconds allowed for the nodes to start (imports, DDS discovery)
STARTUP_TIMEOUT = 25.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mkf_ros.cli.options import add_filter_options

    parser.add_argument("--scenario", default="sweep",
                        help="motion (mkf synth --list; default sweep: full turns about every "
                        "axis and through both gimbal-lock attitudes)")
    parser.add_argument("--duration", type=float, default=30.0, metavar="S",
                        help="seconds of data (default 30)")
    parser.add_argument("--rate", type=float, default=200.0, metavar="HZ",
                        help="IMU rate (default 200)")
    parser.add_argument("--mag-rate", type=float, default=50.0, metavar="HZ",
                        help="magnetometer rate (default 50)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plot", default="mkf_demo.png", metavar="PNG",
                        help="plot file (default ./mkf_demo.png)")
    parser.add_argument("--quiet-nodes", action="store_true", help="hide the nodes' log lines")
    add_filter_options(parser)


# ------------------------------------------------------------------ helpers


def _ros_value(v: Any) -> str:
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_ros_value(x) for x in v) + "]"
    return str(v)


def _exe(name: str, module: str) -> list[str]:
    """The console script next to this Python (what ``ros2 run`` would start), else -m."""
    beside = Path(sys.executable).parent / name
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside)]
    found = shutil.which(name)
    return [found] if found else [sys.executable, "-m", module]


class _Child:
    """A node process whose log lines are relayed (prefixed) and kept."""

    def __init__(self, name: str, cmd: list[str], env: dict[str, str], show: bool) -> None:
        self.name = name
        self.lines: list[str] = []
        self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1)
        self._t = threading.Thread(target=self._relay, args=(show,), daemon=True)
        self._t.start()

    def _relay(self, show: bool) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip()
            self.lines.append(line)
            if show and line:
                print(f"  {self.name:>9} │ {line}", flush=True)

    def stop(self, timeout: float = 5.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        self._t.join(timeout)


def _stamp(m: Any) -> int:
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec


# ------------------------------------------------------------------ the demo


def run(args: argparse.Namespace) -> int:
    from mkf_ros.cli.main import CliError
    from mkf_ros.cli.options import filter_overrides
    from mkf_ros.sim import SCENARIOS

    if args.scenario not in SCENARIOS:
        raise CliError(f"unknown scenario {args.scenario!r}; known: {', '.join(SCENARIOS)}")
    if not (0 < args.duration <= 600 and args.rate > 0 and args.mag_rate > 0):
        raise CliError("--duration must be in (0, 600] s and the rates positive")
    params: dict[str, Any] = {"use_mag": True} | filter_overrides(args)
    try:
        from mkf_ros.core.params import FilterParams

        FilterParams(params)
    except ValueError as e:
        raise CliError(str(e)) from None
    # Keep DDS on this machine and on a domain of our own (every run, every process).
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(random.randint(1, 101))
    if not os.environ.get("ROS_LOG_DIR"):
        os.environ["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix="mkf_demo-roslog-")
    try:
        import rclpy  # noqa: F401
    except ImportError:
        raise CliError("rclpy is not importable: run the demo in the dev environment "
                       "(./run demo) or source a ROS 2 Jazzy install") from None
    return _Demo(args, params).run()


class _Demo:
    def __init__(self, args: argparse.Namespace, params: dict[str, Any]) -> None:
        self.a = args
        self.params = params
        self.truth: dict[int, tuple[float, np.ndarray]] = {}  # stamp → (t recv, q wxyz)
        self.est: list[tuple[int, float, np.ndarray]] = []  # (stamp, t recv, q wxyz)
        self.n_truth = 0
        self.diag: dict[str, str] = {}  #: the estimator's latest /diagnostics values

    def say(self, text: str = "") -> None:
        print(text, flush=True)

    def run(self) -> int:
        a = self.a
        self.say("mkf_ros demo: attitude estimation with the Manifold Kalman Filter, live over "
                 "ROS 2\n")
        self.say(f"  1. player    synthesises '{a.scenario}' for {a.duration:g} s: IMU at "
                 f"{a.rate:g} Hz, magnetometer at {a.mag_rate:g} Hz, and the true orientation")
        p = self.params
        self.say(f"  2. estimator fuses them ({p.get('algorithm', 'mekf').upper()}, chart "
                 f"{p.get('chart', 'rp').upper()}) into imu/data")
        self.say("  3. this process compares imu/data with imu/ground_truth\n")
        self._warm()
        env = dict(os.environ, RCUTILS_COLORIZED_OUTPUT="0", PYTHONUNBUFFERED="1",
                   RCUTILS_CONSOLE_OUTPUT_FORMAT="[{severity}] [{name}]: {message}")
        est_cmd = [*_exe("estimator", "mkf_ros.ros.estimator_main"), "--ros-args"]
        for k, v in self.params.items():
            est_cmd += ["-p", f"{k}:={_ros_value(v)}"]
        ply_cmd = [
            *_exe("player", "mkf_ros.ros.player_node"), "--ros-args",
            "-p", f"scenario:={a.scenario}", "-p", f"duration:={a.duration!r}",
            "-p", f"imu_rate:={a.rate!r}", "-p", f"mag_rate:={a.mag_rate!r}",
            "-p", f"seed:={a.seed}", "-p", "wait_for_subscribers:=1",
            "-p", "wait_topics:=[imu/data_raw, imu/mag, imu/ground_truth]",
            "-p", "start_delay:=1.0"]
        self.say("  the same by hand, in two terminals (on a ROS install: ros2 run mkf_ros "
                 "estimator|player ...):")
        self.say("    " + shlex.join([Path(est_cmd[0]).name, *est_cmd[1:]]))
        self.say("    " + shlex.join([Path(ply_cmd[0]).name, *ply_cmd[1:]]) + "\n")
        return self._run_nodes(est_cmd, ply_cmd, env)

    def _warm(self) -> None:
        from mkf_ros.core.params import BY_NAME
        from mkf_ros.kernels import FIRST_COMPILE_TIME, INSTALLED_PARTS, warmup

        t0 = time.monotonic()
        self.say("  loading the filter kernels (compiled at install time; where that step did "
                 f"not run, the first run compiles them, {FIRST_COMPILE_TIME})...")
        warmup(INSTALLED_PARTS,
               algorithms=(self.params.get("algorithm", BY_NAME["algorithm"].default),))
        dt = time.monotonic() - t0
        self.say(f"  kernels ready in {dt:.1f} s{' (compiled and cached)' if dt > 5 else ''}\n")

    def _run_nodes(self, est_cmd: list[str], ply_cmd: list[str], env: dict[str, str]) -> int:
        import rclpy
        from geometry_msgs.msg import QuaternionStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Imu

        ctx = Context()
        rclpy.init(context=ctx, signal_handler_options=rclpy.SignalHandlerOptions.NO)
        node = Node("mkf_demo_monitor", context=ctx)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        node.create_subscription(QuaternionStamped, "imu/ground_truth", self._on_truth, qos)
        sub = node.create_subscription(Imu, "imu/data", self._on_est, qos)
        from diagnostic_msgs.msg import DiagnosticArray

        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        show = not self.a.quiet_nodes
        t_start = time.monotonic()
        # the estimator first; the player once this monitor has matched the estimator's output
        # (otherwise the first estimates can pass before discovery completes and go unseen); the
        # player then waits until the estimator and this monitor subscribe to its topics
        est = _Child("estimator", est_cmd, env, show)
        ply: _Child | None = None
        try:
            while sub.get_publisher_count() == 0:
                ex.spin_once(timeout_sec=0.05)
                if est.proc.poll() is not None:
                    return self._failed(est, "the estimator exited during start-up")
                if time.monotonic() - t_start > STARTUP_TIMEOUT:
                    return self._failed(est, "the estimator did not come up")
            ply = _Child("player", ply_cmd, env, show)
            code = self._monitor(ex, est, ply, t_start)
        except KeyboardInterrupt:
            self.say("\n  interrupted")
            code = 130
        finally:
            for c in (ply, est):
                if c is not None:
                    c.stop()
            ex.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
        if code == 0:
            code = self._final(time.monotonic() - t_start)
        return code

    def _on_truth(self, m: Any) -> None:
        q = m.quaternion
        self.truth[_stamp(m)] = (time.monotonic(), np.array([q.w, q.x, q.y, q.z]))
        self.n_truth += 1

    def _on_diag(self, m: Any) -> None:
        for st in m.status:
            if "estimator" in st.name:
                self.diag = {kv.key: kv.value for kv in st.values}

    def _on_est(self, m: Any) -> None:
        q = m.orientation
        self.est.append((_stamp(m), time.monotonic(), np.array([q.w, q.x, q.y, q.z])))

    def _pairs(self, since: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(stamps, q_est, q_true, latency s) of the estimates from index ``since`` on."""
        rows = [(s, t, q, self.truth[s]) for s, t, q in self.est[since:] if s in self.truth]
        if not rows:
            z = np.zeros((0, 4))
            return np.zeros(0, np.int64), z, z, np.zeros(0)
        return (np.array([r[0] for r in rows]), np.array([r[2] for r in rows]),
                np.array([r[3][1] for r in rows]), np.array([r[1] - r[3][0] for r in rows]))

    def _monitor(self, ex: Any, est: _Child, ply: _Child, t_start: float) -> int:
        from mkf_ros.evaluation.metrics import orientation_errors
        from mkf_ros.evaluation.plots import euler_deg

        a = self.a
        limit = t_start + STARTUP_TIMEOUT + a.duration * 1.5 + 10.0
        self.say(f"\n  {'time':>6}  {'estimates':>9}   {'true roll':>9} {'pitch':>6} "
                 f"{'yaw':>7}    error over the last second: total / heading / inclination")
        next_line, done_at = time.monotonic() + 1.0, None
        seen = 0
        while True:
            ex.spin_once(timeout_sec=0.05)
            now = time.monotonic()
            if est.proc.poll() is not None:
                return self._failed(est, "the estimator stopped")
            if ply.proc.poll() is not None and done_at is None:
                if ply.proc.returncode != 0:
                    return self._failed(ply, "the player failed")
                done_at = now
            if now >= next_line and self.est:
                stamps, qe, qt, _ = self._pairs(seen)
                seen = len(self.est)
                if len(stamps):
                    err = orientation_errors(qe, qt)
                    r = {k: math.degrees(math.sqrt(float(np.mean(v ** 2))))
                         for k, v in err.items()}
                    rpy = euler_deg(qt[-1])
                    t = (stamps[-1] - min(self.truth)) * 1e-9
                    self.say(f"  {t:5.1f}s  {len(self.est):>9,}   {rpy[0]:8.1f}° {rpy[1]:5.1f}°"
                             f" {rpy[2]:6.1f}°    {r['total']:6.2f}° / {r['heading']:5.2f}° / "
                             f"{r['inclination']:5.2f}°")
                next_line = now + 1.0
            if done_at is not None and ((len(self.est) >= self.n_truth and self.diag.get(
                    "published") == str(len(self.est))) or now - done_at > 2.5):
                return 0
            if now > limit:
                return self._failed(ply, "the demo took too long")

    def _failed(self, child: _Child, why: str) -> int:
        self.say(f"\n  demo failed: {why}. Last lines of the {child.name}:")
        for line in child.lines[-15:]:
            self.say(f"    {line}")
        return 1

    def _final(self, wall: float) -> int:
        from mkf_ros.evaluation.metrics import orientation_errors, rmse_deg
        from mkf_ros.evaluation.plots import accuracy_figure
        from mkf_ros.sim import simulate

        a = self.a
        stamps, qe, qt, lat = self._pairs()
        if len(stamps) == 0:
            self.say("\n  no estimates arrived: is DDS working on this machine? "
                     "(try FASTDDS_BUILTIN_TRANSPORTS=UDPv4)")
            return 1
        t = (stamps - min(self.truth)) * 1e-9
        err = orientation_errors(qe, qt)
        rm = {k: rmse_deg(v) for k, v in err.items()}
        mx = {k: float(np.degrees(v.max())) for k, v in err.items()}
        settled = t >= 1.0
        rs = {k: rmse_deg(v[settled]) if settled.any() else math.nan for k, v in err.items()}
        sim = simulate(a.scenario, duration=a.duration, rate=a.rate, seed=a.seed,
                       mag_rate=min(a.mag_rate, a.rate))
        got = self.diag.get("imu_received")
        self.say(f"\n  done in {wall:.1f} s. The player published {self.n_truth:,} IMU messages; "
                 + (f"the estimator received {int(got):,} and " if got else "the estimator ")
                 + f"answered {len(self.est):,} of them "
                 f"(latency median {np.median(lat) * 1e3:.1f} ms, "
                 f"95% {np.percentile(lat, 95) * 1e3:.1f} ms).")
        if got and int(got) < self.n_truth:
            self.say(f"  ({self.n_truth - int(got)} IMU messages were dropped on the way in: the "
                     "estimator subscribes with best-effort sensor-data QoS, which drops rather "
                     "than queues when the machine is busy; see docs/demo.md)")
        self.say("")
        self.say("  accuracy against the ground truth (degrees)     total  heading  inclination")
        self.say(f"    RMSE, whole run                             {rm['total']:7.3f}  "
                 f"{rm['heading']:7.3f}  {rm['inclination']:11.3f}")
        self.say(f"    RMSE, after the first second                {rs['total']:7.3f}  "
                 f"{rs['heading']:7.3f}  {rs['inclination']:11.3f}")
        self.say(f"    largest error                               {mx['total']:7.3f}  "
                 f"{mx['heading']:7.3f}  {mx['inclination']:11.3f}")
        worst = int(np.argmax(err["total"]))
        if t[worst] < 0.1 and mx["total"] > 5.0 and rs["total"] < 0.2 * mx["total"]:
            self.say(f"    (the largest error is at t = {t[worst]:.2f} s: the first estimate "
                     "comes from the first IMU sample, whose magnetometer sample arrived just "
                     "after it; the heading is fixed from the next one on)")
        for kind, ivs in sim.meta.get("intervals", {}).items():
            inside = np.zeros(len(t), dtype=bool)
            for lo, hi in ivs:
                inside |= (t >= lo) & (t <= hi)
            if inside.any():
                self.say(f"    RMSE during {kind:<31} {rmse_deg(err['total'][inside]):7.3f}  "
                         f"{rmse_deg(err['heading'][inside]):7.3f}  "
                         f"{rmse_deg(err['inclination'][inside]):11.3f}")
        p = self.params
        title = (f"mkf demo: {a.scenario}, {p.get('algorithm', 'mekf').upper()}-"
                 f"{p.get('chart', 'rp').upper()}, IMU {a.rate:g} Hz + magnetometer "
                 f"{a.mag_rate:g} Hz, live over DDS")
        try:
            path = accuracy_figure(a.plot, t, qe, qt, err, title=title,
                                   intervals=sim.meta.get("intervals"))
            self.say(f"\n  plot: {Path(path).resolve()}")
        except OSError as e:
            self.say(f"\n  could not write the plot {a.plot}: {e.strerror or e}")
        self.say("\n  next: mkf synth --list; mkf synth accel_bursts --out b; mkf process b "
                 "--out o --use-mag; docs/demo.md")
        return 0


def main(argv: Sequence[str] | None = None) -> int:  # pragma: no cover - for python -m
    from mkf_ros.cli.main import main as mkf

    return mkf(["demo", *(sys.argv[1:] if argv is None else argv)])
