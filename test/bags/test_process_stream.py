"""mkf_ros.bags.process streams: a bag read, filtered, written and scored in many windows gives
the same output messages and scores as the bag in one window (the whole recording), also when a
window boundary falls on a magnetometer sample or on a gap, for MCAP and sqlite3 input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mkf_ros.bags import BagReader, mcap, reader
from mkf_ros.bags.process import process_bag
from mkf_ros.bags.synth import write_bag
from mkf_ros.sim import simulate


def per_topic(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    with BagReader(bag) as br:
        got = br.read(list(br.topics))
        return {t: list(zip(b.log_ns.tolist(), b.raws, strict=True)) for t, b in got.items()}


@pytest.fixture(scope="module", params=["mcap", "sqlite3"])
def small_chunks(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
                 ) -> Path:
    """12 s of the dropouts scenario (a 1 s gap, a magnetometer outage) at 50 Hz with the
    magnetometer at 25 Hz, written one message per MCAP chunk (every message boundary is a
    chunk boundary; sqlite3: the tests fetch one row at a time)."""
    path = tmp_path_factory.mktemp("in") / f"drop_{request.param}"
    mp = pytest.MonkeyPatch()
    mp.setattr(mcap, "CHUNK_BYTES", 1)
    try:
        write_bag(simulate("dropouts", duration=12.0, rate=50.0, mag_rate=25.0, seed=4), path,
                  request.param)
    finally:
        mp.undo()
    return path


def test_windows_cut_at_a_magnetometer_sample_and_at_the_gap(small_chunks: Path,
                                                             monkeypatch: pytest.MonkeyPatch
                                                             ) -> None:
    """The windows of one message partition the bag by log time, never split equal times,
    and some start exactly at a magnetometer sample and right after the gap."""
    monkeypatch.setattr(reader, "SQLITE_FETCH", 1)
    topics = ["/imu/data_raw", "/imu/mag"]
    with BagReader(small_chunks) as br:
        whole = br.read(topics)
        wins = list(br.read_windows(topics, 1))
    assert len(wins) > 100
    firsts = []
    for w in wins:
        times = np.concatenate([w[t].log_ns for t in topics])
        firsts.append((int(times.min()), {t for t in topics if len(w[t]) and
                                          w[t].log_ns[0] == times.min()}))
    for t in topics:
        joined = np.concatenate([w[t].log_ns for w in wins])
        assert np.array_equal(joined, whole[t].log_ns)
        assert [r for w in wins for r in w[t].raws] == whole[t].raws
    starts = [f[0] for f in firsts]
    assert starts == sorted(set(starts))  # in time, no log time in two windows
    assert any("/imu/mag" in f[1] for f in firsts)
    imu = whole["/imu/data_raw"].log_ns
    gap = int(np.argmax(np.diff(imu))) + 1  # the first message after the 1 s gap
    assert np.diff(imu)[gap - 1] > 0.5e9 and int(imu[gap]) in starts


@pytest.mark.parametrize("use_mag", [True, False])
def test_many_windows_give_the_output_of_one(small_chunks: Path, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch,
                                             use_mag: bool) -> None:
    monkeypatch.setattr(reader, "SQLITE_FETCH", 1)
    kw = dict(params=dict(use_mag=use_mag), copy_input=True, keep_outputs=True)
    one = process_bag(small_chunks, tmp_path / "one", window=None, **kw)  # type: ignore[arg-type]
    many = process_bag(small_chunks, tmp_path / "many", window=1, **kw)  # type: ignore[arg-type]
    assert one.n_out == many.n_out > 500
    assert per_topic(tmp_path / "many") == per_topic(tmp_path / "one")
    assert one.counters == many.counters and one.counters["gaps"] == 1
    assert one.scores is not None and many.scores is not None
    assert many.scores.n == one.scores.n == one.n_out
    for k, v in one.scores.rmse.items():
        assert many.scores.rmse[k] == pytest.approx(v, rel=1e-12)
    assert set(many.scores.windows) == set(one.scores.windows) == {"mag_dropout"}
    for kind, d in one.scores.windows.items():
        for k, v in d.items():
            assert many.scores.windows[kind][k] == pytest.approx(v, rel=1e-12)
    assert one.outputs is not None and many.outputs is not None
    assert np.array_equal(one.outputs.index, many.outputs.index)
    # the plot series: every sample of a short recording, in both
    assert np.array_equal(one.scores.q_est, many.scores.q_est)
