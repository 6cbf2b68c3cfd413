"""MUKF (docs/math.md §6): the kernel against a literal transcription with the full augmentation."""

from __future__ import annotations

import numpy as np
import pytest
from spec_reference import mukf_step_ref

from mkf_ros.core.charts import CHART_NAMES, chart_id, from_chart_at
from mkf_ros.core.mukf import MukfMeasurement, mukf_step, mukf_step_ext
from mkf_ros.core.quaternion import angle_between, rotmat_np

DT, QW, QB = 0.02, np.diag([1.0, 2.0, 0.5]), 1e-6 * np.eye(3)


def _random_state(rng: np.random.Generator, nx: int) -> tuple:
    """A random chart centre, covariance (nx × nx), chart point, rate and bias."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    A = rng.normal(size=(nx, nx)) * 0.1
    return (q, A @ A.T + 1e-3 * np.eye(nx), rng.normal(size=3) * 0.1, rng.normal(size=3),
            rng.normal(size=3) * 0.01)


def _kernel_state(q: np.ndarray, ebar: np.ndarray, w: np.ndarray, b: np.ndarray,
                  P0: np.ndarray, nx: int) -> tuple:
    """Copies the kernel updates in place: ``(q, ē, ω, b, P)`` with P padded to 9 × 9."""
    P = np.zeros((9, 9))
    P[:nx, :nx] = P0
    return q.copy(), ebar.copy(), w.copy(), b.copy(), P


def _packed(vms: list, vrefs: list, Rvs: list, Qvs: list) -> tuple:
    """The kernel's two vector-measurement slots (measured, reference, R, Q), zero-padded."""
    vm_a, vr_a = np.zeros((2, 3)), np.zeros((2, 3))
    Rv_a, Qv_a = np.zeros((2, 3, 3)), np.zeros((2, 3, 3))
    for k in range(len(vms)):
        vm_a[k], vr_a[k], Rv_a[k], Qv_a[k] = vms[k], vrefs[k], Rvs[k], Qvs[k]
    return vm_a, vr_a, Rv_a, Qv_a


def _assert_equals_ref(qc: np.ndarray, e: np.ndarray, wk: np.ndarray, bk: np.ndarray,
                       P: np.ndarray, nx: int, ref: tuple) -> None:
    """Kernel state equals the transcription's (quaternion up to sign), to 1e-10."""
    qm, er, wr, br, Pr = ref
    assert min(np.abs(qc - qm).max(), np.abs(qc + qm).max()) < 1e-10
    np.testing.assert_allclose(e, er, atol=1e-10)
    np.testing.assert_allclose(wk, wr, atol=1e-10)
    np.testing.assert_allclose(bk, br, atol=1e-10)
    np.testing.assert_allclose(P[:nx, :nx], Pr, atol=1e-10)


@pytest.mark.parametrize("nx", [6, 9])
@pytest.mark.parametrize("chart", CHART_NAMES)
@pytest.mark.parametrize("cu", [True, False])
@pytest.mark.parametrize("published", [True, False])
def test_kernel_equals_full_augmentation(nx: int, chart: str, cu: bool, published: bool) -> None:
    """The kernel propagates only the attitude, rate and rate-noise sigma points, sums the
    disturbance and bias points and the linear (ω, b) part in closed form; the result equals
    §6 with all 2N+1 points."""
    rng = np.random.default_rng(nx + 10 * chart_id(chart) + 100 * cu + 1000 * published)
    for nvec in (0, 1, 2):
        for use_w in (True, False):
            if nvec == 0 and not use_w:
                continue
            q, P0, ebar, w, b = _random_state(rng, nx)
            dt, Qw, Qb = DT, QW, QB
            vms = [rng.normal(size=3) for _ in range(nvec)]
            vrefs = [np.array([0, 0, 1.0]), np.array([0, 0.6, -0.8])][:nvec]
            Rvs = [1e-3 * np.eye(3), 4e-4 * np.eye(3)][:nvec]
            B = rng.normal(size=(3, 3)) * 0.05
            Qvs = [1e-2 * np.eye(3), B @ B.T][:nvec]
            wm = w + rng.normal(size=3) * 0.1 if use_w else None
            Rw = 1e-4 * np.eye(3)
            ref = mukf_step_ref(chart_id(chart), cu, published, 1 / 25, q, ebar, w, b, P0, nx,
                                dt, Qw, Qb, vms, vrefs, Rvs, Qvs, wm, Rw)
            qc, e, wk, bk, P = _kernel_state(q, ebar, w, b, P0, nx)
            vm_a, vr_a, Rv_a, Qv_a = _packed(vms, vrefs, Rvs, Qvs)
            use_v = np.array([nvec > 0, nvec > 1])
            ok = mukf_step(chart_id(chart), cu, published, 1 / 25, (qc, e, wk, bk), P, nx, dt,
                           Qw, Qb, (vm_a, vr_a, Rv_a, Qv_a, use_v),
                           (wm if use_w else np.zeros(3), use_w, Rw))
            assert ok
            _assert_equals_ref(qc, e, wk, bk, P, nx, ref)


