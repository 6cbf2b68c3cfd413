"""The simulation procedure of the paper's study (``docs/math.md`` §7.2) as numba kernels.

One *trajectory* is identified by ``(seed, rate, trajectory index)``. Its random numbers come from
three independent, deterministic streams (common random numbers, CRN):

* **init** — the true initial attitude (uniform on S³) and the two uniforms that set the true
  noise levels ``Q_ω^true``, ``Q_v^true`` (§8 item 11);
* **conv** — the measurements of the convergence phase (§7.2 step 2). Every filter variant
  replays this stream from its start, so variant A's k-th convergence measurement is variant B's
  k-th, although the phases end at different k;
* **est** — the Wiener-process motion (100 sub-steps per update) and the measurements of the
  estimation phase (§7.2 step 3). The truth and the measurements are computed once and fed to
  every filter variant.

The measurement noise is stored as standard normals and scaled by ``√R`` inside the filter loop,
so the three sensor grades R ∈ {10⁻², 10⁻⁴, 10⁻⁶} also share one trajectory (CRN across R too).
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit
from mkf_ros.core.charts import from_chart_at
from mkf_ros.core.mekf import mekf_predict, mekf_update
from mkf_ros.core.mukf import mukf_step

# --- study constants (§7.1) -------------------------------------------------------------------
T_SIM = 10.0  #: s, length of the estimation phase
SUBSTEPS = 100  #: simulation sub-steps per filter update (dt / dt_sim)
THETA_E0_DEG = 1.0  #: convergence threshold θ_e0
CONV_CAP = 100_000  #: cap on convergence-phase updates (§8 item 12)
QW_MAX = 100.0  #: rad²/s³, upper bound of the true ω process noise
QV_MAX = 1.0  #: p.d.u., upper bound of the true external disturbance
FILTER_QW = 1.0  #: rad²/s³, the filters' Q_ω
FILTER_QV = 1e-2  #: p.d.u., the filters' Q_v
P0 = 100.0  #: P_0 = P0 · I₆
W0 = 1.0 / 25.0  #: MUKF central weight
MUKF_RATE0 = 1e-10  #: MUKF ω̄_0 = 10⁻¹⁰·(1,1,1) rad/s

# --- variant encoding: one row (kind, chart, chart_update, published_scaling) per filter ---
MEKF, MUKF = 0, 1

# --- status codes of one run ------------------------------------------------------------------
OK = 0  #: converged, estimation phase completed
NON_CONVERGED = 1  #: hit CONV_CAP; the estimation phase was still run (reported separately)
CRASHED_CONV = 2  #: kernel failure or non-finite estimate during the convergence phase
CRASHED_EST = 3  #: kernel failure or non-finite estimate during the estimation phase
#: Convergence phase stopped early at a fixed point of the filter: the attitude block of P did
#: not change (relative :data:`STALL_RTOL`) for :data:`STALL_WINDOW` consecutive updates, so the
#: measurements carry no attitude information into the estimate and it can never reach θ_e0.
#: Counted as non-converged (the estimation phase is run, as after the cap). Deviation from
#: §8 item 12, which only caps the phase: the MUKF with the RV chart and the reset meets such a
#: fixed point from P_0 = 10²·I (its sigma points sit at ±π·u, which are the same rotation, so
#: P_xy = 0 for the attitude; the study's summary explains it) and would otherwise spend the
#: whole cap there.
STALLED = 4
STALL_WINDOW = 1000  #: consecutive convergence updates with an unchanged attitude covariance
#: Relative change of diag(P_ee) below which an update counts as unchanged. At the MUKF-RV
#: fixed point it changes by ~1e-11 per update (the rate-noise sigma points); a filter that
#: learns changes it by > 3e-5 per update (measured on study trajectories at 2, 100, 1000 Hz).
STALL_RTOL = 1e-8


def stream_seeds(seed: int, rate_hz: float, traj: int) -> tuple[np.random.Generator, int,
                                                                   np.random.Generator]:
    """The three streams of trajectory ``(seed, rate, traj)``: init generator, conv seed
    (uint32 for numba's generator, replayed per variant) and est generator.

    Keyed on the rate in mHz, so selecting a subset of cells never changes a trajectory."""
    key = (0x4D4B46, round(float(rate_hz) * 1000), int(traj))
    ss = np.random.SeedSequence(entropy=int(seed), spawn_key=key)
    init, conv, est = ss.spawn(3)
    return (np.random.Generator(np.random.PCG64(init)),
            int(conv.generate_state(1, np.uint32)[0]),
            np.random.Generator(np.random.PCG64(est)))


def noise_sigmas(u_w: float, u_v: float, sampling: str) -> tuple[float, float]:
    """True noise standard deviations from two uniforms (§8 item 11).

    ``sigma``: σ ~ U[0, √Q_max] (default; matches the published curves); ``variance``: the
    literal reading Q ~ U[0, Q_max]."""
    if sampling == "sigma":
        return u_w * np.sqrt(QW_MAX), u_v * np.sqrt(QV_MAX)
    if sampling == "variance":
        return np.sqrt(u_w * QW_MAX), np.sqrt(u_v * QV_MAX)
    raise ValueError(f"noise sampling must be 'sigma' or 'variance', got {sampling!r}")


def trajectory_inputs(seed: int, rate_hz: float, traj: int, sampling: str) -> dict:
    """Everything the filters see of one trajectory (§7.2 steps 1 and 3), as arrays."""
    init, conv_seed, est = stream_seeds(seed, rate_hz, traj)
    q0 = init.standard_normal(4)
    q0 /= np.linalg.norm(q0)
    u_w, u_v = init.random(2)
    sigma_w, sigma_v = noise_sigmas(float(u_w), float(u_v), sampling)
    n = n_updates(rate_hz)
    z_w = est.standard_normal((n, SUBSTEPS, 3))
    z_m = est.standard_normal((n, 12))
    q_true, w_true, vref, vbody = simulate_truth(q0, sigma_w, sigma_v, 1.0 / rate_hz, z_w, z_m)
    return dict(q0=q0, sigma_w=sigma_w, sigma_v=sigma_v, conv_seed=conv_seed, q_true=q_true,
                w_true=w_true, vref=vref, vbody=vbody, z_noise=np.ascontiguousarray(z_m[:, 6:12]))


def n_updates(rate_hz: float) -> int:
    """Number of estimation-phase updates, ``T_sim · f`` (the last one exactly at T_sim)."""
    return round(T_SIM * float(rate_hz))


@jit
def _unit_vector(z0: float, z1: float, z2: float, out: np.ndarray) -> None:
    """Uniform direction on S² from three standard normals."""
    n = np.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
    if n == 0.0:
        out[0], out[1], out[2] = 0.0, 0.0, 1.0
    else:
        out[0], out[1], out[2] = z0 / n, z1 / n, z2 / n


@jit
def _body_of(q: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """``out = R(q)ᵀ v`` (world → body, §1.2), without allocating."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    out[0] = ((1.0 - 2.0 * (q2 * q2 + q3 * q3)) * v[0] + 2.0 * (q1 * q2 + q0 * q3) * v[1]
              + 2.0 * (q1 * q3 - q0 * q2) * v[2])
    out[1] = (2.0 * (q1 * q2 - q0 * q3) * v[0] + (1.0 - 2.0 * (q1 * q1 + q3 * q3)) * v[1]
              + 2.0 * (q2 * q3 + q0 * q1) * v[2])
    out[2] = (2.0 * (q1 * q3 + q0 * q2) * v[0] + 2.0 * (q2 * q3 - q0 * q1) * v[1]
              + (1.0 - 2.0 * (q1 * q1 + q2 * q2)) * v[2])


