"""Bag reading and writing: both storages round-trip through rosbags, the fast readers agree
with rosbags, writes are atomic, and every broken input gives one BagError line."""

from __future__ import annotations

import re
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags import rosbag1, rosbag2, typesys  # a hard dependency (install_requires)

from mkf_ros.bags import BagError, BagReader, BagWriter, cdr
from mkf_ros.bags.synth import read_description, sim_streams, write_bag
from mkf_ros.sim import simulate

TS = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
IMU = "sensor_msgs/msg/Imu"


def _rows(n: int, frame: str = "imu_link", t0: int = 10**18) -> tuple[np.ndarray, np.ndarray]:
    stamps = t0 + np.arange(n, dtype=np.int64) * 5_000_000
    r = np.random.default_rng(n)
    return stamps, cdr.encode(cdr.IMU, stamps, frame, angular_velocity=r.normal(size=(n, 3)),
                              linear_acceleration=r.normal(size=(n, 3)))


def _rosbags_messages(path: Path) -> list[tuple[str, int, bytes]]:
    with rosbag2.Reader(path) as r:
        return [(c.topic, t, bytes(d)) for c, t, d in r.messages()]


@pytest.mark.parametrize(("storage", "compress"),
                         [("mcap", False), ("mcap", True), ("sqlite3", False)])
def test_round_trip_agrees_with_rosbags(tmp_path: Path, storage: str, compress: bool) -> None:
    bag = tmp_path / "b"
    stamps, rows = _rows(5000)
    other = cdr.split_rows(cdr.encode(cdr.MAGNETIC_FIELD, stamps[::7] + 1, "m"))
    with BagWriter(bag, storage, compress=compress) as w:
        ci = w.add_topic("imu/data_raw", IMU)
        cm = w.add_topic("/imu/mag", "sensor_msgs/msg/MagneticField")
        w.write_batch(ci, stamps[:3000], rows[:3000])
        w.write(ci, int(stamps[3000]), bytes(rows[3000]))
        w.write_batch(ci, stamps[3001:], cdr.split_rows(rows[3001:]))
        w.write_batch(cm, stamps[::7] + 1, other)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]  # no temporary left
    ref = _rosbags_messages(bag)
    assert len(ref) == 5000 + len(other)
    imu_ref = [(t, d) for topic, t, d in ref if topic == "/imu/data_raw"]
    assert [t for t, _ in imu_ref] == stamps.tolist()
    assert all(d == bytes(rows[i]) for i, (_, d) in enumerate(imu_ref))
    with BagReader(bag) as br:
        assert br.storage == storage
        assert br.topics["/imu/data_raw"].count == 5000
        assert br.topics["/imu/mag"].msgtype == "sensor_msgs/msg/MagneticField"
        got = br.read(["/imu/data_raw", "/imu/mag"])
        assert got["/imu/data_raw"].log_ns.tolist() == stamps.tolist()
        assert got["/imu/data_raw"].raws == [d for _, d in imu_ref]
        assert got["/imu/mag"].raws == other
        streamed = list(br.messages(["/imu/mag"]))
        assert [d for _, _, d in streamed] == other


def test_bare_storage_files_and_directories_without_metadata(tmp_path: Path) -> None:
    bag = tmp_path / "b"
    stamps, rows = _rows(10)
    with BagWriter(bag, "mcap") as w:
        w.write_batch(w.add_topic("imu", IMU), stamps, rows)
    f = bag / "b.mcap"
    with BagReader(f) as br:
        assert br.read(["/imu"])["/imu"].raws == cdr.split_rows(rows)
    (bag / "metadata.yaml").unlink()
    with BagReader(bag) as br:
        assert len(br.read(["/imu"])["/imu"]) == 10


def test_ros1_bags_are_converted_to_ros2_cdr(tmp_path: Path) -> None:
    ts1 = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    stamps, rows = _rows(20)
    msgs = [TS.deserialize_cdr(bytes(r), IMU) for r in rows]
    path = tmp_path / "old.bag"
    with rosbag1.Writer(path) as w:
        c = w.add_connection("/imu/data_raw", IMU, typestore=ts1)
        for t, m in zip(stamps.tolist(), msgs, strict=True):
            h = ts1.types["std_msgs/msg/Header"](seq=3, stamp=m.header.stamp,
                                                  frame_id=m.header.frame_id)
            m1 = ts1.types[IMU](h, *[getattr(m, f) for f in
                                     ("orientation", "orientation_covariance",
                                      "angular_velocity", "angular_velocity_covariance",
                                      "linear_acceleration", "linear_acceleration_covariance")])
            w.write(c, t, ts1.serialize_ros1(m1, IMU))
    with BagReader(path) as br:
        assert br.storage == "ros1"
        assert br.topics["/imu/data_raw"].msgtype == IMU
        got = br.read(["/imu/data_raw"])["/imu/data_raw"]
    assert got.raws == cdr.split_rows(rows)
    assert got.log_ns.tolist() == stamps.tolist()


