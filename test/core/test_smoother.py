"""The fixed-interval manifold smoother (docs/math.md §11, :mod:`mkf_ros.core.smoother`):
against the closed-form batch solution of a linear-Gaussian model, against the truth of
simulated recordings, its transition Jacobian against finite differences of the prediction,
and the windowed pass against the full-interval one."""

from __future__ import annotations

import numpy as np
import pytest

import mkf_ros
from mkf_ros.core.charts import chart_id, from_chart, to_chart
from mkf_ros.core.filter import AttitudeFilter
from mkf_ros.core.mekf import mekf_predict_t
from mkf_ros.core.quaternion import q_omega, qconj_np, qmul, qmul_np, qnormalize
from mkf_ros.core.smoother import (
    fuse_tilt,
    reversed_inputs,
    rts_linear,
    smooth_reversed_into,
    smooth_run,
    smooth_stream,
    transition_matrix,
    window_sizes,
)
from mkf_ros.core.state import iso33
from mkf_ros.sim import simulate


def _rts_backward(Pa: list, Pp: list, As: list, dt: float, Qs: list, xa: list,
                  xp: list) -> tuple:
    """The backward pass of :func:`rts_linear` over a whole linear forward pass."""
    nx = Pa[0].shape[0]
    xs, Ps = [xa[-1]], [Pa[-1]]
    C, G, X, Po = (np.zeros((nx, nx)) for _ in range(4))
    dxo = np.zeros(nx)
    for k in range(len(Pa) - 2, -1, -1):
        Phi = _phi(As[k], dt, nx)
        Qp = Phi @ Qs[k] @ Phi.T
        dx = xs[0] - xp[k + 1]
        assert rts_linear(nx, Pa[k], Pp[k + 1].copy(), tuple(map(tuple, As[k])), dt, Qp,
                          Ps[0], dx, C, (G, X), Po, dxo)
        xs.insert(0, xa[k] + dxo)
        Ps.insert(0, Po.copy())
    return xs, Ps


def _phi(A: np.ndarray, dt: float, nx: int) -> np.ndarray:
    """``Φ = [[A, Δt I, 0], [0, I, 0], [0, 0, I]]``: the filter's transition (docs/math.md §5)."""
    Phi = np.eye(nx)
    Phi[:3, :3] = A
    Phi[:3, 3:6] = dt * np.eye(3)
    return Phi


def test_rts_linear_equals_batch_least_squares() -> None:
    """(1) A linear-Gaussian model ``x_{k+1} = Φ_k (x_k + w_k)``, ``y_k = H_k x_k + v_k``
    (the filter's ``P⁻ = Φ (P + Q) Φᵀ`` form, Φ of the filter's structure with a random
    3×3 block): the Kalman filter forward in numpy, the
    backward pass through :func:`rts_linear`, against the smoothed means and marginal
    covariances of the batch solution (the information form over all states at once)."""
    rng = np.random.default_rng(3)
    nx, ny, K = 9, 3, 25
    dt = 0.3
    As = [np.eye(3) + 0.3 * rng.normal(size=(3, 3)) for _ in range(K - 1)]
    Phis = [_phi(A, dt, nx) for A in As]
    Qs = []
    for _ in range(K - 1):
        B = 0.3 * rng.normal(size=(nx, nx))
        Qs.append(B @ B.T + 1e-3 * np.eye(nx))
    Hs = [rng.normal(size=(ny, nx)) for _ in range(K)]
    R = 0.5 * np.eye(ny)
    m0, P0 = rng.normal(size=nx), 2.0 * np.eye(nx)
    ys = [rng.normal(size=ny) for _ in range(K)]
    # forward Kalman filter
    xa, Pa, xp, Pp = [], [], [m0], [P0]
    for k in range(K):
        H = Hs[k]
        S = H @ Pp[k] @ H.T + R
        Kg = Pp[k] @ H.T @ np.linalg.inv(S)
        xa.append(xp[k] + Kg @ (ys[k] - H @ xp[k]))
        Pa.append((np.eye(nx) - Kg @ H) @ Pp[k])
        if k < K - 1:
            xp.append(Phis[k] @ xa[k])
            Pp.append(Phis[k] @ (Pa[k] + Qs[k]) @ Phis[k].T)
    xs, Ps = _rts_backward(Pa, Pp, As, dt, Qs, xa, xp)
    # batch: minimise |x0 − m0|²_P0⁻¹ + Σ |x_{k+1} − Φ x_k|²_(ΦQΦᵀ)⁻¹ + Σ |y − H x|²_R⁻¹
    N = nx * K
    Lam, eta = np.zeros((N, N)), np.zeros(N)
    Lam[:nx, :nx] += np.linalg.inv(P0)
    eta[:nx] += np.linalg.solve(P0, m0)
    Ri = np.linalg.inv(R)
    for k in range(K):
        s = slice(nx * k, nx * (k + 1))
        Lam[s, s] += Hs[k].T @ Ri @ Hs[k]
        eta[s] += Hs[k].T @ Ri @ ys[k]
    for k in range(K - 1):
        W = np.linalg.inv(Phis[k] @ Qs[k] @ Phis[k].T)
        A = np.zeros((nx, N))
        A[:, nx * k:nx * (k + 1)] = -Phis[k]
        A[:, nx * (k + 1):nx * (k + 2)] = np.eye(nx)
        Lam += A.T @ W @ A
    cov = np.linalg.inv(Lam)
    mean = cov @ eta
    for k in range(K):
        s = slice(nx * k, nx * (k + 1))
        np.testing.assert_allclose(xs[k], mean[s], atol=1e-8 * (1 + np.abs(mean).max()))
        np.testing.assert_allclose(Ps[k], cov[s, s], atol=1e-8 * np.abs(cov).max())
        if k < K - 1:  # (the last is the numpy filter's)
            np.testing.assert_array_equal(Ps[k], Ps[k].T)  # symmetric by construction
            assert np.linalg.eigvalsh(Ps[k]).min() > 0


