"""The player node: synth mode, bag replay (raw bytes, stamps, windows, selection, remapping,
ROS 1 bags), /clock and loops, bad parameters. In one process with a probe node (fast);
the cross-process path is covered by test_player_roundtrip.py and the demo test."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import QuaternionStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from rosharness import closing_factory, spin_until
from sensor_msgs.msg import Imu, MagneticField

from mkf_ros.bags import cdr
from mkf_ros.bags.synth import DEFAULT_START_NS, sim_streams, write_bag
from mkf_ros.ros.player_node import PlayerError, PlayerNode
from mkf_ros.sim import simulate

pytestmark = pytest.mark.ros
#: the probe must not lose anything (best-effort matching is tested with the estimator)
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
TYPES = {"/imu/data_raw": Imu, "/imu/mag": MagneticField, "/imu/ground_truth": QuaternionStamped}


class Probe:
    """A player and a probe node recording raw messages, spun by one executor."""

    def __init__(self, ctx: Any, params: dict[str, Any], topics: dict[str, Any] | None = None,
                 *, cli_args: list[str] | None = None, namespace: str | None = None,
                 probe_ns: str | None = None) -> None:
        self.player = PlayerNode(context=ctx, namespace=namespace, cli_args=cli_args,
                                 parameter_overrides=[Parameter(k, value=v)
                                                      for k, v in params.items()])
        self.node = Node("probe", context=ctx, namespace=probe_ns)
        #: the raw (CDR) messages received on each topic, in order
        self.got: dict[str, list[bytes]] = {}
        for topic, cls in (topics or TYPES).items():
            self.got[topic] = []
            self.node.create_subscription(cls, topic, self.got[topic].append, RELIABLE, raw=True)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.player)
        self.ex.add_node(self.node)

    def spin_until(self, cond: Callable[[], bool], timeout: float = 20.0) -> bool:
        return spin_until(self.ex, cond, timeout)

    def play(self, timeout: float = 20.0) -> None:
        """Until the player is done and every message it published on a probed topic has
        arrived (event-driven: nothing is assumed to arrive within a fixed time)."""
        assert self.spin_until(lambda: self.player.done, timeout), "player did not finish"
        sent = {self.player.pubs[t].topic_name: n for t, n in self.player.published.items()}
        assert self.spin_until(lambda: all(len(self.got[k]) >= n for k, n in sent.items()
                                           if k in self.got), timeout), (
            f"probe got {({k: len(v) for k, v in self.got.items()})} of {sent}")

    def raws(self, topic: str) -> list[bytes]:
        return list(self.got[topic])

    def close(self) -> None:
        self.ex.shutdown()
        self.player.destroy_node()
        self.node.destroy_node()


@pytest.fixture
def probe(ros_context: Any) -> Iterator[Callable[..., Probe]]:
    """Factory: ``probe(params, topics=None, ...)``; closed after the test."""
    yield from closing_factory(functools.partial(Probe, ros_context))


WAIT = {"wait_for_subscribers": 1, "start_delay": 0.2}


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("player") / "slow"
    write_bag(simulate("slow_rotation", duration=3.0, rate=100.0, mag_rate=25.0, seed=5), path)
    return path


def test_synth_mode_streams_with_truth(probe: Callable[..., Probe]) -> None:
    t_start = time.time_ns()
    p = probe(dict(WAIT, duration=1.0, imu_rate=100.0, mag_rate=20.0, rate=4.0, seed=3,
                   scenario="sweep"))
    p.play()
    imu = cdr.decode(p.raws("/imu/data_raw"), cdr.IMU)
    truth = cdr.decode(p.raws("/imu/ground_truth"), cdr.QUATERNION_STAMPED)
    mag = cdr.decode(p.raws("/imu/mag"), cdr.MAGNETIC_FIELD)
    assert len(imu.stamp_ns) == 101 and len(mag.stamp_ns) == 20
    np.testing.assert_array_equal(imu.stamp_ns, truth.stamp_ns)
    assert t_start <= imu.stamp_ns[0] <= time.time_ns()  # stamps start at the wall clock
    np.testing.assert_allclose(np.diff(imu.stamp_ns), 10_000_000, atol=1)
    sim = p.player.source.sim
    q = truth.fields["quaternion"]
    np.testing.assert_array_equal(q[:, [3, 0, 1, 2]], sim.quat)
    np.testing.assert_array_equal(imu.fields["angular_velocity"], sim.gyr)
    assert imu.fields["orientation_covariance"][0, 0] == -1.0  # REP-145: no orientation
    assert imu.frame_ids == ["imu_link"]


def test_pacing_follows_the_recording(ros_context: Any) -> None:
    """Event-driven: the player's timer is stopped and the test steps it with the steady clock
    it would read. A message of recording time t goes out once (t − t₀)/rate has passed since
    the start, not before: 1 s at 100 Hz played at rate 4 → 51 IMU messages after 0.125 s,
    all 101 after 0.25 s."""
    player = PlayerNode(context=ros_context, parameter_overrides=[
        Parameter(k, value=v) for k, v in dict(
            duration=1.0, imu_rate=100.0, mag_rate=20.0, rate=4.0, seed=3, scenario="sweep",
            wait_for_subscribers=0, start_delay=0.0).items()])
    try:
        player._timer.cancel()

        def published(name: str) -> int:
            return sum(n for t, n in player.published.items()
                       if player.pubs[t].topic_name == name)

        now = 1000.0
        player._step(now)  # starts the playback: the first sample is due at once
        assert player.state == "playing" and published("/imu/data_raw") == 1
        for dt, n_imu, n_mag in ((0.125 - 1e-6, 50, 10), (0.125 + 1e-6, 51, 11),
                                 (0.25 - 1e-6, 100, 20), (0.25 + 1e-6, 101, 20)):
            player._step(now + dt)
            got = (published("/imu/data_raw"), published("/imu/mag"))
            assert got == (n_imu, n_mag), (dt, got)
        assert published("/imu/ground_truth") == 101
    finally:
        player.destroy_node()


def test_bag_mode_publishes_the_recorded_bytes(probe: Callable[..., Probe], bag: Path) -> None:
    p = probe(dict(WAIT, bag=str(bag), rate=5.0))
    p.play()
    want = sim_streams(simulate("slow_rotation", duration=3.0, rate=100.0, mag_rate=25.0,
                                seed=5))
    for s in want.values():
        assert p.raws(s.topic) == cdr.split_rows(s.rows), s.topic
    assert p.player.published == {"/imu/mag": 75, "/imu/data_raw": 301,
                                  "/imu/ground_truth": 301}


def test_window_selection_and_remapping(probe: Callable[..., Probe], bag: Path) -> None:
    p = probe(dict(WAIT, bag=str(bag), rate=5.0, start_offset=1.0, duration=0.5,
                   topics=["imu/data_raw"]),
              topics={"/robot/imu": Imu, "/imu/data_raw": Imu, "/imu/mag": MagneticField},
              cli_args=["--ros-args", "-r", "/imu/data_raw:=/robot/imu"])
    p.play()
    got = cdr.decode(p.raws("/robot/imu"), cdr.IMU)
    assert p.got["/imu/data_raw"] == [] and p.got["/imu/mag"] == []
    t = (got.stamp_ns - DEFAULT_START_NS) * 1e-9
    assert len(t) == 50 and t[0] == pytest.approx(1.0) and t[-1] == pytest.approx(1.49)


def test_relative_topics_follow_the_namespace(probe: Callable[..., Probe], bag: Path) -> None:
    p = probe(dict(bag=str(bag), rate=10.0, relative_topics=True, topics=["/imu/mag"],
                   wait_for_subscribers=1, start_delay=0.2),
              topics={"/robot/imu/mag": MagneticField}, namespace="/robot")
    p.play()
    assert len(p.got["/robot/imu/mag"]) == 75


def clock_ns(raws: list[bytes]) -> np.ndarray:
    """rosgraph_msgs/Clock messages (CDR: 4-byte header, int32 sec, uint32 nanosec) → ns."""
    return np.array([int.from_bytes(m[4:8], "little", signed=True) * 10**9
                     + int.from_bytes(m[8:12], "little") for m in raws])


def test_clock_stops_at_the_end_of_the_recording(probe: Callable[..., Probe],
                                                 tmp_path: Path) -> None:
    """Event-driven (the test steps the player): a timer tick that comes late, as on a busy
    machine, publishes every message then due and a /clock that stays within the recording
    (0.5 s: its last stamp), not the playback time the late tick reads."""
    path = tmp_path / "short"
    write_bag(simulate("static", duration=0.5, rate=50.0, mag_rate=10.0), path, "sqlite3")
    p = probe(dict(bag=str(path), rate=2.0, publish_clock=True, topics=["/imu/data_raw"],
                   wait_for_subscribers=0, start_delay=0.0),
              topics={"/clock": Clock, "/imu/data_raw": Imu})
    p.player._timer.cancel()
    p.player._step(1000.0)  # starts the playback at the first stamp
    p.player._step(1010.0)  # 10 s late: all 26 messages are due (0.25 s at rate 2)
    assert p.spin_until(lambda: len(p.got["/clock"]) == 2 and len(p.got["/imu/data_raw"]) == 26)
    np.testing.assert_array_equal(clock_ns(p.raws("/clock")),
                                  [DEFAULT_START_NS, DEFAULT_START_NS + 500_000_000])


def test_loop_and_clock(probe: Callable[..., Probe], tmp_path: Path) -> None:
    path = tmp_path / "short"
    write_bag(simulate("static", duration=0.5, rate=50.0, mag_rate=10.0), path, "sqlite3")
    p = probe(dict(WAIT, bag=str(path), rate=2.0, loop=True, publish_clock=True,
                   clock_frequency=50.0, topics=["/imu/data_raw"]),
              topics={"/clock": Clock, "/imu/data_raw": Imu})
    assert p.spin_until(lambda: p.player.loops >= 2, 10.0)

    def backward_jumps() -> int:  # of the /clock received so far
        return int(np.count_nonzero(np.diff(clock_ns(p.raws("/clock"))) < 0))

    # one jump per loop; both passes' IMU messages in
    assert p.spin_until(lambda: backward_jumps() >= 2 and len(p.got["/imu/data_raw"]) >= 2 * 26,
                        10.0)
    clocks = clock_ns(p.raws("/clock"))
    jumps = np.flatnonzero(np.diff(clocks) < 0)
    assert clocks[jumps[0] + 1] == DEFAULT_START_NS  # back to the start of the bag
    assert clocks.min() >= DEFAULT_START_NS and clocks.max() <= DEFAULT_START_NS + 0.5e9
    assert not p.player.done


def test_ros1_bag_replay(probe: Callable[..., Probe], tmp_path: Path) -> None:
    from rosbags import rosbag1, typesys
    ts1 = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    ts2 = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    sim = simulate("static", duration=0.2, rate=50.0)
    rows = sim_streams(sim)["imu"].rows
    path = tmp_path / "r1.bag"
    fields = ("orientation", "orientation_covariance", "angular_velocity",
              "angular_velocity_covariance", "linear_acceleration",
              "linear_acceleration_covariance")
    with rosbag1.Writer(path) as w:
        c = w.add_connection("/imu/data_raw", "sensor_msgs/msg/Imu", typestore=ts1)
        for i, r in enumerate(rows):
            m = ts2.deserialize_cdr(bytes(r), "sensor_msgs/msg/Imu")
            h = ts1.types["std_msgs/msg/Header"](seq=i, stamp=m.header.stamp,
                                                  frame_id=m.header.frame_id)
            m1 = ts1.types["sensor_msgs/msg/Imu"](h, *[getattr(m, f) for f in fields])
            w.write(c, DEFAULT_START_NS + i * 20_000_000,
                    ts1.serialize_ros1(m1, "sensor_msgs/msg/Imu"))
    p = probe(dict(WAIT, bag=str(path), rate=5.0), topics={"/imu/data_raw": Imu})
    p.play()
    assert p.raws("/imu/data_raw") == cdr.split_rows(rows)


def test_bad_parameters(ros_context: Any, tmp_path: Path, bag: Path) -> None:
    def make(**params: Any) -> None:
        PlayerNode(context=ros_context,
                   parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])

    with pytest.raises(PlayerError, match="no such bag"):
        make(bag=str(tmp_path / "missing"))
    with pytest.raises(PlayerError, match=r"topic /nope is not in"):
        make(bag=str(bag), topics=["nope"])
    with pytest.raises(PlayerError, match="past the end"):
        make(bag=str(bag), start_offset=10.0)
    with pytest.raises(PlayerError, match="rate must be positive"):
        make(rate=0.0)
    with pytest.raises(PlayerError, match="unknown scenario 'x'"):
        make(scenario="x")
    with pytest.raises(PlayerError, match="scenario_params"):
        make(scenario_params=["acc_peak"])
    with pytest.raises(PlayerError, match="wait_topics: imu/nope is not published"):
        make(wait_topics=["imu/nope"])
    with pytest.raises(PlayerError, match="split_accel must be >= 0"):
        make(split_accel=-1)


def _run_player(*ros_args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return subprocess.run([sys.executable, "-m", "mkf_ros.ros.player_node", "--ros-args",
                           *ros_args], env=env, capture_output=True, text=True, timeout=60)


def test_console_errors_are_one_line(tmp_path: Path) -> None:
    (tmp_path / "x.txt").write_text("not a bag")
    r = _run_player("-p", f"bag:={tmp_path / 'x.txt'}")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("player: unknown storage format"), r.stderr
    r = _run_player("-p", "rate:=fast")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Traceback" not in r.stderr
