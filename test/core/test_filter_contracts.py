"""The library keeps the node's promises (mkf_ros.core.filter, its stateful and batch
APIs): an invalid time step is refused without touching the state, ``Δt = 0`` is defined, an
implausibly large reading is invalid (counted, like the node's 1000 rad/s limit), and the
covariance stays symmetric PSD at the ends of the parameter ranges."""

from __future__ import annotations

import numpy as np
import pytest

import mkf_ros
from mkf_ros.core.filter import AttitudeFilter, record
from mkf_ros.core.params import ALGORITHMS, BY_NAME
from mkf_ros.core.quaternion import angle_between, rotmat
from mkf_ros.sim import simulate

G = 9.80665
ACC = np.array([0.3, -0.2, G])
MAG = np.array([0.0, 20e-6, -40e-6])


def snapshot(f: AttitudeFilter) -> tuple[bytes, ...]:
    """Every array the filter's state lives in, as bytes (bit-identical comparison)."""
    return f._cfg.tobytes(), f._st.tobytes(), f.counters.tobytes()


def running_filter(algorithm: str, use_mag: bool = True) -> AttitudeFilter:
    f = AttitudeFilter(algorithm=algorithm, use_mag=use_mag)
    f.step(0.0, [0.0, 0.0, 0.0], ACC, MAG)
    for _ in range(20):
        f.step(0.01, [0.2, -0.1, 0.05], ACC, MAG)
    return f


def min_eig(P: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(P).min())


# --- item 1: Δt of AttitudeFilter.step ----------------------------------------------------------

@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("dt", [float("nan"), float("inf"), -float("inf"), -0.01, -1e-300,
                                "0.01", True, None, [0.01]])
def test_step_refuses_an_invalid_dt_and_changes_nothing(algorithm: str, dt: object) -> None:
    f = running_filter(algorithm)
    before = snapshot(f)
    with pytest.raises(ValueError, match=r"^dt must be a finite number of seconds >= 0") as e:
        f.step(dt, [0.1, 0.0, 0.0], ACC, MAG)  # type: ignore[arg-type]
    assert "\n" not in str(e.value)
    assert snapshot(f) == before
    f.step(0.01, [0.1, 0.0, 0.0], ACC, MAG)  # and it goes on as if the call had not happened
    assert np.all(np.isfinite(f.quaternion)) and min_eig(f.covariance) > 0


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("name", ["gyr", "acc", "mag"])
def test_step_refuses_a_malformed_sample_naming_it(algorithm: str, name: str) -> None:
    f = running_filter(algorithm)
    before = snapshot(f)
    kw = {"gyr": [0.1, 0.0, 0.0], "acc": ACC, "mag": MAG, name: [1.0, 2.0]}
    with pytest.raises(ValueError, match=rf"^{name} must have 3 components"):
        f.step(0.01, **kw)
    kw[name] = "abc"
    with pytest.raises(ValueError, match=rf"^{name} must be 3 numbers or None"):
        f.step(0.01, **kw)
    assert snapshot(f) == before


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_dt_zero_without_readings_changes_nothing_but_the_sample_count(algorithm: str) -> None:
    """``Δt = 0``: no time passes, so no prediction; with no reading there is nothing to fuse."""
    f = running_filter(algorithm)
    st, q = f._st.copy(), f.quaternion
    P = record(st).P
    n = f.counter_dict()["samples"]
    f.step(0.0)
    assert f.counter_dict()["samples"] == n + 1
    if algorithm == "mukf":
        # its state is (q̄_c, ē): the first step, even an empty one, moves the covariance to
        # the chart of the estimate (paper eq. 47b; measured: q by 2.5e-7 rad, P by 3.5e-5 of
        # its size); from there on an empty Δt = 0 step changes nothing beyond rounding
        P, q = record(f._st).P.copy(), f.quaternion
        f.step(0.0)
        assert angle_between(f.quaternion, q) < 1e-12
        assert np.abs(record(f._st).P - P).max() <= 1e-12 * np.abs(P).max()
        return
    # (the Euler baselines recompute their angles and quaternion: rounding)
    np.testing.assert_allclose(f.quaternion, q, rtol=0, atol=1e-15)
    assert np.abs(record(f._st).P - P).max() <= 1e-14 * np.abs(P).max()  # the UKF: its rounding
    # nor does any other state (the low-pass clocks, the time since the last accelerometer
    # sample, ...), except the cache of the low-pass gains (the last Δt and its gain)
    for name in st.dtype.names:
        if name != "lp_gain":
            np.testing.assert_allclose(f._st[name].astype(float), st[name].astype(float),
                                       rtol=1e-14, atol=1e-15, err_msg=name)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("use_mag", [False, True])
