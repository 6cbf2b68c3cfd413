"""Long random runs (≥ 10⁵ steps) of both filters on every chart, with and without the chart
update: the quaternion stays unit-norm, P stays symmetric positive definite, nothing is NaN.

The check runs inside a compiled loop over the sensor layer so that P is inspected at every one
of the steps (with gyro bias estimation on, so the full 9-state P is exercised)."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from mkf_ros.core.filter import AttitudeFilter, kernel_table, kernels_at, run_step
from mkf_ros.core.linalg import cholesky
from mkf_ros.sim import simulate


@numba.njit(cache=False)
def _run_checked(table, cfg, st, cnt, work, dts, gyr, acc, mag):
    kern = kernels_at(table)
    c, s, k, w = cfg[0], st[0], cnt[0], work[0]
    nx = c.nx
    P = s.P
    worst_norm = 0.0
    worst_asym = 0.0
    for n in range(dts.shape[0]):
        run_step(kern, c, s, k, w, dts[n], (gyr[n, 0], gyr[n, 1], gyr[n, 2]),
                 (acc[n, 0], acc[n, 1], acc[n, 2]), (mag[n, 0], mag[n, 1], mag[n, 2]))
        q = s.q_c
        worst_norm = max(worst_norm, abs(np.sqrt(np.sum(q * q)) - 1.0))
        for i in range(nx):
            for j in range(nx):
                if not np.isfinite(P[i, j]):
                    return n, worst_norm, worst_asym
                worst_asym = max(worst_asym, abs(P[i, j] - P[j, i]))
        _, ok = cholesky(P[:nx, :nx].copy())
        if not ok or not (np.all(np.isfinite(s.w)) and np.all(np.isfinite(s.b))
                          and np.all(np.isfinite(s.e))):
            return n, worst_norm, worst_asym
    return -1, worst_norm, worst_asym


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
    dts = np.r_[0.0, np.diff(stream.t)]
    arrays = f.kernel_arrays()
    bad, worst_norm, worst_asym = _run_checked(kernel_table(arrays.cfg), *arrays, dts,
                                               stream.gyr, stream.acc, stream.mag)
    assert bad == -1, f"P lost positive definiteness or became non-finite at step {bad}"
    assert worst_norm < 1e-12
    assert worst_asym < 1e-15  # rounding only: P is symmetrised every update
    assert f.counter_dict()["update_failed"] == 0
