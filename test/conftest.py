"""Test-wide setup shared by every test under test/.

Runs at import time, i.e. before any test module can import rclpy and before the first
``rclpy.init``; child processes started by tests inherit these variables.
"""

from __future__ import annotations

import os
import random
import tempfile
from collections.abc import Iterator
from typing import Any

import pytest

# Keep DDS discovery on this host (Fast DDS multicasts on every interface otherwise) and
# on a domain of its own, so parallel runs on one machine do not see each other.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 101)))
# pytest-xdist workers (`./run test` runs two) inherit one domain: each takes its own next to
# it (1..101 cyclically), so that one worker's nodes never receive the other's test topics.
# Once per worker: a child process that runs this file again inherits the moved domain and
# the marker, and keeps both.
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
if (_worker.startswith("gw") and _worker[2:].isdigit()
        and os.environ.get("MKF_TEST_DOMAIN_WORKER") != _worker):
    _domain = (int(os.environ["ROS_DOMAIN_ID"]) - 1 + int(_worker[2:])) % 101 + 1
    os.environ["ROS_DOMAIN_ID"] = str(_domain)
    os.environ["MKF_TEST_DOMAIN_WORKER"] = _worker
# rclpy.init raises "failed to initialize logging" if ~/.ros/log cannot be created.
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="mkf_ros-roslog-"))


@pytest.fixture
def ros_context() -> Iterator[Any]:
    """A fresh, initialised ``rclpy.context.Context``, shut down after the test.

    Pass it on explicitly: ``Node(..., context=ctx)``, ``SingleThreadedExecutor(context=ctx)``.
    rclpy is a hard dependency (requirements/ros-jazzy.txt): a broken install fails.
    """
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


@pytest.fixture(scope="session")
def dask_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A real Dask cluster on this machine: ``dask scheduler`` and two ``dask worker``
    processes (one thread each), every port on 127.0.0.1; killed at the end of the session.

    The kernels are compiled (or loaded) here first, so the workers find them in the cache.
    """
    import mkf_ros
    from mkf_ros.parallel import local_cluster
    from mkf_ros.study.runner import warm_up

    mkf_ros.warmup()
    warm_up()
    with local_cluster(2, tmp_path_factory.mktemp("dask")) as cluster:
        yield cluster