@pytest.mark.parametrize("chart", CHART_NAMES)
@pytest.mark.parametrize("cu", [True, False])
def test_converges_from_the_paper_start(chart: str, cu: bool) -> None:
    """From q̄ = 1, P = 100 I, ω̄ = 10⁻¹⁰ (§6 initialisation), a static body observed through a
    new random reference vector per step (§7.2) is found to within 1° well within 3000 steps."""
    rng = np.random.default_rng(3)
    qt = rng.normal(size=4)
    qt /= np.linalg.norm(qt)
    from mkf_ros.core.quaternion import rotmat

    qc, e, w, b = np.array([1.0, 0, 0, 0]), np.zeros(3), np.full(3, 1e-10), np.zeros(3)
    P = 100.0 * np.eye(9)
    R = 1e-4
    for _ in range(3000):
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        vm = rotmat(qt).T @ v + rng.normal(size=3) * np.sqrt(R)
        mukf_step(chart_id(chart), cu, False, 1 / 25, (qc, e, w, b), P, 6, 0.01, np.eye(3),
                  np.zeros((3, 3)), (vm[None], v[None], np.array([R * np.eye(3)]),
                                     np.array([1e-2 * np.eye(3)]), np.array([True])),
                  (rng.normal(size=3) * np.sqrt(R), True, R * np.eye(3)))
    assert np.degrees(angle_between(from_chart_at(chart_id(chart), qc, e), qt)) < 1.0


@pytest.mark.parametrize("nx", [6, 9])
@pytest.mark.parametrize("chart", CHART_NAMES)
@pytest.mark.parametrize("cu", [True, False])
@pytest.mark.parametrize("mode", [0, 1, 2])
def test_ext_equals_full_augmentation(nx: int, chart: str, cu: bool, mode: int) -> None:
    """mukf_step_ext (sums over the state and rate-noise points only, the gyro and zero-rate
    rows from P_xx since they are linear, bias-only points not propagated again, gates on the
    Cholesky factor of each block) against §6 with all 2N+1 points: every noise mode, the
    zero-rate pseudo-measurement, the NIS of every block and a block left out by its gate."""
    rng = np.random.default_rng(7 + nx + 10 * chart_id(chart) + 100 * cu + 1000 * mode)
    for nvec, use_w, use_z, gated in ((1, True, False, False), (2, True, True, False),
                                      (0, True, True, False), (1, False, True, False),
                                      (2, True, False, True), (1, True, True, True)):
        q, P0, ebar, w, b = _random_state(rng, nx)
        dt, Qw, Qb = DT, QW, QB
        vrefs = [np.array([0, 0, 1.0]), np.array([0, 0.6, -0.8])][:nvec]
        vms = [v + rng.normal(size=3) * 0.3 for v in vrefs]
        Rvs = [1e-3 * np.eye(3), 4e-4 * np.eye(3)][:nvec]
        B = rng.normal(size=(3, 3)) * 0.05
        Qvs = [1e-2 * np.eye(3), B @ B.T][:nvec]
        wm = w + rng.normal(size=3) * 0.1
        Rw, z_var = 1e-4 * np.eye(3), 1e-3
        args = (chart_id(chart), cu, mode, 1 / 25, q, ebar, w, b, P0, nx, dt, Qw, Qb, vms, vrefs,
                Rvs, Qvs, wm if use_w else None, Rw, z_var if use_z else None)
        nis_ref: list = []
        ref = mukf_step_ref(*args, nis_out=nis_ref)
        blocks = [0, 1][:nvec] + ([3] if use_w else [])  # kernel's nis slots, in row order
        gates = np.full(4, np.inf)
        drop = ()
        if gated:  # the first vector fails its gate
            gates[0] = 0.9 * nis_ref[0]
            drop = (0,)
            ref = mukf_step_ref(*args, drop=drop)
        qc, e, wk, bk, P = _kernel_state(q, ebar, w, b, P0, nx)
        vm_a, vr_a, Rv_a, Qv_a = _packed(vms, vrefs, Rvs, Qvs)
        nis = np.zeros(4)
        meas = MukfMeasurement(vm_a, vr_a, Rv_a, Qv_a, np.array([nvec > 0, nvec > 1]), wm,
                               use_w, Rw, np.zeros(3), np.zeros(3), False, 0.0, use_z, z_var,
                               gates, True, False, np.zeros((3, 3)), 1.0)
        ok = mukf_step_ext(chart_id(chart), cu, mode, 1 / 25, (qc, e, wk, bk), P, nx, dt, Qw,
                           Qb, meas, nis)
        assert ok
        _assert_equals_ref(qc, e, wk, bk, P, nx, ref)
        np.testing.assert_allclose(nis[blocks], nis_ref[:len(blocks)], rtol=1e-9)


