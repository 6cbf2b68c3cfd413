"""MEKF (docs/math.md §5): known-answer test, and the kernels against a literal transcription."""

from __future__ import annotations

import numpy as np
import pytest
from spec_reference import (
    mekf_heading_update_ref,
    mekf_predict_ref,
    mekf_update_ref,
    mekf_vector_update_ref,
)

from mkf_ros.core.charts import CHART_NAMES, chart_id, from_chart, t_matrix
from mkf_ros.core.mekf import (
    free_heading_transport_t,
    mekf_apply,
    mekf_gyro_update,
    mekf_heading_update,
    mekf_predict,
    mekf_update,
    mekf_vector_update,
)
from mkf_ros.core.quaternion import qmul, rotmat


def _kat_inputs() -> tuple:
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    return q, np.array([0.5, -0.2, 0.1]), np.zeros(3), np.diag([0.01, 0.02, 0.03, 0.1, 0.1, 0.1])


def _kat_step(chart: str, cu: bool) -> tuple:
    q, w, b, P6 = _kat_inputs()
    P = np.zeros((9, 9))
    P[:6, :6] = P6
    mekf_predict(q, w, P, 6, 0.01, np.eye(3), np.zeros((3, 3)))
    ok = mekf_update(chart_id(chart), cu, (q, w, b), P, 6,
                     (np.array([[0.1, -0.2, 0.97]]), np.array([[0.0, 0.0, 1.0]]),
                      np.array([1e-4 * np.eye(3)]), np.array([0.01 * np.eye(3)]),
                      np.array([True])),
                     (np.array([0.52, -0.18, 0.12]), True, 1e-4 * np.eye(3)))
    assert ok
    return q, w, P[:6, :6]


@pytest.mark.parametrize("cu", [True, False])
def test_known_answer_rp(cu: bool) -> None:
    """§5 known-answer test (RP chart, one step), chart update and reset, to 1e-6."""
    q, w, P = _kat_step("rp", cu)
    np.testing.assert_allclose(q, [0.947370, 0.007849, -0.161872, 0.276090], atol=1e-6)
    np.testing.assert_allclose(w, [0.519974, -0.180002, 0.119987], atol=1e-6)
    if cu:
        diag = [6.068587e-3, 6.274503e-3, 1.845337e-2] + [9.9909e-5] * 3
        p01 = 1.539248e-4
    else:
        diag = [7.742978e-3, 6.769181e-3, 1.772198e-2] + [9.9909e-5] * 3
        p01 = 3.993013e-4
    np.testing.assert_allclose(np.diag(P), diag, atol=1e-6, rtol=1e-5)
    assert abs(P[0, 1] - p01) < 1e-6 * 1e-3 + 1e-9


def test_known_answer_rv() -> None:
    q, _, _ = _kat_step("rv", True)
    np.testing.assert_allclose(q, [0.947460, 0.006643, -0.160020, 0.276893], atol=1e-6)


def _random_case(rng: np.random.Generator, nx: int) -> tuple:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    A = rng.normal(size=(nx, nx)) * 0.1
    P = A @ A.T + 1e-3 * np.eye(nx)
    return q, rng.normal(size=3), rng.normal(size=3) * 0.01 * (nx == 9), P