def test_dt_zero_repeats_are_fused_at_one_instant(algorithm: str, use_mag: bool) -> None:
    """Many readings at one instant (Δt = 0, also before the first real step) keep the state
    finite, unit-norm and the covariance symmetric PSD, and the estimate stays where the
    readings put it (level: ACC is 2.1° off vertical)."""
    f = AttitudeFilter(algorithm=algorithm, use_mag=use_mag)
    m = MAG if use_mag else None
    for _ in range(5):
        f.step(0.0, [0.0, 0.0, 0.0], ACC, m)
    for _ in range(50):
        f.step(0.01, [0.0, 0.0, 0.0], ACC, m)
        for _ in range(3):
            f.step(0.0, [0.0, 0.0, 0.0], ACC, m)
    q, P = f.quaternion, f.covariance
    assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-12
    np.testing.assert_array_equal(P, P.T)
    assert min_eig(P) > 0
    S = f.state_covariance
    assert np.all(np.isfinite(S)) and min_eig(0.5 * (S + S.T)) >= -1e-12 * np.trace(S)
    tilt = np.degrees(np.arccos(np.clip((rotmat(q).T @ [0, 0, 1])
                                        @ (ACC / np.linalg.norm(ACC)), -1, 1)))
    assert tilt < 0.5


# --- item 2: implausibly large readings -------------------------------------------------------

SIM = simulate("static", duration=5, rate=100, seed=1)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize(("sensor", "index", "value", "counter"), [
    ("gyr", 200, 1e150, "gyr_invalid"),
    ("gyr", 200, 1e300, "gyr_invalid"),
    ("gyr", 200, 1001.0, "gyr_invalid"),   # the node's limit: 1000 rad/s
    ("acc", 200, 1e150, "acc_invalid"),
    ("acc", 0, 1e200, "acc_invalid"),
    ("mag", 0, 1e155, "mag_invalid"),      # on the first sample
    ("mag", 200, 1e300, "mag_invalid"),
    ("mag", 200, 1e-160, "mag_invalid"),   # its square underflows: no direction
])
def test_estimate_counts_an_implausible_reading_as_invalid(
        algorithm: str, sensor: str, index: int, value: float, counter: str) -> None:
    data = {"gyr": SIM.gyr.copy(), "acc": SIM.acc.copy(), "mag": SIM.mag.copy()}
    data[sensor][index] = np.array([1.0, 0.5, -1.0]) * value / np.sqrt(2.25)
    r = mkf_ros.estimate(data["gyr"], data["acc"], data["mag"], dt=0.01, algorithm=algorithm)
    assert r.counters[counter] == 1
    for name in ("quat", "cov", "omega", "bias", "bias_std"):
        assert np.all(np.isfinite(getattr(r, name))), name
    clean = mkf_ros.estimate(SIM.gyr, SIM.acc, SIM.mag, dt=0.01, algorithm=algorithm)
    # the one sample is skipped: the end result is as good as without it (same truth)
    err = np.degrees(angle_between(r.quat[-1], SIM.quat[-1]))
    err0 = np.degrees(angle_between(clean.quat[-1], SIM.quat[-1]))
    assert err < err0 + 1.0


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_a_gyro_below_the_limit_is_a_reading(algorithm: str) -> None:
    g = SIM.gyr.copy()
    g[200] = [999.0, 0.0, 0.0]
    r = mkf_ros.estimate(g, SIM.acc, dt=0.01, algorithm=algorithm)
    assert r.counters["gyr_invalid"] == 0
    assert np.all(np.isfinite(r.quat)) and np.all(np.isfinite(r.cov))


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_step_counts_an_implausible_reading_as_invalid(algorithm: str) -> None:
    f = running_filter(algorithm)
    f.step(0.01, [1e200, 0.0, 0.0], [1e200, 0.0, 0.0], [0.0, 0.0, 1e200])
    c = f.counter_dict()
    assert (c["gyr_invalid"], c["acc_invalid"], c["mag_invalid"]) == (1, 1, 1)
    for _ in range(10):
        f.step(0.01, [0.0, 0.0, 0.0], ACC, MAG)
    assert np.all(np.isfinite(f.quaternion)) and np.all(np.isfinite(f.state_covariance))


