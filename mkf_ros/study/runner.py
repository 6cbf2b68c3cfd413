"""Runs the study: work units on both cores, results kept cell by cell, resumable.

Layout of an output folder::

    study.json      seed, N_s, convergence cap and the log of runs (wall times)
    parts/*.npz     per-trajectory results of one work unit (the source of truth)
    cells.csv       one row per finished cell (derived from the parts)

A *work unit* is one (noise sampling, rate, chunk of trajectories) with the cells still needed
there. Its trajectories are simulated once and every filter variant × R of the unit runs on them
(common random numbers, see :mod:`mkf_ros.study.sim`). The parent process is the only writer;
every file is written to a temporary name and renamed, so an interrupted run leaves only whole
files and a re-run continues with the missing units.

The units run on a :class:`concurrent.futures.Executor` (:mod:`mkf_ros.parallel`): local worker
processes by default, or a Dask cluster's executor (``mkf study --scheduler``). Only the unit and
its results cross to the worker and back; what a unit computes depends on the unit alone, so the
numbers are the same wherever it ran.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import hashlib
import json
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros import files, parallel
from mkf_ros.study import config as cfg
from mkf_ros.study import sim
from mkf_ros.study.config import Cell
from mkf_ros.study.stats import agreement, cell_stats

CSV_NAME = "cells.csv"
META_NAME = "study.json"
PARTS = "parts"

CSV_FIELDS = (
    "filter", "chart", "update", "R", "rate_hz", "mukf_scaling", "noise_sampling", "n_s", "n_used",
    "mu_deg", "sigma_deg", "ci_lo_deg", "ci_hi_deg", "non_converged", "stalled", "crashed",
    "mu_all_deg", "conv_updates_mean", "published_deg", "published_ci_lo_deg",
    "published_ci_hi_deg", "rel_diff", "within_10pct", "ci_overlap",
)


class StudyError(Exception):
    """A user error (bad folder, mismatching settings): one line for the CLI."""


@dataclass(frozen=True)
class Unit:
    """One work unit: trajectories ``[t0, t1)`` of one (sampling, rate) for ``cells``."""

    sampling: str
    rate_hz: float
    t0: int
    t1: int
    cells: tuple[Cell, ...]
    seed: int
    cap: int

    @property
    def cost(self) -> float:
        return cfg.unit_cost(self.cells, self.t1 - self.t0)


@dataclass
class RunReport:
    """What one call of :func:`run_study` did."""

    finished: list[Cell] = field(default_factory=list)  # cells completed by this run
    already: int = 0  # selected cells that were complete before
    pending: int = 0  # selected cells still incomplete (interrupted)
    elapsed_s: float = 0.0
    cpu_s: float = 0.0  # CPU seconds of the finished units, summed over the workers
    interrupted: bool = False
    unit_cpu_s: list[tuple[Unit, float]] = field(default_factory=list)  # per finished unit
    parent_s: float = 0.0  # time the parent spent writing results (serial part of the run)


# --------------------------------------------------------------------------- signals
@contextlib.contextmanager
def deferred_sigint() -> Iterator[None]:
    """Hold Ctrl-C while results are written; raise it afterwards (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if caught:
        raise KeyboardInterrupt


@contextlib.contextmanager
def _sigint_noted() -> Iterator[list[int]]:
    """Ctrl-C behaves as usual, but is also recorded in the yielded list."""
    if threading.current_thread() is not threading.main_thread():
        yield []
        return
    noted: list[int] = []

    def handler(signum: int, frame: object) -> None:
        noted.append(signum)
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield noted
    finally:
        signal.signal(signal.SIGINT, old)


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    with files.atomic_path(path) as tmp:
        # numpy's stub types **kwds as if a key could be its `allow_pickle: bool` keyword
        np.savez(tmp, **arrays)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- folder and meta
def prepare_folder(out: Path, seed: int, n_s: int, cap: int) -> dict:
    """Create ``out`` (and ``parts/``), check it is writable and that an existing study there
    has the same seed, N_s and cap. Returns the metadata."""
    try:
        (out / PARTS).mkdir(parents=True, exist_ok=True)
        probe = out / f".write-probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise StudyError(f"cannot write to output folder {str(out)!r}: "
                         f"{e.strerror or e}") from None
    for stale in [*out.glob(f".*{files.TMP_MARK}*"), *(out / PARTS).glob(f".*{files.TMP_MARK}*")]:
        stale.unlink(missing_ok=True)  # left by a killed run; never a result
    meta_path = out / META_NAME
    want = {"seed": int(seed), "n_s": int(n_s), "conv_cap": int(cap)}
    if meta_path.exists():
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError) as e:
            raise StudyError(f"{meta_path} is unreadable ({e}); remove it or use another --out") \
                from None
        have = {k: meta.get(k) for k in want}
        if have != want:
            diff = ", ".join(f"{k} {have[k]} (asked {want[k]})" for k in want if have[k] != want[k])
            raise StudyError(f"{str(out)!r} holds a study with {diff}; use another --out")
        return meta
    meta = dict(want, runs=[])
    files.write_text(meta_path, json.dumps(meta, indent=1))
    return meta