def test_writes_are_atomic(tmp_path: Path) -> None:
    bag = tmp_path / "out"
    stamps, rows = _rows(100)
    with pytest.raises(RuntimeError), BagWriter(bag) as w:
        w.write_batch(w.add_topic("imu", IMU), stamps, rows)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with BagWriter(bag) as w:
        w.write_batch(w.add_topic("imu", IMU), stamps, rows)
    with pytest.raises(BagError, match="already exists"):
        BagWriter(bag)
    with BagWriter(bag, "sqlite3", overwrite=True) as w:
        w.write_batch(w.add_topic("imu", IMU), stamps[:5], rows[:5])
    with BagReader(bag) as br:
        assert br.storage == "sqlite3" and br.topics["/imu"].count == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(BagError, match="not a bag"):
        BagWriter(tmp_path / "file.txt", overwrite=True)
    with pytest.raises(BagError, match="unknown storage 'rosbag'"):
        BagWriter(tmp_path / "x", "rosbag")
    with pytest.raises(BagError, match="does not exist"):
        BagWriter(tmp_path / "nodir" / "x")


def _good_bag(tmp_path: Path, storage: str) -> Path:
    sim = simulate("static", duration=60.0, rate=100.0)
    write_bag(sim, tmp_path / storage, storage)
    return tmp_path / storage


def _read_all(path: Path) -> None:
    with BagReader(path) as br:
        br.read(list(br.topics))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_truncated_and_corrupt_storage(tmp_path: Path, storage: str) -> None:
    bag = _good_bag(tmp_path, storage)
    f = next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match=f"cannot read bag {bag}") as e:
        _read_all(bag)
    assert "\n" not in str(e.value)
    f.write_bytes(data[:1000] + bytes(len(data) - 1000))  # zeroed out after 1 kB
    with pytest.raises(BagError, match="cannot read bag"):
        _read_all(bag)


def test_corrupt_chunk_in_an_intact_index(tmp_path: Path) -> None:
    bag = _good_bag(tmp_path, "mcap")
    f = bag / "mcap.mcap"
    data = bytearray(f.read_bytes())
    mid = len(data) // 3
    data[mid:mid + 64] = b"\xff" * 64  # inside a chunk: checksum or record framing fails
    f.write_bytes(bytes(data))
    with pytest.raises(BagError, match="cannot read bag"):
        _read_all(bag)