def test_the_node_and_the_library_share_one_limit() -> None:
    """The stream adapter (the node's rules) counts the same readings as invalid."""
    from mkf_ros.stream.adapter import StreamAdapter

    n = 300
    g, a = SIM.gyr[:n].copy(), SIM.acc[:n].copy()
    g[100], g[150] = [1001.0, 0.0, 0.0], [999.0, 0.0, 0.0]
    a[120] = [0.0, 0.0, 1e6 * G]
    s = StreamAdapter()
    res = s.process(100.0 + SIM.t[:n], g, a)
    assert s.counters["gyr_invalid"] == 1 and s.counters["acc_invalid"] == 1
    assert np.all(np.isfinite(res.quat))
    r = mkf_ros.estimate(g, a, dt=0.01)
    assert r.counters["gyr_invalid"] == 1 and r.counters["acc_invalid"] == 1


# --- items 3 and 4: covariances at the ends of the parameter ranges -----------------------------

def psd_violation(P: np.ndarray) -> float:
    """How far a covariance is from symmetric PSD, relative to its size (0 = PSD)."""
    if not np.all(np.isfinite(P)):
        return np.inf
    asym = float(np.abs(P - P.T).max())
    scale = max(float(np.abs(np.diag(P)).max()), 1e-300)
    return max(asym / scale, -min_eig(0.5 * (P + P.T)) / scale)


@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
def test_node_never_publishes_nan_with_a_very_precise_rest_detector(algorithm: str) -> None:
    """Valid range ends must give valid output: these settings made the bias variance negative at
    the first rest update, and its square root NaN in every angular_velocity_covariance."""
    from mkf_ros.stream.adapter import StreamAdapter

    sim = simulate("static", duration=5, rate=100, seed=1)
    s = StreamAdapter(algorithm=algorithm, gyro_noise=1e-6, rate_process_noise=1e9,
                      rest_rate_stddev=1e-6, angular_velocity_source="bias_corrected")
    res = s.process(100.0 + sim.t, sim.gyr, sim.acc)
    assert s.counters["rest_updates"] > 0
    assert len(res.index) == sim.t.size
    for name in ("quat", "cov", "angular_velocity", "angular_velocity_cov_add",
                 "omega", "bias", "bias_std"):
        assert np.all(np.isfinite(getattr(res, name))), name
    assert np.all(np.diagonal(res.angular_velocity_cov_add, axis1=1, axis2=2) >= 0)


