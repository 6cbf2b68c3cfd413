"""The four charts of the unit-quaternion manifold (docs/math.md §2) and their transition maps and
T-matrices (§3).

A chart maps a unit quaternion ``δ`` near the identity to ``e = φ(δ) ∈ R³`` and back. Every chart
is a small set of kernels (``to_chart``, ``from_chart``, ``T``) plus a saturation radius; the
filters call the dispatchers :func:`to_chart`, :func:`from_chart`, :func:`saturate`,
:func:`t_matrix` and :func:`transition` with a chart id and never look at which chart it is.
:class:`Chart` is the Python face of the same kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.quaternion import a33, q_omega_t, qconj_mul, qmul_t, t3, t4

O, RP, MRP, RV = 0, 1, 2, 3  # noqa: E741 (the paper's name of the orthographic chart)
CHART_NAMES = ("o", "rp", "mrp", "rv")

#: Saturation radius of each chart's image (§2.2, §8 item 5). O uses 2 − 10⁻³ so that δ0 > 0
#: and the O-chart T-matrix (which divides by δ0) stays finite.
RADIUS = np.array((2.0 - 1e-3, np.inf, 4.0, np.pi))

_TINY = 1e-12


@jit
def _canonical(d: tuple) -> tuple:
    """Sign fix ``δ ← −δ`` if ``δ0 < 0`` (§2.1): q and −q are the same rotation."""
    if d[0] < 0.0:
        return (-d[0], -d[1], -d[2], -d[3])
    return d


@jit
def _t_form(alpha: float, beta: float, gamma: float, v: tuple) -> tuple:
    """``α I + β v vᵀ − γ [v]×``: every T-matrix of Table 4 has this form (tuple of rows)."""
    b0, b1, b2 = beta * v[0], beta * v[1], beta * v[2]
    g0, g1, g2 = gamma * v[0], gamma * v[1], gamma * v[2]
    return ((b0 * v[0] + alpha, b0 * v[1] + g2, b0 * v[2] - g1),
            (b1 * v[0] - g2, b1 * v[1] + alpha, b1 * v[2] + g0),
            (b2 * v[0] + g1, b2 * v[1] - g0, b2 * v[2] + alpha))


# Each chart: φ on a 4-tuple δ, φ⁻¹ on a 3-tuple e (Table 2), and T(δ̄) on a 4-tuple (Table 4,
# a tuple of rows). Tuples are passed by value in numba, so the filters run these without heap
# allocations.

# --- O: orthographic ---------------------------------------------------------------------------
@jit
def _o_to(d: tuple) -> tuple:
    d = _canonical(d)
    return (2.0 * d[1], 2.0 * d[2], 2.0 * d[3])


@jit
def _o_from(e: tuple) -> tuple:
    n2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    return (np.sqrt(max(1.0 - 0.25 * n2, 0.0)), 0.5 * e[0], 0.5 * e[1], 0.5 * e[2])


@jit
def _o_t(d: tuple) -> tuple:
    # T = δ0 I − [δv]× + δv δvᵀ / δ0   (Table 4)
    s = -1.0 if d[0] < 0.0 else 1.0
    d0 = s * d[0]
    return _t_form(d0, 1.0 / max(d0, _TINY), 1.0, (s * d[1], s * d[2], s * d[3]))


# --- RP: Rodrigues parameters / gnomonic -------------------------------------------------------
@jit
def _rp_to(d: tuple) -> tuple:
    d = _canonical(d)  # φ(−δ) = φ(δ); the fix only makes the δ0 guard below one-sided
    k = 2.0 / max(d[0], _TINY)
    return (k * d[1], k * d[2], k * d[3])


@jit
def _rp_from(e: tuple) -> tuple:
    s = 1.0 / np.sqrt(4.0 + e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    return (2.0 * s, e[0] * s, e[1] * s, e[2] * s)


@jit
def _rp_t(d: tuple) -> tuple:
    # T = δ0 (δ0 I − [δv]×)   (Table 4); sign-invariant
    return _t_form(d[0] * d[0], 0.0, d[0], (d[1], d[2], d[3]))


# --- MRP: modified Rodrigues parameters / stereographic ---------------------------------------
@jit
def _mrp_to(d: tuple) -> tuple:
    d = _canonical(d)
    k = 4.0 / (1.0 + d[0])
    return (k * d[1], k * d[2], k * d[3])


@jit
def _mrp_from(e: tuple) -> tuple:
    n2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    s = 1.0 / (16.0 + n2)
    return ((16.0 - n2) * s, 8.0 * e[0] * s, 8.0 * e[1] * s, 8.0 * e[2] * s)


@jit
def _mrp_t(d: tuple) -> tuple:
    # T = ½ [ (1 + δ0)(δ0 I − [δv]×) + δv δvᵀ ]   (Table 4)
    s = -1.0 if d[0] < 0.0 else 1.0
    d0 = s * d[0]
    return _t_form(0.5 * (1.0 + d0) * d0, 0.5, 0.5 * (1.0 + d0), (s * d[1], s * d[2], s * d[3]))


# --- RV: rotation vector / equidistant ---------------------------------------------------------
@jit
def _rv_to(d: tuple) -> tuple:
    # robust form 2 atan2(‖δv‖, δ0) δv/‖δv‖ (§2.1 recommendation)
    d = _canonical(d)
    n2 = d[1] * d[1] + d[2] * d[2] + d[3] * d[3]
    if n2 < 0.01 * d[0] * d[0]:
        # x = ‖δv‖/δ0 < 0.1 (almost every deviation): atan2(‖δv‖, δ0)/‖δv‖ = (atan x / x)/δ0 by
        # its series through x¹⁴; the first omitted term, x¹⁶/17 ≤ 5.9e-18, is below half an
        # ulp of the result (≥ 0.99), so this agrees with atan2 to rounding, without sqrt or libm.
        inv = 1.0 / d[0]
        x2 = n2 * inv * inv
        at = 1.0 + x2 * (-1.0 / 3.0 + x2 * (1.0 / 5.0 + x2 * (-1.0 / 7.0 + x2 * (
            1.0 / 9.0 + x2 * (-1.0 / 11.0 + x2 * (1.0 / 13.0 + x2 * (-1.0 / 15.0)))))))
        k = 2.0 * inv * at
        return (k * d[1], k * d[2], k * d[3])
    n = np.sqrt(n2)
    k = 2.0 / max(d[0], _TINY) if n < _TINY else 2.0 * np.arctan2(n, d[0]) / n
    return (k * d[1], k * d[2], k * d[3])


@jit
def _rv_from(e: tuple) -> tuple:
    return q_omega_t(e, 1.0)


@jit
def _rv_t(d: tuple) -> tuple:
    # T = k (δ0 (I − uuᵀ) − [δv]×) + uuᵀ,  k = x/arcsin x, x = ‖δv‖, u = δv/x   (Table 4)
    # rewritten as k δ0 I + c δv δvᵀ − k [δv]×,  c = (1 − k δ0)/x², which has the limit 2/3 at
    # x → 0 (so T → I there, §3.2).
    s = -1.0 if d[0] < 0.0 else 1.0
    d0 = s * d[0]
    v = (s * d[1], s * d[2], s * d[3])
    x2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    if x2 < 1e-8:
        k = 1.0 - x2 / 6.0
        c = 2.0 / 3.0
    else:
        x = np.sqrt(x2)
        k = x / np.arcsin(min(x, 1.0))
        c = (1.0 - k * d0) / x2
    return _t_form(k * d0, c, k, v)


# --- dispatchers -------------------------------------------------------------------------------
@jit
def to_chart_t(chart: int, d: tuple) -> tuple:
    """``e = φ(δ)`` for a deviation ``δ`` from the chart centre (§2.1, Table 2)."""
    if chart == O:
        return _o_to(d)
    if chart == RP:
        return _rp_to(d)
    if chart == MRP:
        return _mrp_to(d)
    return _rv_to(d)


@jit
def from_chart_t(chart: int, e: tuple) -> tuple:
    """``δ = φ⁻¹(e)`` (§2.1); ``e`` must lie in the image (see :func:`saturate_t`)."""
    if chart == O:
        return _o_from(e)
    if chart == RP:
        return _rp_from(e)
    if chart == MRP:
        return _mrp_from(e)
    return _rv_from(e)


@jit
def saturate_t(chart: int, e: tuple) -> tuple:
    """Radially clip ``e`` to the chart's image (§2.2)."""
    r = RADIUS[chart]
    n = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    if n > r:
        k = r / n
        return (e[0] * k, e[1] * k, e[2] * k)
    return e


