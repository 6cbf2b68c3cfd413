"""A ROS node executable and a client driving it, each its own process: what ``ros2 run`` and,
from another terminal, ``ros2 topic pub`` / ``ros2 param set`` / ``ros2 service call`` do.

Shared by test/ros/test_process.py (the editable install's ``estimator``) and
test/test_packaging.py (the colcon install's): one way to run the session, one check of it.
The client is test/ros/proc_client.py; it prints its findings as one JSON line.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

CLIENT = Path(__file__).resolve().parent / "ros" / "proc_client.py"
#: the estimator's ``--ros-args`` of a session: the magnetometer fused, the input reliable
#: (so that nothing may be lost); :func:`check_session` expects them
SESSION_ROS_ARGS = ("-p", "use_mag:=true",
                    "-p", "qos_overrides./imu/data_raw.subscription.reliability:=reliable",
                    "-p", "qos_overrides./imu/mag.subscription.reliability:=reliable")


def run_node_and_client(cmd: Sequence[str], env: dict[str, str], node_fqn: str,
                        cwd: Path | None = None, client_args: Sequence[str] = ()
                        ) -> tuple[dict, str, int]:
    """Start the node, run the client against it, stop the node with SIGINT: the client's
    result, the node's stderr and its exit code."""
    node = subprocess.Popen(list(cmd), env=env, cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        client = subprocess.run([sys.executable, str(CLIENT), node_fqn, "--seconds", "1.0",
                                 *client_args],
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
    """What the client's session with an estimator started with :data:`SESSION_ROS_ARGS`
    must show: parameters set, refused and read back, a reset, an answer to
    every IMU message, finite and in the input's frame; logged, and a clean exit on SIGINT."""
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
