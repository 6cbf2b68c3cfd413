"""The simulator: every scenario's truth is consistent with its sensors and its metadata."""

from __future__ import annotations

import numpy as np
import pytest

from mkf_ros.core.quaternion import q_exp_np as q_exp
from mkf_ros.core.quaternion import q_omega, qmul, qnormalize, rotmat_np
from mkf_ros.sim import MAG_FIELD_ENU, SCENARIOS, simulate
from mkf_ros.sim.motion import GRAVITY, integrate, pitch_deg

QUIET = dict(gyro_noise=0.0, acc_noise=0.0, mag_noise=0.0)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_is_consistent(name: str) -> None:
    s = simulate(name, duration=12.0, rate=100.0, seed=1, **QUIET)
    n = len(s)
    assert n > 1000
    for arr, cols in ((s.gyr, 3), (s.acc, 3), (s.mag, 3), (s.quat, 4), (s.omega, 3),
                      (s.bias, 3), (s.lin_acc, 3), (s.mag_dist, 3), (s.mag_body, 3)):
        assert arr.shape == (n, cols)
    assert s.t.shape == s.t_true.shape == (n,)
    assert np.all(np.diff(s.t_true) > 0)
    assert np.isfinite(s.quat).all() and np.allclose(np.linalg.norm(s.quat, axis=1), 1.0)
    assert np.isfinite(s.gyr).all() and np.isfinite(s.acc).all()
    # noiseless sensors are exactly the model of the module docstring
    R = rotmat_np(s.quat)
    np.testing.assert_allclose(s.gyr, s.omega + s.bias, atol=1e-12)
    acc = np.einsum("nji,nj->ni", R, np.array([0, 0, GRAVITY]) + s.lin_acc)
    np.testing.assert_allclose(s.acc, acc, atol=1e-9)
    ok = s.mag_valid
    mag = np.einsum("nji,nj->ni", R, MAG_FIELD_ENU + s.mag_dist) + s.mag_body
    np.testing.assert_allclose(s.mag[ok], mag[ok], atol=1e-15)
    assert s.meta["scenario"] == name and s.meta["description"]


@pytest.mark.parametrize("name", ["slow_rotation", "fast_rotation", "wiener", "sweep"])
def test_truth_attitude_follows_the_true_rate(name: str) -> None:
    """With one substep the rate is piecewise constant: q_{k+1} = q_k ⊗ q_ω(ω_{k+1}, dt)."""
    s = simulate(name, duration=5.0, rate=200.0, seed=2, substeps=1, **QUIET)
    dt = 1.0 / 200.0
    for k in range(0, len(s) - 1, 97):
        want = qnormalize(qmul(s.quat[k], q_omega(s.omega[k + 1], dt)))
        np.testing.assert_allclose(s.quat[k + 1], want, atol=1e-12)


def test_blocked_integration_matches_the_sequential_product() -> None:
    rng = np.random.default_rng(0)
    w = rng.normal(size=(3001, 3)) * 4.0
    q0 = qnormalize(rng.normal(size=4))
    got = integrate(q0, w, 1e-3)
    q = q0.copy()
    for k in range(w.shape[0]):
        q = qnormalize(qmul(q, q_exp(w[k] * 1e-3)))
        np.testing.assert_allclose(got[k + 1], q, atol=1e-12)
    assert got.shape == (3002, 4)


def test_seed_reproducible_and_keywords_kept() -> None:
    kw = dict(duration=3.0, rate=50.0, seed=7, gyro_noise=0.02, acc_noise=0.1, mag_noise=1e-6,
              gyro_bias=(0.01, 0.0, -0.01), mag_rate=10.0, q0=[1, 0, 0, 0])
    a, b = simulate("wiener", **kw), simulate("wiener", **kw)
    np.testing.assert_array_equal(a.gyr, b.gyr)
    np.testing.assert_array_equal(a.quat, b.quat)
    np.testing.assert_allclose(a.quat[0], [1, 0, 0, 0])
    assert a.mag_valid.sum() == 30  # 10 Hz over 3 s
    np.testing.assert_allclose(a.bias, np.tile([0.01, 0.0, -0.01], (len(a), 1)))
    c = simulate("wiener", **dict(kw, seed=8))
    assert not np.allclose(a.gyr, c.gyr)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="unknown scenario 'nope'"):
        simulate("nope")
    with pytest.raises(ValueError, match="has no parameter 'acc_peak'"):
        simulate("static", acc_peak=2.0)
    with pytest.raises(ValueError, match="positive"):
        simulate("static", duration=0.0)
    with pytest.raises(ValueError, match="mag_rate"):
        simulate("static", mag_rate=0.0)


def test_sweep_visits_both_gimbal_locks_and_turns_about_every_axis() -> None:
    s = simulate("sweep", duration=30.0, rate=100.0, **QUIET)
    p = pitch_deg(s.quat)
    assert p.max() > 89.9 and p.min() < -89.9
    np.testing.assert_allclose(p[0], 0.0, atol=1e-9)  # starts level
    assert len(s.meta["intervals"]["gimbal_lock"]) >= 2
    labels = [seg[2] for seg in s.meta["segments"]]
    assert {"roll 360", "pitch 360", "yaw 360"} <= set(labels)
    # each full turn about a body axis integrates to 360°
    for t0, t1, label in s.meta["segments"][:3]:
        sel = (s.t_true > t0) & (s.t_true <= t1)
        assert np.degrees(np.abs(s.omega[sel]).sum(axis=0).max() * 0.01) == pytest.approx(
            360.0, rel=0.02), label


