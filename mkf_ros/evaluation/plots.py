"""Accuracy plots against ground truth (``mkf process``, ``mkf demo``).

Uses matplotlib's object API with the Agg canvas, so it never touches a GUI backend and works
on headless machines; files are written atomically (temporary name, then rename).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mkf_ros.evaluation.metrics import roll_pitch_yaw
from mkf_ros.files import atomic_path

#: shading of the disturbance intervals a synthetic recording reports
INTERVAL_STYLE = {
    "acc_disturbed": ("tab:orange", "acceleration"),
    "mag_disturbed": ("tab:purple", "magnetic disturbance"),
    "dropout": ("tab:red", "dropout"),
    "mag_dropout": ("tab:pink", "magnetometer outage"),
    "gimbal_lock": ("tab:cyan", "|pitch| > 80°"),
    "fast": ("tab:olive", "fast rotation"),
}
MAX_POINTS = 20_000


def euler_deg(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw in degrees (:func:`mkf_ros.evaluation.metrics.roll_pitch_yaw`)."""
    return np.degrees(roll_pitch_yaw(q_wxyz))


def _breaks(a: np.ndarray) -> np.ndarray:
    """NaN where an angle wraps (±180°), so lines do not cross the plot."""
    a = a.astype(float).copy()
    a[1:][np.abs(np.diff(a)) > 180.0] = np.nan
    return a


def accuracy_figure(path: str | Path, t: np.ndarray, q_est: np.ndarray, q_true: np.ndarray,
                    errors: Mapping[str, np.ndarray], *, title: str = "",
                    intervals: Mapping[str, list] | None = None,
                    rmse: Mapping[str, float] | None = None,
                    envelope: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None
                    = None) -> Path:
    """Errors vs time and roll/pitch/yaw estimated vs true; returns the written file.

    A long recording comes decimated: ``t`` etc. every k-th sample, ``rmse`` (degrees) over
    all of them, and ``envelope`` per error the (bucket times, minimum, maximum) over buckets
    of k samples (rad), drawn as a band behind the line."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    t = np.asarray(t, float)
    step = max(1, len(t) // MAX_POINTS)
    s = slice(None, None, step)
    est, tru = euler_deg(q_est[s]), euler_deg(q_true[s])
    ts = t[s]
    fig = Figure(figsize=(11, 9.5), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(4, 1, sharex=True, height_ratios=[1.3, 1, 1, 1])
    ax = axes[0]
    for key, color in (("total", "k"), ("heading", "tab:blue"), ("inclination", "tab:green")):
        e = np.degrees(np.asarray(errors[key])[s])
        rms = (float(rmse[key]) if rmse is not None else
               float(np.sqrt(np.mean(np.degrees(np.asarray(errors[key])) ** 2))))
        if envelope is not None and key in envelope:
            te, lo, hi = envelope[key]
            ax.fill_between(te, np.degrees(lo), np.degrees(hi), color=color, alpha=0.2, lw=0,
                            step="post")
        ax.plot(ts, e, color=color, lw=0.8, label=f"{key} (RMSE {rms:.2f}°)")
    ax.set_ylabel("error [°]")
    tot = np.degrees(np.asarray(errors["total"] if envelope is None or "total" not in envelope
                                else envelope["total"][2]))
    top = max(float(np.percentile(tot, 99.0)) * 1.6, 0.5) if tot.size else 1.0
    ax.set_ylim(0, min(top, float(tot.max()) * 1.05) if tot.size else 1.0)
    ax.grid(alpha=0.3)
    for ax, i, name in zip(axes[1:], range(3), ("roll", "pitch", "yaw"), strict=True):
        ax.plot(ts, _breaks(tru[:, i]), color="0.55", lw=2.2, label="true")
        ax.plot(ts, _breaks(est[:, i]), color="tab:red", lw=0.9, label="estimated")
        ax.set_ylabel(f"{name} [°]")
        ax.set_ylim(-95 if name == "pitch" else -185, 95 if name == "pitch" else 185)
        ax.grid(alpha=0.3)
    axes[1].legend(loc="upper right", fontsize=8, ncol=2)
    axes[-1].set_xlabel("time [s]")
    shaded = set()
    for kind, ivs in (intervals or {}).items():
        color, label = INTERVAL_STYLE.get(kind, ("0.7", kind))
        for a, b in ivs:
            for ax in axes:
                ax.axvspan(a, max(b, a + 1e-3), color=color, alpha=0.15, lw=0,
                           label=label if (ax is axes[0] and kind not in shaded) else None)
            shaded.add(kind)
    axes[0].legend(loc="upper right", fontsize=8, ncol=2)
    if "gimbal_lock" in (intervals or {}):
        axes[1].text(0.01, 0.03, "at pitch ±90° (shaded) roll and yaw are undefined, only their "
                     "sum or difference is: the errors on top are computed on quaternions",
                     transform=axes[1].transAxes, fontsize=7.5, color="0.3")
    if title:
        fig.suptitle(title, fontsize=11)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return path
