"""Charts, transition maps and T-matrices (docs/math.md §2, §3) with the known-answer values
of §3.2."""

from __future__ import annotations

import numpy as np
import pytest
from core_strategies import unit_quaternions, vectors
from hypothesis import assume, given, settings

from mkf_ros.core.charts import CHART_NAMES, CHARTS, chart_id, from_chart, to_chart
from mkf_ros.core.quaternion import angle_between, qconj_mul, qmul

E_KAT = np.array([0.3, -0.2, 0.1])
E_Q = np.array([0.5, 0.1, -0.2])
# §3.2 known answers: δ̄ = φ⁻¹(e), T(δ̄), ψ(e_q) with that δ̄
KAT = {
    "o": ([0.982344, 0.15, -0.1, 0.05],
          [[1.005249, 0.034730, 0.107635], [-0.065270, 0.992524, 0.144910],
           [-0.092365, -0.155090, 0.984889]], [0.187641, 0.235588, -0.357646]),
    "rp": ([0.982946, 0.147442, -0.098295, 0.049147],
           [[0.966184, 0.048309, 0.096618], [-0.048309, 0.966184, 0.144928],
            [-0.096618, -0.144928, 0.966184]], [0.180049, 0.238443, -0.355231]),
    "mrp": ([0.982652, 0.148699, -0.099133, 0.049566],
            [[0.985184, 0.041766, 0.101958], [-0.056507, 0.979042, 0.144952],
             [-0.094587, -0.149866, 0.975357]], [0.183694, 0.237076, -0.356416]),
    "rv": ([0.982551, 0.149127, -0.099418, 0.049709],
           [[0.991725, 0.039489, 0.103804], [-0.059350, 0.983450, 0.144948],
            [-0.093874, -0.151568, 0.978484]], [0.184964, 0.236597, -0.356818]),
}


@pytest.mark.parametrize("name", CHART_NAMES)
def test_known_answers(name: str) -> None:
    c = CHARTS[name]
    dbar, T, psi = KAT[name]
    d = c.from_chart(E_KAT)
    np.testing.assert_allclose(d, dbar, atol=1e-6)
    np.testing.assert_allclose(c.t_matrix(d), T, atol=1e-6)
    np.testing.assert_allclose(c.transition(d, E_Q), psi, atol=1e-6)


