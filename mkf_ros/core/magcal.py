"""Magnetometer calibration from data: hard-iron offset and soft-iron matrix (docs/math.md §10.1).

A magnetometer on a body with iron reads ``m_raw = A f + h + n`` for the Earth field ``f`` in body
axes; turned in every direction, its samples lie on an ellipsoid. :func:`fit_ellipsoid` fits that
ellipsoid to raw samples (algebraic least squares, then an optional geometric refinement) and
returns the correction the filter applies, ``m = S (m_raw − h)`` (parameters ``mag_bias_x/y/z``
and ``mag_soft_iron``, docs/math.md §9.2), with the quality of the fit: RMS residual, coverage of
the sphere of directions, condition. It refuses (ValueError, one line) samples that cannot
determine the ellipsoid: too few, too little of the sphere covered, or a quadric that is not an
ellipsoid.

Pure NumPy; SciPy (``scipy.optimize.least_squares``) only for the refinement, skipped when it
is not installed (the result says so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

#: Fewer samples than this are refused (9 unknowns in the quadric, and the quality needs more).
MIN_SAMPLES = 20
#: Default refusal threshold on :attr:`MagCalibration.coverage`.
MIN_COVERAGE = 0.25
#: Equal-area cells of the coverage measure: bands of equal height in z (equal area, by
#: Archimedes' hat-box theorem) times equal longitude sectors.
COVERAGE_BANDS = 6
COVERAGE_SECTORS = 12
#: A design matrix (centred, scaled data) more ill-conditioned than this leaves some of the
#: quadric's coefficients undetermined (e.g. samples from turns about one axis only).
MAX_CONDITION = 1e6


@dataclass(frozen=True)
class MagCalibration:
    """A fitted magnetometer calibration, ``m = S (m_raw − h)``, and its quality."""

    offset: np.ndarray  #: h, (3,), the magnetometer's unit
    soft_iron: np.ndarray  #: S, (3, 3), symmetric positive definite
    field_magnitude: float  #: r = |S (m_raw − h)| on the fitted ellipsoid, the same unit
    rms: float  #: RMS of |S (m_i − h)| − r over the samples, field units
    coverage: float  #: fraction of equal-area cells of the sphere holding a calibrated direction
    condition: float  #: condition number of the (centred, scaled) least-squares design matrix
    axis_ratio: float  #: longest / shortest semi-axis of the raw ellipsoid (1 = no soft iron)
    n_samples: int  #: finite samples used
    refined: bool  #: the geometric refinement ran (SciPy available and asked for)
    soft_iron_fitted: bool = True  #: False: hard iron only (S a multiple of I)
    notes: tuple[str, ...] = field(default=())

    @property
    def rms_relative(self) -> float:
        """The RMS residual relative to the field magnitude."""
        return self.rms / self.field_magnitude

    def apply(self, m_raw: ArrayLike) -> np.ndarray:
        """Calibrated samples ``S (m_raw − h)`` (rows), as the filter computes them."""
        m = np.asarray(m_raw, dtype=float)
        return (m - self.offset) @ self.soft_iron.T

    def params(self) -> dict[str, Any]:
        """The estimator's parameters for this calibration (docs/math.md §9.2)."""
        h = [float(x) for x in self.offset]
        return {"mag_bias_x": h[0], "mag_bias_y": h[1], "mag_bias_z": h[2],
                "mag_soft_iron": [float(x) for x in self.soft_iron.reshape(-1)]}

    def summary(self) -> str:
        """A few lines for a terminal or a log."""
        h = ", ".join(f"{x:.6g}" for x in self.offset)
        s = "; ".join(", ".join(f"{x:.5f}" for x in row) for row in self.soft_iron)
        return "\n".join([
            f"samples   {self.n_samples} "
            f"({'ellipsoid' if self.soft_iron_fitted else 'sphere: hard iron only'}, "
            f"{'geometric refinement' if self.refined else 'algebraic fit only'})",
            f"offset    [{h}]",
            f"soft iron [{s}]",
            f"field     {self.field_magnitude:.6g} (calibrated magnitude)",
            f"residual  RMS {self.rms:.4g} ({100 * self.rms_relative:.2f} % of the field)",
            f"coverage  {100 * self.coverage:.0f} % of the sphere of directions "
            f"({COVERAGE_BANDS * COVERAGE_SECTORS} equal-area cells)",
            f"condition {self.condition:.3g}; raw axis ratio {self.axis_ratio:.3f}",
            *(f"note      {n}" for n in self.notes),
        ])


