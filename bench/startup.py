"""Start-up benchmark of the ``estimator`` node (the first start must not wait for a compile): how
long after ``estimator`` starts does the first ``imu/data`` message arrive, with a cold and with a
warm kernel cache?

For each run the estimator is started as its own process (the console script of the chosen
Python environment) with ``MKF_ROS_CACHE_DIR`` pointing at an empty directory (cold) or at the
directory a previous cold run filled (warm). This process publishes ``imu/data_raw`` at 100 Hz
from the moment the estimator is started and records when the first ``imu/data`` arrives. The
time the node reports for loading or compiling its kernels ("filter kernels ready in X s") is
read from its log.

    ./run bench startup                           # 3 cold + 3 warm runs, this checkout's .venv
    ./run bench startup --installed               # the same from a wheel of this checkout,
                                                  # installed into a throw-away venv (the
                                                  # `pip install` / `colcon build` path)
    ./run bench startup --installed --no-precompile --runs 1 --cache cold
                                                  # a wheel built without the install-time
                                                  # compile: the node compiles on first start
    .venv/bin/python bench/startup.py --runs 1 --cache cold

``--installed`` builds the wheel (that runs the install-time kernel compile, which it times),
installs it with ``--no-deps`` into a temporary venv that sees this checkout's ``.venv`` packages,
and runs the estimator from there, so the package's own precompiled kernels are what a cold
user cache falls back on.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

# every process that may start rclpy: discovery on this host only, a domain of its own
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 101)))
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="mkf_ros-bench-log-"))

ROOT = Path(__file__).resolve().parents[1]
READY = re.compile(r"filter kernels ready in ([0-9.]+) s")


def first_output(estimator: list[str], cache: Path, timeout: float) -> tuple[float, float, str]:
    """Start ``estimator`` with kernel cache ``cache``; publish IMU samples until its first
    ``imu/data``. Returns (seconds to first output, reported kernel time, the node's log)."""
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu

    env = dict(os.environ, MKF_ROS_CACHE_DIR=str(cache))
    log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 (read back after the process ends)
    got: list[float] = []
    rclpy.init()
    node = Node("startup_bench")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Imu, "imu/data_raw", qos)
    node.create_subscription(Imu, "imu/data", lambda _m: got.append(time.monotonic()), qos)
    msg = Imu()
    msg.header.frame_id = "imu_link"
    msg.linear_acceleration.z = 9.81
    t0 = time.monotonic()
    # started outside the checkout, so that `-m` cannot import the source tree by accident
    proc = subprocess.Popen(estimator, env=env, stdout=log, stderr=subprocess.STDOUT,
                            cwd=cache.parent)
    try:
        k = 0
        while not got:
            if proc.poll() is not None:
                log.seek(0)
                raise SystemExit(f"startup: the estimator exited ({proc.returncode}):\n"
                                 f"{log.read()}")
            if time.monotonic() - t0 > timeout:
                raise SystemExit(f"startup: no imu/data within {timeout:.0f} s")
            now = time.time()
            msg.header.stamp.sec = int(now)
            msg.header.stamp.nanosec = int((now % 1.0) * 1e9)
            pub.publish(msg)
            k += 1
            rclpy.spin_once(node, timeout_sec=max(0.0, t0 + 0.01 * k - time.monotonic()))
        first = got[0] - t0
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        node.destroy_node()
        rclpy.shutdown()
    log.seek(0)
    text = log.read()
    m = READY.search(text)
    return first, float(m.group(1)) if m else float("nan"), text


def installed_estimator(work: Path, precompile: bool) -> tuple[list[str], float]:
    """Build a wheel of this checkout (timing it: it runs the install-time kernel compile
    unless ``precompile`` is False), install it into a venv layered on the current environment,
    return its estimator command."""
    wheels, src = work / "wheels", work / "src"
    # a clean copy: no build/ left over from an earlier build, no kernels compiled before
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "_kernels", "*.egg-info", "__pycache__", ".*_cache"))
    env = dict(os.environ, MKF_ROS_CACHE_DIR=str(work / "build-cache"))
    if not precompile:
        env["MKF_ROS_NO_PRECOMPILE"] = "1"
    t = time.monotonic()
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(wheels), str(src)], check=True, env=env)
    build = time.monotonic() - t
    venv = work / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    vpy = venv / "bin" / "python"
    code = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = subprocess.run([str(vpy), "-c", code],
                          check=True, capture_output=True, text=True).stdout.strip()
    # the layered venv sees this environment's packages (rclpy, numba, ...) after its own
    Path(site, "_parent_env.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    wheel = next(wheels.glob("mkf_ros-*.whl"))
    # --ignore-installed: otherwise pip, seeing mkf_ros installed in this environment (the
    # checkout's editable install), uninstalls it from here
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--ignore-installed",
                    "-q", "--prefix", str(venv), str(wheel)], check=True)
    where = subprocess.run([str(vpy), "-c", "import mkf_ros; print(mkf_ros.__file__)"],
                           check=True, capture_output=True, text=True, cwd=work).stdout.strip()
    assert Path(where).is_relative_to(venv), f"the layered venv imports mkf_ros from {where}"
    print(f"installed mkf_ros: {Path(where).parent}")
    return [str(vpy), "-m", "mkf_ros.ros.estimator_main"], build


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3, help="runs per cache state (default 3)")
    ap.add_argument("--cache", choices=("cold", "warm", "both"), default="both",
                    help="kernel cache state(s) to measure (default both)")
    ap.add_argument("--installed", action="store_true",
                    help="measure a wheel of this checkout installed into a throw-away venv")
    ap.add_argument("--no-precompile", action="store_true",
                    help="with --installed: build the wheel without the install-time kernel "
                         "compile (MKF_ROS_NO_PRECOMPILE=1), so a cold start compiles")
    ap.add_argument("--timeout", type=float, default=600.0,
                    help="give up on a run after this many seconds (default 600)")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error(f"--runs must be at least 1, got {args.runs}")

    work = Path(tempfile.mkdtemp(prefix="mkf_ros-startup-"))
    try:
        build = None
        if args.installed:
            cmd, build = installed_estimator(work, not args.no_precompile)
        else:
            exe = Path(sys.executable).parent / "estimator"
            cmd = ([str(exe)] if exe.is_file()
                   else [sys.executable, "-m", "mkf_ros.ros.estimator_main"])
        print(f"estimator: {' '.join(cmd)}  (ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, "
              f"LOCALHOST discovery; {os.cpu_count()} cores)")
        if build is not None:
            print(f"wheel build incl. install-time kernel compile: {build:.1f} s")
        print("\n| run | kernel cache | first imu/data after start (s) "
              "| kernels ready, node log (s) |")
        print("|---|---|---|---|")
        states = ["cold", "warm"] if args.cache == "both" else [args.cache]
        warm_dir = None
        for state in states:
            for r in range(args.runs):
                if state == "cold":
                    cache = Path(tempfile.mkdtemp(prefix="cold-", dir=work))
                else:
                    if warm_dir is None:  # fill a cache once, untimed
                        warm_dir = Path(tempfile.mkdtemp(prefix="warm-", dir=work))
                        first_output(cmd, warm_dir, args.timeout)
                    cache = warm_dir
                first, ready, _ = first_output(cmd, cache, args.timeout)
                if state == "cold" and warm_dir is None:
                    warm_dir = cache
                print(f"| {r + 1} | {state} | {first:.2f} | {ready:.2f} |", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
