"""Scoring of orientation estimates against an optical reference (real-data benchmark).

The metric is BROAD's (:func:`mkf_ros.evaluation.metrics.orientation_errors`): with
``e = q_est ⊗ q_ref⁻¹``, total ``2 acos|e_w|``, heading ``2 atan|e_z/e_w|``, inclination
``2 acos √(e_w² + e_z²)``; per recording the RMSE over the valid samples in degrees, per dataset
the plain mean over the recordings that are not excluded.

When the reference world is an unknown constant rotation of ours (RepoIMU: the Vicon quaternion
is relative to the start pose), the estimate is first aligned with one constant global rotation
``G``, the quaternion average (Markley's eigenvector method) of ``q_ref ⊗ q_est⁻¹`` over the
scored samples, and ``G ⊗ q_est`` is compared with ``q_ref``. The same procedure is applied to
every algorithm. Each recording says which alignment and which error kinds apply
(:class:`mkf_ros.evaluation.datasets.Recording`).

:func:`tilt_coverage` checks a published covariance against the same errors: the fraction of
the scored samples whose inclination error lies within k σ of the tilt block of the covariance
(Mahalanobis distance of the horizontal swing rotation vector of ``e``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from mkf_ros.core.frames import swing_rotvec
from mkf_ros.core.quaternion import qconj_np, qmul_np, rotmat_np
from mkf_ros.evaluation.datasets import ALL_ERRORS, Recording
from mkf_ros.evaluation.metrics import orientation_errors

ALIGNMENTS = ("none", "constant_global")


def quat_average(q: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Average rotation of unit quaternions (N, 4) [w, x, y, z]: the unit eigenvector of
    ``Σ wᵢ qᵢ qᵢᵀ`` with the largest eigenvalue (Markley et al. 2007). Sign-invariant (q and −q
    count as the same rotation); returned with w ≥ 0. NaN rows are ignored."""
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    ok = np.isfinite(q).all(axis=1)
    if weights is not None:
        w = np.asarray(weights, dtype=float).reshape(-1)
        ok &= np.isfinite(w)
        w = w[ok]
    else:
        w = np.ones(int(ok.sum()))
    q = q[ok]
    if q.shape[0] == 0:
        raise ValueError("quat_average needs at least one finite quaternion")
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    m = (q * w[:, None]).T @ q
    vals, vecs = np.linalg.eigh(m)
    g = vecs[:, int(np.argmax(vals))]
    return g if g[0] >= 0 else -g


def global_alignment(q_est: np.ndarray, q_ref: np.ndarray,
                     mask: np.ndarray | None = None) -> np.ndarray:
    """Constant rotation ``G`` (4,) that best maps the estimate onto the reference world: the
    quaternion average of ``q_ref ⊗ q_est⁻¹`` over the rows where both are finite (and
    ``mask``, if given). Score ``G ⊗ q_est`` against ``q_ref``."""
    d = qmul_np(q_ref, qconj_np(q_est))
    ok = np.isfinite(d).all(axis=1)
    if mask is not None:
        ok &= mask
    return quat_average(d[ok])


def scored_mask(rec: Recording, q_est: np.ndarray, skip_start: float = 0.0) -> np.ndarray:
    """(N,) bool: samples that are scored: valid reference, finite estimate, and (if
    ``skip_start`` > 0) at least that many seconds after the first sample."""
    m = rec.valid & np.isfinite(q_est).all(axis=1)
    if skip_start > 0:
        m &= rec.t >= rec.t[0] + skip_start
    return m