@pytest.mark.parametrize("w", [(0.3, -0.2, 0.5), (2.0, 1.0, -3.0)])
@pytest.mark.parametrize("chart", ["rp", "rv"])
def test_transition_matrix_against_finite_differences(w: tuple, chart: str) -> None:
    """(3) Φ as the backward pass uses it (:func:`transition_matrix`): the prediction
    :func:`mekf_predict_t` is ``P⁻ = Φ (P + Q̂) Φᵀ`` with exactly this Φ, and Φ is the
    derivative of the predicted error ``φ(q̄⁻* q')`` (and rate, bias) with respect to the
    error at the start (central differences; the attitude-from-rate block is the paper's
    ``Δt I``, exact to ``O(|ω| Δt²)``)."""
    rng = np.random.default_rng(0)
    nx, dt = 9, 0.01
    A = rng.normal(size=(nx, nx))
    P = A @ A.T
    Phi = np.zeros((nx, nx))
    transition_matrix(w, dt, nx, Phi)
    Qw, Qb = 20.0, 1e-8
    Q = np.zeros((nx, nx))
    Q[:3, :3] = Qw * dt ** 3 / 3 * np.eye(3)
    Q[:3, 3:6] = Q[3:6, :3] = -Qw * dt ** 2 / 2 * np.eye(3)
    Q[3:6, 3:6] = Qw * dt * np.eye(3)
    Q[6:, 6:] = Qb * dt * np.eye(3)
    Pp = P.copy()
    q = qnormalize(np.array([0.9, 0.1, -0.3, 0.2]))
    qm = mekf_predict_t(tuple(q), w, Pp, nx, dt, iso33(Qw), iso33(Qb))
    np.testing.assert_allclose(Pp, Phi @ (P + Q) @ Phi.T, rtol=1e-12, atol=1e-12)
    cid = chart_id(chart)

    def predicted_error(x: np.ndarray) -> np.ndarray:
        qx = qnormalize(qmul(q, from_chart(cid, x[:3])))
        wx = np.array(w) + x[3:6]
        qn = qnormalize(qmul(qx, q_omega(wx, dt)))
        return np.concatenate([to_chart(cid, qmul(qconj_np(np.array(qm)), qn)), x[3:6],
                               x[6:9]])

    h = 1e-6
    J = np.zeros((nx, nx))
    for j in range(nx):
        d = np.zeros(nx)
        d[j] = h
        J[:, j] = (predicted_error(d) - predicted_error(-d)) / (2 * h)
    wn = np.linalg.norm(w)
    np.testing.assert_allclose(J[:, :3], Phi[:, :3], atol=1e-8)
    np.testing.assert_allclose(J[:, 6:], Phi[:, 6:], atol=1e-8)
    np.testing.assert_allclose(J[:, 3:6], Phi[:, 3:6], atol=wn * dt ** 2)


