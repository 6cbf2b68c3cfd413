"""The ``player`` node: replays bags, or synthesises IMU streams with ground truth.

**Bag mode** (``-p bag:=PATH``): ROS 2 bags as Jazzy records them (a rosbag2 directory with
MCAP or sqlite3 storage, or a bare ``.mcap``/``.db3`` file) and ROS 1 ``.bag`` files. The
recorded CDR bytes are published as they are (ROS 1 messages are converted to CDR), on the
recorded topic names (remap them with ``-r /imu/data_raw:=/other``, or set
``relative_topics:=true`` so that the node's namespace applies), paced by the recording (log)
times. Header stamps are never touched.

**Synth mode** (no ``bag``): a synthetic recording (``mkf synth --list`` shows the scenarios)
published on ``imu/data_raw`` (sensor_msgs/Imu), ``imu/mag`` (sensor_msgs/MagneticField, T)
and ``imu/ground_truth`` (geometry_msgs/QuaternionStamped, the true orientation sensor → ENU,
same stamps as the IMU). Stamps start at the wall-clock time of the start. With
``split_accel`` N > 0 the IMU goes out as a RealSense driver publishes it, for an estimator with
``input_mode`` split: ``imu/accel`` (every N-th sample, angular velocity zero) and ``imu/gyro``
(every sample, linear acceleration zero) instead of ``imu/data_raw``.

Both modes: ``rate`` (playback speed factor), ``start_offset`` and ``duration`` (s), ``loop``,
``topics`` (selection), ``publish_clock`` (rosgraph_msgs/Clock on ``/clock`` at
``clock_frequency``, so that nodes with ``use_sim_time`` follow the playback; a loop makes the
clock jump back), ``wait_for_subscribers`` + ``start_delay`` (do not start before the consumer
is there: a burst into a fresh best-effort subscription is lost), ``exit_when_done``.

Publishers are RELIABLE, KEEP_LAST(100), VOLATILE: they match reliable and best-effort
(sensor-data QoS, like the estimator's) subscriptions alike.
"""

from __future__ import annotations

import importlib
import sys
import time
from collections.abc import Iterator, Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from mkf_ros.bags import cdr
from mkf_ros.bags.reader import BagError, BagReader, normalize_topic
from mkf_ros.ros.signals import ends_on_signal

QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
TICK = 0.001  # s, period of the publishing timer (steady clock)
LINGER = 0.5  # s, kept alive after the last message so that reliable delivery completes

#: name → (default, description); the ROS parameters of the node
PARAMS: dict[str, tuple[Any, str]] = {
    "bag": ("", "bag to replay (directory, .mcap, .db3 or ROS 1 .bag); empty = synth mode"),
    "topics": (Parameter.Type.STRING_ARRAY, "topics to publish; empty = all"),
    "relative_topics": (False, "publish recorded names without the leading '/' so that the "
                        "node's namespace applies"),
    "rate": (1.0, "playback speed factor"),
    "start_offset": (0.0, "s: start this far into the recording"),
    "duration": (0.0, "s: play this long (0 = to the end; synth mode: 60 s)"),
    "loop": (False, "start over at the end (the clock and the stamps jump back)"),
    "loop_pause": (0.2, "s: wall time between the last message of a pass and the clock "
                   "jumping back, so that subscribers take the last messages first"),
    "publish_clock": (False, "publish the playback time on /clock"),
    "clock_frequency": (100.0, "Hz: /clock messages per second of wall time"),
    "wait_for_subscribers": (0, "wait until each topic of wait_topics has this many "
                             "subscribers"),
    "wait_topics": (Parameter.Type.STRING_ARRAY, "topics to wait for; empty = the "
                    "sensor_msgs/Imu topics"),
    "wait_timeout": (30.0, "s: give up waiting and start anyway"),
    "start_delay": (0.0, "s: pause between the subscribers matching and the first message"),
    "exit_when_done": (True, "shut the node down after the last message (no loop)"),
    # synth mode
    "scenario": ("slow_rotation", "synth mode: motion scenario (mkf synth --list)"),
    "scenario_params": (Parameter.Type.STRING_ARRAY, "synth mode: NAME=VALUE scenario "
                        "parameters"),
    "imu_rate": (200.0, "synth mode: IMU rate, Hz"),
    "mag_rate": (50.0, "synth mode: magnetometer rate, Hz"),
    "seed": (0, "synth mode: random seed"),
    "gyro_noise": (0.01, "synth mode: gyro noise per sample, rad/s"),
    "acc_noise": (0.05, "synth mode: accelerometer noise per sample, m/s^2"),
    "mag_noise": (0.5e-6, "synth mode: magnetometer noise per sample, T"),
    "gyro_bias": ([0.0, 0.0, 0.0], "synth mode: constant gyro bias, rad/s"),
    "mag_field": ([0.0, 25e-6, -43.30127018922193e-6], "synth mode: Earth field in ENU, T"),
    "frame_id": ("imu_link", "synth mode: header.frame_id"),
    "split_accel": (0, "synth mode: > 0 publishes imu/accel (every N-th sample, angular "
                    "velocity zero) and imu/gyro (linear acceleration zero) instead of "
                    "imu/data_raw, as a RealSense driver (estimator input_mode split)"),
}