def aligned_estimate(rec: Recording, q_est: np.ndarray,
                     mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``q_est`` as it is compared with ``rec.q_ref`` (after the recording's alignment) and the
    alignment rotation used (identity for ``"none"``)."""
    q_est = np.asarray(q_est, dtype=float)
    if q_est.shape != rec.q_ref.shape:
        raise ValueError(f"q_est has shape {q_est.shape}, expected {rec.q_ref.shape}")
    if rec.alignment == "none":
        return q_est, np.array([1.0, 0.0, 0.0, 0.0])
    if rec.alignment == "constant_global":
        m = scored_mask(rec, q_est) if mask is None else mask
        g = global_alignment(q_est, rec.q_ref, m)
        return qmul_np(g, q_est), g
    raise ValueError(f"unknown alignment {rec.alignment!r}; known: {', '.join(ALIGNMENTS)}")


def error_series(rec: Recording, q_est: np.ndarray,
                 skip_start: float = 0.0) -> dict[str, np.ndarray]:
    """Per-sample errors (rad) after alignment; NaN where a sample is not scored."""
    m = scored_mask(rec, q_est, skip_start)
    q_al, _ = aligned_estimate(rec, q_est, m)
    errs = orientation_errors(np.where(m[:, None], q_al, 1.0),
                              np.where(m[:, None], rec.q_ref, 1.0))
    return {k: np.where(m, v, np.nan) for k, v in errs.items()}


def score_recording(rec: Recording, q_est: np.ndarray,
                    skip_start: float = 0.0) -> dict[str, float]:
    """RMSE in degrees per error kind; NaN for kinds not meaningful for ``rec`` (see
    ``rec.errors``) or if no sample is scored."""
    errs = error_series(rec, q_est, skip_start)
    out: dict[str, float] = {}
    for k in ALL_ERRORS:
        e = errs[k]
        e = e[np.isfinite(e)]
        out[k] = float(np.degrees(np.sqrt(np.mean(e * e)))) \
            if (k in rec.errors and e.size) else float("nan")
    return out


def dataset_mean(scores: Iterable[Mapping[str, float]],
                 kinds: Sequence[str] = ALL_ERRORS) -> dict[str, float]:
    """Plain mean of per-recording RMSEs per error kind (NaN if there are none)."""
    rows = list(scores)
    return {k: float(np.mean([r[k] for r in rows])) if rows else float("nan") for k in kinds}


# ----------------------------------------------------------------------------------- covariance
def _aligned(rec: Recording, q_est: np.ndarray, cov_world: np.ndarray, skip_start: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scored mask, the aligned estimate and the published covariance about the reference
    world's axes (rotated with the recording's alignment ``G``, as the estimate is)."""
    q_est = np.asarray(q_est, dtype=float)
    cov = np.asarray(cov_world, dtype=float)
    if cov.shape != (q_est.shape[0], 3, 3):
        raise ValueError(f"cov_world has shape {cov.shape}, expected ({q_est.shape[0]}, 3, 3)")
    m = scored_mask(rec, q_est, skip_start)
    q_al, g = aligned_estimate(rec, q_est, m)
    if rec.alignment != "none":  # the covariance is about our world's axes: rotate it with G
        rg = rotmat_np(g)
        cov = rg @ cov @ rg.T
    return m, q_al, cov


def tilt_sigma(rec: Recording, q_est: np.ndarray, cov_world: np.ndarray,
               skip_start: float = 0.0) -> float:
    """The published tilt's sharpness, to read beside :func:`tilt_coverage` (a covariance can
    cover everything by being wide): the median over the scored samples of
    ``√((Σ₀₀ + Σ₁₁)/2)``, the RMS of the two horizontal axes' σ about the reference world, in
    degrees (NaN if no sample is scored or none is finite)."""
    m, _, cov = _aligned(rec, q_est, cov_world, skip_start)
    with np.errstate(invalid="ignore"):
        sd = np.sqrt(0.5 * (cov[m, 0, 0] + cov[m, 1, 1]))
    sd = sd[np.isfinite(sd)]
    return float(np.degrees(np.median(sd))) if len(sd) else float("nan")


def tilt_mahalanobis(rec: Recording, q_est: np.ndarray, cov_world: np.ndarray,
                     skip_start: float = 0.0) -> np.ndarray:
    """(N,) Mahalanobis distance of each sample's inclination error under the published tilt
    covariance; NaN where the sample is not scored (:func:`scored_mask`), +inf where the 2×2
    tilt block is not finite or not positive definite. See :func:`tilt_coverage`."""
    m, q_al, cov = _aligned(rec, q_est, cov_world, skip_start)
    e = qmul_np(np.where(m[:, None], q_al, 1.0), qconj_np(np.where(m[:, None], rec.q_ref, 1.0)))
    eps = swing_rotvec(e)
    a = cov[:, 0, 0]
    c = cov[:, 1, 1]
    b = 0.5 * (cov[:, 0, 1] + cov[:, 1, 0])
    det = a * c - b * b
    pd = np.isfinite(a) & np.isfinite(b) & np.isfinite(c) & (a > 0) & (c > 0) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ex, ey = eps[:, 0], eps[:, 1]
        d2 = (c * ex * ex - 2.0 * b * ex * ey + a * ey * ey) / np.where(pd, det, 1.0)
    d = np.where(pd, np.sqrt(np.maximum(d2, 0.0)), np.inf)
    return np.where(m, d, np.nan)


def tilt_coverage_counts(rec: Recording, q_est: np.ndarray, cov_world: np.ndarray,
                         k: float = 3.0, skip_start: float = 0.0) -> tuple[int, int]:
    """(covered, scored) sample counts of :func:`tilt_coverage` (for pooling over
    recordings)."""
    if "inclination" not in rec.errors:
        return 0, 0
    d = tilt_mahalanobis(rec, q_est, cov_world, skip_start)
    scored = ~np.isnan(d)
    return int((d[scored] <= k).sum()), int(scored.sum())


def tilt_coverage(rec: Recording, q_est: np.ndarray, cov_world: np.ndarray, k: float = 3.0,
                  skip_start: float = 0.0) -> float:
    """Covariance honesty: the fraction of the scored samples whose inclination error lies
    within ``k`` standard deviations of the published tilt covariance (NaN if none is scored
    or inclination is not meaningful for ``rec``).

    ``cov_world`` is (N, 3, 3), the orientation covariance about the world axes in rad² (what
    ``mkf_ros.estimate(...).cov`` returns). Per scored sample (:func:`scored_mask`), after the
    recording's alignment exactly as in :func:`score_recording`:

    1. error quaternion ``e = q_est ⊗ q_ref⁻¹`` (with ``q_est`` replaced by ``G ⊗ q_est`` for the
       ``constant_global`` alignment);
    2. swing–twist decomposition about the world z axis, ``e = swing ⊗ twist_z``; the swing's
       rotation vector ε is horizontal, ε = (ε_x, ε_y, 0), and ``|ε|`` equals BROAD's inclination
       error ``2·acos√(e_w² + e_z²)`` (:func:`swing_rotvec`);
    3. Σ_xy is the upper-left 2×2 block of the covariance (for ``constant_global`` of
       ``R(G) Σ R(G)ᵀ``, the covariance about the reference world's axes);
    4. the sample is covered if ``√(ε_xyᵀ Σ_xy⁻¹ ε_xy) ≤ k``. A non-finite or not positive
       definite Σ_xy counts as not covered.

    For a Gaussian error with exactly the published covariance the expected coverage is the χ²
    (2 degrees of freedom) probability ``1 − exp(−k²/2)``: 98.9 % at k = 3, 39.3 % at k = 1."""
    covered, n = tilt_coverage_counts(rec, q_est, cov_world, k, skip_start)
    return covered / n if n else float("nan")
