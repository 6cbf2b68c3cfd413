"""Real-sensor extensions (issue 6) on synthetic data with known truth: gyro bias, accelerometer
and magnetometer rejection, heading-only magnetometer, hard/soft-iron calibration, recovery.
Each test also shows that the feature matters (the same data without it does clearly worse)."""

from __future__ import annotations

import numpy as np
import pytest

import mkf_ros
from mkf_ros.metrics import orientation_errors, rmse_deg
from mkf_ros.sim import simulate

ALGOS = ["mekf", "mukf"]
NO_ROBUSTNESS = dict(acc_gate=0.0, acc_norm_tolerance=1000.0, mag_gate=0.0,
                     mag_norm_tolerance=1000.0, mag_dip_tolerance=3.1416, mag_mode="vector",
                     rest_detection=False)


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("use_mag", [True, False])
def test_bias_converges_at_rest(algorithm: str, use_mag: bool) -> None:
    """Issue 6 target: a 0.02 rad/s constant bias, estimated within 0.002 rad/s after 30 s
    still (all axes: rest detection observes the rate directly; with it off, only the
    horizontal axes are observable without a magnetometer, and σ says so for the vertical)."""
    sim = simulate("static", duration=30, rate=100, seed=1, gyro_bias=(0.02, -0.02, 0.02),
                   q0=np.array([1.0, 0, 0, 0]))
    mag = sim.mag if use_mag else None
    r = mkf_ros.estimate(sim.gyr, sim.acc, mag, dt=0.01, algorithm=algorithm)
    assert np.all(np.abs(r.bias[-1] - sim.bias[-1]) < 0.002), r.bias[-1]
    assert np.all(r.bias_std[-1] < 0.002)
    assert r.counters["rest_updates"] > 2000
    if not use_mag:
        r = mkf_ros.estimate(sim.gyr, sim.acc, dt=0.01, algorithm=algorithm,
                             rest_detection=False)
        assert np.all(np.abs(r.bias[-1, :2] - sim.bias[-1, :2]) < 0.002)  # level: x, y horizontal
        assert r.bias_std[-1, 2] > 0.01  # the vertical axis stays (honestly) unknown


@pytest.mark.parametrize("algorithm", ALGOS)
def test_bias_tracks_while_moving(algorithm: str) -> None:
    sim = simulate("gyro_bias", duration=60, rate=100, seed=4)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    assert np.all(np.abs(r.bias[-1] - sim.bias[-1]) < 0.003)
    err = orientation_errors(r.quat, sim.quat)
    off = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                           estimate_gyro_bias=False)
    err_off = orientation_errors(off.quat, sim.quat)
    assert rmse_deg(err["total"][500:]) < 0.5 * rmse_deg(err_off["total"][500:])


@pytest.mark.parametrize("algorithm", ALGOS)
def test_translational_acceleration_does_not_tilt(algorithm: str) -> None:
    """3 g bursts in random directions (issue 6 target): inclination RMSE ≤ 0.5°, never
    above 3°; the accelerometer magnitude gate catches the bursts (counted)."""
    sim = simulate("accel_bursts", duration=60, rate=100, seed=3)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    incl = orientation_errors(r.quat, sim.quat)["inclination"][100:]
    assert rmse_deg(incl) < 0.5 and np.degrees(incl.max()) < 3.0
    assert r.counters["acc_rejected_norm"] > 100
    off = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                           **NO_ROBUSTNESS, acc_disturbance=0.3)
    assert rmse_deg(orientation_errors(off.quat, sim.quat)["inclination"][100:]) > rmse_deg(incl)


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("mag_mode,max_deg", [("vector", 15.0), ("heading", 15.0)])
def test_magnetic_disturbance_is_rejected(algorithm: str, mag_mode: str, max_deg: float) -> None:
    """A 25 µT horizontal field change for 12 s (it turns the measured north by up to 45°, and
    its magnitude and dip stay near their limits): heading RMSE ≤ 3° and max ≤ 15° (the peak
    comes at its falling edge) through it and 5 s after (issue 6 target); > 20°
    without the rejection; inclination untouched."""
    sim = simulate("mag_disturbance", duration=60, rate=100, seed=2)
    a, b = sim.meta["intervals"]["mag_disturbed"][0]
    win = (sim.t >= a) & (sim.t <= b + 5.0)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                         mag_mode=mag_mode)
    err = orientation_errors(r.quat, sim.quat)
    assert rmse_deg(err["heading"][win]) < 3.0 and np.degrees(err["heading"][win].max()) < max_deg
    assert rmse_deg(err["inclination"][100:]) < 0.5
    assert r.counters["mag_rejected_norm"] > 500
    off = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                           **NO_ROBUSTNESS)
    assert rmse_deg(orientation_errors(off.quat, sim.quat)["heading"][win]) > 20.0


