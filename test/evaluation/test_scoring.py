"""Scoring against an optical reference (mkf_ros.evaluation.scoring): the BROAD error metric with
the constant global alignment, and the covariance honesty check :func:`tilt_coverage`, against
independent constructions (known errors built from rotation vectors, no real data)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from quat_helpers import canon, quat_z, random_quats

from mkf_ros.core.quaternion import qconj_np, qmul_np
from mkf_ros.evaluation.datasets import Recording
from mkf_ros.evaluation.metrics import orientation_errors
from mkf_ros.evaluation.scoring import (
    dataset_mean,
    error_series,
    global_alignment,
    quat_average,
    score_recording,
    swing_rotvec,
    tilt_coverage,
    tilt_coverage_counts,
    tilt_mahalanobis,
    tilt_sigma,
)

DEG = math.pi / 180.0


def qexp(rv: np.ndarray) -> np.ndarray:
    """Quaternion of rotation vectors (..., 3): angle |rv| about rv / |rv|."""
    rv = np.asarray(rv, dtype=float)
    th = np.linalg.norm(rv, axis=-1, keepdims=True)
    axis = np.divide(rv, th, out=np.zeros_like(rv), where=th > 0)
    return np.concatenate([np.cos(th / 2), np.sin(th / 2) * axis], axis=-1)


def _rec(q_ref: np.ndarray, alignment: str = "none") -> Recording:
    n = q_ref.shape[0]
    z = np.zeros((n, 3))
    return Recording("r", "test", np.arange(n) * 0.01, z, z, None, q_ref, alignment=alignment)


def _iso_cov(n: int, sigma: float) -> np.ndarray:
    return np.broadcast_to(sigma**2 * np.eye(3), (n, 3, 3)).copy()


# ----------------------------------------------------------------------------------- RMSE scoring
def test_alignment_recovers_constant_rotation() -> None:
    q_est = random_quats(300, 3)
    g_true = canon(np.array([0.3, -0.5, 0.7, 0.2]))
    q_ref = qmul_np(g_true, q_est)
    q_ref[::7] *= -1.0  # sign flips must not matter
    q_ref[5] = np.nan  # invalid rows are ignored
    g = global_alignment(q_est, q_ref)
    np.testing.assert_allclose(canon(g), g_true, atol=1e-12)
    s = score_recording(_rec(q_ref, "constant_global"), q_est)
    assert max(s.values()) < 1e-5
    # without the alignment the same estimate is far off
    assert score_recording(_rec(q_ref, "none"), q_est)["total"] > 10.0


def test_alignment_is_an_average_under_noise() -> None:
    rng = np.random.default_rng(7)
    q_est = random_quats(2000, 4)
    noise = canon(np.column_stack([np.ones(2000), rng.normal(0, 0.01, (2000, 3))]))
    g_true = canon(np.array([1.0, 0.2, 0.1, -0.3]))
    q_ref = qmul_np(qmul_np(g_true, noise), q_est)
    g = global_alignment(q_est, q_ref)
    assert 2 * np.degrees(np.arccos(min(1.0, abs(float(g @ g_true))))) < 0.1


def test_inclination_ignores_heading_offset() -> None:
    q_ref = random_quats(200, 5)
    q_est = qmul_np(quat_z(0.4), q_ref)  # world-frame heading offset of 0.4 rad
    s = score_recording(_rec(q_ref, "none"), q_est)
    assert s["inclination"] < 1e-5
    assert s["heading"] == pytest.approx(np.degrees(0.4), abs=1e-9)
    assert s["total"] == pytest.approx(np.degrees(0.4), abs=1e-9)
    tilt = np.array([math.cos(0.05), math.sin(0.05), 0.0, 0.0])  # 0.1 rad about world x
    s2 = score_recording(_rec(q_ref, "none"), qmul_np(tilt, q_est))
    assert s2["inclination"] == pytest.approx(np.degrees(0.1), rel=1e-6)


def test_scoring_meaningful_kinds_skip_start_and_mean() -> None:
    q_ref = random_quats(100, 6)
    r = _rec(q_ref, "none")
    r.errors = ("inclination",)
    q_est = q_ref.copy()
    q_est[:10] = qmul_np(np.array([math.cos(0.1), math.sin(0.1), 0, 0]), q_ref[:10])
    s = score_recording(r, q_est)
    assert np.isnan(s["total"]) and np.isnan(s["heading"]) and s["inclination"] > 1.0
    assert score_recording(r, q_est, skip_start=0.1)["inclination"] < 1e-5
    e = error_series(r, q_est, skip_start=0.05)
    assert np.isnan(e["inclination"][:5]).all() and np.isfinite(e["inclination"][5:]).all()
    m = dataset_mean([{"total": 1.0, "heading": 2.0, "inclination": 3.0},
                      {"total": 3.0, "heading": 4.0, "inclination": 5.0}])
    assert m == {"total": 2.0, "heading": 3.0, "inclination": 4.0}
    assert canon(quat_average(np.vstack([q_ref[0], -q_ref[0]]))) == pytest.approx(
        canon(q_ref[0]))




# ----------------------------------------------------------------------------------- swing
def test_swing_recovers_a_constructed_tilt_and_ignores_the_twist() -> None:
    """e = exp(ε) ⊗ twist_z(ψ) with a horizontal ε: the swing's rotation vector is ε, whatever
    ψ and the sign of e."""
    rng = np.random.default_rng(11)
    n = 2000
    ang = rng.uniform(0.0, math.pi * 0.999, n)
    az = rng.uniform(-math.pi, math.pi, n)
    eps = np.column_stack([ang * np.cos(az), ang * np.sin(az), np.zeros(n)])
    psi = rng.uniform(-math.pi, math.pi, n)
    e = qmul_np(qexp(eps), qexp(np.column_stack([np.zeros((n, 2)), psi])))
    e[::3] *= -1.0
    np.testing.assert_allclose(swing_rotvec(e), eps[:, :2], atol=1e-9)
    # tiny tilts (the r → 0 limit) and the identity
    small = np.array([[1e-9, -2e-9, 0.0], [0.0, 0.0, 0.0]])
    e2 = qmul_np(qexp(small), quat_z(0.7))
    np.testing.assert_allclose(swing_rotvec(e2), small[:, :2], atol=1e-15)
    # a half turn about a horizontal axis (n = 0): angle π about that axis
    half = np.array([0.0, math.cos(0.3), math.sin(0.3), 0.0])
    np.testing.assert_allclose(swing_rotvec(half), [math.pi * math.cos(0.3),
                                                    math.pi * math.sin(0.3)], atol=1e-12)


def test_swing_norm_is_the_broad_inclination() -> None:
    q_ref = random_quats(3000, 12)
    q_est = random_quats(3000, 13)  # arbitrary errors, up to half turns
    e = qmul_np(q_est, qconj_np(q_ref))
    incl = orientation_errors(q_est, q_ref)["inclination"]
    np.testing.assert_allclose(np.linalg.norm(swing_rotvec(e), axis=1), incl, atol=1e-9)


# ----------------------------------------------------------------------------------- coverage
@pytest.mark.parametrize("axis", [(1.0, 0.0), (0.0, 1.0), (math.sqrt(0.5), -math.sqrt(0.5))])
def test_coverage_of_a_known_tilt(axis: tuple[float, float]) -> None:
    """A 2° tilt error with σ = 1° about every axis: Mahalanobis distance 2, covered at k = 3
    and not at k = 1.5, whatever the horizontal axis and the heading."""
    q_ref = random_quats(50, 14)
    rv = np.array([axis[0], axis[1], 0.0]) * 2.0 * DEG
    q_est = qmul_np(qmul_np(qexp(rv), quat_z(0.3)), q_ref)  # tilt and a heading error
    r = _rec(q_ref)
    cov = _iso_cov(50, 1.0 * DEG)
    np.testing.assert_allclose(tilt_mahalanobis(r, q_est, cov), 2.0, rtol=1e-9)
    assert tilt_coverage(r, q_est, cov, k=3.0) == 1.0
    assert tilt_coverage(r, q_est, cov, k=1.5) == 0.0
    assert tilt_coverage_counts(r, q_est, cov, k=3.0) == (50, 50)


def test_pure_heading_error_is_always_covered() -> None:
    q_ref = random_quats(40, 15)
    q_est = qmul_np(quat_z(2.5), q_ref)  # 143° about world z
    r = _rec(q_ref)
    cov = _iso_cov(40, 1e-6)  # a tiny published covariance
    np.testing.assert_allclose(tilt_mahalanobis(r, q_est, cov), 0.0, atol=1e-6)
    assert tilt_coverage(r, q_est, cov, k=1e-3) == 1.0


def test_coverage_uses_the_full_2x2_block() -> None:
    """Random correlated covariances and random tilts: the distance is √(εᵀ Σ_xy⁻¹ ε) with the
    upper-left block; the z row and column play no part."""
    rng = np.random.default_rng(16)
    n = 500
    a = rng.normal(size=(n, 3, 3)) * 0.03
    cov = a @ np.swapaxes(a, 1, 2) + 1e-5 * np.eye(3)
    eps = np.column_stack([rng.normal(0, 0.05, (n, 2)), np.zeros(n)])
    q_ref = random_quats(n, 17)
    q_est = qmul_np(qmul_np(qexp(eps), qexp(np.column_stack([np.zeros((n, 2)),
                                                             rng.normal(0, 1, n)]))), q_ref)
    want = np.sqrt(np.einsum("ni,nij,nj->n", eps[:, :2], np.linalg.inv(cov[:, :2, :2]),
                             eps[:, :2]))
    got = tilt_mahalanobis(_rec(q_ref), q_est, cov)
    np.testing.assert_allclose(got, want, rtol=1e-7)
    cov2 = cov.copy()
    cov2[:, 2, :] = 123.0
    cov2[:, :, 2] = -7.0
    np.testing.assert_allclose(tilt_mahalanobis(_rec(q_ref), q_est, cov2), want, rtol=1e-7)


def test_gaussian_errors_with_the_published_covariance() -> None:
    """Errors drawn from N(0, Σ_xy): the coverage is the χ²(2) probability 1 − exp(−k²/2)."""
    rng = np.random.default_rng(18)
    n = 20000
    sxy = np.array([[4.0, 1.5], [1.5, 1.0]]) * DEG**2
    eps = rng.multivariate_normal([0.0, 0.0], sxy, n)
    q_ref = random_quats(n, 19)
    q_est = qmul_np(qexp(np.column_stack([eps, np.zeros(n)])), q_ref)
    cov = np.zeros((n, 3, 3))
    cov[:, :2, :2] = sxy
    cov[:, 2, 2] = 1.0
    r = _rec(q_ref)
    for k in (1.0, 2.0, 3.0):
        assert tilt_coverage(r, q_est, cov, k=k) == pytest.approx(1 - math.exp(-k * k / 2),
                                                                  abs=0.01)
    assert tilt_coverage(r, q_est, cov / 4.0, k=3.0) < 0.75  # overconfident by 2× in σ


def test_invalid_covariances_are_not_covered_and_unscored_samples_not_counted() -> None:
    q_ref = random_quats(8, 20)
    q_est = q_ref.copy()  # zero error: covered by any valid covariance
    cov = _iso_cov(8, 0.01)
    cov[1] = np.nan
    cov[2] = 0.0  # singular
    cov[3, 0, 0] = -1e-4  # not positive definite
    cov[4, 0, 1] = cov[4, 1, 0] = 0.02  # |ρ| > 1: not positive definite
    q_ref[5] = np.nan  # not scored (no reference)
    q_est[6] = np.nan  # not scored (no estimate)
    r = _rec(q_ref)
    d = tilt_mahalanobis(r, q_est, cov)
    assert np.isnan(d[[5, 6]]).all() and np.isinf(d[1:5]).all() and d[0] == 0.0 and d[7] == 0.0
    assert tilt_coverage_counts(r, q_est, cov) == (2, 6)
    assert tilt_coverage(r, q_est, cov) == pytest.approx(2 / 6)
    # skip_start drops the first samples from both counts
    assert tilt_coverage_counts(r, q_est, cov, skip_start=0.015) == (1, 4)  # 0, 1 dropped
    # no scored sample / inclination not meaningful: NaN
    assert np.isnan(tilt_coverage(_rec(np.full((3, 4), np.nan)), q_ref[:3], cov[:3]))
    r.errors = ("total",)
    assert np.isnan(tilt_coverage(r, q_est, cov))
    with pytest.raises(ValueError, match="shape"):
        tilt_coverage(_rec(q_ref), q_est, cov[:, :2, :2])


def test_coverage_rotates_the_covariance_with_the_constant_alignment() -> None:
    """RepoIMU-like: the reference world is ours turned 90° about z (G). A ±2° error about our x
    axis is about the reference's y axis; with σ_x = 1°, σ_y = 10° in our world, the rotated
    covariance gives distance 2 (σ = 1° along the error), the unrotated one would give 0.2."""
    n = 400
    q_true = random_quats(n, 21)
    g = quat_z(math.pi / 2)
    q_ref = qmul_np(g, q_true)
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)  # symmetric errors: the average is G
    rv = np.column_stack([sign * 2.0 * DEG, np.zeros(n), np.zeros(n)])
    q_est = qmul_np(qexp(rv), q_true)
    cov = np.broadcast_to(np.diag([1.0, 100.0, 1.0]) * DEG**2, (n, 3, 3)).copy()
    r = _rec(q_ref, "constant_global")
    np.testing.assert_allclose(canon(global_alignment(q_est, q_ref)), canon(g), atol=1e-12)
    np.testing.assert_allclose(tilt_mahalanobis(r, q_est, cov), 2.0, rtol=1e-6)
    assert tilt_coverage(r, q_est, cov, k=1.5) == 0.0
    assert tilt_coverage(r, q_est, cov, k=3.0) == 1.0


def test_tilt_sigma_is_the_median_horizontal_sigma_of_the_scored_samples() -> None:
    """The sharpness figure beside the coverage: the median over the scored samples of the RMS
    of the two horizontal σ (degrees); samples without a reference are not scored."""
    q_ref = np.tile([1.0, 0, 0, 0], (4, 1))
    q_ref[3] = np.nan  # no reference: not scored
    rec = _rec(q_ref)
    cov = np.tile(np.diag([0.01**2, 0.02**2, 1.0]), (4, 1, 1))
    cov[3] = np.diag([1.0, 1.0, 1.0])
    cov[2] = np.diag([0.03**2, 0.03**2, 1.0])
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    assert abs(tilt_sigma(rec, q, cov, 0.0) - 0.9059) < 1e-3  # √((1e-4 + 4e-4)/2) rad


def test_tilt_sigma_is_about_the_reference_world_after_alignment() -> None:
    """With the constant global alignment the covariance turns with the estimate (as for the
    coverage): an estimate whose world is the reference's turned 90° about x has its y and z
    axes swapped, so the horizontal σ are the published x and z ones."""
    q_ref = random_quats(50, seed=4)
    q_est = qmul_np(qexp(np.array([90 * DEG, 0.0, 0.0])), q_ref)  # G = R_x(−90°)
    cov = np.tile(np.diag([0.01**2, 0.05**2, 0.02**2]), (50, 1, 1))
    got = tilt_sigma(_rec(q_ref, "constant_global"), q_est, cov)
    assert abs(got - math.degrees(math.sqrt((0.01**2 + 0.02**2) / 2))) < 1e-6