def coverage(directions: ArrayLike, bands: int = COVERAGE_BANDS,
             sectors: int = COVERAGE_SECTORS) -> float:
    """Fraction of the ``bands × sectors`` equal-area cells of the unit sphere that hold at least
    one of ``directions`` (rows, any length; normalised here). Bands have equal height in z, so
    equal area; sectors equal longitude."""
    d = np.asarray(directions, dtype=float).reshape(-1, 3)
    n = np.linalg.norm(d, axis=1)
    d = d[n > 0] / n[n > 0, None]
    if len(d) == 0:
        return 0.0
    band = np.minimum(((d[:, 2] + 1.0) * 0.5 * bands).astype(int), bands - 1)
    lon = np.arctan2(d[:, 1], d[:, 0]) + math.pi
    sector = np.minimum((lon / (2 * math.pi) * sectors).astype(int), sectors - 1)
    return len(np.unique(band * sectors + sector)) / (bands * sectors)


def _finite_rows(m_raw: ArrayLike) -> np.ndarray:
    m = np.asarray(m_raw, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"magnetometer samples must be an (N, 3) array, got shape {m.shape}")
    m = m[np.all(np.isfinite(m), axis=1)]
    if len(m) < MIN_SAMPLES:
        raise ValueError(f"magnetometer calibration needs at least {MIN_SAMPLES} finite samples, "
                         f"got {len(m)}")
    return m


