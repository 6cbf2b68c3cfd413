"""Throughput of ``mkf process`` end to end (read, filter, write; plots excluded).

    ./run bench process_speed [--imu 200000] [--storage mcap sqlite3] [--chart rp] [--repeat 3]

Synthesises a bag (IMU 200 Hz, magnetometer 50 Hz, ground truth; not timed), warms the
kernels, then times ``mkf process BAG --out OUT --no-plot`` in this process, with and without
the magnetometer, and prints one table row per run (the best of ``--repeat``, which matters on
a shared machine): wall time, IMU messages per second, and the stages (read + decode, filter =
``StreamAdapter.process``, encode + write). Two reference rows
show what bounds the pipeline: the same bag with the filter replaced by nothing (I/O only) and
``mkf_ros.estimate`` (the core's batch loop) on the same arrays.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def _bag(tmp: Path, n_imu: int, storage: str) -> tuple[Path, object]:
    from mkf_ros.bags.synth import write_bag
    from mkf_ros.sim import simulate

    rate = 200.0
    sim = simulate("slow_rotation", duration=(n_imu - 1) / rate, rate=rate, mag_rate=50.0,
                   substeps=1, seed=1)
    path = tmp / f"in_{storage}"
    write_bag(sim, path, storage)
    return path, sim


def _cli(bag: Path, out: Path, storage: str, extra: list[str]) -> tuple[float, str]:
    from mkf_ros.cli.main import main

    shutil.rmtree(out, ignore_errors=True)
    buf = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(buf):
        code = main(["process", str(bag), "--out", str(out), "--storage", storage,
                     "--no-plot", "--quiet", *extra])
    el = time.perf_counter() - t0
    if code != 0:
        sys.exit(f"mkf process failed ({code}): {buf.getvalue()}")
    return el, buf.getvalue()


def _io_only(bag: Path, out: Path, storage: str) -> float:
    """Read + decode IMU/mag/truth, encode imu/data from the input rows, write: no filter."""
    from mkf_ros.bags import BagReader, BagWriter, cdr

    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    with BagReader(bag) as br:
        b = br.read(["/imu/data_raw", "/imu/mag", "/imu/ground_truth"])
    imu = cdr.decode(b["/imu/data_raw"].data, cdr.IMU)
    cdr.decode(b["/imu/mag"].data, cdr.MAGNETIC_FIELD)
    cdr.decode(b["/imu/ground_truth"].data, cdr.QUATERNION_STAMPED)
    rows = imu.rows.copy()
    n = len(rows)
    cdr.set_fields(rows, cdr.IMU, orientation=np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
                   orientation_covariance=np.zeros((n, 9)))
    with BagWriter(out, storage) as w:
        w.write_batch(w.add_topic("imu/data", cdr.IMU.msgtype), b["/imu/data_raw"].log_ns, rows)
    return time.perf_counter() - t0


def _estimate(sim: Any, use_mag: bool, args: argparse.Namespace) -> float:
    import mkf_ros

    t0 = time.perf_counter()
    mkf_ros.estimate(sim.gyr, sim.acc, sim.mag if use_mag else None, timestamps=sim.t,
                     algorithm=args.algorithm, chart=args.chart)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--imu", type=int, default=200_000, help="IMU messages (default 200000)")
    ap.add_argument("--storage", nargs="+", default=["mcap", "sqlite3"],
                    choices=["mcap", "sqlite3"])
    ap.add_argument("--algorithm", default="mekf", choices=["mekf", "mukf"])
    ap.add_argument("--chart", default="rp", choices=["o", "rp", "mrp", "rv"])
    ap.add_argument("--repeat", type=int, default=3, help="runs of each row, the best kept")
    args = ap.parse_args()
    import mkf_ros

    t0 = time.perf_counter()
    mkf_ros.warmup()
    print(f"kernels ready in {time.perf_counter() - t0:.1f} s; {args.algorithm.upper()}-"
          f"{args.chart.upper()}, {args.imu:,} IMU messages at 200 Hz + magnetometer 50 Hz + "
          "ground truth per bag\n")
    rows = []
    filt = ["--algorithm", args.algorithm, "--chart", args.chart]
    with tempfile.TemporaryDirectory(prefix="mkf_bench_") as d:
        tmp = Path(d)
        for storage in args.storage:
            bag, sim = _bag(tmp, args.imu, storage)
            mb = sum(f.stat().st_size for f in bag.iterdir()) / 1e6
            for use_mag in (True, False):
                flag = "--use-mag" if use_mag else "--no-use-mag"
                el, text = min(_cli(bag, tmp / "out", storage, [*filt, flag])
                               for _ in range(args.repeat))
                m = re.search(r"read ([\d.]+), filter ([\d.]+) .*write ([\d.]+)", text)
                stages = " / ".join(m.groups()) if m else "?"
                rows.append((f"mkf process ({storage}, {mb:.0f} MB), use_mag "
                             f"{str(use_mag).lower()}", el, args.imu / el, stages))
            el = min(_io_only(bag, tmp / "out3", storage) for _ in range(args.repeat))
            rows.append((f"I/O only, no filter ({storage})", el, args.imu / el, "-"))
        for use_mag in (True, False):
            el = min(_estimate(sim, use_mag, args) for _ in range(args.repeat))
            rows.append((f"core batch mkf_ros.estimate, use_mag {str(use_mag).lower()}", el,
                         args.imu / el, "-"))
    w = max(len(r[0]) for r in rows)
    print(f"| {'run':<{w}} | wall s | IMU msgs/s | read / filter / write s |")
    print(f"|{'-' * (w + 2)}|-------:|-----------:|------------------------:|")
    for name, el, rate, stages in rows:
        print(f"| {name:<{w}} | {el:6.2f} | {rate:10,.0f} | {stages:>23} |")


if __name__ == "__main__":
    main()
