"""Accuracy on real recordings with optical ground truth: our MEKF/MUKF against VQF, x-io Fusion,
Madgwick and Mahony, all on the same samples, in one run.

    ./run bench real_data DATASET_DIR [DATASET_DIR ...] [--only NAME] [--filter-params k=v ...]

e.g. ``./run bench real_data ../shared/eval-data/repoimu/TStick ../shared/eval-data/ese650``.
Each folder's format is detected from its content (:mod:`mkf_ros.datasets`: RepoIMU T-stick CSV,
ESE650 raw ``.mat``). Prints per recording and per dataset the total / heading / inclination RMSE
in degrees (BROAD metric, :mod:`mkf_ros.scoring`; RepoIMU after one constant global alignment
applied identically to every algorithm; ESE650 inclination only), then a summary table with the
targets of issue 6. Our filters run with the defaults of :data:`mkf_ros.core.params.PARAMS`
unless ``--filter-params`` overrides them (validated like every other front end).

Peers, as in ``eval-data/README.md``: ``vqf`` (VQF, causal, and the acausal offline VQF for
reference), ``imufusion`` (x-io Fusion), ``ahrs`` (Madgwick 9D; on datasets without a
magnetometer Madgwick 6D and Mahony with k_P = 1, k_I = 0.3 — ``ahrs`` is pure Python and slow),
plus plain gyro integration from the first accelerometer tilt. Peers that
output NWU (imufusion, ahrs) are rotated to ENU by prepending ``[cos 45°, 0, 0, sin 45°]``.
Peers take a fixed sample period: they get the mean one, (t[-1] − t[0]) / (N − 1); ours gets the
timestamps. ``--time-base median`` instead replaces every recording's stamps by a regular grid at
the *median* period for every algorithm (ours included). On ESE650 the median period (9.6 ms) is
4 % shorter than the true mean one (10.0 ms: the stamps alternate 9.5 / 10.6 ms), which scales
every gyro reading by 0.96 and happens to offset that board's uncalibrated, ~5 % high gyro
sensitivity; the peer figures in ``eval-data/README.md`` were measured that way.

The data are not in the repository and not used by the tests (no licence stated).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import multiprocessing as mp
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.core.params import BY_NAME
from mkf_ros.core.quaternion import qmul_np
from mkf_ros.datasets import ALL_ERRORS, Recording, read_dataset
from mkf_ros.scoring import dataset_mean, score_recording

#: NWU → ENU: rotation by +90° about the up axis, prepended to a sensor → NWU quaternion.
Q_ENU_FROM_NWU = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])

#: Parameters the benchmark sets per column (they cannot be overridden globally).
FIXED_BY_BENCH = ("algorithm", "use_mag")

#: Targets of issue 6 (mean over the dataset, degrees, default parameters).
TARGETS = {
    "repoimu": [("9D", "total", "vqf 9D", 3.02), ("9D", "inclination", None, 2.5)],
    "ese650": [("6D", "inclination", None, 2.6)],
}


# ----------------------------------------------------------------------------------- algorithms
@dataclass(frozen=True)
class Algo:
    """One column: ``run(rec, dim, overrides)`` returns (N, 4) sensor → ENU quaternions."""

    name: str  # e.g. "mekf"; the column is f"{name} {dim}"
    dims: tuple[str, ...]  # "6D", "9D"
    run: Callable[[Recording, str, dict[str, Any]], np.ndarray]
    only_6d_datasets: bool = False  # run only where there is no magnetometer
    note: str = ""


def _ours(algorithm: str) -> Callable[[Recording, str, dict[str, Any]], np.ndarray]:
    def run(rec: Recording, dim: str, overrides: dict[str, Any]) -> np.ndarray:
        import mkf_ros

        mag = rec.mag if dim == "9D" else None
        res = mkf_ros.estimate(rec.gyr, rec.acc, mag, timestamps=rec.t, algorithm=algorithm,
                               use_mag=dim == "9D", **overrides)
        return res.quat
    return run


def _period(rec: Recording) -> float:
    """The fixed sample period given to the peers: the mean one, (t[-1] − t[0]) / (N − 1)."""
    return float((rec.t[-1] - rec.t[0]) / (len(rec) - 1))


def _c(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


def _vqf(rec: Recording, dim: str, _o: dict[str, Any]) -> np.ndarray:
    from vqf import VQF

    f = VQF(_period(rec))
    if dim == "9D":
        return f.updateBatch(_c(rec.gyr), _c(rec.acc), _c(rec.mag))["quat9D"]
    return f.updateBatch(_c(rec.gyr), _c(rec.acc))["quat6D"]


def _vqf_offline(rec: Recording, dim: str, _o: dict[str, Any]) -> np.ndarray:
    from vqf import offlineVQF

    mag = _c(rec.mag) if dim == "9D" else None
    out = offlineVQF(_c(rec.gyr), _c(rec.acc), mag, _period(rec))
    return out["quat9D" if dim == "9D" else "quat6D"]


def _fusion(rec: Recording, dim: str, _o: dict[str, Any]) -> np.ndarray:
    """x-io Fusion with its own defaults (``Ahrs()``, NWU, gain 0.5), deg/s and g in."""
    import imufusion

    ahrs = imufusion.Ahrs()
    ahrs.set_sample_period(_period(rec))
    gdeg = np.degrees(rec.gyr)
    ag = rec.acc / 9.80665
    n = len(rec)
    out = np.empty((n, 4))
    if dim == "9D":
        mag = _c(rec.mag)
        for i in range(n):
            ahrs.update(gdeg[i], ag[i], mag[i])
            out[i] = ahrs.get_quaternion()
    else:
        for i in range(n):
            ahrs.update_no_magnetometer(gdeg[i], ag[i])
            out[i] = ahrs.get_quaternion()
    return qmul_np(Q_ENU_FROM_NWU, out)


def _madgwick(rec: Recording, dim: str, _o: dict[str, Any]) -> np.ndarray:
    """``ahrs`` Madgwick with its default gains (0.033 IMU, 0.041 MARG); output NWU."""
    from ahrs.filters import Madgwick

    kw: dict[str, Any] = {"mag": _c(rec.mag)} if dim == "9D" else {}
    q = Madgwick(gyr=_c(rec.gyr), acc=_c(rec.acc), frequency=1.0 / _period(rec), **kw).Q
    return qmul_np(Q_ENU_FROM_NWU, q)


def _mahony(rec: Recording, dim: str, _o: dict[str, Any]) -> np.ndarray:
    """``ahrs`` Mahony, k_P = 1, k_I = 0.3 (the best peer on ESE650); output NWU."""
    from ahrs.filters import Mahony

    kw: dict[str, Any] = {"mag": _c(rec.mag)} if dim == "9D" else {}
    q = Mahony(gyr=_c(rec.gyr), acc=_c(rec.acc), frequency=1.0 / _period(rec), k_P=1.0,
               k_I=0.3, **kw).Q
    return qmul_np(Q_ENU_FROM_NWU, q)


def _gyro_only(rec: Recording, _dim: str, _o: dict[str, Any]) -> np.ndarray:
    """Tilt from the first accelerometer sample, then the gyro integrated (no correction)."""
    a = rec.acc[0] / np.linalg.norm(rec.acc[0])
    ax = np.cross(a, [0.0, 0.0, 1.0])
    s = float(np.linalg.norm(ax))
    ang = math.atan2(s, float(a[2]))
    q0, q1, q2, q3 = (math.cos(ang / 2), *(ax / s * math.sin(ang / 2))) if s > 1e-12 \
        else (1.0, 0.0, 0.0, 0.0)
    rv = rec.gyr[:-1] * np.diff(rec.t)[:, None]  # rotation vectors of the steps (body frame)
    th = np.linalg.norm(rv, axis=1)
    half = 0.5 * th
    k = np.where(th > 1e-12, np.sin(half) / np.where(th > 1e-12, th, 1.0), 0.5)
    steps = np.column_stack([np.cos(half), rv * k[:, None]]).tolist()
    out = np.empty((len(rec), 4))
    out[0] = q0, q1, q2, q3
    for i, (p0, p1, p2, p3) in enumerate(steps, start=1):  # q ⊗ dq, plain floats (fast)
        q0, q1, q2, q3 = (q0 * p0 - q1 * p1 - q2 * p2 - q3 * p3,
                          q0 * p1 + q1 * p0 + q2 * p3 - q3 * p2,
                          q0 * p2 - q1 * p3 + q2 * p0 + q3 * p1,
                          q0 * p3 + q1 * p2 - q2 * p1 + q3 * p0)
        n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        q0, q1, q2, q3 = q0 / n, q1 / n, q2 / n, q3 / n
        out[i] = q0, q1, q2, q3
    return out


ALGOS: tuple[Algo, ...] = (
    Algo("mekf", ("6D", "9D"), _ours("mekf")),
    Algo("mukf", ("6D", "9D"), _ours("mukf")),
    # the seed report's baselines (issue 7, mkf_ros.core.baselines), through the same sensor layer
    Algo("euler_kf", ("6D", "9D"), _ours("euler_kf"), note="report §II, fixed"),
    Algo("euler_ukf", ("6D", "9D"), _ours("euler_ukf"), note="report §III, fixed"),
    Algo("madgwick-ours", ("6D", "9D"), _ours("madgwick"), note="mkf_ros Madgwick, beta 0.041"),
    Algo("vqf", ("6D", "9D"), _vqf, note="vqf 2.1.2, causal"),
    Algo("vqf-offline", ("6D", "9D"), _vqf_offline, note="acausal (uses the future): reference"),
    Algo("fusion", ("6D", "9D"), _fusion, note="imufusion 1.3.3 defaults"),
    Algo("madgwick", ("9D",), _madgwick, note="ahrs 0.4.0 defaults"),
    Algo("madgwick", ("6D",), _madgwick, only_6d_datasets=True, note="ahrs 0.4.0 defaults "
         "(6D only where there is no magnetometer: pure Python, slow)"),
    Algo("mahony", ("6D",), _mahony, only_6d_datasets=True, note="ahrs 0.4.0, k_P=1, k_I=0.3"),
    Algo("gyro-only", ("6D",), _gyro_only, note="first-sample tilt + gyro integration"),
)


def columns(has_mag: bool, patterns: list[str] | None) -> list[tuple[Algo, str]]:
    """The (algorithm, dim) columns for a dataset, filtered by fnmatch ``patterns``."""
    cols = []
    for a in ALGOS:
        if a.only_6d_datasets and has_mag:
            continue
        for d in a.dims:
            if d == "9D" and not has_mag:
                continue
            label = f"{a.name} {d}"
            if patterns and not any(fnmatch.fnmatch(label, p) for p in patterns):
                continue
            cols.append((a, d))
    return cols


# ----------------------------------------------------------------------------------- running
def _task(args: tuple[int, Recording, list[str] | None, dict[str, Any], float]
          ) -> tuple[int, str, dict[str, dict[str, float]], dict[str, float]]:
    """Run every column on one recording; returns scores per column and CPU seconds."""
    idx, rec, patterns, overrides, skip = args
    scores: dict[str, dict[str, float]] = {}
    secs: dict[str, float] = {}
    for algo, dim in columns(rec.has_mag, patterns):
        label = f"{algo.name} {dim}"
        t0 = time.perf_counter()
        try:
            q = algo.run(rec, dim, overrides)
        except ImportError as e:
            scores[label] = {"error": f"not installed: {e.name}"}  # type: ignore[dict-item]
            continue
        secs[label] = time.perf_counter() - t0
        scores[label] = score_recording(rec, np.asarray(q, dtype=float), skip)
    return idx, rec.name, scores, secs


def _warm() -> None:
    import mkf_ros

    mkf_ros.warmup()


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``k=v`` strings → validated filter parameters (``Param.validate``; lists as
    comma-separated numbers)."""
    out: dict[str, Any] = {}
    for it in items:
        if "=" not in it:
            raise SystemExit(f"--filter-params: expected NAME=VALUE, got {it!r}")
        k, v = (s.strip() for s in it.split("=", 1))
        p = BY_NAME.get(k)
        if p is None or p.scope != "filter":
            known = ", ".join(n for n, q in BY_NAME.items() if q.scope == "filter")
            raise SystemExit(f"--filter-params: unknown filter parameter {k!r}; known: {known}")
        if k in FIXED_BY_BENCH:
            raise SystemExit(f"--filter-params: {k} is set per column by the benchmark "
                             "(use --algorithms to choose columns)")
        val: Any = [x for x in v.replace("[", "").replace("]", "").split(",") if x.strip()] \
            if p.type is list else v
        try:
            out[k] = p.validate(val)
        except ValueError as e:
            raise SystemExit(f"--filter-params: {e}") from None
    return out