@jit
def to_chart(chart: int, d: np.ndarray) -> np.ndarray:
    """Array form of :func:`to_chart_t`."""
    return np.array(to_chart_t(chart, t4(d)))


@jit
def from_chart(chart: int, e: np.ndarray) -> np.ndarray:
    """Array form of :func:`from_chart_t`."""
    return np.array(from_chart_t(chart, t3(e)))


@jit
def saturate(chart: int, e: np.ndarray) -> np.ndarray:
    """Array form of :func:`saturate_t`."""
    return np.array(saturate_t(chart, t3(e)))


@jit
def t_matrix_t(chart: int, d: tuple) -> tuple:
    """``T(δ̄) = ∂e_p̄/∂e_q̄`` at ``e_q̄ = φ(δ̄)`` (§3.2, Table 4), as a tuple of rows."""
    if chart == O:
        return _o_t(d)
    if chart == RP:
        return _rp_t(d)
    if chart == MRP:
        return _mrp_t(d)
    return _rv_t(d)


@jit
def t_matrix(chart: int, d: np.ndarray) -> np.ndarray:
    """Array form of :func:`t_matrix_t`."""
    return a33(t_matrix_t(chart, t4(d)))


@jit
def transition(chart: int, dbar: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Transition map ``ψ(e) = φ(δ̄* * φ⁻¹(e))`` from the q̄- to the (q̄ * δ̄)-chart (§3.1)."""
    return to_chart(chart, qconj_mul(dbar, from_chart(chart, e)))


@jit
def from_chart_at_t(chart: int, qbar: tuple, e: tuple) -> tuple:
    """``φ_q̄⁻¹(e) = q̄ * φ⁻¹(e)`` (§2.3, eq. 12), normalised."""
    q = qmul_t(qbar, from_chart_t(chart, e))
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@jit_inline
def from_chart_at(chart: int, qbar: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Array form of :func:`from_chart_at_t`."""
    return np.array(from_chart_at_t(chart, t4(qbar), t3(e)))


def chart_id(name: str) -> int:
    """Chart id for a name in :data:`CHART_NAMES`; ``ValueError`` naming the choices otherwise."""
    key = str(name).lower()
    if key not in CHART_NAMES:
        raise ValueError(f"chart must be one of {', '.join(CHART_NAMES)}, got {name!r}")
    return CHART_NAMES.index(key)


@dataclass(frozen=True)
class Chart:
    """A chart of S³ (§2): the Python face of the kernels above."""

    name: str

    @property
    def id(self) -> int:
        return chart_id(self.name)

    @property
    def radius(self) -> float:
        """Saturation radius of the image (§2.2)."""
        return float(RADIUS[self.id])

    def to_chart(self, d: np.ndarray) -> np.ndarray:
        return to_chart(self.id, np.asarray(d, dtype=float))

    def from_chart(self, e: np.ndarray) -> np.ndarray:
        return from_chart(self.id, np.asarray(e, dtype=float))

    def saturate(self, e: np.ndarray) -> np.ndarray:
        return saturate(self.id, np.asarray(e, dtype=float))

    def t_matrix(self, dbar: np.ndarray) -> np.ndarray:
        return t_matrix(self.id, np.asarray(dbar, dtype=float))

    def transition(self, dbar: np.ndarray, e: np.ndarray) -> np.ndarray:
        return transition(self.id, np.asarray(dbar, dtype=float), np.asarray(e, dtype=float))


CHARTS = {name: Chart(name) for name in CHART_NAMES}