@jit
def simulate_truth(
    q0: np.ndarray, sigma_w: float, sigma_v: float, dt: float, z_w: np.ndarray, z_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Estimation-phase truth and noise-free-of-R measurements (§7.2 step 3).

    Per update: ``SUBSTEPS`` times ``ω ← ω + σ_ω ξ √dt_sim`` then ``q ← q * q_ω(ω, dt_sim)``
    (normalised); then a new reference ``v`` uniform on S² (``z_m[n, 0:3]``) and the disturbed
    body vector ``R(q)ᵀ (v + σ_v z_m[n, 3:6])``. Returns ``q_true, ω_true, v, R(q)ᵀ(v + w_v)``
    per update; the sensor noise ``√R z_m[n, 6:12]`` is added by the filter loop.
    """
    n = z_w.shape[0]
    ns = z_w.shape[1]
    dts = dt / ns
    s = sigma_w * np.sqrt(dts)
    q_true = np.empty((n, 4))
    w_true = np.empty((n, 3))
    vref = np.empty((n, 3))
    vbody = np.empty((n, 3))
    a0, a1, a2, a3 = q0[0], q0[1], q0[2], q0[3]
    w0 = w1 = w2 = 0.0
    d = np.empty(3)
    for k in range(n):
        for j in range(ns):
            w0 += s * z_w[k, j, 0]
            w1 += s * z_w[k, j, 1]
            w2 += s * z_w[k, j, 2]
            # q ← q * q_ω(ω, dt_sim)  (§1.3, sinc form)
            nw = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            half = 0.5 * nw * dts
            sc = 0.5 * dts * (1.0 - half * half / 6.0) if half < 1e-4 else np.sin(half) / nw
            c0, c1, c2, c3 = np.cos(half), w0 * sc, w1 * sc, w2 * sc
            b0 = a0 * c0 - a1 * c1 - a2 * c2 - a3 * c3
            b1 = a0 * c1 + a1 * c0 + a2 * c3 - a3 * c2
            b2 = a0 * c2 + a2 * c0 + a3 * c1 - a1 * c3
            b3 = a0 * c3 + a3 * c0 + a1 * c2 - a2 * c1
            inv = 1.0 / np.sqrt(b0 * b0 + b1 * b1 + b2 * b2 + b3 * b3)
            a0, a1, a2, a3 = b0 * inv, b1 * inv, b2 * inv, b3 * inv
        q_true[k, 0], q_true[k, 1], q_true[k, 2], q_true[k, 3] = a0, a1, a2, a3
        w_true[k, 0], w_true[k, 1], w_true[k, 2] = w0, w1, w2
        _unit_vector(z_m[k, 0], z_m[k, 1], z_m[k, 2], vref[k])
        for i in range(3):
            d[i] = vref[k, i] + sigma_v * z_m[k, 3 + i]
        _body_of(q_true[k], d, vbody[k])
    return q_true, w_true, vref, vbody


@jit
def _angle(p: np.ndarray, q: np.ndarray) -> float:
    """``θ = 2 arccos|p·q|`` (§7.3, eq. 72), rad."""
    d = abs(p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3])
    return 2.0 * np.arccos(min(d, 1.0))


@jit
def _step(spec: tuple, state: tuple, dt: float, noise: tuple, vectors: tuple, wm: np.ndarray,
          qhat: np.ndarray) -> bool:
    """One filter update with (Δt, v_m, ω_m, v) through the core kernels (§5, §6): the variant
    ``spec = (kind, chart, chart_update, published scaling)``, the state ``(q̄_c, ē, ω̄, b̄,
    P)``, ``noise = (Q_ω, Q_b, R_ω)``, ``vectors = (v_m, v, R_v, Q_v, use_v)``; writes the
    estimate into ``qhat``. False on a kernel failure or a non-finite estimate."""
    kind, chart, cu, pub = spec
    qc, eb, w, b, P = state
    Qw, Qb, Rw = noise
    if kind == MEKF:
        mekf_predict(qc, w, P, 6, dt, Qw, Qb)
        ok = mekf_update(chart, cu, (qc, w, b), P, 6, vectors, (wm, True, Rw))
        qhat[:] = qc
    else:
        ok = mukf_step(chart, cu, pub, W0, (qc, eb, w, b), P, 6, dt, Qw, Qb, vectors,
                       (wm, True, Rw))
        qhat[:] = from_chart_at(chart, qc, eb)
    return ok and np.isfinite(qhat[0] + qhat[1] + qhat[2] + qhat[3])


@jit
def _filter_noise() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The filters' noise matrices of the study (§7.2): ``Q_ω``, ``Q_b = 0``, ``R_ω``, ``R_v``
    (these two set per sensor grade by :func:`_set_grade`), ``Q_v``."""
    Qw = np.zeros((3, 3))
    Qb = np.zeros((3, 3))
    Rw = np.zeros((3, 3))
    Rv = np.zeros((1, 3, 3))
    Qv = np.zeros((1, 3, 3))
    for i in range(3):
        Qw[i, i] = FILTER_QW
        Qv[0, i, i] = FILTER_QV
    return Qw, Qb, Rw, Rv, Qv


@jit
def _set_grade(Rw: np.ndarray, Rv: np.ndarray, r: float) -> None:
    """Sensor grade ``r``: ``R_ω = R_v = r I`` (§7.2)."""
    for i in range(3):
        for j in range(3):
            Rw[i, j] = r if i == j else 0.0
            Rv[0, i, j] = Rw[i, j]


@jit
def _buffers() -> tuple:
    """One run's buffers: the measurement in use (one vector), the measured and reference
    vector, the measured rate, the filter state ``q̄_c, ē, ω̄, b̄, P`` (set by
    :func:`_init_state`) and the estimate ``q̂``."""
    return (np.ones(1, dtype=np.bool_), np.empty((1, 3)), np.empty((1, 3)), np.empty(3),
            np.empty(4), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros((9, 9)), np.empty(4))


@jit
def _init_state(kind: int, qc: np.ndarray, eb: np.ndarray, w: np.ndarray,
                P: np.ndarray) -> None:
    """§7.1 initialisation: ``q̄ = (1, 0, 0, 0)``, ``ē = 0``, ``ω̄ = 0`` (MUKF:
    :data:`MUKF_RATE0`), ``P = P0 I₆``."""
    qc[0], qc[1], qc[2], qc[3] = 1.0, 0.0, 0.0, 0.0
    eb[:] = 0.0
    w[:] = MUKF_RATE0 if kind == MUKF else 0.0
    P[:, :] = 0.0
    for i in range(6):
        P[i, i] = P0


@jit
def run_trajectory(specs: np.ndarray, rs: np.ndarray, dt: float, convergence: tuple,
                   truth: tuple, out: tuple) -> None:
    """Run every filter variant ``specs[i] = (kind, chart, chart_update, published_scaling)``
    at every sensor grade ``rs[j]`` on one trajectory (§7.2 steps 1–4): ``convergence = (q0,
    sigma_v, conv_seed, cap)``, ``truth = (q_true, w_true, vref, vbody, z_noise)`` (the
    estimation phase's), ``out = (out_err, out_conv, out_status)``.

    Convergence phase: fixed truth ``q0``, ``ω = 0``; measurement k uses the k-th draw of the
    numba generator seeded with ``conv_seed`` (order: v, w_v, r_v, r_ω), replayed identically for
    every variant; stops when ``θ(q̂, q0) < θ_e0``, after ``cap`` updates, or at a fixed point
    (:data:`STALLED`). Estimation phase:
    the precomputed truth. Outputs: mean error ``(1/(T f)) Σ θ_n`` in rad (NaN if crashed), the
    number of convergence updates, and the status code.
    """
    out_err, out_conv, out_status = out
    Qw, Qb, Rw, Rv, Qv = _filter_noise()
    use_v, vm, vr, wm, qc, eb, w, b, P, qhat = _buffers()
    for iv in range(specs.shape[0]):
        kind, chart = specs[iv, 0], specs[iv, 1]
        cu, pub = specs[iv, 2] != 0, specs[iv, 3] != 0
        run = ((kind, chart, cu, pub), (qc, eb, w, b, P), dt, (Qw, Qb, Rw),
               (vm, vr, Rv, Qv, use_v), wm, qhat)
        for ir in range(rs.shape[0]):
            r = rs[ir]
            _set_grade(Rw, Rv, r)
            _init_state(kind, qc, eb, w, P)
            k, status = _converge(run, convergence, np.sqrt(r))
            out_conv[iv, ir] = k
            if status == CRASHED_CONV:
                out_status[iv, ir] = status
                out_err[iv, ir] = np.nan
                continue
            status, err = _estimate(run, truth, np.sqrt(r), status)
            out_status[iv, ir] = status
            out_err[iv, ir] = err


@jit
def _converge(run: tuple, convergence: tuple, sr: float) -> tuple[int, int]:
    """§7.2 step 2, the convergence phase of one variant (``run``: the arguments of
    :func:`_step`) at one sensor grade (``sr``, the noise's standard deviation): returns the
    number of updates and the status."""
    spec, state, dt, noise, vectors, wm, qhat = run
    q0, sigma_v, conv_seed, cap = convergence
    vm, vr = vectors[0], vectors[1]
    P = state[4]
    theta0 = np.deg2rad(THETA_E0_DEG)
    d = np.empty(3)
    np.random.seed(conv_seed)
    status = NON_CONVERGED
    k = 0
    same = 0  # consecutive updates that left diag(P_ee) unchanged
    p_prev = np.empty(3)
    for i in range(3):
        p_prev[i] = P[i, i]
    while k < cap:
        _unit_vector(np.random.standard_normal(), np.random.standard_normal(),
                     np.random.standard_normal(), vr[0])
        for i in range(3):
            d[i] = vr[0, i] + sigma_v * np.random.standard_normal()
        _body_of(q0, d, vm[0])
        for i in range(3):
            vm[0, i] += sr * np.random.standard_normal()
        for i in range(3):
            wm[i] = sr * np.random.standard_normal()
        k += 1
        if not _step(spec, state, dt, noise, vectors, wm, qhat):
            return k, CRASHED_CONV
        if _angle(qhat, q0) < theta0:
            return k, OK
        moved = False
        for i in range(3):
            if abs(P[i, i] - p_prev[i]) > STALL_RTOL * abs(p_prev[i]):
                moved = True
            p_prev[i] = P[i, i]
        same = 0 if moved else same + 1
        if same >= STALL_WINDOW:
            return k, STALLED
    return k, status


@jit
def _estimate(run: tuple, truth: tuple, sr: float, status: int) -> tuple[int, float]:
    """§7.2 step 3, the estimation phase on the shared truth: returns the status (``status``
    of the convergence phase, or :data:`CRASHED_EST`) and the mean error (rad; NaN if
    crashed)."""
    spec, state, dt, noise, vectors, wm, qhat = run
    q_true, w_true, vref, vbody, z_noise = truth
    vm, vr = vectors[0], vectors[1]
    n_est = q_true.shape[0]
    acc = 0.0
    for n in range(n_est):
        for i in range(3):
            vr[0, i] = vref[n, i]
            vm[0, i] = vbody[n, i] + sr * z_noise[n, i]
            wm[i] = w_true[n, i] + sr * z_noise[n, 3 + i]
        if not _step(spec, state, dt, noise, vectors, wm, qhat):
            return CRASHED_EST, np.nan
        acc += _angle(qhat, q_true[n])
    return status, acc / n_est


@jit
def run_updates(spec: np.ndarray, r: float, dt: float, vref: np.ndarray, vbody: np.ndarray,
                w_true: np.ndarray, z_noise: np.ndarray) -> np.ndarray:
    """Feed one filter variant the measurements of an estimation phase, nothing else (the
    speed benchmark, paper Fig. 4 / §7.4). Returns the final estimate."""
    kind, chart = spec[0], spec[1]
    cu, pub = spec[2] != 0, spec[3] != 0
    sr = np.sqrt(r)
    Qw, Qb, Rw, Rv, Qv = _filter_noise()
    _set_grade(Rw, Rv, r)
    use_v, vm, vr, wm, qc, eb, w, b, P, qhat = _buffers()
    _init_state(kind, qc, eb, w, P)
    for n in range(vref.shape[0]):
        for i in range(3):
            vr[0, i] = vref[n, i]
            vm[0, i] = vbody[n, i] + sr * z_noise[n, i]
            wm[i] = w_true[n, i] + sr * z_noise[n, 3 + i]
        _step((kind, chart, cu, pub), (qc, eb, w, b, P), dt, (Qw, Qb, Rw),
              (vm, vr, Rv, Qv, use_v), wm, qhat)
    return qhat