def _world_error(q: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """Rotation vector of ``q_true q̂*`` (world axes: the covariance's, docs/math.md §9.6)."""
    d = qmul_np(q_true, qconj_np(q))
    d = d * np.where(d[:, :1] < 0, -1.0, 1.0)
    n = np.linalg.norm(d[:, 1:], axis=1, keepdims=True)
    ang = 2 * np.arctan2(n, d[:, :1])
    return d[:, 1:] * np.where(n > 0, ang / np.maximum(n, 1e-300), 2.0)


@pytest.mark.parametrize("scenario", ["wiener", "slow_rotation", "accel_bursts"])
@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
def test_smoother_beats_filter_and_is_consistent(scenario: str, algorithm: str) -> None:
    """(2) On simulated recordings (9D, default parameters) the smoothed attitude error (RMS
    against the truth) is below the filter's, and its covariance is consistent: the mean NEES
    of the 3-D world-axis error within a band around its χ²₃ expectation 3 (the published
    covariance includes the accelerometer's misalignment, which the simulation lacks: the
    band's lower end allows that), and ≥ 90 % of the samples within the 3σ ellipsoid (χ²₃ at
    99.7 %: 14.16)."""
    d = simulate(scenario, duration=30.0, seed=4)
    # the simulation's own noise model: no misalignment, scale error or correlated disturbance
    # (a bursty acceleration keeps the default acc_disturbance)
    matched = dict(acc_alignment_error=0.0, gyro_scale_error=0.0, mag_disturbance=0.001,
                   mag_disturbance_time=0.0, acc_disturbance_time=0.0)
    if scenario != "accel_bursts":
        matched["acc_disturbance"] = 0.05
    r = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, algorithm=algorithm,
                         smooth=True, **matched)
    r0 = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, algorithm=algorithm,
                          smooth=True)  # default parameters: the error is lower too
    e0 = [_world_error(q, d.quat)[100:] for q in (r0.quat, r0.filtered_quat)]
    # at least 10 % lower; with bursts of acceleration that the default magnetometer weight
    # (mag_disturbance 0.1) couples into the heading, lower (measured 0.94 MEKF, 0.93 MUKF)
    gain = 1.0 if scenario == "accel_bursts" else 0.9
    assert np.sqrt(np.mean(e0[0] ** 2)) < gain * np.sqrt(np.mean(e0[1] ** 2))
    assert r.smoothed and r.filtered_quat is not None and r.filtered_cov is not None
    skip = 100  # the first second: the alignment
    es = _world_error(r.quat, d.quat)[skip:]
    ef = _world_error(r.filtered_quat, d.quat)[skip:]
    rms_s = np.sqrt(np.mean(np.sum(es ** 2, axis=1)))
    rms_f = np.sqrt(np.mean(np.sum(ef ** 2, axis=1)))
    # measured: smoothed / filtered 0.73 (slow rotation), 0.96 (MEKF) and 0.99 (MUKF) on the
    # Wiener motion, whose filter error is already low (0.0045 rad at seed 4; with the default
    # parameters, above, the smoother gains more than 10 % on both)
    assert rms_s < rms_f, (rms_s, rms_f)
    cov = r.cov[skip:]
    nees = np.einsum("ni,nij,nj->n", es, np.linalg.inv(cov), es)
    if scenario == "accel_bursts":
        covf = r.filtered_cov[skip:]
        nees_f = np.einsum("ni,nij,nj->n", ef, np.linalg.inv(covf), ef)
        assert nees.mean() < 2.0 * nees_f.mean(), (nees.mean(), nees_f.mean())
    else:
        # (measured 0.45–0.71: the low-pass of the accelerometer carries the gyro bias's prior
        # uncertainty, docs/math.md §9.1, and the simulated gyro has no bias)
        assert 0.3 < nees.mean() < 6.0, nees.mean()
        assert np.mean(nees <= 14.16) >= 0.9
    assert np.isfinite(r.quat).all() and np.isfinite(r.cov).all()
    np.testing.assert_array_equal(r.cov, np.swapaxes(r.cov, 1, 2))
    assert np.linalg.eigvalsh(r.cov).min() >= 0
    assert np.linalg.eigvalsh(r.cov).max() <= np.pi ** 2 / 3 * (1 + 1e-9)
    # the last sample has no future: smoothed = filtered
    np.testing.assert_allclose(r.quat[-1], r.filtered_quat[-1], atol=1e-12)
    np.testing.assert_allclose(r.cov[-1], r.filtered_cov[-1], atol=1e-15)