def closed_form_transition(name: str, dbar: np.ndarray, e: np.ndarray) -> np.ndarray:
    """The closed forms of the spec's Table 3 (§3.1), written independently of the code."""
    d0, dv = dbar[0], dbar[1:]
    n = np.linalg.norm(e)
    if name == "o":
        ep = d0 * e - np.sqrt(4 - n * n) * dv - np.cross(dv, e)
        dp0 = d0 * np.sqrt(1 - n * n / 4) + dv @ e / 2
        return ep if dp0 >= 0 else -ep
    if name == "rp":
        return 2 * (d0 * e - 2 * dv - np.cross(dv, e)) / (2 * d0 + dv @ e)
    if name == "mrp":
        return 4 * (8 * d0 * e - (16 - n * n) * dv - 8 * np.cross(dv, e)) / (
            16 + n * n + d0 * (16 - n * n) + 8 * dv @ e)
    u = e / n
    dpv = np.sin(n / 2) * (d0 * u - np.cross(dv, u)) - np.cos(n / 2) * dv
    dp0 = d0 * np.cos(n / 2) + np.sin(n / 2) * dv @ u
    if dp0 < 0:
        dpv = -dpv
    return 2 * dpv / np.linalg.norm(dpv) * np.arcsin(min(np.linalg.norm(dpv), 1.0))


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=100, deadline=None)
@given(e=vectors(scale=0.8), eq=vectors(scale=0.8))
def test_transition_matches_closed_form(name: str, e: np.ndarray, eq: np.ndarray) -> None:
    c = CHARTS[name]
    # the closed forms are 0/0 at e_q = 0 and at e_q = e
    assume(np.linalg.norm(eq) > 1e-3 and np.linalg.norm(eq - e) > 1e-3)
    d = c.from_chart(e)
    expect = closed_form_transition(name, d, eq)
    if name == "mrp":  # the closed form is the s = +1 branch
        dp = qconj_mul(d, c.from_chart(eq))
        assume(dp[0] > 0)
    np.testing.assert_allclose(c.transition(d, eq), expect, atol=1e-9)


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=150, deadline=None)
@given(e=vectors(scale=3.5))
def test_round_trip_inside_image(name: str, e: np.ndarray) -> None:
    c = CHARTS[name]
    assume(np.linalg.norm(e) < 0.98 * min(c.radius, 3.5))
    np.testing.assert_allclose(c.to_chart(c.from_chart(e)), e, atol=1e-9)
    assert abs(np.linalg.norm(c.from_chart(e)) - 1) < 1e-12


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=150, deadline=None)
@given(d=unit_quaternions())
def test_sign_invariance_and_inverse(name: str, d: np.ndarray) -> None:
    """q and −q give the same chart point (§2.1 sign handling); φ⁻¹(φ(δ)) is the same rotation."""
    c = CHARTS[name]
    assume(abs(d[0]) > 1e-3)
    np.testing.assert_allclose(c.to_chart(d), c.to_chart(-d), atol=1e-12)
    if name != "o" or abs(d[0]) > 0.05:  # O is ill-conditioned near 180° (δ0 → 0)
        back = c.from_chart(c.saturate(c.to_chart(d)))
        assert angle_between(back, d) < 1e-6


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=100, deadline=None)
@given(d=unit_quaternions())
def test_transition_of_new_centre_is_zero(name: str, d: np.ndarray) -> None:
    """ψ(φ(δ̄)) = 0: the new centre is the origin of the new chart (§3.1)."""
    c = CHARTS[name]
    assume(d[0] > 0.05)
    e = c.to_chart(d)
    np.testing.assert_allclose(c.transition(c.from_chart(e), e), 0.0, atol=1e-9)


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=100, deadline=None)
@given(e=vectors(scale=1.5))
def test_t_matrix_is_the_jacobian_of_the_transition(name: str, e: np.ndarray) -> None:
    """T(δ̄) = ∂ψ/∂e at e = φ(δ̄), by central finite differences (§3.2)."""
    c = CHARTS[name]
    assume(np.linalg.norm(e) < 0.9 * min(c.radius, 1.5))
    d = c.from_chart(e)
    h = 1e-6
    J = np.empty((3, 3))
    for k in range(3):
        dk = np.zeros(3)
        dk[k] = h
        J[:, k] = (c.transition(d, e + dk) - c.transition(d, e - dk)) / (2 * h)
    np.testing.assert_allclose(c.t_matrix(d), J, atol=1e-7)


@pytest.mark.parametrize("name", CHART_NAMES)
def test_t_matrix_limits(name: str) -> None:
    c = CHARTS[name]
    np.testing.assert_allclose(c.t_matrix(np.array([1.0, 0, 0, 0])), np.eye(3), atol=1e-15)
    d = c.from_chart(np.array([1e-9, 0, 0]))  # RV's series branch
    assert np.all(np.isfinite(c.t_matrix(d)))


#: Saturation radii of the spec (§2.2): O clipped to 2 − 10⁻³ (the recommendation, so that
#: δ0 > 0), RP unbounded, MRP 4, RV π. Written here, not read from the code under test.
SPEC_RADIUS = {"o": 2.0 - 1e-3, "rp": np.inf, "mrp": 4.0, "rv": np.pi}


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=100, deadline=None)
@given(e=vectors(scale=20.0))
def test_saturation(name: str, e: np.ndarray) -> None:
    c = CHARTS[name]
    s = c.saturate(e)
    r = SPEC_RADIUS[name]
    n = np.linalg.norm(e)
    assert c.radius == r
    if n <= r:
        np.testing.assert_array_equal(s, e)
    else:  # radially onto the sphere of radius r (§2.2)
        np.testing.assert_allclose(np.linalg.norm(s), r, rtol=1e-12)
        np.testing.assert_allclose(s / np.linalg.norm(s), e / n, atol=1e-12)
    q = c.from_chart(s)
    assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1) < 1e-12


