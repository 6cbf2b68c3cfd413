"""Euler-angle filters at gimbal lock: a synthetic sweep through pitch ±90° (docs/baselines.md).

    ./run bench gimbal_sweep [--duration S] [--seed N] [--plot PATH] [--no-plot]

Simulates the ``sweep`` scenario (:mod:`mkf_ros.sim`: full turns about x, y, z and the diagonal,
and both gimbal-lock attitudes, pitch +90° and −90°, with a turn about the then vertical body x
axis while there), runs every algorithm of :data:`mkf_ros.core.params.ALGORITHMS` with default
parameters, 6D and 9D, and prints per algorithm the max and RMS error inside and outside the
gimbal-lock intervals (true |pitch| > 80°, ``meta['intervals']['gimbal_lock']``): inclination
for 6D (heading is unobservable), total for 9D; plus the ``gimbal_lock`` counter of the Euler
filters and the accelerometer samples the χ² gate rejected (a filter over-confident after a
failure rejects the very samples that would correct it). The plot (error vs time, intervals
shaded) goes to ``docs/baselines/gimbal_sweep.png``.
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

import numpy as np

import mkf_ros
from mkf_ros.core.params import ALGORITHMS
from mkf_ros.evaluation.metrics import orientation_errors
from mkf_ros.sim import simulate
from mkf_ros.sim.motion import pitch_deg

DEFAULT_PLOT = Path(__file__).resolve().parents[1] / "docs" / "baselines" / "gimbal_sweep.png"
COLORS = {"mekf": "tab:blue", "mukf": "tab:cyan", "euler_kf": "tab:red",
          "euler_ukf": "tab:orange", "madgwick": "tab:green"}


def run(duration: float, seed: int) -> tuple[object, dict[tuple[str, str], dict]]:
    """Simulate once; every (algorithm, dim) → error series (deg), counters."""
    sim = simulate("sweep", duration=duration, rate=100.0, seed=seed)
    out: dict[tuple[str, str], dict] = {}
    for algo in ALGORITHMS:
        for dim in ("6D", "9D"):
            mag = sim.mag if dim == "9D" else None
            r = mkf_ros.estimate(sim.gyr, sim.acc, mag, timestamps=sim.t, algorithm=algo)
            e = orientation_errors(r.quat, sim.quat)
            err = np.degrees(e["inclination" if dim == "6D" else "total"])
            finite = bool(np.isfinite(r.quat).all() and np.isfinite(r.cov).all())
            out[(algo, dim)] = {"err": err, "counters": r.counters, "finite": finite}
    return sim, out


def table(sim: object, res: dict[tuple[str, str], dict]) -> str:
    inside = sim.mask("gimbal_lock")  # type: ignore[attr-defined]
    lines = [
        f"sweep: {sim.t[-1]:.0f} s at 100 Hz, seed {sim.meta['seed']}; "  # type: ignore[attr-defined]
        f"{inside.mean() * 100:.1f} % of the samples inside the gimbal-lock intervals "
        "(true |pitch| > 80°)",
        "",
        "| algorithm | dim | error | inside max | inside RMS | outside max | outside RMS "
        "| gimbal_lock count | acc χ² rejections | finite |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for (algo, dim), r in res.items():
        err = r["err"]
        cells = []
        for m in (inside, ~inside):
            cells += [f"{err[m].max():.2f}", f"{np.sqrt(np.mean(err[m] ** 2)):.2f}"]
        kind = "inclination" if dim == "6D" else "total"
        lines.append(f"| {algo} | {dim} | {kind} | " + " | ".join(cells)
                     + f" | {r['counters']['gimbal_lock']} | {r['counters']['acc_rejected_chi2']} "
                     f"| {'yes' if r['finite'] else 'NO'} |")
    return "\n".join(lines)


def plot(sim: object, res: dict[tuple[str, str], dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = sim.t  # type: ignore[attr-defined]
    fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True,
                             gridspec_kw={"height_ratios": [1, 2, 2]})
    axes[0].plot(t, pitch_deg(sim.quat), color="k", lw=0.8)  # type: ignore[attr-defined]
    axes[0].set_ylabel("true pitch [°]")
    axes[0].set_yticks([-90, 0, 90])
    w = 10  # plot the max over 0.1 s windows: readable, and a small file
    n = len(t) // w * w
    tw = t[:n:w]
    for ax, dim, kind in ((axes[1], "6D", "inclination"), (axes[2], "9D", "total")):
        for algo in ALGORITHMS:
            e = np.maximum(res[(algo, dim)]["err"][:n].reshape(-1, w).max(axis=1), 1e-3)
            ax.semilogy(tw, e, color=COLORS.get(algo), lw=0.9, label=algo)
        ax.set_ylabel(f"{dim} {kind} error [°]\n(max per 0.1 s)")
        ax.set_ylim(1e-2, 200)
        ax.grid(True, which="major", alpha=0.3)
    for ax in axes:
        for a, b in sim.meta["intervals"].get("gimbal_lock", []):  # type: ignore[attr-defined]
            ax.axvspan(a, b, color="0.85", lw=0)
    axes[1].legend(ncol=5, fontsize=8, loc="upper left")
    axes[2].set_xlabel("time [s]  (shaded: true |pitch| > 80°, gimbal lock of ZYX Euler angles)")
    fig.suptitle("Synthetic sweep through pitch ±90°: Euler-angle filters vs MEKF/MUKF/Madgwick",
                 fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=80)
    plt.close(fig)
    from PIL import Image  # matplotlib's own dependency: a 64-colour palette keeps the file small

    Image.open(buf).convert("RGB").quantize(64).save(path, optimize=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds (default 60: two "
                    "sweep cycles)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plot", type=Path, default=DEFAULT_PLOT)
    ap.add_argument("--no-plot", action="store_true")
    args = ap.parse_args(argv)
    if not args.duration > 0:
        print(f"gimbal_sweep: --duration must be positive, got {args.duration}", file=sys.stderr)
        return 2
    sim, res = run(args.duration, args.seed)
    print(table(sim, res))
    if not args.no_plot:
        plot(sim, res, args.plot)
        print(f"\nplot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