def _git_state() -> str:
    root = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty"],
                             capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    return rev or "unknown"


# ----------------------------------------------------------------------------------- printing
def _f(x: float) -> str:
    return "—" if not np.isfinite(x) else f"{x:.2f}"


def print_dataset(fmt: str, folder: str, recs: list[Recording],
                  results: dict[str, dict[str, dict[str, float]]],
                  cols: list[str]) -> dict[str, dict[str, float]]:
    """Per-recording tables (one per meaningful error kind) and the dataset means."""
    kinds = [k for k in ALL_ERRORS if any(k in r.errors for r in recs)]
    incl = [r for r in recs if not r.excluded]
    excl = [r for r in recs if r.excluded]
    print(f"\n## {fmt}: {folder} — {len(incl)} recordings in the mean"
          + (f", {len(excl)} excluded ({', '.join(r.name for r in excl)})" if excl else ""))
    notes = [f"{r.name}: {r.note}" for r in recs if r.note]
    for n in notes:
        print(f"   note: {n}")
    means: dict[str, dict[str, float]] = {}
    for c in cols:
        rows = [results[r.name][c] for r in incl if "error" not in results[r.name].get(c, {})]
        means[c] = dataset_mean(rows) if len(rows) == len(incl) else \
            {k: float("nan") for k in ALL_ERRORS}
    w = max(len(r.name) for r in recs) + 2
    cw = max(8, *(len(c) for c in cols))
    for k in kinds:
        print(f"\n{k} RMSE [deg]")
        print(f"| {'recording':<{w}} | " + " | ".join(f"{c:>{cw}}" for c in cols) + " |")
        print(f"|{'-' * (w + 2)}|" + "|".join("-" * (cw + 1) + ":" for _ in cols) + "|")
        for group, rs in (("", incl), ("excluded: ", excl)):
            for r in rs:
                cells = [_f(results[r.name].get(c, {}).get(k, float("nan"))) for c in cols]
                print(f"| {group + r.name:<{w}} | " + " | ".join(f"{x:>{cw}}" for x in cells)
                      + " |")
            if not group:
                print(f"| {'**mean**':<{w}} | "
                      + " | ".join(f"{_f(means[c][k]):>{cw}}" for c in cols) + " |")
    return means