@pytest.mark.parametrize("nx", [6, 9])
@pytest.mark.parametrize("chart", CHART_NAMES)
@pytest.mark.parametrize("cu", [True, False])
def test_kernel_equals_joint_update(nx: int, chart: str, cu: bool) -> None:
    """Predict + update with two vector sensors (one non-isotropic disturbance) and the gyro:
    the block-sequential kernel equals the spec's joint update to 1e-10."""
    rng = np.random.default_rng(nx * 10 + chart_id(chart) + 100 * cu)
    for _ in range(20):
        q, w, b, P0 = _random_case(rng, nx)
        Qw, Qb, dt = np.diag([1.0, 2.0, 0.5]), 1e-6 * np.eye(3), 0.02
        vrefs = [np.array([0, 0, 1.0]), np.array([0, 0.5, -0.8])]
        # readings near the prediction (large random ones would saturate the chart at 180°,
        # where the RV T-matrix is discontinuous and rounding picks a side)
        vms = [rotmat(q).T @ v + rng.normal(size=3) * 0.2 for v in vrefs]
        Rvs = [1e-3 * np.eye(3), 4e-4 * np.eye(3)]
        B = rng.normal(size=(3, 3)) * 0.05
        Qvs = [1e-2 * np.eye(3), B @ B.T]
        wm = w + rng.normal(size=3) * 0.1
        Rw = 1e-4 * np.eye(3)
        qr, Pr = mekf_predict_ref(q, w, P0, nx, dt, Qw, Qb)
        qr, wr, br, Pr = mekf_update_ref(chart_id(chart), cu, qr, w, b, Pr, nx, vms, vrefs, Rvs,
                                         Qvs, wm, Rw)
        qk, wk, bk = q.copy(), w.copy(), b.copy()
        Pk = np.zeros((9, 9))
        Pk[:nx, :nx] = P0
        mekf_predict(qk, wk, Pk, nx, dt, Qw, Qb)
        assert mekf_update(chart_id(chart), cu, (qk, wk, bk), Pk, nx,
                           (np.array(vms), np.array(vrefs), np.array(Rvs), np.array(Qvs),
                            np.array([True, True])), (wm, True, Rw))
        np.testing.assert_allclose(qk, qr, atol=1e-10)
        np.testing.assert_allclose(wk, wr, atol=1e-10)
        np.testing.assert_allclose(bk, br, atol=1e-10)
        np.testing.assert_allclose(Pk[:nx, :nx], Pr, atol=1e-10)


def test_any_subset_of_sensors() -> None:
    """Gyro only or vector only (§8 item 15); with nothing the state is unchanged."""
    rng = np.random.default_rng(7)
    q, w, b, P0 = _random_case(rng, 6)
    vm = np.array([[0.0, 0.1, 1.0]])
    vr = np.array([[0.0, 0.0, 1.0]])
    Rv = np.array([1e-3 * np.eye(3)])
    for use_v, use_w in ([False], True), ([True], False):
        k = 1 if use_v[0] else 0
        qr, _, _, Pr = mekf_update_ref(1, True, q, w, b, P0, 6, [vm[0]][:k], [vr[0]][:k],
                                         [Rv[0]][:k], [Rv[0]][:k], w + 0.1 if use_w else None,
                                         1e-4 * np.eye(3))
        qk, wk, bk = q.copy(), w.copy(), b.copy()
        Pk = np.zeros((9, 9))
        Pk[:6, :6] = P0
        mekf_update(1, True, (qk, wk, bk), Pk, 6, (vm, vr, Rv, Rv, np.array(use_v)),
                    (w + 0.1, use_w, 1e-4 * np.eye(3)))
        np.testing.assert_allclose(qk, qr, atol=1e-12)
        np.testing.assert_allclose(Pk[:6, :6], Pr, atol=1e-12)
    qk, Pk = q.copy(), np.zeros((9, 9))
    Pk[:6, :6] = P0
    mekf_update(1, True, (qk, w.copy(), b.copy()), Pk, 6, (vm, vr, Rv, Rv, np.array([False])),
                (w, False, 1e-4 * np.eye(3)))
    np.testing.assert_allclose(qk, q, atol=1e-15)
    np.testing.assert_allclose(Pk[:6, :6], P0, atol=1e-15)


def test_not_positive_definite_is_reported_not_nan() -> None:
    q, w, b, _ = _random_case(np.random.default_rng(1), 6)
    P = np.zeros((9, 9))
    P[0, 0] = -1.0  # corrupt
    ok = mekf_update(1, True, (q, w, b), P, 6,
                     (np.array([[0, 0, 1.0]]), np.array([[0, 0, 1.0]]), np.zeros((1, 3, 3)),
                      np.zeros((1, 3, 3)), np.array([True])), (w, False, np.eye(3)))
    assert not ok
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(P))


