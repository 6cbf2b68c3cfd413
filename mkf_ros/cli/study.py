"""``mkf study``: the paper's simulation study (``docs/math.md`` §7), with figures and summary.

Runs every selected cell (filter × chart × chart update/reset × R × rate) on N_s trajectories,
resumably, on all cores (or on a Dask cluster with ``--scheduler``), then writes ``cells.csv``,
the figures and ``summary.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

HELP = "reproduce the paper's simulation study (Figs. 5-7, speed) with CSV, figures and summary"

QUICK_N_S = 100


def _list(s: str) -> list[str]:
    return [x for x in (p.strip() for p in s.split(",")) if x]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mkf_ros.study import config as cfg
    from mkf_ros.study.sim import CONV_CAP

    g = parser.add_argument_group("size and output")
    g.add_argument("--n-s", type=int, default=None, metavar="N",
                   help="trajectories per cell (default 1000; 100 with --quick)")
    g.add_argument("--quick", action="store_true",
                   help=f"N_s = {QUICK_N_S}, every cell (default output mkf-study-quick/)")
    g.add_argument("--out", type=Path, default=None,
                   help="output folder (default mkf-study/ or mkf-study-quick/); a re-run "
                        "resumes the study found there")
    g.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    g.add_argument("--workers", type=int, default=None,
                   help="processes (default: number of cores)")
    g.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="run the work units on the Dask cluster of this scheduler "
                        "(tcp://HOST:8786) instead of local processes; needs mkf_ros[cluster] "
                        "and the same mkf_ros on every worker (docs/study/cluster.md)")
    g.add_argument("--cap", type=int, default=CONV_CAP,
                   help=f"convergence-phase cap in updates (default {CONV_CAP}, §8 item 12)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    s = parser.add_argument_group("cell selection (comma-separated lists)")
    s.add_argument("--filters", default=",".join(cfg.FILTERS), help="mekf,mukf")
    s.add_argument("--charts", default=",".join(cfg.CHARTS), help="o,rp,mrp,rv")
    s.add_argument("--updates", default=",".join(cfg.UPDATES),
                   help="cu (chart update), reset (no chart update)")
    s.add_argument("--R", dest="rs", default="1e-2,1e-4,1e-6",
                   help="sensor noise variances R (default 1e-2,1e-4,1e-6)")
    s.add_argument("--rates", default=",".join(f"{r:g}" for r in cfg.RATES_HZ),
                   help="update rates in Hz (default 2,5,10,50,100,500,1000)")
    s.add_argument("--mukf-scaling", default="published",
                   help="MUKF ω-noise scaling: published (Q_ω·Δt², the paper's figures), "
                        "consistent (Q_ω·Δt), or both (default published)")
    s.add_argument("--noise-sampling", default="sigma",
                   help="true noise levels: sigma (σ ~ U[0, √Q_max], default), variance "
                        "(Q ~ U[0, Q_max], the literal reading), or both (§8 item 11)")
    r = parser.add_argument_group("report")
    r.add_argument("--report-only", action="store_true",
                   help="do not simulate; rebuild figures and summary from --out")
    r.add_argument("--no-report", action="store_true", help="no figures and summary")
    r.add_argument("--speed", action=argparse.BooleanOptionalAction, default=None,
                   help="measure filter speeds (Fig. 4 analogue) for the summary (default: "
                        "when the whole selection is finished and none was measured yet)")
    r.add_argument("--docs", type=Path, default=None,
                   help="also write the summary as DIR/README.md with its figures in DIR/figures")


def _selection(args: argparse.Namespace) -> list:
    from mkf_ros.cli.main import CliError
    from mkf_ros.study import config as cfg
    from mkf_ros.study.sim import n_updates

    try:
        filters = cfg.validate(_list(args.filters), cfg.FILTERS, "filter")
        charts = cfg.validate(_list(args.charts), cfg.CHARTS, "chart")
        updates = cfg.validate(_list(args.updates), cfg.UPDATES, "update")
        scal = cfg.validate([args.mukf_scaling], (*cfg.SCALINGS, "both"), "MUKF scaling")[0]
        samp = cfg.validate([args.noise_sampling], (*cfg.SAMPLINGS, "both"), "noise sampling")[0]
    except ValueError as e:
        raise CliError(str(e)) from None
    rs: list[float] = []
    rates: list[float] = []
    for what, text, dest in (("R", args.rs, rs), ("rate", args.rates, rates)):
        for x in _list(text):
            try:
                v = float(x)
            except ValueError:
                raise CliError(f"{what} must be a number, got {x!r}") from None
            if not v > 0 or v == float("inf"):
                raise CliError(f"{what} must be positive and finite, got {x!r}")
            dest.append(v)
    for v in rates:
        if n_updates(v) < 1:
            raise CliError(f"rate {v:g} Hz gives no update in the 10 s estimation phase; "
                           "use at least 0.1 Hz")
    if not (filters and charts and updates and rs and rates):
        raise CliError("the selection is empty")
    return cfg.cells(filters, charts, updates, rs, rates,
                     cfg.SCALINGS if scal == "both" else (scal,),
                     cfg.SAMPLINGS if samp == "both" else (samp,))


def run(args: argparse.Namespace) -> int:
    from mkf_ros import parallel
    from mkf_ros.cli.main import CliError
    from mkf_ros.study import runner

    n_s = args.n_s if args.n_s is not None else (QUICK_N_S if args.quick else 1000)
    if n_s < 2:
        raise CliError(f"--n-s must be at least 2 (a standard deviation needs two runs), got {n_s}")
    if args.cap < 1:
        raise CliError(f"--cap must be at least 1, got {args.cap}")
    workers = args.workers if args.workers is not None else _cores()
    if workers < 1:
        raise CliError(f"--workers must be at least 1, got {workers}")
    out = args.out if args.out is not None else Path("mkf-study-quick" if args.quick
                                                     else "mkf-study")
    cells = _selection(args)
    interrupted = False
    try:
        if args.report_only:
            meta = runner.read_meta(out)
            n_s = int(meta["n_s"])
        else:
            runner.prepare_folder(out, args.seed, n_s, args.cap)  # errors before any output
            with contextlib.ExitStack() as stack:
                executor, where = None, f"{workers} worker(s)"
                if args.scheduler:
                    c = stack.enter_context(parallel.cluster(args.scheduler))
                    executor, workers = c.executor, c.threads
                    where = f"Dask cluster {args.scheduler} ({workers} worker threads)"
                print(f"mkf study: {len(cells)} cells x N_s = {n_s}, seed {args.seed}, "
                      f"{where} -> {out}/", file=sys.stderr)
                rep = runner.run_study(cells, n_s, args.seed, out, workers=workers,
                                       cap=args.cap, progress=not args.no_progress,
                                       command=_command(args, n_s, out), executor=executor)
            interrupted = rep.interrupted
            done = len(cells) - rep.pending
            print(f"mkf study: {done}/{len(cells)} cells finished ({rep.already} before, "
                  f"{len(rep.finished)} now) in {_hms(rep.elapsed_s)}"
                  + ("; interrupted - run the same command again to resume" if interrupted
                     else ""), file=sys.stderr)
        if not args.no_report and not interrupted:
            _report(args, out, cells, n_s)
    except (runner.StudyError, parallel.ClusterError) as e:
        raise CliError(str(e)) from None
    except OSError as e:
        raise CliError(f"{e.filename or out}: {e.strerror or e}") from None
    return 130 if interrupted else 0


def _report(args: argparse.Namespace, out: Path, cells: list, n_s: int) -> None:
    from mkf_ros.study import report

    rows = {k: r for k, r in report.load_rows(out).items()}
    complete = all(c.key in rows for c in cells)
    speed = args.speed if args.speed is not None else (
        complete and not (out / report.SPEED_NAME).exists())
    if speed:
        print("mkf study: measuring filter speeds (Fig. 4 analogue) ...", file=sys.stderr)
        report.measure_and_store_speed(out)
    t = time.perf_counter()
    written = report.write_report(out, docs=args.docs)
    print(f"mkf study: report in {_hms(time.perf_counter() - t)}: "
          + ", ".join(str(p) for p in written), file=sys.stderr)


def _command(args: argparse.Namespace, n_s: int, out: Path) -> str:
    """The canonical command line of this run (for the summary)."""
    from mkf_ros.study import config as cfg
    from mkf_ros.study.sim import CONV_CAP

    parts = ["mkf study", "--quick" if args.quick and args.n_s is None else f"--n-s {n_s}",
             f"--seed {args.seed}"]
    defaults = {"filters": ",".join(cfg.FILTERS), "charts": ",".join(cfg.CHARTS),
                "updates": ",".join(cfg.UPDATES), "rs": "1e-2,1e-4,1e-6",
                "rates": ",".join(f"{r:g}" for r in cfg.RATES_HZ), "mukf_scaling": "published",
                "noise_sampling": "sigma"}
    for k, d in defaults.items():
        v = getattr(args, k)
        if v != d:
            parts.append(f"--{'R' if k == 'rs' else k.replace('_', '-')} {v}")
    if args.cap != CONV_CAP:
        parts.append(f"--cap {args.cap}")
    if args.scheduler:
        parts.append(f"--scheduler {args.scheduler}")
    parts.append(f"--out {out}")
    return " ".join(parts)


def _cores() -> int:
    from mkf_ros.parallel import cores

    return cores()


def _hms(s: float) -> str:
    m, sec = divmod(round(s), 60)
    return f"{m} min {sec:02d} s" if m else f"{s:.1f} s"