def test_step_equals_ext_without_gates() -> None:
    """mukf_step (no gates, no NIS) is mukf_step_ext with infinite gates."""
    rng = np.random.default_rng(5)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    A = rng.normal(size=(9, 9)) * 0.1
    P0 = A @ A.T + 1e-3 * np.eye(9)
    w, b = rng.normal(size=3), rng.normal(size=3) * 0.01
    vm, vr = rng.normal(size=(2, 3)), np.array([[0, 0, 1.0], [0, 0.6, -0.8]])
    Rv, Qv = np.array([1e-3 * np.eye(3)] * 2), np.array([1e-2 * np.eye(3)] * 2)
    out = []
    for ext in (False, True):
        qc, e, wk, bk, P = q.copy(), np.full(3, 0.05), w.copy(), b.copy(), P0.copy()
        common = (1, True, 1, 1 / 25, (qc, e, wk, bk), P, 9, 0.01, np.eye(3), 1e-6 * np.eye(3))
        vectors, gyro = (vm, vr, Rv, Qv, np.array([True, True])), (w + 0.1, True,
                                                                    1e-4 * np.eye(3))
        if ext:
            assert mukf_step_ext(*common, MukfMeasurement(
                *vectors, *gyro, np.zeros(3), np.zeros(3), False, 0.0, False, 0.0,
                np.full(4, np.inf), True, False, np.zeros((3, 3)), 1.0), np.zeros(4))
        else:
            assert mukf_step(*common, vectors, gyro)
        out.append(np.concatenate([qc, e, wk, bk, P.ravel()]))
    np.testing.assert_array_equal(out[0], out[1])


def _ext(chart: str, q, P0, ebar, w, b, vm, vr, Rv, Qv, use_v, heading=None,
         tilt: bool = False, nx: int = 9, cu: bool = True, wm=None, bias_gain_h: float = 1.0):
    """mukf_step_ext on copies (integrated noise); returns (q̄, ē, ω̄, b̄, P)."""
    qc, e, wk, bk = q.copy(), ebar.copy(), w.copy(), b.copy()
    P = np.zeros((9, 9))
    P[:nx, :nx] = P0
    hm, href, var_h = heading if heading is not None else (np.zeros(3), np.zeros(3), 0.0)
    meas = MukfMeasurement(vm, vr, Rv, Qv, use_v, wm if wm is not None else w, wm is not None,
                           1e-4 * np.eye(3), hm, href, heading is not None, var_h, False, 0.0,
                           np.full(4, np.inf), True, tilt, np.zeros((3, 3)), 1.0, bias_gain_h)
    assert mukf_step_ext(chart_id(chart), cu, 2, 1 / 25, (qc, e, wk, bk), P, nx, DT, QW, QB,
                         meas, np.zeros(4))
    return qc, e, wk, bk, P[:nx, :nx]


