"""Peak memory and throughput of ``mkf process`` (and ``mkf synth``) against recording length.

    ./run bench stream_memory [--minutes 2 10 60] [--synth-minutes 2 10 60] [--dir DIR]
                              [--reference CMD] [--smooth [MODE ...]]

For each duration, writes an input bag at 1 kHz IMU, 100 Hz magnetometer and 1 kHz ground
truth (``wiener`` motion: one minute simulated once, then tiled with shifted stamps and log
times, written as it goes, so the set-up itself stays small; not timed), then runs
``mkf process BAG --out OUT --use-mag --no-plot --quiet`` as a child process under
``/usr/bin/time -v`` and prints a table: duration, IMU messages, peak RSS of the child, wall
time, IMU messages/s. ``--synth-minutes`` times ``mkf synth wiener --rate 1000 --mag-rate 100``
the same way (``--synth-scenario``, ``--synth-args`` for other options; seed 7), the
messages/s being IMU messages (all messages: IMU + magnetometer + ground truth, also listed).
``--reference CMD`` runs another ``mkf`` (e.g. a checkout of main: ``"env PYTHONPATH=DIR
python -m mkf_ros.cli.main"``) on the same bags or with the same synth options, and the output
bags are compared message by message (topic, log time, bytes). ``--smooth`` also runs
``mkf process --smooth MODE`` (the fixed-interval smoother, bounded memory) on each bag.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def tiled_bag(path: Path, minutes: float) -> int:
    """A wiener recording of ``minutes`` (one simulated minute, repeated); IMU messages."""
    from mkf_ros.bags.synth import CUSTOM_KEY, DEFAULT_START_NS, interleave, sim_streams
    from mkf_ros.bags.writer import BagWriter
    from mkf_ros.sim import simulate

    tile = min(60.0, minutes * 60.0)
    sim = simulate("wiener", duration=tile - 1e-3, rate=1000.0, mag_rate=100.0, seed=7)
    n_tiles = round(minutes * 60.0 / tile)
    n = 0
    with BagWriter(path, "mcap", overwrite=True) as w:
        conns = None
        for k in range(n_tiles):
            st = sim_streams(sim, start_ns=DEFAULT_START_NS + round(k * tile * 1e9))
            order = [st["imu"], st["mag"], st["truth"]]
            if conns is None:
                conns = [w.add_topic(s.topic, s.msgtype) for s in order]
                w._w.set_custom_data(CUSTOM_KEY, "{}")
            which, t, raws = interleave([order[i] for i in (1, 0, 2)])
            w.write_batch(np.array([conns[i].id for i in (1, 0, 2)])[which], t, raws)
            n += len(st["imu"].log_ns)
    return n


def timed(cmd: list[str]) -> tuple[float, float, str]:
    """Run ``cmd`` under /usr/bin/time -v: (peak RSS MB, wall s, stdout)."""
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    p = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, env=env)
    if p.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr[-3000:]}")
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr).group(1))
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", p.stderr)
    parts = [float(x) for x in wall.group(1).split(":")]
    sec = sum(v * 60 ** i for i, v in enumerate(reversed(parts)))
    return rss / 1024, sec, p.stdout


def digest(bag: Path) -> dict[str, tuple[str, int]]:
    """Per topic: sha256 over (log time, bytes) of every message, and the count."""
    from mkf_ros.bags import BagReader

    out: dict[str, tuple[str, int]] = {}
    with BagReader(bag) as br:
        for topic in sorted(br.topics):
            h, ht, n = hashlib.sha256(), hashlib.sha256(), 0  # bytes, log times
            for win in br.read_windows([topic], 200_000):
                b = win[topic]
                ht.update(b.log_ns.astype("<i8").tobytes())
                for r in b.raws:
                    h.update(len(r).to_bytes(4, "little") + r)
                n += len(b)
            out[topic] = (h.hexdigest() + ht.hexdigest(), n)
    return out


def synth_counts(text: str) -> dict[str, int]:
    """Messages per topic from ``mkf synth``'s report."""
    return {t: int(k.replace(",", "")) for t, k in
            re.findall(r"^\s+(/\S+)\s+([\d,]+) messages$", text, re.M)}


