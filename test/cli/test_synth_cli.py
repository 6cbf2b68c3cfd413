"""``mkf synth``: reproducible bags in both storages, holding exactly the simulation."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mkf_ros.bags import BagReader, cdr
from mkf_ros.bags.synth import read_description
from mkf_ros.cli.main import main
from mkf_ros.sim import SCENARIOS, simulate


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_holds_the_simulation(tmp_path: Path, storage: str,
                                  capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "b"
    assert main(["synth", "accel_bursts", "--out", str(out), "--storage", storage,
                 "--duration", "6", "--rate", "100", "--mag-rate", "20", "--seed", "4",
                 "--gyro-bias", "0.01", "0", "0", "--param", "acc_peak=2.5",
                 "--frame-id", "base_imu"]) == 0
    text = capsys.readouterr().out
    assert f"wrote {out} ({storage})" in text and "/imu/data_raw" in text
    sim = simulate("accel_bursts", duration=6.0, rate=100.0, mag_rate=20.0, seed=4,
                   gyro_bias=(0.01, 0, 0), acc_peak=2.5)
    with BagReader(out) as br:
        assert br.storage == storage
        assert {t: i.msgtype for t, i in br.topics.items()} == {
            "/imu/data_raw": "sensor_msgs/msg/Imu", "/imu/mag": "sensor_msgs/msg/MagneticField",
            "/imu/ground_truth": "geometry_msgs/msg/QuaternionStamped"}
        got = br.read(list(br.topics))
    imu = cdr.decode(got["/imu/data_raw"].raws, cdr.IMU)
    np.testing.assert_array_equal(imu.fields["linear_acceleration"], sim.acc)
    np.testing.assert_array_equal(imu.fields["angular_velocity_covariance"][0, [0, 4, 8]],
                                  [1e-4] * 3)
    assert imu.frame_ids == ["base_imu"]
    assert imu.stamp_ns[0] == 1_704_067_200 * 10**9
    mag = cdr.decode(got["/imu/mag"].raws, cdr.MAGNETIC_FIELD)
    np.testing.assert_array_equal(mag.fields["magnetic_field"], sim.mag[sim.mag_valid])
    assert len(mag.stamp_ns) == 120
    desc = read_description(out)
    assert desc["params"] == {"acc_peak": 2.5, "burst_every": 3.0}
    assert len(desc["intervals"]["acc_disturbed"]) == len(sim.meta["intervals"]["acc_disturbed"])


def test_list_names_every_scenario(capsys: pytest.CaptureFixture) -> None:
    assert main(["synth", "--list"]) == 0
    text = capsys.readouterr().out
    for name in SCENARIOS:
        assert re.search(rf"^{name}\s", text, re.M)


@pytest.mark.parametrize(("argv", "pattern"), [
    (["synth", "static"], "give the output bag with --out BAG"),
    (["synth", "--out", "x"], "give a SCENARIO"),
    (["synth", "spin", "--out", "x"], "unknown scenario 'spin'; known: static"),
    (["synth", "static", "--out", "x", "--param", "gap"], "--param needs NAME=VALUE"),
    (["synth", "static", "--out", "x", "--param", "gap=a"], "is not a number"),
    (["synth", "dropouts", "--out", "x", "--param", "gapp=1"], "has no parameter 'gapp'"),
    (["synth", "static", "--out", "x", "--storage", "db"], "unknown storage 'db'"),
    (["synth", "static", "--out", "x", "--rate", "0"], "--rate must be positive"),
])
def test_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch,
                       argv: list[str], pattern: str) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and pattern in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_existing_bag_needs_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = str(tmp_path / "b")
    args = ["synth", "static", "--out", out, "--duration", "1"]
    assert main(args) == 0
    assert main(args) == 2
    assert "already exists (use --overwrite" in capsys.readouterr().err
    assert main([*args, "--overwrite", "--storage", "sqlite3"]) == 0
    with BagReader(out) as br:
        assert br.storage == "sqlite3"


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    from rosbags import rosbag2

    with rosbag2.Reader(path) as r:
        return [(c.topic, t, bytes(d)) for c, t, d in r.messages()]


def test_synth_streams_the_bag_of_the_whole_recording(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """With chunks of 7 samples the command writes the messages and the description of the
    bag of the whole simulation (dropped samples, magnetometer at its own rate, split topics)."""
    from mkf_ros.bags.synth import write_bag
    from mkf_ros.sim import motion

    monkeypatch.setattr(motion, "CHUNK_SAMPLES", 7)
    out = tmp_path / "b"
    assert main(["synth", "dropouts", "--out", str(out), "--duration", "8", "--rate", "50",
                 "--mag-rate", "15", "--seed", "5", "--split-accel", "3",
                 "--param", "gap=0.5"]) == 0
    ref = tmp_path / "ref"
    write_bag(simulate("dropouts", duration=8.0, rate=50.0, mag_rate=15.0, seed=5, gap=0.5,
                       chunk=401), ref, split_accel=3)
    assert _messages(out) == _messages(ref)
    assert read_description(out) == read_description(ref)


def test_a_failure_while_writing_leaves_no_bag(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import mkf_ros.bags.synth as synth
    from mkf_ros.sim import motion

    monkeypatch.setattr(motion, "CHUNK_SAMPLES", 50)
    real, calls = synth.sim_streams, []

    def failing(*a: object, **k: object) -> object:
        calls.append(1)
        if len(calls) == 4:
            raise OSError("disk full")
        return real(*a, **k)

    monkeypatch.setattr(synth, "sim_streams", failing)
    with pytest.raises(OSError, match="disk full"):
        main(["synth", "wiener", "--out", str(tmp_path / "b"), "--duration", "10",
              "--rate", "100"])
    assert len(calls) == 4 and list(tmp_path.iterdir()) == []