def test_causal_outputs_unchanged_by_smoothing() -> None:
    """The forward pass is the causal filter: ``filtered_quat`` equals :func:`estimate`'s with
    the forward pass's defaults (the heading's full gain on the bias, docs/math.md §11.1)."""
    d = simulate("slow_rotation", duration=5.0, seed=2)
    r = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, mag_bias_gain=1.0)
    s = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, smooth=True)
    np.testing.assert_array_equal(s.filtered_quat, r.quat)
    np.testing.assert_array_equal(s.filtered_cov, r.cov)


@pytest.mark.parametrize("use_mag", [True, False])
def test_windowed_equals_full_interval(use_mag: bool) -> None:
    """(4) Windows of 2000 samples with 4000 of overlap (40 s at 100 Hz) against the
    full-interval smoother on a 2-minute recording with a gyro bias and a gap (a
    re-alignment): every attitude within 0.01° (the overlap's truncation, docs/math.md §11.4;
    measured: 0.06° with 5 s of overlap, 0.005° with 20 s, < 0.003° with 40 s)."""
    d = simulate("wiener", duration=120.0, seed=5, gyro_bias=(0.01, -0.02, 0.005))
    gyr = d.gyr.copy()
    dts = np.concatenate([[0.0], np.diff(d.t)])
    dts[6000] = 1.0  # a gap: longer than max_dt
    mag = d.mag if use_mag else np.full_like(d.mag, np.nan)
    out = []
    for window, overlap in ((len(dts), 0), (2000, 4000)):
        f = AttitudeFilter(use_mag=use_mag)
        out.append(smooth_run(f, dts, gyr, d.acc, mag, window, overlap))
    (f_full, s_full), (f_win, s_win) = out
    np.testing.assert_array_equal(f_full.quat, f_win.quat)
    ang = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(s_full.quat * s_win.quat, axis=1)),
                                           0, 1)))
    assert ang.max() < 0.01, ang.max()
    # and the smoothing did something: far more than that from the filter
    angf = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(f_full.quat * s_full.quat, axis=1)),
                                            0, 1)))
    assert np.median(angf) > 10 * ang.max()


def test_default_overlap_is_a_minute_at_any_rate() -> None:
    """docs/math.md §11.4: the default overlap is 60 s of the recording, not a count of
    samples (at most one window, 2¹⁷ samples); the window stays 2¹⁷ samples; an explicit
    overlap is taken as given; without a known period one window's worth."""
    assert window_sizes(None, None, 1 / 100) == (131072, 6000)
    assert window_sizes(None, None, 1 / 286) == (131072, 17160)
    assert window_sizes(None, None, 1 / 1000) == (131072, 60000)
    assert window_sizes(None, None, 1 / 4000) == (131072, 131072)
    assert window_sizes(500, 7, 1 / 1000) == (500, 7)
    assert window_sizes(500, None, 0.0) == (500, 500)
    with pytest.raises(ValueError, match="window must be >= 1"):
        window_sizes(0, None, 0.01)
    with pytest.raises(ValueError, match="overlap >= 0"):
        window_sizes(10, -1, 0.01)


def test_default_overlap_spans_a_fast_recording() -> None:
    """At 1 kHz a 40 s recording smoothed in windows of 4000 samples with the default overlap
    (60 s) is the full-interval smoother's, bit for bit: every window's backward pass starts
    from the recording's end (with an overlap of 2¹⁵ samples, 33 s at this rate, it did not)."""
    d = simulate("wiener", duration=40.0, rate=1000.0, seed=3)
    full = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, smooth=True)
    win = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, smooth=True, smooth_window=4000)
    short = mkf_ros.estimate(d.gyr, d.acc, d.mag, timestamps=d.t, smooth=True,
                             smooth_window=4000, smooth_overlap=1 << 15)
    np.testing.assert_array_equal(win.quat, full.quat)
    np.testing.assert_array_equal(win.cov, full.cov)
    assert not np.array_equal(short.quat, full.quat)