@pytest.mark.parametrize("name", CHART_NAMES)
def test_saturation_at_the_image_boundary(name: str) -> None:
    """Far outside the image, the saturated point is on the spec's radius (§2.2), and for O
    it keeps δ0 = √(1 − r²/4) ≥ 0.0316 > 0, so that the O-chart T-matrix of Table 4 (written
    here, without any guard) is finite and equals the code's (no ``max(δ0, tiny)`` needed)."""
    c = CHARTS[name]
    for u in (np.array([1.0, 0, 0]), np.array([0.6, -0.8, 0.0]), np.array([1.0, 1, 1]) / 3**0.5):
        s = c.saturate(1e3 * u)
        if name == "rp":  # RP's image is all of R³: nothing to clip
            np.testing.assert_array_equal(s, 1e3 * u)
            continue
        np.testing.assert_allclose(s, SPEC_RADIUS[name] * u, rtol=1e-12)
        d = c.from_chart(s)
        if name == "o":
            d0_spec = np.sqrt(1 - SPEC_RADIUS["o"] ** 2 / 4)  # = 0.0316
            assert d[0] == pytest.approx(d0_spec, rel=1e-6) and d[0] > 0.03
            dv = d[1:]
            with np.errstate(divide="raise", invalid="raise"):
                t_spec = d[0] * np.eye(3) - skew_np(dv) + np.outer(dv, dv) / d[0]
            np.testing.assert_allclose(c.t_matrix(d), t_spec, rtol=1e-12, atol=1e-12)
        assert np.all(np.isfinite(c.t_matrix(d)))


def skew_np(a: np.ndarray) -> np.ndarray:
    """``[a]×`` (so that ``[a]× b = a × b``), written out."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


@pytest.mark.parametrize("name", CHART_NAMES)
@settings(max_examples=50, deadline=None)
@given(e=vectors(scale=0.05))
def test_charts_agree_to_second_order(name: str, e: np.ndarray) -> None:
    """φ⁻¹(e) = (1 − ‖e‖²/8, e/2) + O(‖e‖³) for every chart (paper eq. 10)."""
    n = np.linalg.norm(e)
    np.testing.assert_allclose(CHARTS[name].from_chart(e), np.r_[1 - n * n / 8, e / 2],
                               atol=n**3 + 1e-15)


def test_centred_chart_maps_the_centre_to_zero() -> None:
    from mkf_ros.core.charts import from_chart_at

    def to_chart_at(cid: int, qbar: np.ndarray, q: np.ndarray) -> np.ndarray:
        """φ_q̄(q) = φ(q̄* * q) (§2.3, eq. 11)."""
        return to_chart(cid, qconj_mul(qbar, q))

    qbar = np.array([0.5, 0.5, -0.5, 0.5])
    for name in CHART_NAMES:
        cid = chart_id(name)
        np.testing.assert_allclose(to_chart_at(cid, qbar, qbar), 0, atol=1e-15)
        e = np.array([0.1, -0.2, 0.05])
        q = from_chart_at(cid, qbar, e)
        np.testing.assert_allclose(q, qmul(qbar, CHARTS[name].from_chart(e)), atol=1e-15)
        np.testing.assert_allclose(to_chart_at(cid, qbar, q), e, atol=1e-12)


@pytest.mark.parametrize("bad", ["x", "RPY", "", None])
def test_unknown_chart_is_a_clear_error(bad: object) -> None:
    with pytest.raises(ValueError, match="chart must be one of o, rp, mrp, rv"):
        chart_id(bad)  # type: ignore[arg-type]


def test_chart_names_select_the_spec_maps() -> None:
    """Each name (and its id, through :func:`chart_id`, as the filters use it) selects the map
    of that name in the spec's Table 2: for a rotation by θ, ‖φ(δ)‖ is 2 sin(θ/2) (O),
    2 tan(θ/2) (RP), 4 tan(θ/4) (MRP) and θ (RV); and φ⁻¹ is that chart's closed form."""
    norm = {"o": lambda th: 2 * np.sin(th / 2), "rp": lambda th: 2 * np.tan(th / 2),
            "mrp": lambda th: 4 * np.tan(th / 4), "rv": lambda th: th}
    inverse = {"o": lambda e: np.r_[np.sqrt(1 - e @ e / 4), e / 2],
               "rp": lambda e: np.r_[2.0, e] / np.sqrt(4 + e @ e),
               "mrp": lambda e: np.r_[16 - e @ e, 8 * e] / (16 + e @ e),
               "rv": lambda e: np.r_[np.cos(np.linalg.norm(e) / 2),
                                     e / np.linalg.norm(e) * np.sin(np.linalg.norm(e) / 2)]}
    axis = np.array([2.0, -1.0, 2.0]) / 3.0
    th = 1.3
    d = np.r_[np.cos(th / 2), np.sin(th / 2) * axis]
    for name in CHART_NAMES:
        for via in (CHARTS[name].to_chart(d), to_chart(chart_id(name), d),
                    to_chart(chart_id(name.upper()), d)):
            np.testing.assert_allclose(via, norm[name](th) * axis, rtol=1e-12)
        e = norm[name](th) * axis
        np.testing.assert_allclose(from_chart(chart_id(name), e), inverse[name](e), atol=1e-12)
