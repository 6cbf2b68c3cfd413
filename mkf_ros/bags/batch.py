"""Many bags at once (``mkf process BAG [BAG ...] --out DIR``): a layer over the one-bag
:func:`mkf_ros.bags.process.process_bag`, which it calls unchanged for every bag.

Each bag is one work unit, run on an executor from :mod:`mkf_ros.parallel` (local processes or a
Dask cluster); the largest bags go first. A unit writes only its own output bag (atomically, see
:class:`mkf_ros.bags.writer.BagWriter`) and plot, and returns a small :class:`BagSummary`;
a bag that fails becomes a summary with its one-line error and the others go on.
On a cluster the workers read the inputs and write the outputs themselves, so the paths must be
the same on every worker (a shared file system); they are made absolute here.
"""

from __future__ import annotations

import concurrent.futures as cf
import csv
import io
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mkf_ros.bags.reader import STORAGE_SUFFIXES, BagError

#: adapter counters that count traffic, not events (left out of the events column)
NOT_EVENTS = ("imu_received", "mag_received", "mag_fused")


def events(counters: Mapping[str, int]) -> dict[str, int]:
    """The counters worth reporting: everything that happened besides normal traffic."""
    return {k: v for k, v in counters.items() if v and k not in NOT_EVENTS}


# --------------------------------------------------------------------------- finding bags
def is_folder_of_bags(path: Path) -> bool:
    """True for a directory that is not itself one bag: a bag directory has ``metadata.yaml``
    or (as :class:`~mkf_ros.bags.reader.BagReader` accepts) exactly one .mcap/.db3 file and
    nothing else that could be a bag."""
    if not path.is_dir() or (path / "metadata.yaml").is_file():
        return False
    entries = [p for p in path.iterdir() if not p.name.startswith(".")]
    storage = [p for p in entries if p.is_file() and p.suffix in (".mcap", ".db3")]
    others = [p for p in entries if p.is_dir() or p.suffix == ".bag"]
    return not (len(storage) == 1 and not others)


def _bags_below(folder: Path, exclude: Path | None) -> list[Path]:
    found: list[Path] = []
    for root, dirs, files in os.walk(folder):
        here = Path(root)
        if exclude is not None and here.resolve() == exclude:
            dirs[:] = []
            continue
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))  # hidden: partial outputs
        if (here / "metadata.yaml").is_file() and here != folder:
            found.append(here)
            dirs[:] = []
            continue
        if here != folder and not is_folder_of_bags(here):
            found.append(here)  # a directory holding one storage file, as the reader takes it
            dirs[:] = []
            continue
        found += [here / f for f in sorted(files)
                  if Path(f).suffix in STORAGE_SUFFIXES and not f.startswith(".")]
    return found


def find_bags(inputs: Iterable[str | Path], exclude: str | Path | None = None
              ) -> list[tuple[Path, Path]]:
    """``(bag, output name)`` for every bag in ``inputs``.

    A bag (rosbag2 directory, .mcap, .db3 or ROS 1 .bag file) stands for itself and is named by
    its stem; a folder of bags stands for every bag below it (``exclude``, the output folder, is
    skipped), named by its path below the folder without the suffix. :class:`BagError` for an
    input that does not exist, a folder without bags, or two bags with the same name.
    """
    excl = Path(exclude).resolve() if exclude is not None else None
    pairs: list[tuple[Path, Path]] = []
    for item in inputs:
        p = Path(item)
        if not p.exists():
            raise BagError(f"no such bag or folder: {p}")
        if is_folder_of_bags(p):
            below = _bags_below(p, excl)
            if not below:
                raise BagError(f"no bag in folder {p} (looked for rosbag2 directories and "
                               ".mcap, .db3, .bag files)")
            pairs += sorted(((b, b.relative_to(p).with_suffix("") if b.is_file()
                              else b.relative_to(p)) for b in below), key=lambda bn: bn[1])
        else:
            pairs.append((p, Path(p.stem if p.is_file() else p.name)))
    seen: dict[Path, Path] = {}
    for bag, name in pairs:
        if name in seen:
            raise BagError(f"{seen[name]} and {bag} would both be written as {name}; "
                           "process them into different --out folders")
        seen[name] = bag
    return pairs


# --------------------------------------------------------------------------- one bag
@dataclass(frozen=True)
class BagJob:
    """One bag to process: absolute paths and the keyword arguments of ``process_bag``."""

    bag: str
    out: str
    plot: str | None  #: plot path (drawn when the bag has ground truth), None: no plot
    params: dict[str, Any]
    options: dict[str, Any]

    @property
    def size(self) -> int:
        """Bytes on disk (the cost estimate that orders the work, largest first)."""
        p = Path(self.bag)
        try:
            if p.is_dir():
                return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
            return p.stat().st_size
        except OSError:
            return 0


@dataclass
class BagSummary:
    """What processing one bag gave (small: this is what a worker sends back)."""

    bag: str
    out: str
    error: str | None = None
    n_imu: int = 0
    n_mag: int = 0
    n_out: int = 0
    events: dict[str, int] = field(default_factory=dict)
    rmse: dict[str, float] | None = None  #: degrees: total, heading, inclination
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    plot: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def plot_result(r: Any, bag: str | Path, path: str | Path) -> Path:
    """The accuracy plot of a scored :class:`~mkf_ros.bags.process.ProcessResult` (errors over
    time, intervals of a synthetic bag shaded), written atomically to ``path``."""
    from mkf_ros.evaluation.plots import accuracy_figure

    s, p = r.scores, r.params
    title = (f"{Path(bag).name}: {p['algorithm'].upper()}-{p['chart'].upper()}, "
             f"use_mag {str(p['use_mag']).lower()}")
    return accuracy_figure(path, s.t, s.q_est, s.q_true, s.errors, title=title,
                           intervals=s.intervals, rmse=s.rmse, envelope=s.envelope)


