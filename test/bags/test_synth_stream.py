"""Synthetic bags written chunk by chunk: the messages of the whole-recording bag, the split
accelerometer picked across chunk boundaries, the description written last, and nothing left
behind when the generation fails half-way."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags import rosbag2

from mkf_ros.bags import cdr
from mkf_ros.bags.synth import TOPICS, Stream, read_description, sim_streams, split_imu, write_bag
from mkf_ros.sim import SimData, SimStream, simulate


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    """Every message as rosbags reads it: (topic, log time, bytes), in its order."""
    with rosbag2.Reader(path) as r:
        return [(c.topic, t, bytes(d)) for c, t, d in r.messages()]


@pytest.mark.parametrize(("scenario", "storage", "split"), [
    ("dropouts", "mcap", 3), ("sweep", "sqlite3", 0), ("time_jump", "mcap", 0),
    ("jitter", "sqlite3", 4)])
def test_streamed_bag_is_the_whole_recording_bag(tmp_path: Path, scenario: str, storage: str,
                                                 split: int) -> None:
    kw: dict[str, Any] = dict(duration=24.0, rate=50.0, mag_rate=15.0, seed=2, substeps=4)
    whole = tmp_path / "whole"
    counts = write_bag(simulate(scenario, **kw), whole, storage, split_accel=split)
    for chunk in (1, 37):
        out = tmp_path / f"chunks{chunk}"
        got = write_bag(SimStream(scenario, chunk=chunk, **kw), out, storage, split_accel=split)
        assert got == counts
        assert _messages(out) == _messages(whole)
        assert read_description(out) == read_description(whole)
    desc = read_description(whole)
    assert desc is not None
    if scenario == "sweep":  # found while streaming, stored at the end
        assert len(desc["intervals"]["gimbal_lock"]) >= 2
    if scenario == "dropouts":
        assert len(desc["intervals"]["dropout"]) == 2
        assert counts[TOPICS["accel"]] == -(-counts[TOPICS["gyro"]] // 3)


def test_split_imu_offset_continues_every_kth_message() -> None:
    """Chunks of the combined stream, each split with the messages before it as offset, give
    the split of the whole stream."""
    sim = simulate("slow_rotation", duration=2.0, rate=50.0, substeps=2)
    imu = sim_streams(sim)["imu"]
    acc, gyr = split_imu(imu, 4)
    parts, done = [], 0
    for a, b in ((0, 3), (3, 4), (4, 50), (50, 101)):
        chunk = Stream(imu.topic, imu.msgtype, imu.log_ns[a:b], imu.rows[a:b])
        parts.append(split_imu(chunk, 4, offset=done))
        done = b
    np.testing.assert_array_equal(np.concatenate([p[0].rows for p in parts]), acc.rows)
    np.testing.assert_array_equal(np.concatenate([p[0].log_ns for p in parts]), acc.log_ns)
    np.testing.assert_array_equal(np.concatenate([p[1].rows for p in parts]), gyr.rows)
    assert len(acc.log_ns) == 26
    av = cdr.decode(cdr.split_rows(acc.rows), cdr.IMU).fields["angular_velocity"]
    assert not av.any()


class _FailsHalfWay:
    """A stream that breaks after some chunks (as a full disk or a bug would)."""

    def __init__(self, stream: SimStream, after: int) -> None:
        self.stream, self.after, self.meta = stream, after, stream.meta

    def __iter__(self) -> Iterator[SimData]:
        for k, part in enumerate(self.stream):
            if k == self.after:
                raise RuntimeError("generation failed")
            yield part


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_failure_half_way_leaves_no_bag(tmp_path: Path, storage: str) -> None:
    out = tmp_path / "b"
    stream = SimStream("wiener", duration=10.0, rate=100.0, chunk=100)
    with pytest.raises(RuntimeError, match="generation failed"):
        write_bag(_FailsHalfWay(stream, 5), out, storage)  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []
    # an existing bag being replaced stays as it was
    write_bag(simulate("static", duration=1.0), out, storage)
    before = _messages(out)
    with pytest.raises(RuntimeError, match="generation failed"):
        write_bag(_FailsHalfWay(SimStream("wiener", duration=10.0, rate=100.0, chunk=100), 3),
                  out, storage, overwrite=True)  # type: ignore[arg-type]
    assert _messages(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["b"]