def test_missing_unknown_and_empty_inputs(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such bag"):
        BagReader(tmp_path / "nope")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(BagError, match="unknown storage format"):
        BagReader(tmp_path / "x.txt")
    (tmp_path / "e.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="empty"):
        BagReader(tmp_path / "e.mcap")
    (tmp_path / "g.mcap").write_bytes(b"garbage" * 100)
    with pytest.raises(BagError, match="cannot read bag"):
        BagReader(tmp_path / "g.mcap")
    (tmp_path / "d").mkdir()
    with pytest.raises(BagError, match="not a bag"):
        BagReader(tmp_path / "d")
    bag = _good_bag(tmp_path, "sqlite3")
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text().replace("storage_identifier: sqlite3",
                                             "storage_identifier: foo"))
    with pytest.raises(BagError, match="cannot read bag"):
        BagReader(bag)
    db = tmp_path / "c.db3"
    sqlite3.connect(db).execute("CREATE TABLE x (a)").connection.commit()
    with pytest.raises(BagError, match="cannot read bag"):
        BagReader(db)


def test_a_file_named_bag_that_is_not_one_says_what_it_is(tmp_path: Path) -> None:
    """A rosbag2 file renamed .bag, a text file named .bag: an error naming what the file is
    (not a decoder's message such as "'utf-8' codec can't decode byte 0x89")."""
    for storage, suffix, what in (("sqlite3", ".db3", "an sqlite3 database"),
                                  ("mcap", ".mcap", "an MCAP file")):
        f = next(p for p in _good_bag(tmp_path, storage).iterdir() if p.suffix == suffix)
        renamed = tmp_path / f"{storage}.bag"
        f.rename(renamed)
        with pytest.raises(BagError) as e:
            BagReader(renamed)
        assert str(e.value) == (f"cannot read bag {renamed}: it is {what} (rosbag2 {suffix}), "
                                f"not a ROS 1 bag (.bag) as its name says (rename it to "
                                f"{storage}{suffix})")
    notes = tmp_path / "notes.bag"
    notes.write_text("topic: imu\nrate: 100\n")
    with pytest.raises(BagError, match=r"^cannot read bag .*notes\.bag: it is a text file "
                       r"\(starting 'topic: imu'\), not a ROS 1 bag \(\.bag\)$"):
        BagReader(notes)
    blob = tmp_path / "blob.db3"
    blob.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(BagError, match=r"it is not an sqlite3 database \(rosbag2 \.db3\) \(its "
                       r"first bytes .* are those of no bag format"):
        BagReader(blob)


def test_resolve_names_topics_and_types(tmp_path: Path) -> None:
    bag = _good_bag(tmp_path, "mcap")
    with BagReader(bag) as br:
        assert br.resolve("imu/data_raw", IMU) == "/imu/data_raw"
        with pytest.raises(BagError, match=r"IMU topic /imu/nope not in .* \(sensor_msgs/Imu "
                           r"topics: /imu/data_raw \([\d,]+ messages\)\)$"):
            br.resolve("imu/nope", IMU, role="IMU")
        with pytest.raises(BagError, match="is sensor_msgs/msg/MagneticField, expected"):
            br.resolve("/imu/mag", IMU)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_synthetic_bag_holds_the_simulation(tmp_path: Path, storage: str) -> None:
    sim = simulate("time_jump", duration=5.0, rate=100.0, mag_rate=25.0, seed=3)
    counts = write_bag(sim, tmp_path / "s", storage)
    assert counts == {"/imu/data_raw": 501, "/imu/mag": 125, "/imu/ground_truth": 501}
    want = sim_streams(sim)
    with BagReader(tmp_path / "s") as br:
        got = br.read(["/imu/data_raw", "/imu/mag", "/imu/ground_truth"])
        order = [t for t, _, _ in br.messages()]
    assert order[:3] == ["/imu/mag", "/imu/data_raw", "/imu/ground_truth"]
    for s in want.values():
        b = got[s.topic]
        assert b.raws == cdr.split_rows(s.rows) and b.log_ns.tolist() == s.log_ns.tolist()
    imu = cdr.decode(got["/imu/data_raw"].raws, cdr.IMU)
    np.testing.assert_array_equal(imu.fields["angular_velocity"], sim.gyr)
    assert np.all(np.diff(got["/imu/data_raw"].log_ns) > 0)
    assert (np.diff(imu.stamp_ns) < 0).sum() == 1  # the jump is in the stamps only
    truth = cdr.decode(got["/imu/ground_truth"].raws, cdr.QUATERNION_STAMPED)
    np.testing.assert_array_equal(truth.fields["quaternion"][:, 3], sim.quat[:, 0])
    np.testing.assert_array_equal(truth.stamp_ns, imu.stamp_ns)
    desc = read_description(tmp_path / "s")
    assert desc["scenario"] == "time_jump" and desc["time_jumps"][0][0] == 250


def test_mcap_fast_path_variants(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Messages of several lengths in one topic, files written by rosbags itself, and chunks
    without a message index (records walked) all read like rosbags reads them."""
    from mkf_ros.bags.mcap import McapFile

    stamps, rows = _rows(3000)
    other = cdr.split_rows(cdr.encode(cdr.IMU, stamps[:40] + 1, "a_longer_frame_id"))
    mixed = cdr.split_rows(rows[:2000]) + other
    times = np.concatenate([stamps[:2000], stamps[:40] + 1])
    path = tmp_path / "rb"
    with rosbag2.Writer(path, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as w:
        c = w.add_connection("/imu", IMU, typestore=TS)
        c2 = w.add_connection("/other", IMU, typestore=TS)
        for t, r in sorted(zip(times.tolist(), mixed, strict=True), key=lambda x: x[0]):
            w.write(c, t, r)
        w.write(c2, int(stamps[5]), bytes(rows[5]))
    ref = [(t, d) for topic, t, d in _rosbags_messages(path) if topic == "/imu"]
    for walk in (False, True):
        if walk:
            monkeypatch.setattr(McapFile, "_indexed_offsets", lambda *a: None)
        with BagReader(path) as br:
            got = br.read(["/imu", "/other"])
        assert got["/imu"].rows is None  # two lengths: a list of bytes
        assert got["/imu"].raws == [d for _, d in ref]
        assert got["/imu"].log_ns.tolist() == [t for t, _ in ref]
        assert got["/other"].raws == [bytes(rows[5])]



@pytest.mark.parametrize(("edit", "meaning"), [
    (lambda t: re.sub(r"\n(\s*)version: \d+", "\n", t, count=1),
     "metadata.yaml is incomplete or not rosbag2 metadata"),
    (lambda t: "5\n", "metadata.yaml is not rosbag2 metadata"),
    (lambda t: "- 1\n- 2\n", "metadata.yaml is not rosbag2 metadata"),
])
def test_corrupt_metadata_says_what_is_wrong_with_the_file(tmp_path: Path, edit: Any,
                                                           meaning: str) -> None:
    """A user must learn what is wrong with the file: these answered with the backend's internals
    only ("KeyError('version')", "'int' object is not subscriptable")."""
    bag = _good_bag(tmp_path, "sqlite3")
    meta = bag / "metadata.yaml"
    meta.write_text(edit(meta.read_text()))
    with pytest.raises(BagError) as e:
        _read_all(bag)
    assert str(e.value).startswith(f"cannot read bag {bag}: {meaning} (")
    assert "\n" not in str(e.value)