def process_job(job: BagJob) -> BagSummary:
    """Process one bag; any failure becomes the summary's one-line ``error`` (never raised)."""
    from mkf_ros.bags.process import process_bag

    t0 = time.perf_counter()
    res = BagSummary(bag=job.bag, out=job.out)
    try:
        r = process_bag(job.bag, job.out, job.params, **job.options)
        res.n_imu, res.n_mag, res.n_out = r.n_imu, r.n_mag, r.n_out
        res.events, res.notes = events(r.counters), list(r.notes)
        if r.scores is not None:
            res.rmse = {k: float(v) for k, v in r.scores.rmse.items()}
            if job.plot:
                res.plot = str(plot_result(r, job.bag, job.plot))
    except (BagError, ValueError, OSError) as e:
        res.error = str(e)
    except Exception as e:  # anything else: this bag fails, the batch goes on
        res.error = f"{type(e).__name__}: {e}"
    res.seconds = time.perf_counter() - t0
    return res


# --------------------------------------------------------------------------- many bags
def run_batch(jobs: Sequence[BagJob], executor: cf.Executor, in_flight: int,
              on_done: Callable[[BagSummary], None] | None = None) -> list[BagSummary]:
    """Process ``jobs`` on ``executor`` (largest bag first, ``in_flight`` at a time); the
    summaries in the order of ``jobs``. A bag whose worker died is reported as failed."""
    from mkf_ros import parallel

    results: dict[int, BagSummary] = {}
    order = sorted(range(len(jobs)), key=lambda i: -jobs[i].size)

    def done(item: tuple[int, BagJob], s: BagSummary) -> None:
        results[item[0]] = s
        if on_done is not None:
            on_done(s)

    def failed(item: tuple[int, BagJob], e: BaseException) -> bool:
        msg = str(e).splitlines()[0] if str(e) else ""
        if isinstance(e, parallel.WorkerDied):  # this bag's own process crashed
            error = msg
        else:
            why = "its worker died" if parallel.is_worker_loss(e) else "failed"
            error = f"{why} ({type(e).__name__}{': ' + msg if msg else ''})"
        done(item, BagSummary(bag=item[1].bag, out=item[1].out, error=error))
        return True

    parallel.run_in_order(executor, _process_item, [(i, jobs[i]) for i in order], in_flight,
                          done, failed)
    return [results[i] for i in range(len(jobs))]


def _process_item(item: tuple[int, BagJob]) -> BagSummary:
    return process_job(item[1])


# --------------------------------------------------------------------------- report
def _rmse_text(r: dict[str, float] | None) -> str:
    if not r:
        return "-"
    return " / ".join(f"{r[k]:.3f}" if math.isfinite(r[k]) else "nan"
                      for k in ("total", "heading", "inclination"))


def summary_table(summaries: Sequence[BagSummary], names: Sequence[str]) -> str:
    """The per-bag table ``mkf process`` prints for several bags."""
    head = ("bag", "IMU msgs", "mag msgs", "outputs", "RMSE° total / heading / incl.", "s",
            "events")
    rows = []
    for name, s in zip(names, summaries, strict=True):
        if s.ok:
            ev = ", ".join(f"{k} {v}" for k, v in s.events.items()) or "-"
            rows.append((name, f"{s.n_imu:,}", f"{s.n_mag:,}", f"{s.n_out:,}",
                         _rmse_text(s.rmse), f"{s.seconds:.1f}", ev))
        else:
            rows.append((name, "FAILED", "", "", "", f"{s.seconds:.1f}", s.error or ""))
    w = [max(len(str(r[i])) for r in (head, *rows)) for i in range(len(head) - 1)]
    right = (False, True, True, True, True, True)

    def line(r: tuple) -> str:
        cells = [str(c).rjust(w[i]) if right[i] else str(c).ljust(w[i])
                 for i, c in enumerate(r[:-1])]
        return "  ".join(cells) + "  " + str(r[-1])

    return "\n".join([line(head), *(line(r) for r in rows)])


def summary_csv(summaries: Sequence[BagSummary], names: Sequence[str]) -> str:
    """The same as CSV (``DIR/summary.csv``): one row per bag."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["bag", "input", "output", "ok", "error", "imu_msgs", "mag_msgs", "outputs",
                "rmse_total_deg", "rmse_heading_deg", "rmse_inclination_deg", "seconds",
                "events"])
    for name, s in zip(names, summaries, strict=True):
        r = s.rmse or {}
        w.writerow([name, s.bag, s.out if s.ok else "", int(s.ok), s.error or "", s.n_imu,
                     s.n_mag, s.n_out, *(f"{r[k]:.6g}" if k in r else ""
                                         for k in ("total", "heading", "inclination")),
                     f"{s.seconds:.3f}", ";".join(f"{k}={v}" for k, v in s.events.items())])
    return buf.getvalue()