def test_smoother_refuses_baselines() -> None:
    d = simulate("slow_rotation", duration=1.0, seed=0)
    with pytest.raises(ValueError, match="mekf or mukf"):
        mkf_ros.estimate(d.gyr, d.acc, timestamps=d.t, algorithm="madgwick", smooth=True)


def test_reversed_inputs_integrate_the_path_backwards() -> None:
    """(§11.5) A step's gyro and Δt describe the interval ending at its sample: integrating the
    reversed recording's yaw rate gives, at every sample, the forward path's angle there minus
    its final angle (the rotation from the end back to that sample), with uneven steps."""
    rng = np.random.default_rng(0)
    n = 50
    dts = rng.uniform(0.005, 0.02, n)
    w = rng.normal(0.0, 2.0, n)
    gyr = np.column_stack([np.zeros(n), np.zeros(n), w])
    acc = rng.normal(size=(n, 3))
    mag = rng.normal(size=(n, 3))
    theta = np.cumsum(w * dts)  # forward angle at each sample (the first step from t = −Δt₀)
    dr, gr, ar, mr = reversed_inputs(dts, gyr, acc, mag)
    phi = np.cumsum(gr[1:, 2] * dr[1:])  # from the reversed first sample (the last one)
    np.testing.assert_allclose(phi, (theta[::-1] - theta[-1])[1:], atol=1e-12)
    np.testing.assert_array_equal(ar, acc[::-1])
    np.testing.assert_array_equal(mr, mag[::-1])
    assert (dr > 0).all()


def test_reversed_pass_streamed_starts_anew_at_each_reset() -> None:
    """``smooth_reversed_into`` (``mkf process --smooth two-way``'s reversed pass) over two
    recordings one after the other (a step per row: ``Δt, ω_g, a, m``), told that the filter
    started anew at the second: each recording's rows are those of the smoother over that
    recording reversed alone (``smooth_run`` over ``reversed_inputs``), bit for bit, in windows
    shorter than either; it reads forward blocks of at most a window + overlap (+ the next
    step) and hands every step's row out once."""
    recs = [simulate(s, duration=3.0, rate=100.0, mag_rate=25.0, seed=i)
            for i, s in enumerate(("slow_rotation", "wiener"))]
    u = np.concatenate([np.column_stack([np.r_[0.01, np.diff(d.t)], d.gyr, d.acc, d.mag])
                        for d in recs])
    n = len(u)
    reads: list[tuple[int, int]] = []

    def read(a: int, b: int) -> tuple[np.ndarray, ...]:
        reads.append((a, b))
        return u[a:b, 0], u[a:b, 1:4], u[a:b, 4:7], u[a:b, 7:10]

    q, P, ok = np.zeros((n, 4)), np.zeros((n, 3, 3)), np.zeros(n, dtype=bool)
    seen = np.zeros(n, dtype=int)

    def write(first: int, qb: np.ndarray, Pb: np.ndarray, okb: np.ndarray) -> None:
        sl = slice(first, first + len(okb))
        q[sl], P[sl], ok[sl] = qb, Pb, okb
        seen[sl] += 1

    params = AttitudeFilter(use_mag=True).params
    ticks: list[int] = []
    smooth_reversed_into(params, n, read, [len(recs[0].t)], 120, 70, write,
                         ticks.append)  # type: ignore[arg-type]
    assert sum(ticks) == n and len(ticks) == 4  # two windows per recording
    assert (seen == 1).all() and all(b - a <= 191 for a, b in reads)
    start = 0
    for d in recs:
        part = slice(start, start + len(d.t))
        seg = u[part]
        filt, sm = smooth_run(AttitudeFilter(params), *reversed_inputs(
            seg[:, 0], seg[:, 1:4], seg[:, 4:7], seg[:, 7:10]), 120, 70)
        np.testing.assert_array_equal(q[part], sm.quat[::-1])
        np.testing.assert_array_equal(P[part], sm.cov[::-1])
        np.testing.assert_array_equal(ok[part], filt.initialized[::-1])
        assert ok[part].sum() > 0.9 * len(d.t)
        start += len(d.t)