def read_meta(out: Path) -> dict:
    path = Path(out) / META_NAME
    if not path.exists():
        raise StudyError(f"no study in {str(out)!r} (missing {META_NAME})")
    return json.loads(path.read_text())


# --------------------------------------------------------------------------- parts
class Parts:
    """Index of the per-trajectory results in ``parts/``: cell key → {t0: (t1, arrays)}."""

    def __init__(self, out: Path) -> None:
        self.dir = Path(out) / PARTS
        self.index: dict[str, dict[int, tuple[int, dict[str, np.ndarray]]]] = {}
        for path in sorted(self.dir.glob("*.npz")):
            with np.load(path) as z:
                self._add({k: z[k] for k in z.files})

    def _add(self, arrays: dict[str, np.ndarray]) -> None:
        t0, t1 = int(arrays["t0"]), int(arrays["t1"])
        for i, key in enumerate(arrays["keys"]):
            self.index.setdefault(str(key), {})[t0] = (t1, {
                "err": arrays["err"][i], "status": arrays["status"][i],
                "conv": arrays["conv"][i], "sigma_w": arrays["sigma_w"],
                "sigma_v": arrays["sigma_v"]})

    def has(self, key: str, t0: int) -> bool:
        return t0 in self.index.get(key, {})

    def complete(self, key: str, n_s: int) -> bool:
        ranges = self.index.get(key, {})
        if len(ranges) < -(-n_s // cfg.CHUNK):  # cheap test first: called for every unit
            return False
        return all(t0 in ranges for t0, _ in cfg.chunks(n_s))

    def write(self, unit: Unit, res: dict[str, np.ndarray]) -> None:
        keys = np.array([c.key for c in unit.cells])
        digest = hashlib.sha1("|".join(keys).encode()).hexdigest()[:10]
        name = (f"{unit.sampling}_f{round(unit.rate_hz * 1000):07d}_"
                f"t{unit.t0:06d}-{unit.t1:06d}_{digest}.npz")
        arrays = dict(keys=keys, t0=np.array(unit.t0), t1=np.array(unit.t1), **res)
        _save_npz(self.dir / name, **arrays)
        self._add(arrays)

    def arrays(self, cell: Cell, n_s: int) -> dict[str, np.ndarray]:
        """All trajectories of a complete cell, concatenated in trajectory order."""
        ranges = self.index[cell.key]
        parts = [ranges[t0][1] for t0, _ in cfg.chunks(n_s)]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


# --------------------------------------------------------------------------- CSV
def _fmt(x: float | int | bool | None) -> str:
    if x is None:
        return ""
    if isinstance(x, bool):
        return "1" if x else "0"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if not np.isfinite(x):
        return "nan"
    return f"{float(x):.6g}"


def cell_row(cell: Cell, arrays: dict[str, np.ndarray]) -> dict[str, str]:
    """The CSV row of a cell: statistics (docs/math.md §7.3), counts, the published value and
    agreement."""
    s = cell_stats(arrays["err"], arrays["status"], arrays["conv"])
    pub, pci = cell.published_deg, cell.published_ci_deg
    rel, within, overlap = agreement(s, pub, pci)
    row = {
        "filter": cell.filter, "chart": cell.chart, "update": cell.update,
        "R": f"{cell.r:.0e}", "rate_hz": f"{cell.rate_hz:g}", "mukf_scaling": cell.mukf_scaling,
        "noise_sampling": cell.sampling, "n_s": _fmt(s.n_s), "n_used": _fmt(s.n_used),
        "mu_deg": _fmt(s.mu), "sigma_deg": _fmt(s.sigma), "ci_lo_deg": _fmt(s.ci_lo),
        "ci_hi_deg": _fmt(s.ci_hi), "non_converged": _fmt(s.non_converged),
        "stalled": _fmt(s.stalled),
        "crashed": _fmt(s.crashed), "mu_all_deg": _fmt(s.mu_all),
        "conv_updates_mean": _fmt(s.conv_updates_mean), "published_deg": _fmt(pub),
        "published_ci_lo_deg": _fmt(pci[0] if pci else None),
        "published_ci_hi_deg": _fmt(pci[1] if pci else None),
        "rel_diff": _fmt(rel) if pub is not None else "",
        "within_10pct": _fmt(within) if pub is not None else "",
        "ci_overlap": _fmt(overlap) if pub is not None else "",
    }
    return row


def row_key(row: dict[str, str]) -> str:
    return row_cell(row).key


def row_cell(row: dict[str, str]) -> Cell:
    return Cell(row["filter"], row["chart"], row["update"], float(row["R"]),
                float(row["rate_hz"]), row["mukf_scaling"], row["noise_sampling"])


def read_rows(out: Path) -> dict[str, dict[str, str]]:
    """Rows of ``cells.csv`` by cell key (empty if there is none yet)."""
    path = Path(out) / CSV_NAME
    if not path.exists():
        return {}
    with open(path, newline="") as f:
        return {row_key(r): r for r in csv.DictReader(f)}


def write_rows(out: Path, rows: dict[str, dict[str, str]]) -> None:
    ordered = sorted(rows.values(), key=lambda r: row_cell(r).sort_key())
    lines: list[str] = []

    class _Sink:
        def write(self, s: str) -> None:
            lines.append(s)

    w = csv.DictWriter(_Sink(), fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    w.writerows(ordered)
    files.write_text(Path(out) / CSV_NAME, "".join(lines))


# --------------------------------------------------------------------------- work
def run_unit(unit: Unit) -> dict[str, np.ndarray]:
    """Simulate the unit's trajectories once and run all its variants × R on each."""
    specs, rs, variants = cfg.specs_array(unit.cells)
    n = unit.t1 - unit.t0
    nv, nr = specs.shape[0], rs.shape[0]
    err = np.empty((n, nv, nr))
    conv = np.empty((n, nv, nr), dtype=np.int64)
    status = np.empty((n, nv, nr), dtype=np.int8)
    sig_w = np.empty(n)
    sig_v = np.empty(n)
    dt = 1.0 / unit.rate_hz
    for i, traj in enumerate(range(unit.t0, unit.t1)):
        inp = sim.trajectory_inputs(unit.seed, unit.rate_hz, traj, unit.sampling)
        sig_w[i], sig_v[i] = inp["sigma_w"], inp["sigma_v"]
        sim.run_trajectory(specs, rs, dt, _convergence(inp, unit.cap), _truth(inp),
                           (err[i], conv[i], status[i]))
    vi = {v: k for k, v in enumerate(variants)}
    ri = {r: k for k, r in enumerate(rs.tolist())}
    idx = [(vi[c.variant], ri[c.r]) for c in unit.cells]
    return dict(
        err=np.degrees(np.stack([err[:, a, b] for a, b in idx])),
        conv=np.stack([conv[:, a, b] for a, b in idx]).astype(np.int32),
        status=np.stack([status[:, a, b] for a, b in idx]),
        sigma_w=sig_w, sigma_v=sig_v)


def _timed_unit(unit: Unit) -> tuple[Unit, dict[str, np.ndarray], float]:
    """Run a unit; also return the CPU seconds it took (robust to a busy machine)."""
    t = time.process_time()
    res = run_unit(unit)
    return unit, res, time.process_time() - t


def warm_up() -> None:
    """Compile (or load from the cache) the kernels before forking the workers."""
    inp = sim.trajectory_inputs(0, 10.0, 0, "sigma")
    specs = np.array([[sim.MEKF, 1, 1, 1], [sim.MUKF, 1, 1, 1]], dtype=np.int64)
    out = (np.empty((2, 1)), np.empty((2, 1), dtype=np.int64), np.empty((2, 1), dtype=np.int8))
    sim.run_trajectory(specs, np.array([1e-4]), 0.1, _convergence(inp, 3), _truth(inp), out)


def _convergence(inp: dict, cap: int) -> tuple:
    """The convergence phase's inputs of :func:`~mkf_ros.study.sim.run_trajectory`."""
    return inp["q0"], inp["sigma_v"], inp["conv_seed"], cap


def _truth(inp: dict) -> tuple:
    """The estimation phase's inputs of :func:`~mkf_ros.study.sim.run_trajectory`."""
    return inp["q_true"], inp["w_true"], inp["vref"], inp["vbody"], inp["z_noise"]


def plan(cells: Sequence[Cell], n_s: int, seed: int, cap: int, parts: Parts,
         done: Iterable[str]) -> list[Unit]:
    """The work units still needed for ``cells``: the groups of one (sampling, rate) in order of
    decreasing cost per trajectory, so that the last units are cheap and both workers finish
    together (longest-processing-time-first)."""
    done = set(done)
    groups: dict[tuple[str, float], list[Cell]] = {}
    for c in cells:
        if c.key not in done:
            groups.setdefault((c.sampling, c.rate_hz), []).append(c)
    units = []
    order = sorted(groups.items(), key=lambda kv: (-cfg.unit_cost(kv[1], 1), kv[0]))
    for (sampling, rate), group in order:
        for t0, t1 in cfg.chunks(n_s):
            need = tuple(c for c in group if not parts.has(c.key, t0))
            if need:
                units.append(Unit(sampling, rate, t0, t1, need, seed, cap))
    return units


def run_study(
    cells: Sequence[Cell], n_s: int, seed: int, out: Path | str, workers: int = 2,
    cap: int = sim.CONV_CAP, progress: bool = True,
    on_unit: Callable[[Unit], None] | None = None, command: str | None = None,
    executor: cf.Executor | None = None,
) -> RunReport:
    """Run (or resume) the study of ``cells`` with ``n_s`` trajectories each into ``out``.

    ``executor``: where the units run, e.g. a Dask cluster's (:func:`mkf_ros.parallel.connect`),
    with ``workers`` its number of parallel slots; the caller owns it. Default: ``workers`` local
    processes (the parent itself for one).
    ``on_unit`` is called in the parent after each finished unit (tests use it to interrupt);
    ``command`` is logged in ``study.json`` for the summary.
    A ``KeyboardInterrupt`` stops the workers; every finished unit and cell is kept and the
    report says ``interrupted``. A unit lost with its worker (a killed process, a vanished
    cluster node that Dask gave up on) stops the run after the running units finished, with a
    :class:`StudyError`; a re-run does the missing units.
    """
    out = Path(out)
    meta = prepare_folder(out, seed, n_s, cap)
    run = _StudyRun(out, n_s, {c.key: c for c in cells}, on_unit)
    run.resume()
    units = plan(list(run.selected.values()), n_s, seed, cap, run.parts, run.rows)
    run.pending = {c.key for u in units for c in u.cells}
    if progress and units:
        run.open_bar(sum(u.cost for u in units))
    try:
        run.execute(units, workers, executor)
    except KeyboardInterrupt:
        run.report.interrupted = True
    finally:
        run.close(meta, {"workers": workers, "units": len(units), "command": command})
    return run.report


@dataclass
class _StudyRun:
    """:func:`run_study`'s state: the selected cells, their rows and parts, the report, the
    cells still pending, the progress bar; its steps."""

    out: Path
    n_s: int
    selected: dict[str, Cell]
    on_unit: Callable[[Unit], None] | None
    rows: dict = field(init=False)
    parts: Parts = field(init=False)
    report: RunReport = field(default_factory=RunReport)
    pending: set[str] = field(default_factory=set)
    bar: Any = None
    lost: list[tuple[Unit, BaseException]] = field(default_factory=list)
    t_start: float = field(default_factory=time.perf_counter)

    def __post_init__(self) -> None:
        self.rows = read_rows(self.out)
        self.parts = Parts(self.out)

    def resume(self) -> None:
        """The rows of cells whose parts are complete but whose row is missing (a run killed
        between the two writes)."""
        self.report.already = sum(1 for k in self.selected if k in self.rows)
        for c in self.selected.values():
            if c.key not in self.rows and self.parts.complete(c.key, self.n_s):
                self.rows[c.key] = cell_row(c, self.parts.arrays(c, self.n_s))
                self.report.finished.append(c)
        if self.report.finished:
            write_rows(self.out, self.rows)

    def open_bar(self, total: float) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, unit="", unit_scale=False,
                        bar_format="{desc} {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]"
                                   " {postfix}", desc="mkf study", dynamic_ncols=True)
        self._bar_cells()

    def _bar_cells(self) -> None:
        self.bar.set_postfix_str(f"cells {len(self.rows.keys() & self.selected.keys())}/"
                                 f"{len(self.selected)}")

    def finish(self, unit: Unit, res: dict[str, np.ndarray], cpu: float) -> None:
        """A unit's results in: its part file, and the rows of the cells it completed."""
        t_parent = time.perf_counter()
        self.report.cpu_s += cpu
        self.report.unit_cpu_s.append((unit, cpu))
        with deferred_sigint():  # the part file and the CSV rows are written as a whole
            self.parts.write(unit, res)
            new = [c for c in unit.cells
                   if c.key in self.pending and self.parts.complete(c.key, self.n_s)]
            for c in new:
                self.rows[c.key] = cell_row(c, self.parts.arrays(c, self.n_s))
                self.pending.discard(c.key)
                self.report.finished.append(c)
            if new:
                write_rows(self.out, self.rows)
        self.report.parent_s += time.perf_counter() - t_parent
        if self.bar is not None:
            self.bar.update(unit.cost)
            self._bar_cells()
        if self.on_unit is not None:
            self.on_unit(unit)

    def failed(self, unit: Unit, e: BaseException) -> bool:
        self.lost.append((unit, e))
        return False  # submit no more; the running units still finish and are kept

    def execute(self, units: list[Unit], workers: int, executor: cf.Executor | None) -> None:
        """Run ``units`` on ``executor`` (default: ``workers`` local processes, the kernels
        warmed before forking); a unit lost with its worker is a :class:`StudyError` once the
        running ones finished."""
        ex = executor
        if units and ex is None:
            with _sigint_noted() as noted:
                try:
                    warm_up()  # before forking: the workers inherit the kernels
                except Exception:
                    if noted:  # Ctrl-C inside numba's compiler can surface as another error
                        raise KeyboardInterrupt from None
                    raise
            n = min(workers, len(units))
            ex = parallel.InlineExecutor() if n <= 1 else parallel.local_pool(n)
        if units and ex is not None:
            try:
                parallel.run_in_order(ex, _timed_unit, units, 2 * max(1, workers),
                                      lambda u, r: self.finish(*r), self.failed)
            except BaseException:
                if executor is None:
                    parallel.stop_now(ex)
                raise
            if executor is None:
                ex.shutdown(wait=True)
        if self.lost:
            bug = next((e for _, e in self.lost if not parallel.is_worker_loss(e)), None)
            if bug is not None:
                raise bug
            e = self.lost[0][1]
            raise StudyError(f"{len(self.lost)} work unit(s) lost with their worker "
                             f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
                             "; the finished units are kept - run the same command again to "
                             "resume")

    def close(self, meta: dict, run: dict[str, Any]) -> None:
        """The bar closed, the report completed and the run logged in ``study.json``
        (``run``: its workers, units and command)."""
        if self.bar is not None:
            self.bar.close()
        report = self.report
        report.elapsed_s = time.perf_counter() - self.t_start
        report.pending = len(self.pending)
        meta.setdefault("runs", []).append({
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "elapsed_s": round(report.elapsed_s, 1), "cpu_s": round(report.cpu_s, 1),
            "workers": run["workers"], "units": run["units"],
            "cells_finished": len(report.finished), "cells_selected": len(self.selected),
            "interrupted": report.interrupted, "command": run["command"]})
        files.write_text(self.out / META_NAME, json.dumps(meta, indent=1))