def print_summary(all_means: list[tuple[str, int, dict[str, dict[str, float]]]]) -> None:
    """Dataset × algorithm table and the issue-6 targets."""
    print("\n## Summary: mean RMSE over each dataset [deg] (total / heading / inclination)\n")
    print("| dataset | recordings | algorithm | total | heading | inclination |")
    print("|---|---:|---|---:|---:|---:|")
    for fmt, n, means in all_means:
        for c, m in means.items():
            print(f"| {fmt} | {n} | {c} | {_f(m['total'])} | {_f(m['heading'])} | "
                  f"{_f(m['inclination'])} |")
    print("\n## Issue 6 targets (default parameters unless --filter-params was given)\n")
    for fmt, _n, means in all_means:
        for dim, kind, peer, nominal in TARGETS.get(fmt, []):
            bound = nominal
            src = f"{nominal:.2f} (fixed)"
            if peer is not None:
                pv = means.get(peer, {}).get(kind, float("nan"))
                bound = pv if np.isfinite(pv) else nominal
                src = f"{peer} measured here {_f(pv)} (README {nominal:.2f})"
            for ours in ("mekf", "mukf"):
                v = means.get(f"{ours} {dim}", {}).get(kind, float("nan"))
                if not np.isfinite(v):
                    continue
                ok = "PASS" if v < bound else "FAIL"
                print(f"- {fmt} {dim} mean {kind}: {ours} {v:.2f} < {src}: {ok}")


