"""``mkf process BAG [BAG ...] --out DIR``: many bags in parallel, locally (``--jobs``) or on a
Dask cluster (``--scheduler``), one progress bar over the bags and a summary table.

Every bag goes through the one-bag :func:`mkf_ros.bags.process.process_bag` with the same
options (:mod:`mkf_ros.bags.batch`); ``DIR/NAME`` is its output bag, ``DIR/NAME.png`` its plot
(bags with ground truth) and ``DIR/summary.csv`` the table. A bag that fails is reported in the
table and the others still finish; the exit code is then 1.
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import sys
from pathlib import Path
from typing import Any


def wanted(args: argparse.Namespace) -> bool:
    """Several bags, a folder of bags, or ``--jobs``/``--scheduler``: the batch mode.
    One bag without those keeps the one-bag behaviour (``--out`` is the output bag)."""
    from mkf_ros.bags.batch import is_folder_of_bags

    return (len(args.bags) > 1 or args.jobs is not None or args.scheduler is not None
            or is_folder_of_bags(Path(args.bags[0])))


def _jobs(args: argparse.Namespace, out: Path,
          params: dict[str, Any]) -> tuple[list[Any], list[str]]:
    from mkf_ros.bags.batch import BagJob, find_bags
    from mkf_ros.cli.main import CliError

    try:
        pairs = find_bags(args.bags, exclude=out)
    except Exception as e:
        raise CliError(str(e)) from None
    options = dict(imu_topic=args.imu_topic, mag_topic=args.mag_topic,
                   truth_topic=args.truth_topic, output_topic=args.output_topic,
                   storage=args.storage, overwrite=args.overwrite, copy_input=args.copy_input,
                   skip=args.skip, smooth=args.smooth, smooth_window=args.smooth_window,
                   smooth_overlap=args.smooth_overlap)
    jobs, names, existing = [], [], []
    for bag, name in pairs:
        dest = out.resolve() / name
        if dest == bag.resolve() or bag.resolve() in dest.parents:
            raise CliError(f"--out {out} would write {dest} over or into the input {bag}")
        if dest.exists() and not args.overwrite:
            existing.append(dest)
        jobs.append(BagJob(bag=str(bag.resolve()), out=str(dest),
                           plot=None if args.no_plot else str(dest) + ".png",
                           params=params, options=options))
        names.append(name.as_posix())
    if existing:
        more = f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""
        raise CliError(f"{existing[0]}{more} already exists (use --overwrite to replace)")
    return jobs, names


def run(args: argparse.Namespace, params: dict[str, Any]) -> int:
    from mkf_ros import parallel
    from mkf_ros.bags.batch import run_batch, summary_csv, summary_table
    from mkf_ros.cli.main import CliError
    from mkf_ros.files import write_text

    if args.storage not in ("mcap", "sqlite3"):
        raise CliError(f"unknown storage {args.storage!r} (choose from mcap, sqlite3)")
    if args.plot:
        raise CliError("--plot names one file; with several bags each plot is DIR/NAME.png "
                       "(or use --no-plot)")
    if args.jobs is not None and args.jobs < 1:
        raise CliError(f"--jobs must be at least 1, got {args.jobs}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file; with several bags it must be a folder")
    if (out / "metadata.yaml").is_file():
        raise CliError(f"--out {out} is a bag; with several bags it must be a folder")
    jobs, names = _jobs(args, out, params)
    try:
        for j in jobs:
            Path(j.out).parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CliError(f"cannot write to {out}: {e.strerror or e}") from None

    from tqdm import tqdm

    failed = 0
    with contextlib.ExitStack() as stack:
        if args.scheduler:
            try:
                c = stack.enter_context(parallel.cluster(args.scheduler))
            except parallel.ClusterError as e:
                raise CliError(str(e)) from None
            executor, slots = c.executor, c.threads
            where = f"Dask cluster {args.scheduler} ({slots} worker threads)"
        else:
            slots = min(args.jobs if args.jobs is not None else parallel.cores(), len(jobs))
            from mkf_ros.core.params import BY_NAME
            from mkf_ros.kernels import INSTALLED_PARTS, warmup

            # before forking: the workers inherit the kernels (the smoothers' compiled on
            # their first use)
            warmup((*INSTALLED_PARTS, "smoother") if args.smooth else INSTALLED_PARTS,
                   algorithms=(params.get("algorithm", BY_NAME["algorithm"].default),))
            # one forked process per bag: a bag that crashes its process fails alone
            executor = parallel.ForkPerUnit(slots)
            where = f"{slots} process(es)"
        print(f"mkf process: {len(jobs)} bags, {where} -> {out}/", file=sys.stderr)
        bar = stack.enter_context(tqdm(total=len(jobs), unit="bag", desc="mkf process",
                                       file=sys.stderr, dynamic_ncols=True,
                                       disable=True if args.quiet else None))

        def done(s: Any) -> None:
            nonlocal failed
            failed += not s.ok
            bar.update(1)
            if failed:
                bar.set_postfix_str(f"{failed} failed")

        try:
            summaries = run_batch(jobs, executor, 2 * slots, done)
        except BaseException:
            if not args.scheduler:
                parallel.stop_now(executor)
                _remove_partial(jobs)
            raise
    # a worker that died while writing could not remove its temporary folder (every other
    # failure does): no unit is running any more, so remove them here
    _remove_partial([j for j, s in zip(jobs, summaries, strict=True) if not s.ok])
    print(summary_table(summaries, names))
    write_text(out / "summary.csv", summary_csv(summaries, names))
    ok = sum(s.ok for s in summaries)
    print(f"{len(summaries)} bags: {ok} processed, {len(summaries) - ok} failed -> {out}/ "
          f"(table: {out / 'summary.csv'})")
    return 0 if ok == len(summaries) else 1


def _remove_partial(jobs: list[Any]) -> None:
    """Temporary folders of the bags the stopped workers were writing (never a result)."""
    for j in jobs:
        out = Path(j.out)
        for tmp in out.parent.glob(f".{out.name}.partial-*"):
            shutil.rmtree(tmp, ignore_errors=True)
