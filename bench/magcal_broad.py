"""Magnetometer calibration (docs/math.md §10.1) on BROAD's attached-magnet trials: does a
calibration fitted on the start of the disturbance bring the 9D error back to that of the
undisturbed trials?

    ./run bench magcal_broad BROAD_DIR [--cal-seconds S] [--algorithm mekf|mukf]

BROAD (Laidig et al., Data 6(7):72, 2021, CC BY 4.0) trials 32 and 34 carry a magnet on the
board 1 cm / 3 cm from the IMU. In these recordings the magnet is on the board for about a minute
of the motion phase only (the rest before and after reads the undisturbed field: |m| ≈ 44 µT,
steady). The script finds that phase from the data (rolling 2 s standard deviation of |m| above
``--magnet-threshold`` µT: a constant offset makes |m| swing as the body turns, an undisturbed
field does not) and reports, per trial:

* the fits (ellipsoid, and hard iron only) on the first ``--cal-seconds`` of the magnet phase
  (from the start of the motion, at least 2 s after the magnet appears): hard iron, soft iron,
  RMS residual, coverage; and what ``fit_ellipsoid`` says about the trial's first minute of
  recording, as the issue first proposed (rest without the magnet + the magnet's first seconds:
  refused);
* the 9D total RMSE (BROAD metric, degrees) over the rest of the magnet phase after the
  calibration window, and over the rest of the trial's motion after it, for the filter
  (i) without calibration (its consistency checks refuse the magnet's field: gyro-only heading),
  (ii) with the calibration as parameters for the whole trial (``mag_bias_*``, ``mag_soft_iron``:
  wrong again once the magnet is removed), (iii) with calibrated magnetometer samples while the
  magnet is on and raw ones otherwise (a user who calibrates when fitting the magnet and restores
  the parameters when removing it);
* next to the undisturbed trials' mean 9D total RMSE (their whole motion phase, and the same
  relative time window) and the target: within 10 % of it.

The data are not in the repository; the tests never use them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

import mkf_ros
from mkf_ros.core.magcal import MagCalibration, fit_ellipsoid
from mkf_ros.evaluation.datasets import Recording, read_broad_trial
from mkf_ros.evaluation.scoring import error_series

TARGET = 1.10  #: calibrated error within 10 % of the undisturbed trials'


def rolling_std(x: np.ndarray, n: int) -> np.ndarray:
    """Centred rolling standard deviation over ``n`` samples (NaN at the ends)."""
    c = np.cumsum(np.r_[0.0, x])
    c2 = np.cumsum(np.r_[0.0, x * x])
    s, s2 = (c[n:] - c[:-n]) / n, (c2[n:] - c2[:-n]) / n
    out = np.full(len(x), np.nan)
    out[n // 2:n // 2 + len(s)] = np.sqrt(np.maximum(s2 - s * s, 0.0))
    return out


def magnet_phase(rec: Recording, threshold: float) -> tuple[float, float] | None:
    """First and last time (s) at which |m| swings like a field carried by the body."""
    assert rec.mag is not None
    sd = rolling_std(np.linalg.norm(rec.mag, axis=1), int(2.0 * rec.meta["rate"]))
    idx = np.flatnonzero(sd > threshold)
    return (float(rec.t[idx[0]]), float(rec.t[idx[-1]])) if len(idx) else None


def total_rmse(rec: Recording, q: np.ndarray, a: float, b: float) -> float:
    """9D total error RMSE (degrees) over the scored samples with a ≤ t < b."""
    e = error_series(rec, q)["total"]
    k = np.isfinite(e) & (rec.t >= a) & (rec.t < b)
    return float(np.degrees(np.sqrt(np.mean(e[k] ** 2)))) if k.any() else float("nan")


def estimate(rec: Recording, mag: np.ndarray, algorithm: str, **params: Any) -> np.ndarray:
    res = mkf_ros.estimate(rec.gyr, rec.acc, mag, timestamps=rec.t, algorithm=algorithm,
                           use_mag=True, **params)
    return np.asarray(res.quat)


def fit_or_reason(m: np.ndarray, soft_iron: bool = True) -> MagCalibration | str:
    try:
        return fit_ellipsoid(m, soft_iron=soft_iron)
    except ValueError as e:
        return str(e)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("broad", type=Path, help="BROAD folder (NN_*.mat, trials.json)")
    ap.add_argument("--cal-seconds", type=float, default=20.0,
                    help="calibration window at the start of the magnet phase (default 20 s)")
    ap.add_argument("--magnet-threshold", type=float, default=3.0,
                    help="rolling std of |m| (µT) that marks the magnet phase (default 3)")
    ap.add_argument("--algorithm", default="mekf", choices=("mekf", "mukf"))
    args = ap.parse_args(argv)
    trials = json.loads((args.broad / "trials.json").read_text())["trials"]
    files = sorted(args.broad.glob("[0-9][0-9]_*.mat"))
    undisturbed = [f for f in files if "undisturbed" in trials.get(f.stem, {}).get("groups", [])]
    magnets = [f for f in files if "attached_magnet" in trials.get(f.stem, {}).get("groups", [])]
    if not magnets or not undisturbed:
        print(f"magcal_broad: error: no attached-magnet or undisturbed trials in {args.broad}")
        return 2

    rows = []
    windows: list[tuple[float, float, float]] = []  # (cal end, magnet end) relative to motion
    print(f"algorithm {args.algorithm}; calibration on the first {args.cal_seconds:g} s of the "
          "magnet phase\n")
    for f in magnets:
        rec = read_broad_trial(f)
        assert rec.mag is not None
        phase = magnet_phase(rec, args.magnet_threshold)
        if phase is None:
            print(f"{f.stem}: no magnet phase found (threshold {args.magnet_threshold} µT)")
            continue
        on0, on1 = phase
        first_minute = fit_or_reason(rec.mag[rec.t < rec.t[0] + 60.0])
        move = rec.t[rec.valid]
        # the window starts with the motion (and not before the magnet has settled: while it
        # is being fitted the offset changes)
        t_cal0 = max(on0 + 2.0, float(move[0]))
        t_cal_end, t_end = t_cal0 + args.cal_seconds, float(move[-1]) + 1e-9
        print(f"{f.stem}: magnet on {on0:.1f} … {on1:.1f} s; motion {move[0]:.1f} … "
              f"{move[-1]:.1f} s")
        print(f"  first minute of the recording: "
              f"{first_minute if isinstance(first_minute, str) else 'fitted'}")
        raw_q = estimate(rec, rec.mag, args.algorithm)
        mag_on = (rec.t >= on0) & (rec.t <= on1)
        windows.append((t_cal_end - float(move[0]), on1 - float(move[0]),
                        t_end - float(move[0])))
        for kind, soft in (("ellipsoid", True), ("hard iron only", False)):
            cal = fit_or_reason(rec.mag[(rec.t >= t_cal0) & (rec.t < t_cal_end)], soft)
            if isinstance(cal, str):
                print(f"  {kind}, window {t_cal0:.1f} … {t_cal_end:.1f} s: {cal}")
                continue
            print(f"  {kind}, window {t_cal0:.1f} … {t_cal_end:.1f} s:")
            print("    " + cal.summary().replace("\n", "\n    "))
            par_q = estimate(rec, rec.mag, args.algorithm, **cal.params())
            mixed = np.where(mag_on[:, None], cal.apply(rec.mag), rec.mag)
            mix_q = estimate(rec, mixed, args.algorithm)
            for label, a, b in (("rest of magnet phase", t_cal_end, on1),
                                ("rest of the trial", t_cal_end, t_end)):
                rows.append((f.stem[:2], kind, label, f"{a:.0f}–{b:.0f}",
                             total_rmse(rec, raw_q, a, b), total_rmse(rec, par_q, a, b),
                             total_rmse(rec, mix_q, a, b)))

    und_full, und_win = [], []
    for f in undisturbed:
        rec = read_broad_trial(f)
        assert rec.mag is not None
        q = estimate(rec, rec.mag, args.algorithm)
        t0 = float(rec.t[rec.valid][0])
        und_full.append(total_rmse(rec, q, -np.inf, np.inf))
        und_win.append(np.mean([total_rmse(rec, q, t0 + a, t0 + b) for a, b, _ in windows])
                       if windows else float("nan"))
    ref_full, ref_win = float(np.mean(und_full)), float(np.nanmean(und_win))
    print(f"\nundisturbed trials ({len(undisturbed)}): 9D total RMSE {ref_full:.2f}° over their "
          f"motion, {ref_win:.2f}° over the magnet trials' scored windows (same time after "
          "motion start)")
    print(f"target: calibrated ≤ {TARGET:.2f} × {ref_full:.2f}° = {TARGET * ref_full:.2f}°\n")
    head = ("trial", "fit", "scored window", "t [s]", "uncalibrated", "calibrated (params)",
            "calibrated while on")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for trial, kind, label, span, raw, par, mix in rows:
        print(f"| {trial} | {kind} | {label} | {span} | {raw:.2f}° | {par:.2f}° | {mix:.2f}° |")
    print()
    for trial, kind, label, _span, _raw, par, mix in rows:
        for name, v in (("params", par), ("while on", mix)):
            ok = v <= TARGET * ref_full
            print(f"{'PASS' if ok else 'FAIL'}  {trial} {kind}, {label}, calibrated ({name}): "
                  f"{v:.2f}° vs {TARGET * ref_full:.2f}°")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