def test_smooth_stream_holds_one_window() -> None:
    """``smooth_stream`` reads the recording in pieces of at most ``window + overlap``
    samples, in order, each once, and yields every sample's rows once, in order."""
    d = simulate("slow_rotation", duration=5.0, rate=100.0, seed=1)
    dts = np.r_[0.01, np.diff(d.t)]
    reads: list[tuple[int, int]] = []

    def read(a: int, b: int) -> tuple[np.ndarray, ...]:
        reads.append((a, b))
        return dts[a:b], d.gyr[a:b], d.acc[a:b], np.full((b - a, 3), np.nan)

    got = [(pos, len(sr.initialized)) for pos, _, sr in
           smooth_stream(AttitudeFilter(), len(dts), read, 100, 60)]  # type: ignore[arg-type]
    assert all(b - a <= 160 for a, b in reads)
    assert [a for a, _ in reads] == [0, *(b for _, b in reads[:-1])] and reads[-1][1] == len(dts)
    assert [p for p, _ in got] == list(np.cumsum([0] + [k for _, k in got])[:-1])
    assert sum(k for _, k in got) == len(dts)


def _q_rotvec(v: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(v)
    return np.r_[np.cos(th / 2), v / th * np.sin(th / 2)] if th > 0 else np.r_[1.0, 0, 0, 0]


def _q_yaw_pitch_roll(yaw: float, pitch: float, roll: float) -> np.ndarray:
    qz, qy, qx = (_q_rotvec(np.array(v)) for v in ([0, 0, yaw], [0, pitch, 0], [roll, 0, 0]))
    return qmul_np(qmul_np(qz, qy), qx)


@pytest.mark.parametrize("yaw_b", [0.0, 1.2, -2.9])
def test_fuse_tilt_meets_halfway_whatever_the_second_heading(yaw_b: float) -> None:
    """(§11.5) Two estimates of equal, independent tilt variance whose tilts differ by 2°
    about the world x axis fuse to the midpoint (1° from each), whatever heading the second's
    world frame gave it. The two share their samples (correlation unknown): the published
    tilt variance is covariance intersection's bound (ω = ½), here the inputs' own, not half
    of it, plus the two estimates' spread about the midpoint, (1°)² about x (eq. 11.5d: a
    mixture of the two with equal weights); the heading's is the first's. A non-finite second
    estimate leaves the first."""
    q_true = _q_yaw_pitch_roll(0.7, 0.2, -0.1)
    err = np.radians(2.0)
    q_f = qmul_np(_q_rotvec(np.array([err, 0, 0])), q_true)[None]  # world-axis error 2°
    q_b = qmul_np(_q_rotvec(np.array([0, 0, yaw_b])), q_true)[None]  # exact tilt, own heading
    a, c = 1e-4, 4e-3
    P_f = np.diag([a, a, c])[None]
    P_b = np.diag([a, a, 9.0])[None]
    q, P = fuse_tilt(q_f, P_f, q_b, P_b)
    e = _world_error(q, q_true[None])[0]
    np.testing.assert_allclose(e, _world_error(q_f, q_true[None])[0] / 2, atol=1e-6)
    assert abs(np.linalg.norm(e) - err / 2) < 1e-6
    np.testing.assert_allclose(P[0], np.diag([a + (err / 2) ** 2, a, c]), rtol=1e-6,
                               atol=1e-12)
    q2, P2 = fuse_tilt(np.r_[q_f, q_f], np.r_[P_f, P_f], np.r_[q_b, np.full((1, 4), np.nan)],
                       np.r_[P_b, P_b])
    np.testing.assert_array_equal(q2[1], q_f[0])
    np.testing.assert_array_equal(P2[1], P_f[0])


def test_fuse_tilt_covariance_is_symmetric_psd_for_random_inputs() -> None:
    rng = np.random.default_rng(3)
    n = 200
    q = rng.normal(size=(2, n, 4))
    q /= np.linalg.norm(q, axis=2, keepdims=True)
    L = rng.normal(size=(2, n, 3, 3)) * 0.1
    P = L @ np.swapaxes(L, 2, 3)
    qf, Pf = fuse_tilt(q[0], P[0], q[1], P[1])
    np.testing.assert_allclose(np.linalg.norm(qf, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(Pf, np.swapaxes(Pf, 1, 2))
    assert np.linalg.eigvalsh(Pf).min() > -1e-15
    # covariance intersection's bound: where the two tilts agree (the second a turn of the
    # first about the vertical) the fused tilt variance is never above twice the first's
    twist = np.c_[np.cos(q[1][:, 0]), np.zeros((n, 2)), np.sin(q[1][:, 0])]
    _, Pt = fuse_tilt(q[0], P[0], qmul_np(twist, q[0]), P[1])
    assert (np.trace(Pt[:, :2, :2], axis1=1, axis2=2)
            <= 2 * np.trace(P[0][:, :2, :2], axis1=1, axis2=2) * (1 + 1e-9)).all()


@pytest.mark.parametrize("deg", [0.5, 5.0, 30.0])
def test_fuse_tilt_covers_two_estimates_that_disagree(deg: float) -> None:
    """(eq. 11.5d) Two estimates whose tilts differ by far more than their covariances say
    (σ 0.06–0.11°): a model is wrong somewhere, and the published tilt covariance covers both
    of them: the second moment of two points of equal weight puts each within √2 σ
    (Mahalanobis² ≤ 2) of the fused estimate, where covariance intersection's bound alone put
    them 2–250σ away."""
    q_true = _q_yaw_pitch_roll(-0.4, 0.1, 0.3)
    th = np.radians(deg)
    axis = np.array([0.6, 0.8, 0.0])
    q_f = qmul_np(_q_rotvec(th / 2 * axis), q_true)[None]
    q_b = qmul_np(_q_rotvec(-th / 2 * axis), q_true)[None]
    a = 1e-6
    P_f, P_b = np.diag([a, a, 1e-3])[None], np.diag([a, 4 * a, 1e-3])[None]
    q, P = fuse_tilt(q_f, P_f, q_b, P_b)
    for other in (q_f, q_b):
        e = _world_error(other, q)[0][:2]  # the other estimate's tilt about the fused one
        assert e @ np.linalg.solve(P[0, :2, :2], e) <= 2.0 + 1e-3, deg


@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
def test_two_way_smoother_on_a_run(algorithm: str) -> None:
    """(§11.5) Smoothed both ways, on a simulated sensor carried by a runner (2 min in a pocket,
    default parameters): the tilt error is below the causal filter's, the covariance finite,
    symmetric PSD and honest (≥ 90 % of the tilt errors within 3σ); the heading, omega and
    bias are the forward smoother's."""
    d = simulate("running", duration=60.0, seed=2)
    kw = dict(timestamps=d.t, algorithm=algorithm)
    r = mkf_ros.estimate(d.gyr, d.acc, d.mag, smooth="two-way", **kw)
    s = mkf_ros.estimate(d.gyr, d.acc, d.mag, smooth=True, **kw)
    skip = 200
    up = np.array([0.0, 0.0, 1.0])

    def tilt(q: np.ndarray) -> np.ndarray:
        e = _world_error(q, d.quat)[skip:]
        return e - np.outer(e @ up, up)

    t_two, t_filt = tilt(r.quat), tilt(r.filtered_quat)
    rms = [float(np.sqrt(np.mean(np.sum(t ** 2, axis=1)))) for t in (t_two, t_filt)]
    assert rms[0] < rms[1], rms
    cov = r.cov[skip:, :2, :2]
    m = np.einsum("ni,nij,nj->n", t_two[:, :2], np.linalg.inv(cov), t_two[:, :2])
    assert np.mean(m <= 11.83) >= 0.9  # χ²₂ at 99.73 %
    assert np.isfinite(r.quat).all() and np.isfinite(r.cov).all()
    np.testing.assert_array_equal(r.cov, np.swapaxes(r.cov, 1, 2))
    assert np.linalg.eigvalsh(r.cov).min() >= 0
    np.testing.assert_array_equal(r.omega, s.omega)
    np.testing.assert_array_equal(r.bias, s.bias)
    np.testing.assert_array_equal(r.filtered_quat, s.filtered_quat)


def test_smooth_mode_is_checked() -> None:
    d = simulate("slow_rotation", duration=1.0, seed=0)
    with pytest.raises(ValueError, match="smooth must be"):
        mkf_ros.estimate(d.gyr, d.acc, timestamps=d.t, smooth="backwards")