def test_accel_bursts_reach_three_g_only_inside_their_intervals() -> None:
    s = simulate("accel_bursts", duration=30.0, rate=200.0, seed=4, **QUIET)
    inside = s.mask("acc_disturbed")
    a = np.linalg.norm(s.lin_acc, axis=1)
    assert a[~inside].max() < 1e-9
    assert 1.4 * GRAVITY < a.max() <= 3.0 * GRAVITY + 1e-9
    assert len(s.meta["intervals"]["acc_disturbed"]) >= 5
    for t0, t1 in s.meta["intervals"]["acc_disturbed"]:  # velocity returns to zero
        sel = (s.t_true >= t0) & (s.t_true <= t1)
        v = s.lin_acc[sel].sum(axis=0) / 200.0
        assert np.linalg.norm(v) < 0.05 * a[sel].max()


def test_mag_disturbance_changes_the_field_only_in_its_interval() -> None:
    s = simulate("mag_disturbance", duration=20.0, rate=100.0, **QUIET)
    (t0, t1), = s.meta["intervals"]["mag_disturbed"]
    assert (t0, t1) == pytest.approx((8.0, 12.0))
    norm = np.linalg.norm(s.mag, axis=1)
    out = ~s.mask("mag_disturbed")
    np.testing.assert_allclose(norm[out], 50e-6, rtol=1e-9)
    mid = np.abs(s.t_true - 10.0) < 1.0
    assert np.all(np.abs(norm[mid] - 50e-6) > 5e-6)


def test_dropouts_remove_samples_and_the_magnetometer() -> None:
    s = simulate("dropouts", duration=20.0, rate=100.0, mag_rate=50.0, **QUIET)
    gaps = np.diff(s.t)
    assert np.isclose(gaps.max(), 1.0 + 0.01, atol=0.011)  # the long gap
    assert (gaps > 0.05).sum() == 2  # 5-sample gap and the long one
    assert len(s) < 2001
    out = s.mask("mag_dropout")
    assert out.sum() > 150 and not s.mag_valid[out].any()
    assert s.mag_valid[~out].sum() > 0.45 * (~out).sum()


def test_jitter_and_time_jump_stamps() -> None:
    j = simulate("jitter", duration=5.0, rate=100.0, jitter=0.3)
    assert np.all(np.diff(j.t) > 0)
    dev = np.abs(j.t - j.t_true)
    assert dev.max() <= 0.3 / 100.0 + 1e-12 and dev.max() > 0.2 / 100.0
    s = simulate("time_jump", duration=10.0, rate=100.0, jump=2.0)
    d = np.diff(s.t)
    assert (d < 0).sum() == 1
    k = int(np.argmin(d)) + 1
    assert d[k - 1] == pytest.approx(-2.0 + 0.01)
    assert s.meta["time_jumps"] == [(k, pytest.approx(s.t[k - 1]), pytest.approx(s.t[k]))]
    np.testing.assert_allclose(np.diff(s.t_true), 0.01)


def test_bias_drift_and_constant_bias() -> None:
    d = simulate("bias_drift", duration=30.0, rate=100.0, **QUIET)
    assert np.abs(d.bias[-1] - d.bias[0]).max() > 0.005
    np.testing.assert_allclose(d.bias[0], 0.0, atol=1e-3)
    g = simulate("gyro_bias", duration=3.0, rate=100.0, gyro_bias=(0.001, 0, 0), **QUIET)
    np.testing.assert_allclose(g.bias[-1], [0.021, -0.03, 0.015])


def test_fast_rotation_and_vibration_are_fast() -> None:
    f = simulate("fast_rotation", duration=10.0, rate=400.0)
    assert np.linalg.norm(f.omega, axis=1).max() > 7.0
    v = simulate("vibration", duration=5.0, rate=400.0, **QUIET)
    spec = np.abs(np.fft.rfft(v.lin_acc[:, 0]))
    freqs = np.fft.rfftfreq(len(v), 1 / 400.0)
    assert freqs[np.argmax(spec[1:]) + 1] > 20.0


def test_laps_turn_half_a_circle_with_their_centripetal_acceleration() -> None:
    """`laps` (speed v, straight S, turn T): each turn is a half turn to the left about the
    vertical, the body stays level, and at the turn's peak rate 2π/T the accelerometer reads
    gravity plus v·2π/T along the body's y axis (the centripetal acceleration of a body moving
    along its x axis), and gravity alone on the straights."""
    v, s0, tt = 3.0, 4.0, 3.0
    sim = simulate("laps", duration=21.0, rate=200.0, seed=3, speed=v, straight=s0,
                   turn_time=tt, gyro_noise=0.0, acc_noise=0.0, gyro_bias=(0.0, 0.0, 0.0))
    up = np.einsum("nji,j->ni", rotmat_np(sim.quat), np.array([0.0, 0.0, 1.0]))
    assert np.abs(up - [0.0, 0.0, 1.0]).max() < 1e-9  # level throughout

    def heading(k: int) -> float:
        R = rotmat_np(sim.quat[k])
        return float(np.arctan2(R[1, 0], R[0, 0]))

    k0, k1 = np.searchsorted(sim.t, [s0 - 0.5, s0 + tt + 0.5])
    turned = (heading(k1) - heading(k0)) % (2 * np.pi)
    assert turned == pytest.approx(np.pi, abs=1e-3)
    peak = np.searchsorted(sim.t, s0 + tt / 2)
    assert sim.acc[peak] == pytest.approx([0.0, v * 2 * np.pi / tt, GRAVITY], abs=1e-6)
    straight = sim.t % (s0 + tt) < s0 - 0.01
    assert np.abs(sim.acc[straight] - [0.0, 0.0, GRAVITY]).max() < 1e-9
