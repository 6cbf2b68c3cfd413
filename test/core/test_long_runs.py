"""Long random runs (≥ 10⁵ steps) of both filters on every chart, with and without the chart
update: the quaternion stays unit-norm, P stays symmetric positive definite, nothing is NaN.

The check runs inside a compiled loop over the sensor layer so that P is inspected at every one
of the steps (with gyro bias estimation on, so the full 9-state P is exercised)."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from mkf_ros.core.filter import AttitudeFilter
from mkf_ros.core.linalg import cholesky
from mkf_ros.core.sensor import sensor_step
from mkf_ros.core.state import S_QC
from mkf_ros.sim import simulate


@numba.njit(cache=False)
def _run_checked(cfg, nz, st, P, fl, cnt, dts, gyr, acc, mag):
    nx = int(cfg[4])
    worst_norm = 0.0
    worst_asym = 0.0
    for n in range(dts.shape[0]):
        sensor_step(cfg, nz, st, P, fl, cnt, dts[n], gyr[n], acc[n], mag[n])
        q = st[S_QC:S_QC + 4]
        worst_norm = max(worst_norm, abs(np.sqrt(np.sum(q * q)) - 1.0))
        for i in range(nx):
            for j in range(nx):
                if not np.isfinite(P[i, j]):
                    return n, worst_norm, worst_asym, cnt
                worst_asym = max(worst_asym, abs(P[i, j] - P[j, i]))
        _, ok = cholesky(P[:nx, :nx].copy())
        if not ok or not np.all(np.isfinite(st)):
            return n, worst_norm, worst_asym, cnt
    return -1, worst_norm, worst_asym, cnt


@pytest.fixture(scope="module")
def stream():
    # 1000 s at 100 Hz of the paper's Wiener motion (Q_ω = 1), gyro bias, 20 Hz magnetometer
    return simulate("wiener", duration=1000, rate=100, seed=11, gyro_bias=(0.01, -0.02, 0.005),
                    mag_rate=20)


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
@pytest.mark.parametrize("chart", ["o", "rp", "mrp", "rv"])
@pytest.mark.parametrize("cu", [True, False])
def test_long_run_invariants(stream, algorithm: str, chart: str, cu: bool) -> None:
    n = stream.t.size
    assert n >= 100_000
    f = AttitudeFilter(algorithm=algorithm, chart=chart, chart_update=cu, use_mag=True,
                       estimate_gyro_bias=True, rate_process_noise=1.0)
    cfg, nz, st, P, fl, cnt, _ = f.kernel_arrays()
    dts = np.r_[0.0, np.diff(stream.t)]
    bad, worst_norm, worst_asym, cnt = _run_checked(cfg, nz, st, P, fl, cnt, dts, stream.gyr,
                                                    stream.acc, stream.mag)
    assert bad == -1, f"P lost positive definiteness or became non-finite at step {bad}"
    assert worst_norm < 1e-12
    assert worst_asym < 1e-15  # rounding only: P is symmetrised every update
    assert cnt[8] == 0  # update_failed