RANGE_ENDS = {
    # parameter range ends that once failed, each with the sensors and the data it failed on
    "precise_rest": (dict(gyro_noise=1e-6, rate_process_noise=1e9, rest_rate_stddev=1e-6),
                     "static", 0.01, False),
    "paper_mag": (dict(init_mode="paper", mag_reference=[1e6, -1e6, -1e6], mag_noise=1e-6,
                       mag_disturbance=0.0), "static", 0.01, True),
    "long_steps": (dict(rate_process_noise=1e9, max_dt=3600.0), "static", 10.0, False),
    "precise_acc": (dict(acc_noise=1e-6, acc_disturbance=0.0, rate_process_noise=1e9),
                    "slow_rotation", 0.01, False),
}


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("case", sorted(RANGE_ENDS))
def test_covariance_stays_psd_at_the_range_ends(algorithm: str, case: str) -> None:
    kw, scenario, dt, use_mag = RANGE_ENDS[case]
    sim = simulate(scenario, duration=10, rate=100, seed=2)
    f = AttitudeFilter(algorithm=algorithm, use_mag=use_mag, **kw)
    n = 40 if dt > 1 else sim.t.size
    worst = 0.0
    for k in range(n):
        f.step(dt if k else 0.0, sim.gyr[k], sim.acc[k], sim.mag[k] if use_mag else None)
        worst = max(worst, psd_violation(f.state_covariance))
        assert np.all(np.isfinite(f.quaternion)) and np.all(np.isfinite(f.bias)), k
        assert psd_violation(f.covariance) <= 1e-9, k
    assert worst <= 1e-9


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("use_mag", [False, True])
def test_no_attitude_variance_beyond_unknown_at_the_extreme_rate_noise(algorithm: str,
                                                                      use_mag: bool) -> None:
    """An angle uniform over ±180° has variance π²/3; a Gaussian beyond it about any axis means
    nothing. At the largest accepted rate_process_noise the published covariance reached
    5e15 rad² (MUKF) and 1e8 rad² (Euler UKF). Now every published eigenvalue is ≤ π²/3 at
    every sample (and the MKFs' own attitude block too, within the 1e-6 by which it may exceed
    the cap before it is scaled back)."""
    sim = simulate("slow_rotation", duration=3, rate=100, seed=3)
    f = AttitudeFilter(algorithm=algorithm, use_mag=use_mag,
                       rate_process_noise=BY_NAME["rate_process_noise"].range[1])
    cap = np.pi ** 2 / 3 * (1 + 1e-9)
    for k in range(sim.t.size):
        f.step(0.01 if k else 0.0, sim.gyr[k], sim.acc[k], sim.mag[k] if use_mag else None)
        assert np.linalg.eigvalsh(f.covariance).max() <= cap, k
        assert psd_violation(f.covariance) <= 1e-9, k
        if algorithm in ("mekf", "mukf"):
            assert np.linalg.eigvalsh(f.state_covariance[:3, :3]).max() <= cap * (1 + 1e-6), k


@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
@pytest.mark.parametrize("tiny", [2.182963053890949e-290, 5e-324])
def test_any_non_zero_mag_reference_is_a_direction(algorithm: str, tiny: float) -> None:
    """The parameter check accepts any non-zero ``mag_reference`` as the field's direction.
    Found by the long property profile: ``[2.2e-290] * 3``, whose squared length underflows to
    0, was accepted with ``init_mode: paper`` and gave NaN at the first sample (the filter took
    it for "no reference"). It is the direction ``[1, 1, 1]``: the outputs equal those with
    that reference."""
    sim = simulate("slow_rotation", duration=2, rate=100, seed=3)
    outs = []
    for ref in ([tiny] * 3, [1.0, 1.0, 1.0]):
        f = AttitudeFilter(algorithm=algorithm, use_mag=True, init_mode="paper",
                           mag_reference=ref)
        q = []
        for k in range(sim.t.size):
            f.step(0.01 if k else 0.0, sim.gyr[k], sim.acc[k], sim.mag[k])
            q.append(f.quaternion)
        outs.append(np.array(q))
    assert np.isfinite(outs[0]).all()
    np.testing.assert_array_equal(outs[0], outs[1])