# ----------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("datasets", nargs="+", metavar="DATASET_DIR",
                    help="dataset folders (format detected from the content)")
    ap.add_argument("--only", action="append", default=None, metavar="NAME",
                    help="only recordings whose name contains NAME (repeatable)")
    ap.add_argument("--filter-params", nargs="+", default=[], metavar="K=V",
                    help="override our filter's parameters (both MEKF and MUKF), e.g. "
                         "estimate_gyro_bias=true acc_disturbance=0.5")
    ap.add_argument("--algorithms", nargs="+", default=None, metavar="PATTERN",
                    help="only these columns (fnmatch on 'NAME DIM', e.g. 'mekf*' 'vqf 9D'); "
                         f"names: {', '.join(a.name for a in ALGOS)}")
    ap.add_argument("--skip-start", type=float, default=0.0, metavar="S",
                    help="do not score the first S seconds of each recording (default 0: "
                         "every valid sample, the metric's definition)")
    ap.add_argument("--time-base", choices=("true", "median"), default="true",
                    help="'true' (default): ours gets the timestamps, peers the mean period; "
                         "'median': every algorithm gets a regular grid at the median period "
                         "(reproduces the README's ESE650 peer figures, see the module doc)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="worker processes over recordings (default: 2)")
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="also write every score to FILE")
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.filter_params)
    t_start = time.perf_counter()

    datasets: list[tuple[str, str, list[Recording]]] = []
    for folder in args.datasets:
        fmt, recs = read_dataset(folder)
        if args.only:
            recs = [r for r in recs if any(s in r.name for s in args.only)]
        if args.time_base == "median":
            recs = [replace(r, t=r.t[0] + np.arange(len(r)) * float(np.median(np.diff(r.t))))
                    for r in recs]
        if recs:
            datasets.append((fmt, folder, recs))
    if not datasets:
        print("no recordings selected", file=sys.stderr)
        return 1
    t_read = time.perf_counter() - t_start

    print("# Real-data benchmark (bench/real_data.py)")
    print(f"code: {_git_state()}; our filter overrides: {overrides or 'none (defaults)'}; "
          f"skip_start: {args.skip_start:g} s; time base: {args.time_base}")
    tasks = [(i, r, args.algorithms, overrides, args.skip_start)
             for i, (_f_, _d, recs) in enumerate(datasets) for r in recs]
    tasks.sort(key=lambda t: -len(t[1]))  # longest first, for load balance
    results: list[dict[str, dict[str, dict[str, float]]]] = [{} for _ in datasets]
    cpu: dict[str, float] = {}
    jobs = max(1, min(args.jobs, len(tasks)))
    _warm()  # compile (or load) the kernels once here, so that workers only load the cache
    if jobs > 1:
        ctx = mp.get_context("spawn")
        with ctx.Pool(jobs, initializer=_warm) as pool:
            outs = list(pool.imap_unordered(_task, tasks))
    else:
        outs = [_task(t) for t in tasks]
    for idx, name, scores, secs in outs:
        results[idx][name] = scores
        for k, v in secs.items():
            cpu[k] = cpu.get(k, 0.0) + v

    all_means = []
    for (fmt, folder, recs), res in zip(datasets, results, strict=True):
        cols = [f"{a.name} {d}" for a, d in columns(recs[0].has_mag, args.algorithms)]
        means = print_dataset(fmt, folder, recs, res, cols)
        all_means.append((fmt, sum(not r.excluded for r in recs), means))
        excl = [r for r in recs if r.excluded]
        if excl:
            em = {c: dataset_mean([res[r.name][c] for r in excl]) for c in cols
                  if all("error" not in res[r.name].get(c, {"error": 1}) for r in excl)}
            all_means.append((f"{fmt} (excluded only)", len(excl), em))
        errs = {c for r in recs for c, s in res[r.name].items() if "error" in s}
        for c in sorted(errs):
            why = next(res[r.name][c]["error"] for r in recs if "error" in res[r.name][c])
            print(f"   {c}: {why}")
    print_summary(all_means)

    n_samples = sum(len(r) for _f_, _d, recs in datasets for r in recs)
    wall = time.perf_counter() - t_start
    print(f"\nelapsed: {wall:.1f} s wall ({t_read:.1f} s reading, {jobs} worker processes), "
          f"{n_samples:,} samples per column")
    print("CPU s per column (summed over recordings): "
          + ", ".join(f"{k} {v:.1f}" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1])))
    if args.json:
        payload = {
            "code": _git_state(), "overrides": overrides, "skip_start": args.skip_start,
            "time_base": args.time_base,
            "datasets": [
                {"format": fmt, "folder": folder,
                 "recordings": [{"name": r.name, "excluded": r.excluded, "note": r.note,
                                 "samples": len(r), "valid": int(r.valid.sum()),
                                 "scores": res[r.name]} for r in recs]}
                for (fmt, folder, recs), res in zip(datasets, results, strict=True)],
            "means": {fmt: m for fmt, _n, m in all_means},
            "elapsed_s": wall,
        }
        args.json.write_text(json.dumps(payload, indent=1, default=float))
        print(f"scores written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
