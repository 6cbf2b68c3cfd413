"""Overhead of running the study on a Dask cluster, and the study's wall time extrapolated.

    ./run bench cluster_overhead [--n-s 20] [--repeat 2] [--workers 2] [--json FILE]

Runs the cells of ``mkf study --quick`` (every cell of the default selection, 336) on ``--n-s``
trajectories each, through the one runner (:func:`mkf_ros.study.runner.run_study`) on three
executors, interleaved ``--repeat`` times (the best run counts: the machine is shared):

* ``serial``  — one process (the parent runs every unit);
* ``local``   — ``--workers`` forked processes (``mkf study --workers N``);
* ``dask``    — a real Dask cluster on 127.0.0.1: ``dask scheduler`` and ``--workers``
  ``dask worker --nthreads 1`` processes (``mkf study --scheduler``), started once, not timed.

Every run must give the same ``cells.csv`` (common random numbers), which is checked. Prints the
timing table (overhead of Dask relative to the local processes), the work units and their cost
distribution per rate (CPU s per unit), the serial part (time the parent spends writing results,
per unit), and the wall time of the full study at N_s = 10⁴ on 16/64/256 cores extrapolated from
those measurements (LPT list scheduling of the measured unit costs + the parent's serial work).
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any


def run_once(mode: str, cells: list, n_s: int, workers: int, out: Path, cluster: Any) -> dict:
    from mkf_ros.study import runner

    shutil.rmtree(out, ignore_errors=True)
    c0 = cpu_all(cluster)
    t0 = time.perf_counter()
    if mode == "serial":
        rep = runner.run_study(cells, n_s, 1, out, workers=1, progress=False)
    elif mode == "local":
        rep = runner.run_study(cells, n_s, 1, out, workers=workers, progress=False)
    else:
        rep = runner.run_study(cells, n_s, 1, out, workers=cluster.threads, progress=False,
                               executor=cluster.executor)
    wall = time.perf_counter() - t0
    cpu_total = cpu_all(cluster) - c0
    if rep.interrupted or rep.pending:
        sys.exit(f"{mode}: the study did not finish")
    return {"mode": mode, "wall_s": wall, "cpu_s": rep.cpu_s, "cpu_total_s": cpu_total,
            "parent_s": rep.parent_s,
            "units": [(u.rate_hz, cpu) for u, cpu in rep.unit_cpu_s],
            "csv": (out / runner.CSV_NAME).read_text()}


def cpu_all(cluster: Any) -> float:
    """CPU seconds so far of this process, its reaped children (the local worker processes)
    and every process of the Dask cluster (scheduler, nannies, workers): the work of a run
    whatever else the shared machine is doing, unlike its wall time."""
    import resource

    import psutil

    t = time.process_time()
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    t += ru.ru_utime + ru.ru_stime
    if cluster is not None:
        procs = [psutil.Process(p.pid) for p in (cluster.local.scheduler,
                                                 *cluster.local.workers.values())]
        for q in [*procs, *(c for p in procs for c in p.children(recursive=True))]:
            ct = q.cpu_times()
            t += ct.user + ct.system
    return t


def lpt_makespan(costs: list[float], cores: int) -> float:
    """Wall time of list scheduling ``costs`` (sorted longest first, as the runner submits them)
    on ``cores`` identical cores."""
    free = [0.0] * cores
    for c in sorted(costs, reverse=True):
        heapq.heapreplace(free, free[0] + c)
    return max(free)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-s", type=int, default=20, help="trajectories per cell (default 20; "
                    "the quick study is 100)")
    ap.add_argument("--repeat", type=int, default=2, help="interleaved repetitions (default 2)")
    ap.add_argument("--workers", type=int, default=2, help="local processes = Dask workers")
    ap.add_argument("--modes", default="serial,local,dask", help="subset of serial,local,dask")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    if args.n_s < 1 or args.repeat < 1 or args.workers < 1:
        ap.error("--n-s, --repeat and --workers must be at least 1")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or set(modes) - {"serial", "local", "dask"}:
        ap.error(f"--modes: choose from serial, local, dask, got {args.modes!r}")

    from mkf_ros import parallel
    from mkf_ros.kernels import warm_all
    from mkf_ros.study import config as cfg

    cells = cfg.cells()
    print(f"warming kernels (mkf_ros {warm_all()})", file=sys.stderr)
    tmp = Path(tempfile.mkdtemp(prefix="mkf-cluster-bench-"))
    runs: dict[str, list[dict]] = defaultdict(list)
    try:
        import contextlib

        with contextlib.ExitStack() as stack:
            cluster = None
            if "dask" in modes:
                t0 = time.perf_counter()
                lc = stack.enter_context(parallel.local_cluster(args.workers, tmp / "cluster"))
                cluster = stack.enter_context(parallel.cluster(lc.address))
                cluster.local = lc  # type: ignore[attr-defined]
                start_s = time.perf_counter() - t0
                print(f"Dask cluster {lc.address}: {cluster.threads} worker threads, started "
                      f"and connected in {start_s:.1f} s (not timed below)", file=sys.stderr)
            for i in range(args.repeat):
                for m in modes:
                    r = run_once(m, cells, args.n_s, args.workers, tmp / m, cluster)
                    runs[m].append(r)
                    print(f"  run {i + 1} {m:6s} {r['wall_s']:7.1f} s wall, "
                          f"{r['cpu_s']:7.1f} s CPU in units", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    ref = runs[modes[0]][0]["csv"]
    same = all(r["csv"] == ref for rs in runs.values() for r in rs)
    if not same:
        sys.exit("the executors gave different cells.csv: not a timing question any more")
    report(args, modes, runs, len(cells))


def report(args: argparse.Namespace, modes: list[str], runs: dict[str, list[dict]],
           n_cells: int) -> None:
    from mkf_ros.study import config as cfg

    n_units = len(runs[modes[0]][0]["units"])
    best = {m: min(runs[m], key=lambda r: r["wall_s"]) for m in modes}
    load = os.getloadavg()[0]
    print(f"\n{n_cells} cells x N_s = {args.n_s} = {n_units} work units "
          f"({cfg.CHUNK} trajectories each), {args.workers} workers, {os.cpu_count()} cores, "
          f"load average {load:.1f} at the end; best of {args.repeat} (all runs listed); "
          "identical cells.csv from every run\n")
    cpu_best = {m: min(r["cpu_total_s"] for r in runs[m]) for m in modes}
    print("| executor | wall (best) | wall, all runs | wall vs local | CPU in units | "
          "CPU of all processes (best) | CPU vs local | parent (serial) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for m in modes:
        b = best[m]
        rel = (f"{100 * (b['wall_s'] / best['local']['wall_s'] - 1):+.1f} %"
               if "local" in best else "")
        crel = (f"{100 * (cpu_best[m] / cpu_best['local'] - 1):+.1f} %"
                if "local" in best else "")
        every = ", ".join(f"{r['wall_s']:.1f}" for r in runs[m])
        print(f"| {m} | {b['wall_s']:.1f} s | {every} | {rel} | {b['cpu_s']:.1f} s | "
              f"{cpu_best[m]:.1f} s | {crel} | {b['parent_s']:.2f} s |")

    # cost distribution per rate (CPU s per unit, from every run of every mode)
    per_rate: dict[float, list[float]] = defaultdict(list)
    for m in modes:
        for rate, cpu in best[m]["units"]:
            per_rate[rate].append(cpu)
    total = sum(statistics.fmean(v) * (len(v) / len(modes)) for v in per_rate.values())
    print("\nwork units: one (rate, 5 trajectories) for every cell of that rate; CPU s per unit"
          " (all executors' best runs)\n")
    print("| rate Hz | units | cells per unit | CPU s / unit mean | min | max | share of CPU |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    n_rate = n_cells // len(per_rate)
    for rate in sorted(per_rate):
        v = per_rate[rate]
        mean = statistics.fmean(v)
        print(f"| {rate:g} | {len(v) // len(modes)} | {n_rate} | {mean:.2f} | {min(v):.2f} | "
              f"{max(v):.2f} | {100 * mean * len(v) / len(modes) / total:.1f} % |")

    # serial part: the parent's writing per unit (it runs beside the workers); Dask's
    # per-unit dispatch cost = (wall_dask - wall_local) * workers / units
    parent_per_unit = statistics.fmean(best[m]["parent_s"] / n_units for m in modes)
    dispatch = 0.0
    if "dask" in best and "local" in best:
        dispatch = max(0.0, (best["dask"]["wall_s"] - best["local"]["wall_s"])
                       * args.workers / n_units)
    serial_fraction = parent_per_unit / (total / n_units + parent_per_unit)
    print(f"\nserial part: the parent spends {1000 * parent_per_unit:.1f} ms per unit writing "
          f"its part file (serial fraction {100 * serial_fraction:.2f} % of the work); Dask "
          f"adds {1000 * dispatch:.0f} ms per unit on a worker (dask - local wall x workers / "
          "units)")

    # extrapolation: N_s = 1e4, same cells; unit cost per rate as measured
    n_s_full = 10_000
    scale_units = math.ceil(n_s_full / cfg.CHUNK)
    costs = [statistics.fmean(v) + dispatch for v in per_rate.values() for _ in
             range(scale_units)]
    cpu_full = sum(costs)
    serial_full = parent_per_unit * len(costs)
    print(f"\nfull study at N_s = 10^4 ({n_cells} cells): {len(costs):,} units, "
          f"{cpu_full / 3600:.1f} CPU h; the parent's serial work {serial_full / 60:.1f} min\n")
    print("| cores | LPT makespan of the units | parent (serial) | expected wall | speed-up |")
    print("|---:|---:|---:|---:|---:|")
    extra = {}
    for cores in (2, 16, 64, 256):
        mk = lpt_makespan(costs, cores)
        wall = max(mk, serial_full) + parent_per_unit  # the parent keeps up or limits
        extra[cores] = wall
        print(f"| {cores} | {mk / 60:.1f} min | {serial_full / 60:.1f} min | "
              f"{wall / 3600:.2f} h ({wall / 60:.0f} min) | {cpu_full / wall:.0f}x |")
    if args.json:
        from mkf_ros import files

        files.write_text(args.json, json.dumps({
            "n_s": args.n_s, "workers": args.workers, "units": n_units,
            "best": {m: {k: best[m][k] for k in ("wall_s", "cpu_s", "cpu_total_s", "parent_s")}
                     for m in modes},
            "all_wall_s": {m: [r["wall_s"] for r in runs[m]] for m in modes},
            "unit_cpu_s_mean": {str(k): statistics.fmean(v) for k, v in per_rate.items()},
            "parent_s_per_unit": parent_per_unit, "dask_dispatch_s_per_unit": dispatch,
            "full_wall_s": extra}, indent=1))


if __name__ == "__main__":
    main()