@pytest.mark.parametrize("chart", CHART_NAMES)
def test_projected_gain_costs_exactly_its_joseph_term(chart: str) -> None:
    """A gain projected by the real-sensor extensions (gravity tilt-only) is sub-optimal: the
    covariance after it is the optimal update's plus exactly ΔK P_yy ΔKᵀ, with K₀ and P_yy
    from the full 2N+1-point transcription and ΔK = −blockdiag(u uᵀ) K₀ on the gravity
    columns (u the world vertical at the new mean); and the attitude correction has no
    component along the world vertical."""
    rng = np.random.default_rng(11 + chart_id(chart))
    for _ in range(5):
        q, P0, ebar, w, b = _random_state(rng, 9)
        vr = np.array([[0, 0, 1.0], [0, 0, 0]])
        vm = np.array([rng.normal(size=3) * 0.2 + vr[0], np.zeros(3)])
        Rv, Qv = np.array([1e-3 * np.eye(3)] * 2), np.array([1e-2 * np.eye(3)] * 2)
        use_v = np.array([True, False])
        q0, e0, _, _, P_opt = _ext(chart, q, P0, ebar, w, b, vm, vr, Rv, Qv, use_v)
        q1, e1, _, _, P_tilt = _ext(chart, q, P0, ebar, w, b, vm, vr, Rv, Qv, use_v, tilt=True)
        np.testing.assert_allclose(q0, q1, atol=1e-15)  # same sigma points, same mean
        ref: dict = {}
        mukf_step_ref(chart_id(chart), True, 2, 1 / 25, q, ebar, w, b, P0, 9, DT, QW, QB,
                      [vm[0]], [vr[0]], [Rv[0]], [Qv[0]], None, None, internals=ref)
        u = rotmat_np(q1)[2]
        np.testing.assert_allclose(ref["u"], u, atol=1e-12)
        dK = -np.kron(np.eye(3), np.outer(u, u)) @ ref["K0"]  # all three rows are gravity's
        term = dK @ ref["Pyy"] @ dK.T
        assert np.abs(term).max() > 1e-9  # the projection does cost something here
        np.testing.assert_allclose(P_tilt - P_opt, term, atol=1e-10 * np.abs(P_opt).max())
        # the correction ē (in the chart at the new mean q̄⁻, gravity the only measurement):
        # none of it about the world vertical u = R(q̄⁻)ᵀ ẑ (saturation keeps the direction)
        assert abs(u @ e1) < 1e-12 * max(1.0, np.linalg.norm(e1))
        assert np.linalg.norm(e1) > 1e-6
        assert abs(u @ e0) > 1e-9  # the optimal gain does turn about it


def _heading_inputs(rng: np.random.Generator, q: np.ndarray) -> tuple:
    """A magnetometer reading for the heading row: the field (dip 60° down) seen from an
    attitude near q, a horizontal north reference and the row's variance."""
    field = np.array([0.0, np.cos(np.radians(60)), -np.sin(np.radians(60))])
    q_seen = q + rng.normal(size=4) * 0.05
    q_seen /= np.linalg.norm(q_seen)
    return rotmat_np(q_seen).T @ field, np.array([0.0, 1.0, 0.0]), 1e-3


@pytest.mark.parametrize("bias_gain_h", [1.0, 0.3])
@pytest.mark.parametrize("nx", [6, 9])
@pytest.mark.parametrize("chart", CHART_NAMES)
@pytest.mark.parametrize("tilt", [False, True], ids=["vector", "tilt_only"])
def test_heading_row_equals_transcription(nx: int, chart: str, tilt: bool,
                                          bias_gain_h: float) -> None:
    """The MUKF's heading row (ψ carried through every sigma point, unwrapped around the
    central one; the gain of each group projected onto the world vertical; Joseph form), alone
    and with a tilt-only gravity row and the gyro, against the full 2N+1-point transcription
    with the gain K written column by column and P = P_xx − K P_xyᵀ − P_xy Kᵀ + K P_yy Kᵀ; the
    heading's bias rows times ``bias_gain_h`` (``mag_bias_gain``, docs/math.md §9.2)."""
    rng = np.random.default_rng(3 + nx + 10 * chart_id(chart) + 100 * tilt)
    for nvec in (0, 1):
        for with_gyro in (False, True):
            q, P0, ebar, w, b = _random_state(rng, nx)
            heading = _heading_inputs(rng, q)
            vr = np.array([[0, 0, 1.0], [0, 0, 0]])
            vm = np.array([rotmat_np(q).T @ vr[0] + rng.normal(size=3) * 0.1, np.zeros(3)])
            Rv, Qv = np.array([1e-3 * np.eye(3)] * 2), np.array([1e-2 * np.eye(3)] * 2)
            wm = w + rng.normal(size=3) * 0.1 if with_gyro else None
            got = _ext(chart, q, P0, ebar, w, b, vm, vr, Rv, Qv, np.array([nvec > 0, False]),
                       heading=heading, tilt=tilt, nx=nx, wm=wm, bias_gain_h=bias_gain_h)
            want = mukf_step_ref(chart_id(chart), True, 2, 1 / 25, q, ebar, w, b, P0, nx, DT,
                                 QW, QB, [vm[0]][:nvec], [vr[0]][:nvec], [Rv[0]][:nvec],
                                 [Qv[0]][:nvec], wm, 1e-4 * np.eye(3), heading=heading,
                                 tilt_v0=tilt, heading_bias_gain=bias_gain_h)
            qk, ek, wk, bk, Pk = got
            qm, er, wr, br, Pr = want
            assert min(np.abs(qk - qm).max(), np.abs(qk + qm).max()) < 1e-10
            np.testing.assert_allclose(ek, er, atol=1e-10)
            np.testing.assert_allclose(wk, wr, atol=1e-10)
            np.testing.assert_allclose(bk, br, atol=1e-10)
            np.testing.assert_allclose(Pk, Pr, atol=1e-10)