def read_description(bag: Path) -> object:
    from mkf_ros.bags.synth import read_description as rd

    return rd(bag)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="*", default=[2, 10, 60])
    ap.add_argument("--synth-minutes", type=float, nargs="*", default=[2, 10, 60])
    ap.add_argument("--synth-scenario", default="wiener", help="scenario (default wiener)")
    ap.add_argument("--synth-args", default="", metavar="ARGS",
                    help="more mkf synth options, e.g. '--split-accel 4 --storage sqlite3'")
    ap.add_argument("--dir", type=Path, default=None, help="work folder (default: a temp dir)")
    ap.add_argument("--reference", default=None, metavar="CMD",
                    help="another mkf to compare outputs with (e.g. main's); for synth the "
                    "messages (per topic: sha-256 of log times and of CDR bytes) and the "
                    "bag's description (custom_data) are compared")
    ap.add_argument("--smooth", nargs="*", default=None, choices=("rts", "two-way"),
                    metavar="MODE", help="also time mkf process --smooth MODE (rts, two-way; "
                    "none given: rts) on each bag, beside the causal run")
    args = ap.parse_args()
    mkf = [sys.executable, "-m", "mkf_ros.cli.main"]
    work = args.dir or Path(tempfile.mkdtemp(prefix="stream_memory-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for m in args.minutes:
            bag = work / f"in_{m:g}min"
            n = tiled_bag(bag, m)
            out = work / f"out_{m:g}min"
            shutil.rmtree(out, ignore_errors=True)
            rss, wall, _ = timed([*mkf, "process", str(bag), "--out", str(out), "--use-mag",
                                  "--no-plot", "--quiet"])
            rows.append(("process", m, n, rss, wall, 0))
            print(f"process {m:g} min: {n:,} IMU msgs, {rss:,.0f} MB, {wall:.1f} s", flush=True)
            for mode in ([] if args.smooth is None else args.smooth or ["rts"]):
                sm = work / f"smooth_{m:g}min"
                shutil.rmtree(sm, ignore_errors=True)
                rss_s, wall_s, _ = timed([*mkf, "process", str(bag), "--out", str(sm),
                                          "--use-mag", "--no-plot", "--quiet", "--smooth",
                                          mode])
                rows.append((f"process --smooth {mode}", m, n, rss_s, wall_s, 0))
                print(f"process --smooth {mode} {m:g} min: {rss_s:,.0f} MB, {wall_s:.1f} s",
                      flush=True)
                shutil.rmtree(sm, ignore_errors=True)
            if args.reference:
                ref = work / f"ref_{m:g}min"
                shutil.rmtree(ref, ignore_errors=True)
                rss_r, wall_r, _ = timed([*args.reference.split(), "process", str(bag), "--out",
                                          str(ref), "--use-mag", "--no-plot", "--quiet"])
                same = digest(ref) == digest(out)
                print(f"  reference: {rss_r:,.0f} MB, {wall_r:.1f} s; output messages "
                      f"{'IDENTICAL' if same else 'DIFFERENT'}", flush=True)
                shutil.rmtree(ref, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)
            shutil.rmtree(bag, ignore_errors=True)
        for m in args.synth_minutes:
            out = work / f"synth_{m:g}min"
            shutil.rmtree(out, ignore_errors=True)
            synth = ["synth", args.synth_scenario, "--rate", "1000", "--mag-rate", "100",
                     "--duration", f"{m * 60:g}", "--seed", "7", *args.synth_args.split()]
            rss, wall, text = timed([*mkf, *synth, "--out", str(out)])
            counts = synth_counts(text)
            n = counts.get("/imu/data_raw", counts.get("/imu/gyro", 0))
            rows.append(("synth", m, n, rss, wall, sum(counts.values())))
            print(f"synth {m:g} min: {sum(counts.values()):,} msgs ({n:,} IMU), {rss:,.0f} MB, "
                  f"{wall:.1f} s", flush=True)
            if args.reference:
                ref = work / f"synth_ref_{m:g}min"
                shutil.rmtree(ref, ignore_errors=True)
                rss_r, wall_r, _ = timed([*args.reference.split(), *synth, "--out", str(ref)])
                d_out, d_ref = digest(out), digest(ref)
                same = d_out == d_ref
                desc = read_description(out) == read_description(ref)
                print(f"  reference: {rss_r:,.0f} MB, {wall_r:.1f} s; output messages "
                      f"{'IDENTICAL' if same else 'DIFFERENT'}, description "
                      f"{'identical' if desc else 'DIFFERENT'}", flush=True)
                for topic, (h, k) in sorted(d_out.items()):
                    print(f"    {topic:<20} {k:>9,} msgs  sha256 {h[:16]}…{h[64:80]}…  "
                          f"{'=' if d_ref.get(topic) == (h, k) else '≠'} reference")
                shutil.rmtree(ref, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)
    finally:
        if args.dir is None:
            shutil.rmtree(work, ignore_errors=True)
    print("\n| command | duration | IMU messages | all messages | peak RSS | wall s "
          "| IMU messages/s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for what, m, n, rss, wall, total in rows:
        print(f"| `mkf {what}` | {m:g} min | {n:,} | {f'{total:,}' if total else ''} | "
              f"{rss:,.0f} MB | {wall:.1f} | {n / wall:,.0f} |")


if __name__ == "__main__":
    main()
