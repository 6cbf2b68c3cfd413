"""Gyro bias from a window of samples at rest (docs/math.md §10.2).

Used by the estimator node's ``~/calibrate_gyro`` service; pure NumPy, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

#: Fewer gyro samples than this are refused (no meaningful spread).
MIN_SAMPLES = 10


@dataclass(frozen=True)
class RestBias:
    """The gyro bias measured at rest and what the window looked like."""

    bias: np.ndarray  #: (3,) rad/s, the mean gyro reading
    stddev: np.ndarray  #: (3,) rad/s, standard error of that mean (s/√n)
    gyro_spread: np.ndarray  #: (3,) rad/s, sample standard deviation of the gyro
    acc_spread: float  #: m/s², largest per-axis sample standard deviation of the accelerometer
    n: int  #: gyro samples used

    def summary(self) -> str:
        b = ", ".join(f"{x:.6f}" for x in self.bias)
        s = ", ".join(f"{x:.6f}" for x in self.stddev)
        return f"gyro bias [{b}] rad/s, σ [{s}] rad/s ({self.n} samples)"


def rest_bias(gyr: ArrayLike, acc: ArrayLike | None, *, max_gyro_stddev: float,
              max_acc_stddev: float) -> RestBias:
    """The bias ``b̂ = mean(ω_m)`` of gyro samples taken at rest and its standard error
    ``s/√n`` per axis (docs/math.md §10.2). ValueError (one line, naming the reason) when the
    window shows motion: a gyro axis whose sample standard deviation exceeds
    ``max_gyro_stddev`` (rad/s), or an accelerometer axis above ``max_acc_stddev`` (m/s²);
    or too few samples. Non-finite rows are dropped."""
    g = np.asarray(gyr, dtype=float).reshape(-1, 3)
    g = g[np.all(np.isfinite(g), axis=1)]
    if len(g) < MIN_SAMPLES:
        raise ValueError(f"gyro calibration needs at least {MIN_SAMPLES} gyro samples, "
                         f"got {len(g)}")
    spread = g.std(axis=0, ddof=1)
    if np.any(spread > max_gyro_stddev):
        ax = "xyz"[int(np.argmax(spread))]
        raise ValueError(f"gyro calibration refused: the sensor moved (gyro {ax} varied by "
                         f"{spread.max():.4f} rad/s RMS, limit {max_gyro_stddev:g}); keep it "
                         "still and call again")
    acc_spread = 0.0
    if acc is not None:
        a = np.asarray(acc, dtype=float).reshape(-1, 3)
        a = a[np.all(np.isfinite(a), axis=1)]
        if len(a) >= 2:
            acc_spread = float(a.std(axis=0, ddof=1).max())
        if acc_spread > max_acc_stddev:
            raise ValueError(f"gyro calibration refused: the sensor moved (accelerometer varied "
                             f"by {acc_spread:.3f} m/s² RMS, limit {max_acc_stddev:g}); keep it "
                             "still and call again")
    return RestBias(bias=g.mean(axis=0), stddev=spread / np.sqrt(len(g)), gyro_spread=spread,
                    acc_spread=acc_spread, n=len(g))