@pytest.mark.parametrize("algorithm", ALGOS)
def test_heading_mode_does_not_pull_inclination(algorithm: str) -> None:
    """A wrong magnetic reference (dip off by 20°) cannot tilt the estimate in heading mode;
    the paper's vector model is dragged by it."""
    sim = simulate("slow_rotation", duration=40, rate=100, seed=6)
    dip = np.radians(60 - 20)
    wrong = [0.0, np.cos(dip), -np.sin(dip)]
    kw = dict(timestamps=sim.t, algorithm=algorithm, mag_reference=wrong,
              mag_dip_tolerance=3.1416)
    r6 = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    rh = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, mag_mode="heading", **kw)
    rv = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, mag_mode="vector", mag_gate=0.0, **kw)
    i6, ih, iv = (rmse_deg(orientation_errors(r.quat, sim.quat)["inclination"][100:])
                  for r in (r6, rh, rv))
    assert ih < 1.2 * i6 + 0.02
    assert iv > 3 * ih


@pytest.mark.parametrize("algorithm", ALGOS)
def test_hard_and_soft_iron_calibration(algorithm: str) -> None:
    sim = simulate("slow_rotation", duration=40, rate=100, seed=8)
    S = np.array([[1.1, 0.05, 0.0], [0.05, 0.9, 0.02], [0.0, 0.02, 1.05]])  # soft iron
    h = np.array([30e-6, -20e-6, 10e-6])  # hard iron
    raw = np.linalg.solve(S, sim.mag.T).T + h  # what a distorted sensor reports
    cal = dict(mag_bias_x=h[0], mag_bias_y=h[1], mag_bias_z=h[2], mag_soft_iron=list(S.ravel()))
    good = mkf_ros.estimate(sim.gyr, sim.acc, raw, timestamps=sim.t, algorithm=algorithm, **cal)
    ref = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    bad = mkf_ros.estimate(sim.gyr, sim.acc, raw, timestamps=sim.t, algorithm=algorithm)
    e_good, e_ref, e_bad = (rmse_deg(orientation_errors(r.quat, sim.quat)["heading"][100:])
                            for r in (good, ref, bad))
    assert abs(e_good - e_ref) < 1e-6  # calibration undoes the distortion exactly
    assert e_bad > 5 * e_good


@pytest.mark.parametrize("algorithm", ALGOS)
def test_recovers_from_a_bad_start(algorithm: str) -> None:
    """Initialised during a 0.5 g sideways push (tilt 27° wrong): the gate then rejects the
    good samples, and recovery after acc_recovery_time brings the estimate back."""
    sim = simulate("static", duration=10, rate=100, seed=9, q0=np.array([1.0, 0, 0, 0]))
    acc = sim.acc.copy()
    acc[0] += np.array([0.5 * 9.81, 0.0, 0.0])
    r = mkf_ros.estimate(sim.gyr, acc, timestamps=sim.t, algorithm=algorithm)
    incl = np.degrees(orientation_errors(r.quat, sim.quat)["inclination"])
    assert incl[0] > 20.0
    assert incl[300:].max() < 1.0


def test_rejections_are_counted_by_reason() -> None:
    sim = simulate("accel_bursts", duration=20, rate=100, seed=3)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t)
    for name in ("acc_rejected_norm", "acc_rejected_chi2", "mag_rejected_norm",
                 "mag_rejected_dip", "mag_rejected_chi2", "rest_updates"):
        assert name in r.counters
    assert r.counters["acc_rejected_norm"] > 0