@pytest.mark.parametrize("nx", [6, 9])
def test_update_equals_public_blocks(nx: int) -> None:
    """mekf_update (tuple rotation, one scratch array, inlined blocks) equals the public block
    kernels the product filter calls, one after another, to the last bit."""
    rng = np.random.default_rng(11 + nx)
    q, w, b, P0 = _random_case(rng, nx)
    vrefs = np.array([[0, 0, 1.0], [0, 0.5, -0.8]])
    vms = np.array([rotmat(q).T @ v + rng.normal(size=3) * 0.2 for v in vrefs])
    B = rng.normal(size=(3, 3)) * 0.05
    Rv, Qv = np.array([1e-3 * np.eye(3), 4e-4 * np.eye(3)]), np.array([1e-2 * np.eye(3), B @ B.T])
    wm, Rw = w + rng.normal(size=3) * 0.1, 1e-4 * np.eye(3)
    out = []
    for public in (False, True):
        qk, wk, bk = q.copy(), w.copy(), b.copy()
        Pk = np.zeros((9, 9))
        Pk[:nx, :nx] = P0
        if public:
            R, dx = rotmat(qk), np.zeros(nx)
            for k in range(2):
                assert mekf_vector_update(Pk, nx, dx, R, vms[k], vrefs[k], Rv[k], Qv[k],
                                          np.inf) >= 0
            assert mekf_gyro_update(Pk, nx, dx, wk, bk, wm, Rw, np.inf) >= 0
            mekf_apply(2, True, qk, wk, bk, Pk, nx, dx)
        else:
            assert mekf_update(2, True, (qk, wk, bk), Pk, nx,
                               (vms, vrefs, Rv, Qv, np.array([True, True])), (wm, True, Rw))
        out.append(np.concatenate([qk, wk, bk, Pk.ravel()]))
    np.testing.assert_array_equal(out[0], out[1])


# ---------------------------------------------------------------- heading-only magnetometer


def _psi(q: np.ndarray, m_body: np.ndarray, ref: np.ndarray) -> float:
    """The heading residual of the spec's measurement ``0 = ψ(q)``, from the rotation matrix
    (independent of the kernel): the angle about the world vertical from the horizontal part
    of ``R(q) m`` to the horizontal reference."""
    mw = rotmat(q) @ m_body
    return float(np.arctan2(mw[0] * ref[1] - mw[1] * ref[0], mw[0] * ref[0] + mw[1] * ref[1]))


def _heading_case(seed: int) -> tuple:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    dip = np.radians(rng.uniform(-70.0, 70.0))
    ref_w = np.array([0.0, np.cos(dip), np.sin(dip)])  # field: north and dip
    psi_err = np.radians(rng.uniform(-10.0, 10.0))  # the measured field is off by this
    qz = np.array([np.cos(psi_err / 2), 0.0, 0.0, np.sin(psi_err / 2)])
    m_body = rotmat(q).T @ (rotmat(qz) @ ref_w)
    return q, m_body, np.array([0.0, 1.0, 0.0]), dip


@pytest.mark.parametrize("seed", range(5))
def test_heading_jacobian_matches_finite_differences(seed: int) -> None:
    """The MEKF's heading update (docs/math.md §9.2) linearises ψ(q̄ * δ(e)) with the full Jacobian,
    tilt coupling (≈ tan(dip)) included, so that ``S = H P Hᵀ + var`` counts the tilt
    uncertainty. Read ``S`` back from the returned NIS = r²/S for attitude covariances
    ``ε a aᵀ`` along several directions a and compare ``(S − var)/ε = (H·a)²`` with central
    differences of ψ about q̄ (the old ``H = −uᵀ`` fails this wherever the dip is not zero)."""
    q, m_body, ref, dip = _heading_case(seed)
    h = 1e-6
    fd = np.array([(_psi(qmul(q, from_chart(chart_id("rv"), h * e)), m_body, ref)
                    - _psi(qmul(q, from_chart(chart_id("rv"), -h * e)), m_body, ref)) / (2 * h)
                   for e in np.eye(3)])
    u = rotmat(q)[2]  # the world vertical in body axes: a turn about it moves ψ by −1
    assert fd @ u == pytest.approx(-1.0, abs=1e-6)
    eps, var = 1e-4, 1e-3
    r = -_psi(q, m_body, ref)
    dirs = [*np.eye(3), np.array([1.0, 1.0, 0.0]), np.array([0.0, 1.0, -1.0]),
            np.array([1.0, 0.0, 1.0]), u]
    for a in dirs:
        P = np.zeros((9, 9))
        P[:3, :3] = eps * np.outer(a, a)
        nis = mekf_heading_update(P, 6, np.zeros(9), rotmat(q), m_body, ref, var, np.inf)
        assert (r * r / nis - var) / eps == pytest.approx((fd @ a) ** 2, rel=1e-5, abs=1e-9)
    tilt = fd - (fd @ u) * u
    if abs(dip) > np.radians(20):
        assert np.linalg.norm(tilt) > 0.3 * abs(np.tan(dip))  # the coupling the old H dropped