class PlayerError(Exception):
    """Unusable parameters or bag (one line; the node does not start)."""


def message_class(msgtype: str) -> Any:
    """The rclpy class of ``pkg/msg/Name`` (ImportError/AttributeError if not installed)."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


class Source:
    """Messages to play: ``(topic, log time ns, CDR bytes)`` in log-time order, repeatable."""

    topics: dict[str, str]  #: topic → message type
    description: str

    def messages(self) -> Iterator[tuple[str, int, bytes]]:
        raise NotImplementedError


class BagSource(Source):
    def __init__(self, path: str, topics: Sequence[str], start_offset: float,
                 duration: float) -> None:
        self.reader = BagReader(path)
        br = self.reader
        if topics:
            names = []
            for t in topics:
                n = normalize_topic(t)
                if n not in br.topics:
                    have = ", ".join(sorted(br.topics))
                    raise PlayerError(f"topic {n} is not in {path} (topics: {have})")
                names.append(n)
        else:
            names = list(br.topics)
        self.topics = {n: br.topics[n].msgtype for n in names}
        self.start = br.start_ns + round(start_offset * 1e9)
        if self.start >= br.end_ns and br.message_count:
            raise PlayerError(f"start_offset {start_offset:g} s is past the end of {path} "
                              f"({(br.end_ns - br.start_ns) * 1e-9:.1f} s long)")
        self.stop = self.start + round(duration * 1e9) if duration > 0 else None
        span = ((self.stop or br.end_ns) - self.start) * 1e-9
        self.description = f"{path} ({br.storage}, {span:.1f} s, {len(self.topics)} topics)"

    def messages(self) -> Iterator[tuple[str, int, bytes]]:
        return self.reader.messages(self.topics, self.start, self.stop)


class SynthSource(Source):
    def __init__(self, p: dict[str, Any], start_ns: int) -> None:
        import numpy as np

        from mkf_ros.bags.synth import interleave, sim_streams, split_imu
        from mkf_ros.sim import SCENARIOS, simulate

        if p["scenario"] not in SCENARIOS:
            raise PlayerError(f"unknown scenario {p['scenario']!r}; known: "
                              f"{', '.join(SCENARIOS)}")
        kw: dict[str, Any] = {}
        for item in p["scenario_params"]:
            name, sep, value = item.partition("=")
            try:
                vals = tuple(float(v) for v in value.split(","))
            except ValueError:
                vals = ()
            if not sep or not vals:
                raise PlayerError(f"scenario_params: expected NAME=VALUE, got {item!r}")
            kw[name.strip()] = vals[0] if len(vals) == 1 else vals
        duration = p["duration"] if p["duration"] > 0 else 60.0
        if not (p["imu_rate"] > 0 and p["mag_rate"] > 0):
            raise PlayerError("imu_rate and mag_rate must be positive")
        if p["split_accel"] < 0:
            raise PlayerError(f"split_accel must be >= 0 (0: one imu/data_raw topic), got "
                              f"{p['split_accel']}")
        try:
            sim = simulate(p["scenario"], duration=p["start_offset"] + duration,
                           rate=p["imu_rate"], seed=p["seed"], gyro_noise=p["gyro_noise"],
                           acc_noise=p["acc_noise"], mag_noise=p["mag_noise"],
                           gyro_bias=tuple(p["gyro_bias"]), mag_field=np.asarray(p["mag_field"]),
                           mag_rate=min(p["mag_rate"], p["imu_rate"]), **kw)
        except ValueError as e:
            raise PlayerError(str(e)) from None
        streams = sim_streams(sim, start_ns=start_ns, frame_id=p["frame_id"],
                              topics={"imu": "imu/data_raw", "mag": "imu/mag",
                                      "truth": "imu/ground_truth"})
        imu = [streams["imu"]]
        if p["split_accel"] > 0:  # at equal times: accelerometer, then gyro (as mkf synth)
            imu = list(split_imu(streams["imu"], p["split_accel"], "imu/accel", "imu/gyro"))
        order = [streams["mag"], *imu, streams["truth"]]  # mag first at equal times
        which, t, raws = interleave(order)
        names = [s.topic for s in order]
        keep = t >= start_ns + round(p["start_offset"] * 1e9)
        want = set(normalize_topic(x).lstrip("/") for x in p["topics"]) or set(names)
        unknown = want - set(names)
        if unknown:
            raise PlayerError(f"topic {sorted(unknown)[0]} is not synthesised (topics: "
                              f"{', '.join(names)})")
        self._msgs = [(names[w], int(ti), r) for w, ti, r, k in
                      zip(which.tolist(), t.tolist(), raws, keep.tolist(), strict=True)
                      if k and names[w] in want]
        self.topics = {s.topic: s.msgtype for s in order if s.topic in want}
        split = (f", accelerometer on imu/accel every {p['split_accel']} samples"
                 if p["split_accel"] > 0 else "")
        self.description = (f"synthetic {p['scenario']} ({duration:g} s, IMU {p['imu_rate']:g} "
                            f"Hz{split}, magnetometer {min(p['mag_rate'], p['imu_rate']):g} Hz, "
                            f"seed {p['seed']})")
        self.sim = sim

    def messages(self) -> Iterator[tuple[str, int, bytes]]:
        return iter(self._msgs)


class PlayerNode(Node):
    """Publishes a :class:`Source` paced by its log times (see the module docstring)."""

    def __init__(self, node_name: str = "player", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self.p = self._declare()
        p = self.p
        for name, lo in (("rate", 0.0), ("clock_frequency", 0.0)):
            if not p[name] > lo:
                raise PlayerError(f"{name} must be positive, got {p[name]}")
        for name in ("start_offset", "duration", "wait_timeout", "start_delay", "loop_pause"):
            if p[name] < 0:
                raise PlayerError(f"{name} must be >= 0, got {p[name]}")
        try:
            if p["bag"]:
                self.source: Source = BagSource(p["bag"], p["topics"], p["start_offset"],
                                                p["duration"])
            else:
                self.source = SynthSource(p, time.time_ns())
        except BagError as e:
            raise PlayerError(str(e)) from None
        log = self.get_logger()
        self.pubs: dict[str, Any] = {}
        self.published: dict[str, int] = {}
        for topic, msgtype in self.source.topics.items():
            try:
                cls = message_class(msgtype)
            except (ImportError, AttributeError, ValueError):
                log.warning(f"skipping {topic}: message type {msgtype} is not installed")
                continue
            name = topic.lstrip("/") if p["relative_topics"] else topic
            self.pubs[topic] = self.create_publisher(cls, name, QOS)
            self.published[topic] = 0
        if not self.pubs:
            raise PlayerError("nothing to publish (no topic with an installed message type)")
        if p["wait_topics"]:
            by_name = {t.lstrip("/"): t for t in self.pubs}
            missing = [w for w in p["wait_topics"] if w.strip().lstrip("/") not in by_name]
            if missing:
                raise PlayerError(f"wait_topics: {missing[0]} is not published (topics: "
                                  f"{', '.join(self.pubs)})")
            wait = [by_name[w.strip().lstrip("/")] for w in p["wait_topics"]]
        else:
            wait = [t for t, m in self.source.topics.items()
                    if m == cdr.IMU.msgtype and t in self.pubs] or list(self.pubs)[:1]
        self._wait_pubs = [self.pubs[t] for t in wait]
        self._clock_pub = None
        if p["publish_clock"]:
            from rosgraph_msgs.msg import Clock as ClockMsg

            self._clock_pub = self.create_publisher(ClockMsg, "/clock", CLOCK_QOS)
        self.state = "waiting"
        self.failed = ""
        self.loops = 0
        self._t_wait = time.monotonic()
        self._it: Iterator[tuple[str, int, bytes]] = iter(())
        self._next: tuple[str, int, bytes] | None = None
        self._t0_wall = 0.0  # monotonic s
        self._t0_bag = 0  # bag ns
        self._t_taken = 0  # bag ns of the last message taken
        self._last_clock = -1.0
        self._done_at = 0.0
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(TICK, self._tick, clock=self._steady)
        pubs = ", ".join(self.pubs[t].topic_name for t in self.pubs)
        log.info(f"playing {self.source.description} at rate {p['rate']:g}"
                 f"{', looping' if p['loop'] else ''}"
                 f"{', publishing /clock' if self._clock_pub else ''}: {pubs}")

    # --- parameters ----------------------------------------------------------------------------
    def _declare(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, (default, doc) in PARAMS.items():
            self.declare_parameter(name, default, ParameterDescriptor(description=doc))
            try:
                v = self.get_parameter(name).value
            except ParameterUninitializedException:
                v = []
            out[name] = list(v) if isinstance(default, (list, Parameter.Type)) and v else v
            if isinstance(default, float) and isinstance(v, int):
                out[name] = float(v)
        return out

    # --- playback ------------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self.state == "done"

    def _start(self, now: float) -> None:
        self._it = self.source.messages()
        self._next = next(self._it, None)
        if self._next is None:
            self.get_logger().warning("no messages in the selected window")
            self.state = "done"
            return
        self._t0_wall = now
        self._t0_bag = self._next[1]
        self._t_taken = self._t0_bag
        self._last_clock = -1.0
        self.state = "playing"

    def _bag_now(self, now: float) -> int:
        return self._t0_bag + round((now - self._t0_wall) * self.p["rate"] * 1e9)

    def _publish_clock(self, now: float, force: bool = False) -> None:
        if self._clock_pub is None:
            return
        if force or now - self._last_clock >= 1.0 / self.p["clock_frequency"]:
            # never ahead of the next message, nor (a late tick) past the end of the recording
            t = min(self._bag_now(now),
                    self._t_taken if self._next is None else self._next[1])
            self._clock_pub.publish(cdr.clock_message(t))
            self._last_clock = now

    def _tick(self) -> None:
        try:
            self._step(time.monotonic())
        except BagError as e:  # a bag that breaks mid-way (truncated chunk)
            self.get_logger().error(str(e))
            self.state = "done"
            self.failed = str(e)

    def _step(self, now: float) -> None:
        p = self.p
        if self.state == "waiting":
            n = p["wait_for_subscribers"]
            lacking = [w.topic_name for w in self._wait_pubs if w.get_subscription_count() < n]
            if n > 0 and lacking:
                if now - self._t_wait < p["wait_timeout"]:
                    return
                self.get_logger().warning(
                    f"fewer than {n} subscriber(s) on {', '.join(lacking)} after "
                    f"{p['wait_timeout']:g} s; starting anyway")
            self.state = "delay"
            self._t_wait = now
        if self.state == "delay":
            if now - self._t_wait < p["start_delay"]:
                return
            self._start(now)
            self._publish_clock(now, force=True)
        if self.state == "playing":
            rate = p["rate"]
            while self._next is not None:
                topic, t, raw = self._next
                if self._t0_wall + (t - self._t0_bag) * 1e-9 / rate > now:
                    break
                pub = self.pubs.get(topic)
                if pub is not None:
                    pub.publish(raw)
                    self.published[topic] += 1
                self._t_taken = t
                self._next = next(self._it, None)
            self._publish_clock(now)
            if self._next is None:
                if p["loop"]:
                    self.state = "pausing"
                    self._done_at = now
                else:
                    self.state = "finishing"
                    self._done_at = now
        if self.state == "pausing" and now - self._done_at >= p["loop_pause"]:
            self.loops += 1
            self.get_logger().info(f"end of the recording: loop {self.loops}")
            self._start(now)
            self._publish_clock(now, force=True)
        if self.state == "finishing" and now - self._done_at >= LINGER:
            self.state = "done"
            total = sum(self.published.values())
            counts = ", ".join(f"{self.pubs[t].topic_name} {n}" for t, n in
                               self.published.items())
            self.get_logger().info(f"done: published {total} messages ({counts})")


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``player`` (``ros2 run mkf_ros player [--ros-args -p bag:=PATH ...]``)."""
    args = list(sys.argv if argv is None else argv)
    plain = remove_ros_args(args)
    if any(a in ("-h", "--help") for a in plain[1:]):
        print(__doc__)
        print("parameters:")
        for name, (default, doc) in PARAMS.items():
            d = "[]" if isinstance(default, Parameter.Type) else repr(default)
            print(f"  {name:<22} {doc} (default {d})")
        return 0
    rclpy.init(args=args)
    try:
        node = PlayerNode()
    except (PlayerError, BagError) as e:
        print(f"player: {e}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except Exception as e:  # a parameter of the wrong type (rclpy raises several kinds)
        print(f"player: invalid parameter: {' '.join(str(e).split())}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    code = 0
    try:
        with ends_on_signal(rclpy.get_default_context()):
            while rclpy.ok() and not (node.done and node.p["exit_when_done"]):
                executor.spin_once(timeout_sec=0.1)
            code = 1 if node.failed else 0
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

