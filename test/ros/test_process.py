"""The installed ``estimator`` console script as a separate process, driven by a separate
client process (what ``ros2 run``, ``ros2 topic pub`` and ``ros2 param set`` do)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest

pytestmark = pytest.mark.ros
HERE = Path(__file__).resolve().parent
CLIENT = HERE / "proc_client.py"


def console_script(name: str) -> Path:
    exe = Path(sys.executable).parent / name
    if not exe.is_file():
        pytest.skip(f"{exe} not installed (pip install -e .)")
    return exe


def run_node_and_client(cmd: Sequence[str], env: dict[str, str], node_fqn: str,
                        cwd: Path | None = None) -> tuple[dict, str, int]:
    """Start the node, run the client against it, stop the node with SIGINT."""
    node = subprocess.Popen(list(cmd), env=env, cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        client = subprocess.run([sys.executable, str(CLIENT), node_fqn, "--seconds", "1.0"],
                                env=env, cwd=cwd, capture_output=True, text=True, timeout=240)
    finally:
        node.send_signal(signal.SIGINT)
        try:
            _, err = node.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            node.kill()
            _, err = node.communicate()
    lines = [ln for ln in client.stdout.splitlines() if ln.startswith("{")]
    assert lines, f"client printed no result:\n{client.stdout}\n{client.stderr}\nnode:\n{err}"
    return json.loads(lines[-1]), err, node.returncode


def check_session(res: dict, err: str, rc: int) -> None:
    assert res["ok"], f"{res}\nnode stderr:\n{err}"
    assert res["set_algorithm"] == [True, ""]
    ok, reason = res["set_bad_chart"]
    assert not ok and "chart must be one of o, rp, mrp, rv, got 'xyz'" in reason
    assert res["get"] == ["mukf", True]
    assert res["reset"][0] is True
    # every IMU message gives an output, except the one(s) right after the reset until the
    # filter is re-aligned (the first one re-aligns): nothing lost
    assert res["received"] == res["sent"], res
    assert res["finite"] and res["frame_id"] == "imu_link"
    assert "listening on /imu/data_raw and /imu/mag" in err
    assert "parameters changed: algorithm='mukf'" in err
    assert rc == 0, f"estimator exit code {rc} after SIGINT:\n{err}"
    assert "Traceback" not in err


@pytest.mark.parametrize("executor", ["events", "single"])
def test_console_script_with_client_process(tmp_path, executor: str) -> None:
    exe = console_script("estimator")
    env = dict(os.environ, RCUTILS_CONSOLE_OUTPUT_FORMAT="[{severity}] [{name}]: {message}")
    cmd = [str(exe), f"--executor={executor}", "--ros-args", "-p", "use_mag:=true",
           "-p", "qos_overrides./imu/data_raw.subscription.reliability:=reliable",
           "-p", "qos_overrides./imu/mag.subscription.reliability:=reliable"]
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