@pytest.mark.parametrize("seed", range(3))
def test_heading_update_agrees_with_the_mukf(seed: int) -> None:
    """For a small covariance the MEKF's linearised heading row and the MUKF's, which carries
    ψ through the sigma points, see the same innovation covariance and move the estimate
    alike (the two filters disagreed while the MEKF's heading row had no tilt coupling)."""
    from mkf_ros.core.filter import AttitudeFilter

    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    field = np.array([0.0, np.cos(0.9), -np.sin(0.9)])  # north, dip 52° down
    acc = rotmat(q).T @ np.array([0.0, 0.0, 9.80665])
    qz = np.array([np.cos(0.02), 0.0, 0.0, np.sin(0.02)])  # then the field turns by 2.3°
    mags = (rotmat(q).T @ field, rotmat(q).T @ (rotmat(qz) @ field))
    res = {}
    for algorithm in ("mekf", "mukf"):
        # a small covariance: the linearisation's premise (a looser mag_disturbance than 0.05
        # widens the heading prior and the two differ by its curvature, 2.6 % at 0.1)
        f = AttitudeFilter(algorithm=algorithm, use_mag=True, mag_reference=list(field),
                           rest_detection=False,
                           mag_disturbance=0.05)
        f.step(0.0, np.zeros(3), acc, mags[0])  # alignment: heading from this field
        for _ in range(20):
            f.step(0.01, np.zeros(3), acc, mags[0])
        q0 = f.quaternion
        f.step(0.01, np.zeros(3), acc, mags[1])
        d = qmul(f.quaternion, q0 * np.array([1.0, -1.0, -1.0, -1.0]))  # world-frame change
        res[algorithm] = (q0, 2.0 * np.arcsin(np.clip(d[3], -1.0, 1.0)), f.covariance)
    (a0, ta, ca), (b0, tb, cb) = res["mekf"], res["mukf"]
    assert np.degrees(np.arccos(min(1.0, abs(a0 @ b0)))) * 2 < 0.05  # the same prior
    assert abs(ta) > 1e-5  # the update did turn the estimate
    assert ta == pytest.approx(tb, rel=0.02)
    assert ca[2, 2] == pytest.approx(cb[2, 2], rel=0.05)  # the yaw variance after it


# ---------------------------------------------------------------- the extensions' updates,
# against literal transcriptions (spec_reference.py): the tilt-only accelerometer and the
# heading-only magnetometer, each a Kalman update with a projected gain in Joseph form