def _algebraic(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares quadric ``xᵀ Q x + 2 pᵀ x + k = 0`` with ``trace Q = 3`` (centred, scaled
    samples ``x``): returns the centre, ``M`` with ``(x − c)ᵀ M (x − c) = 1`` and the condition
    number of the design matrix. ValueError if the quadric is not an ellipsoid."""
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    # Q = diag(1 + α, 1 + β, 1 − α − β) + off-diagonals: x²+y²+z² moves to the right-hand side
    D = np.column_stack([X * X - Z * Z, Y * Y - Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z,
                         2 * X, 2 * Y, 2 * Z, np.ones_like(X)])
    rhs = -(X * X + Y * Y + Z * Z)
    sv = np.linalg.svd(D, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    if not cond < MAX_CONDITION:
        raise ValueError(f"magnetometer calibration: the samples do not determine an ellipsoid "
                         f"(condition {cond:.3g}); turn the sensor about every axis, not one")
    a, b, qxy, qxz, qyz, px, py, pz, k = np.linalg.lstsq(D, rhs, rcond=None)[0]
    Q = np.array([[1 + a, qxy, qxz], [qxy, 1 + b, qyz], [qxz, qyz, 1 - a - b]])
    p = np.array([px, py, pz])
    try:
        c = -np.linalg.solve(Q, p)
    except np.linalg.LinAlgError:
        raise ValueError("magnetometer calibration: the fitted quadric has no centre "
                         "(not an ellipsoid)") from None
    g = float(c @ Q @ c - k)
    M = Q / g if g != 0 else Q * math.inf
    ev = np.linalg.eigvalsh(M) if np.all(np.isfinite(M)) else np.array([-1.0])
    if not np.all(ev > 0):
        raise ValueError("magnetometer calibration: the fitted quadric is not an ellipsoid "
                         "(samples too noisy or too few directions)")
    return c, M, cond


def _sphere(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares sphere ``|x − c|² = ρ²`` (hard iron only; centred, scaled samples): the
    centre, ``M = I/ρ²`` and the condition number of the design matrix."""
    D = np.column_stack([2 * x, np.ones(len(x))])
    sv = np.linalg.svd(D, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    if not cond < MAX_CONDITION:
        raise ValueError(f"magnetometer calibration: the samples do not determine a sphere "
                         f"(condition {cond:.3g}); turn the sensor in more directions")
    s = np.linalg.lstsq(D, np.sum(x * x, axis=1), rcond=None)[0]
    c = s[:3]
    rho2 = float(s[3] + c @ c)
    if not rho2 > 0:
        raise ValueError("magnetometer calibration: the fitted sphere has no radius")
    return c, np.eye(3) / rho2, cond


def _sym_sqrt(M: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(M)
    return (V * np.sqrt(w)) @ V.T


def _refine(m: np.ndarray, h: np.ndarray, S: np.ndarray, r: float, soft_iron: bool
            ) -> tuple[np.ndarray, np.ndarray] | None:
    """Geometric refinement: minimise ``Σ (|S (m_i − h)| − r)²`` over ``h`` and symmetric ``S``
    (a multiple of I without ``soft_iron``; r fixed: it sets the scale), from the algebraic
    solution. None without SciPy."""
    try:
        from scipy.optimize import least_squares
    except ImportError:
        return None
    iu = np.triu_indices(3)

    def unpack(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not soft_iron:
            return theta[:3], theta[3] * np.eye(3)
        Sm = np.zeros((3, 3))
        Sm[iu] = theta[3:]
        Sm = Sm + np.triu(Sm, 1).T
        return theta[:3], Sm

    def residual(theta: np.ndarray) -> np.ndarray:
        hh, Sm = unpack(theta)
        return np.linalg.norm((m - hh) @ Sm.T, axis=1) - r

    start = np.concatenate([h, S[iu] if soft_iron else [S[0, 0]]])
    sol = least_squares(residual, start, method="lm", x_scale="jac")
    hh, Sm = unpack(sol.x)
    if not (np.all(np.isfinite(sol.x)) and np.all(np.linalg.eigvalsh(Sm) > 0)):
        return None
    return hh, Sm


def _refusal(cov: float, min_coverage: float) -> str:
    return (f"magnetometer calibration refused: the samples cover {100 * cov:.0f} % of the "
            f"sphere of directions (at least {100 * min_coverage:.0f} % needed); turn the sensor "
            "through more orientations (upside down, on its sides)")


def fit_ellipsoid(m_raw: ArrayLike, *, refine: bool = True, min_coverage: float = MIN_COVERAGE,
                  field_magnitude: float | None = None, soft_iron: bool = True
                  ) -> MagCalibration:
    """Fit the hard-iron offset ``h`` and soft-iron matrix ``S`` to raw magnetometer samples
    (docs/math.md §10.1).

    ``m_raw``: (N, 3) raw samples in any unit (non-finite rows are dropped), taken while the
    sensor is turned through as many directions as possible. ``S`` is the symmetric matrix that
    maps the fitted ellipsoid onto a sphere of radius ``field_magnitude`` (default: the
    ellipsoid's geometric-mean radius, so ``det S = 1`` and the unit is unchanged).
    ``refine``: a geometric least-squares refinement after the algebraic fit (SciPy).
    ``soft_iron=False`` fits the hard-iron offset only (a sphere, ``S`` a multiple of I): for a
    magnet on the body, and whenever the coverage is partial — the soft-iron terms then trade
    off against the offset with almost no change in the residual, and the directions (the
    heading) suffer (docs/math.md §10.1).

    Raises ValueError (one line) for too few samples, samples that do not determine an
    ellipsoid, or a coverage of the sphere of calibrated directions below ``min_coverage``.
    """
    m = _finite_rows(m_raw)
    if field_magnitude is not None and not (math.isfinite(field_magnitude)
                                            and field_magnitude > 0):
        raise ValueError(f"field_magnitude must be a positive number, got {field_magnitude!r}")
    centre0 = m.mean(axis=0)
    scale0 = float(np.sqrt(np.mean(np.sum((m - centre0) ** 2, axis=1))))
    if not scale0 > 0:
        raise ValueError("magnetometer calibration: all samples are equal (sensor not turned?)")
    raw_cov = coverage(m - centre0)
    if raw_cov < min_coverage:  # before the fit: a band of directions gives no ellipsoid
        raise ValueError(_refusal(raw_cov, min_coverage))
    c, M, cond = (_algebraic if soft_iron else _sphere)((m - centre0) / scale0)
    h = centre0 + scale0 * c
    M = M / scale0**2  # (m − h)ᵀ M (m − h) = 1 in the sensor's unit
    radii = 1.0 / np.sqrt(np.linalg.eigvalsh(M))
    axis_ratio = float(radii.max() / radii.min())
    r = float(field_magnitude) if field_magnitude is not None else float(np.prod(radii) ** (1 / 3))
    S = r * _sym_sqrt(M)
    notes: list[str] = []
    refined = False
    if refine:
        out = _refine(m, h, S, r, soft_iron)
        if out is None:
            notes.append("geometric refinement skipped (SciPy not installed or it diverged)")
        else:
            h, S = out
            refined = True
    cal = (m - h) @ S.T
    norms = np.linalg.norm(cal, axis=1)
    rms = float(np.sqrt(np.mean((norms - r) ** 2)))
    cov = coverage(cal)
    if cov < min_coverage:
        raise ValueError(_refusal(cov, min_coverage))
    return MagCalibration(offset=h, soft_iron=S, field_magnitude=r, rms=rms, coverage=cov,
                          condition=cond, axis_ratio=axis_ratio, n_samples=len(m),
                          refined=refined, notes=tuple(notes), soft_iron_fitted=soft_iron)


def params_yaml(cal: MagCalibration, node_name: str = "/**") -> str:
    """The calibration as a ROS parameters file fragment (``--ros-args --params-file``, and
    ``mkf process --params``): the node's ``mag_bias_*`` and ``mag_soft_iron``."""
    p = cal.params()
    soft = ", ".join(repr(x) for x in p["mag_soft_iron"])
    return "\n".join([
        "# magnetometer calibration (mkf calibrate-mag; docs/math.md §10.1):",
        f"# RMS residual {cal.rms:.4g} ({100 * cal.rms_relative:.2f} % of the field), "
        f"coverage {100 * cal.coverage:.0f} %, {cal.n_samples} samples",
        f"{node_name}:",
        "  ros__parameters:",
        f"    mag_bias_x: {p['mag_bias_x']!r}",
        f"    mag_bias_y: {p['mag_bias_y']!r}",
        f"    mag_bias_z: {p['mag_bias_z']!r}",
        f"    mag_soft_iron: [{soft}]",
    ]) + "\n"
