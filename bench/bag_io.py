"""Bag I/O options on one long MCAP bag: the hand-written MCAP reader/writer
(``mkf_ros.bags.mcap``), the ``mcap`` PyPI library and rosbags' own MCAP storage.

    ./run bench bag_io [--minutes 10] [--dir DIR]

Writes the input (1 kHz IMU, 100 Hz magnetometer, 1 kHz ground truth; as
``bench/stream_memory.py``), then for each option, in a child process under
``/usr/bin/time -v``: **read** every message of the three topics (log time and CDR bytes), and
**write** the IMU messages as a new bag (uncompressed chunks). Prints messages/s, MB/s and the
child's peak RSS.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

TOPICS = ["/imu/data_raw", "/imu/mag", "/imu/ground_truth"]


def _mcap_file(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def read_handwritten(bag: Path) -> tuple[int, int]:
    from mkf_ros.bags import BagReader

    n = size = 0
    with BagReader(bag) as br:
        for win in br.read_windows(TOPICS, 50_000):
            for b in win.values():
                n += len(b)
                size += b.rows.size if b.rows is not None else sum(map(len, b.raws))
    return n, size


def read_mcap_library(bag: Path) -> tuple[int, int]:
    from mcap.reader import make_reader

    n = size = 0
    with _mcap_file(bag).open("rb") as f:
        for _, _, m in make_reader(f).iter_messages(topics=TOPICS, log_time_order=True):
            n += 1
            size += len(m.data)
    return n, size


def read_rosbags(bag: Path) -> tuple[int, int]:
    from rosbags.rosbag2 import Reader

    n = size = 0
    with Reader(bag) as r:
        conns = [c for c in r.connections if c.topic in TOPICS]
        for _, _, raw in r.messages(connections=conns):
            n += 1
            size += len(raw)
    return n, size


def _imu(bag: Path):  # type: ignore[no-untyped-def]
    from mkf_ros.bags import BagReader

    with BagReader(bag) as br:
        return br.read(["/imu/data_raw"])["/imu/data_raw"]


def write_handwritten(bag: Path, out: Path) -> tuple[int, int]:
    from mkf_ros.bags import cdr
    from mkf_ros.bags.writer import BagWriter

    b = _imu(bag)
    t0 = time.perf_counter()
    with BagWriter(out, "mcap") as w:
        c = w.add_topic("/imu/data", cdr.IMU.msgtype)
        for a in range(0, len(b), 50_000):
            w.write_batch(c, b.log_ns[a:a + 50_000], b.rows[a:a + 50_000])
    print(f"write-only {time.perf_counter() - t0:.3f}")
    return len(b), b.rows.size


def write_mcap_library(bag: Path, out: Path) -> tuple[int, int]:
    from mcap.writer import CompressionType, Writer

    from mkf_ros.bags.reader import _typestore

    b = _imu(bag)
    raws = b.raws
    t0 = time.perf_counter()
    out.mkdir()
    with (out / "out.mcap").open("wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start("ros2", "bench")
        ts = _typestore()
        from rosbags.typesys.msg import get_types_from_msg  # noqa: F401  (typestore import)

        sid = w.register_schema("sensor_msgs/msg/Imu", "ros2msg",
                                ts.generate_msgdef("sensor_msgs/msg/Imu")[0].encode())
        cid = w.register_channel("/imu/data", "cdr", sid)
        for t, raw in zip(b.log_ns.tolist(), raws, strict=True):
            w.add_message(cid, log_time=t, data=raw, publish_time=t)
        w.finish()
    print(f"write-only {time.perf_counter() - t0:.3f}")
    return len(raws), sum(map(len, raws))


def write_rosbags(bag: Path, out: Path) -> tuple[int, int]:
    from rosbags.rosbag2 import StoragePlugin, Writer

    from mkf_ros.bags import cdr
    from mkf_ros.bags.reader import _typestore

    b = _imu(bag)
    raws = b.raws
    t0 = time.perf_counter()
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/imu/data", cdr.IMU.msgtype, typestore=_typestore())
        for t, raw in zip(b.log_ns.tolist(), raws, strict=True):
            w.write(c, t, raw)
    print(f"write-only {time.perf_counter() - t0:.3f}")
    return len(raws), sum(map(len, raws))


OPTIONS = {"read hand-written (mkf_ros.bags.mcap)": read_handwritten,
           "read mcap library": read_mcap_library,
           "read rosbags (its MCAP storage)": read_rosbags,
           "write hand-written (mkf_ros.bags.mcap)": write_handwritten,
           "write mcap library": write_mcap_library,
           "write rosbags (its MCAP storage)": write_rosbags}


def child(name: str, bag: Path, out: Path) -> None:
    fn = OPTIONS[name]
    t0 = time.perf_counter()
    n, size = fn(bag, out) if name.startswith("write") else fn(bag)  # type: ignore[operator]
    print(f"result {n} {size} {time.perf_counter() - t0:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--dir", type=Path, default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--bag", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.bag, args.dir)
        return
    sys.path.insert(0, str(Path(__file__).parent))
    from stream_memory import tiled_bag, timed

    work = args.dir or Path(tempfile.mkdtemp(prefix="bag_io-"))
    work.mkdir(parents=True, exist_ok=True)
    bag = work / "in"
    try:
        shutil.rmtree(bag, ignore_errors=True)
        tiled_bag(bag, args.minutes)
        mb = _mcap_file(bag).stat().st_size / 1e6
        print(f"input: {args.minutes:g} min, {mb:,.0f} MB MCAP\n")
        print("| option | messages | wall s | messages/s | MB/s | peak RSS |")
        print("| --- | ---: | ---: | ---: | ---: | ---: |")
        for name in OPTIONS:
            out = work / "out"
            shutil.rmtree(out, ignore_errors=True)
            rss, _, text = timed([sys.executable, __file__, "--child", name, "--bag", str(bag),
                                  "--dir", str(out)])
            n, size, sec = text.split("result ")[1].split()
            w = [ln for ln in text.splitlines() if ln.startswith("write-only")]
            el = float(w[0].split()[1]) if w else float(sec)  # writes: the writing alone
            print(f"| {name} | {int(n):,} | {el:.2f} | {int(n) / el:,.0f} | "
                  f"{int(size) / 1e6 / el:,.0f} | {rss:,.0f} MB |", flush=True)
            shutil.rmtree(out, ignore_errors=True)
    finally:
        if args.dir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