@pytest.mark.parametrize("nx", [6, 9])
@pytest.mark.parametrize("tilt_only", [True, False], ids=["tilt_only", "vector"])
def test_vector_update_equals_transcription(nx: int, tilt_only: bool) -> None:
    """mekf_vector_update (tilt-only: the closed form ``P − K₀(PHᵀ)ᵀ + c_gh u uᵀ`` of the
    Joseph form) equals ``(I − KH) P (I − KH)ᵀ + K R Kᵀ`` with ``K = blockdiag(I − uuᵀ) K₀``,
    the state correction ``K r`` and the NIS, after an earlier block has moved Δx."""
    rng = np.random.default_rng(31 + nx + 2 * tilt_only)
    for _ in range(10):
        q, _, _, P0 = _random_case(rng, nx)
        vref = np.array([0.0, 0.0, 1.0])
        vm = rotmat(q).T @ vref + rng.normal(size=3) * 0.2
        B = rng.normal(size=(3, 3)) * 0.05
        Rv, Qv = 1e-3 * np.eye(3), B @ B.T + 1e-2 * np.eye(3)
        dx0 = rng.normal(size=nx) * 0.01
        Pr, dxr, nisr = mekf_vector_update_ref(P0, nx, dx0, q, vm, vref, Rv, Qv, tilt_only)
        Pk = np.zeros((9, 9))
        Pk[:nx, :nx] = P0
        dxk = dx0.copy()
        nis = mekf_vector_update(Pk, nx, dxk, rotmat(q), vm, vref, Rv, Qv, np.inf, tilt_only)
        np.testing.assert_allclose(Pk[:nx, :nx], Pr, atol=1e-12)
        np.testing.assert_allclose(dxk, dxr, atol=1e-12)
        assert nis == pytest.approx(nisr, rel=1e-10)
        if tilt_only:  # nothing about the world vertical, for any group
            u = rotmat(q)[2]
            for g in range(nx // 3):
                assert abs(u @ (dxk - dx0)[3 * g:3 * g + 3]) < 1e-14


@pytest.mark.parametrize("bias_gain", [1.0, 0.3])
@pytest.mark.parametrize("nx", [6, 9])
def test_heading_update_equals_transcription(nx: int, bias_gain: float) -> None:
    """mekf_heading_update equals the literal heading-only Kalman update: ``H = [−(d × m), 0]``,
    the gain of each group projected onto the vertical, the bias's times ``bias_gain``
    (``mag_bias_gain``, docs/math.md §9.2), Joseph form, innovation ``−ψ − HΔx``."""
    for seed in range(8):
        q, m_body, ref, _ = _heading_case(100 + seed)
        rng = np.random.default_rng(seed)
        A = rng.normal(size=(nx, nx)) * 0.05
        P0 = A @ A.T + 1e-4 * np.eye(nx)
        dx0 = rng.normal(size=nx) * 0.01
        var = 1e-3
        Pr, dxr, nisr = mekf_heading_update_ref(P0, nx, dx0, q, m_body, ref, var, bias_gain)
        Pk = np.zeros((9, 9))
        Pk[:nx, :nx] = P0
        dxk = dx0.copy()
        nis = mekf_heading_update(Pk, nx, dxk, rotmat(q), m_body, ref, var, np.inf, bias_gain)
        np.testing.assert_allclose(Pk[:nx, :nx], Pr, atol=1e-12)
        np.testing.assert_allclose(dxk, dxr, atol=1e-12)
        assert nis == pytest.approx(nisr, rel=1e-10)


@pytest.mark.parametrize("chart", CHART_NAMES)
def test_free_heading_transport_carries_the_vertical(chart: str) -> None:
    """docs/math.md §9.3: with the heading unobserved the chart update's map ``M`` takes the
    world vertical in the body before the correction, ``u``, to the one after it, ``u⁺ =
    R(δ̄)ᵀ u``, and acts as the chart's ``T(δ̄)`` on every direction across ``u``. The reason,
    checked on quaternions: the reset's error ``δ̄* ⊗ exp(θ u)`` is ``exp(θ u⁺) ⊗ δ̄*``, so it
    tilts the body by the same angle whatever the heading error θ."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        d = from_chart(chart_id(chart), rng.normal(0.0, 0.05, 3))
        qn = qmul(q, d)
        u, un = rotmat(q)[2], rotmat(qn)[2]
        np.testing.assert_allclose(un, rotmat(d).T @ u, atol=1e-12)
        T = t_matrix(chart_id(chart), d)
        M = np.array(free_heading_transport_t(tuple(map(tuple, T)), tuple(u), tuple(un)))
        np.testing.assert_allclose(M @ u, un, atol=1e-12)
        w = np.cross(u, rng.normal(size=3))
        np.testing.assert_allclose(M @ w, T @ w, atol=1e-12)
        tilts = []
        for theta in (0.1, 1.0, 3.0):
            e = np.concatenate([[np.cos(theta / 2)], np.sin(theta / 2) * u])  # exp(θ u)
            err = qmul(d * np.array([1.0, -1.0, -1.0, -1.0]), e)  # δ̄* ⊗ exp(θ u)
            tilts.append(np.arccos(np.clip(rotmat(err).T @ un @ un, -1.0, 1.0)))
        np.testing.assert_allclose(tilts, tilts[0], atol=1e-9)
