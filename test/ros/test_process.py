"""The installed ``estimator`` console script as a separate process, driven by a separate
client process (what ``ros2 run``, ``ros2 topic pub`` and ``ros2 param set`` do)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from proc_session import SESSION_ROS_ARGS, check_session, run_node_and_client

pytestmark = pytest.mark.ros


def console_script(name: str) -> Path:
    exe = Path(sys.executable).parent / name
    assert exe.is_file(), f"{exe} not installed (pip install -e .)"
    return exe


@pytest.mark.parametrize("executor", ["events", "single"])
def test_console_script_with_client_process(tmp_path, executor: str) -> None:
    exe = console_script("estimator")
    env = dict(os.environ, RCUTILS_CONSOLE_OUTPUT_FORMAT="[{severity}] [{name}]: {message}")
    cmd = [str(exe), f"--executor={executor}", "--ros-args", *SESSION_ROS_ARGS]
    res, err, rc = run_node_and_client(cmd, env, "/estimator", cwd=tmp_path)
    check_session(res, err, rc)
    assert f"spinning with the {executor} executor" in err


def test_console_script_bad_arguments(tmp_path) -> None:
    exe = console_script("estimator")
    for args, msg in ((["--executor=multi"], "executor must be one of events, single"),
                      (["--use-mag"], "unknown argument '--use-mag'")):
        p = subprocess.run([str(exe), *args], env=dict(os.environ), cwd=tmp_path,
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and msg in p.stderr, p.stderr
    h = subprocess.run([str(exe), "--help"], env=dict(os.environ), cwd=tmp_path,
                       capture_output=True, text=True, timeout=60)
    assert h.returncode == 0 and "imu/data_raw" in h.stdout and "~/reset" in h.stdout


def test_console_script_bad_parameter_is_one_line(tmp_path) -> None:
    exe = console_script("estimator")
    p = subprocess.run([str(exe), "--ros-args", "-p", "world_frame:=ecef"],
                       env=dict(os.environ), cwd=tmp_path, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1] == (
        "estimator: invalid parameter: world_frame must be one of enu, ned, nwu, got 'ecef'")
    assert "Traceback" not in p.stderr


def test_console_script_sigterm(tmp_path) -> None:
    exe = console_script("estimator")
    node = subprocess.Popen([str(exe)], env=dict(os.environ), cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # wait until it is up (it logs where it listens), then stop it like systemd would
        line = ""
        while "listening on" not in line:
            line = node.stderr.readline()
            assert line, "estimator exited before it was up"
        node.send_signal(signal.SIGTERM)
        _, err = node.communicate(timeout=30)
    finally:
        if node.poll() is None:
            node.kill()
    assert node.returncode == 0, err
    assert "Traceback" not in err
