"""Real-sensor extensions (docs/math.md §9) on synthetic data with known truth: gyro bias,
accelerometer and magnetometer rejection, heading-only magnetometer, hard/soft-iron calibration,
recovery. Each test also shows that the feature matters (the same data without it does clearly
worse)."""

from __future__ import annotations

import numpy as np
import pytest

import mkf_ros
from mkf_ros.evaluation.metrics import orientation_errors, rmse_deg, roll_pitch_yaw
from mkf_ros.sim import simulate

ALGOS = ["mekf", "mukf"]
NO_ROBUSTNESS = dict(mag_norm_tolerance=1000.0, mag_mode="vector",
                     rest_detection=False, acc_time_constant=0.0, acc_disturbance_time=0.0,
                     mag_disturbance_time=0.0, mag_consistency_tolerance=1000.0,
                     gyro_scale_error=0.0)


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("use_mag", [True, False])
def test_bias_converges_at_rest(algorithm: str, use_mag: bool) -> None:
    """Target: a 0.02 rad/s constant bias, estimated within 0.002 rad/s after 30 s
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
    """3 g pushes in random directions, 0.3–1 s each (one period of a sine: the body moves and
    stops): inclination RMSE ≤ 1.5°, never above 5°, the raw samples more than half a g off
    gravity counted as left out of the blend. (0.5° was the first target; since the
    accelerometer is low-passed in an almost inertial frame, which averages out shaking but
    carries a push for its memory: measured 1.2° here, where the paper's raw accelerometer
    without any of the robustness gets 1.0°; on sustained shaking it is 0.6° against more
    than 4× that, :func:`test_sustained_shaking_does_not_tilt`, and on BROAD's real shaking
    0.5° against 26–60°.)"""
    sim = simulate("accel_bursts", duration=60, rate=100, seed=3)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    incl = orientation_errors(r.quat, sim.quat)["inclination"][100:]
    assert rmse_deg(incl) < 1.5 and np.degrees(incl.max()) < 5.0
    assert r.counters["acc_rejected_norm"] > 100


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("mag_mode,max_deg", [("vector", 15.0), ("heading", 15.0)])
def test_magnetic_disturbance_is_rejected(algorithm: str, mag_mode: str, max_deg: float) -> None:
    """A 25 µT horizontal field change for 12 s (it turns the measured north by up to 45°, and
    its magnitude and dip stay near their limits): heading RMSE ≤ 3° and max ≤ 15° (the peak
    comes at its falling edge) through it and 5 s after (the target for a magnet on the body); > 10°
    without the magnetometer's tests (magnitude, consistency, heading mode; 16° with only the
    fixed χ² gate left); inclination untouched."""
    sim = simulate("mag_disturbance", duration=60, rate=100, seed=2)
    a, b = sim.meta["intervals"]["mag_disturbed"][0]
    win = (sim.t >= a) & (sim.t <= b + 5.0)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                         mag_mode=mag_mode)
    err = orientation_errors(r.quat, sim.quat)
    assert rmse_deg(err["heading"][win]) < 3.0 and np.degrees(err["heading"][win].max()) < max_deg
    # (vector mode lets the field tilt the estimate: the disturbance's edges, fused before the
    # tests see them, leave 0.59° (MEKF); heading mode, the default, 0.5° at most)
    assert rmse_deg(err["inclination"][100:]) < (0.5 if mag_mode == "heading" else 0.7)
    assert r.counters["mag_rejected_norm"] > 500
    off = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                           **NO_ROBUSTNESS)
    assert rmse_deg(orientation_errors(off.quat, sim.quat)["heading"][win]) > 10.0


@pytest.mark.parametrize("algorithm", ALGOS)
def test_heading_mode_does_not_pull_inclination(algorithm: str) -> None:
    """A wrong magnetic reference (dip off by 20°) cannot tilt the estimate in heading mode;
    the paper's vector model is dragged by it."""
    sim = simulate("slow_rotation", duration=40, rate=100, seed=6)
    dip = np.radians(60 - 20)
    wrong = [0.0, np.cos(dip), -np.sin(dip)]
    kw = dict(timestamps=sim.t, algorithm=algorithm, mag_reference=wrong)
    r6 = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    rh = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, mag_mode="heading", **kw)
    rv = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, mag_mode="vector", **kw)
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
    good samples, and recovery after ``state.ACC_RECOVERY_TIME`` brings the estimate back."""
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
                 "mag_rejected_chi2", "rest_updates"):
        assert name in r.counters
    assert r.counters["acc_rejected_norm"] > 0


# ---------------------------------------------------------------- real-world motion


@pytest.mark.parametrize("algorithm", ALGOS)
def test_sustained_shaking_does_not_tilt(algorithm: str) -> None:
    """Two 15 s stretches of shaking at up to 10 g with rocking up to 6 rad/s (BROAD's fast
    translation): without a magnetometer the inclination stays within 1.5° RMS and 5° at
    worst (0.62° / 0.63° RMS). (The raw samples alone, ``acc_time_constant = 0``, were more
    than 4× worse here while their variance missed the recent excess power; with it they hold
    this simulation too, 0.58° RMS: test_raw_accelerometer_alone_survives_shaking. On BROAD's
    real shaking the low-pass still matters: 0.71° against 4.97°, docs/real_data.md.)"""
    sim = simulate("shaking", duration=60, rate=100, seed=3)
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    incl = orientation_errors(r.quat, sim.quat)["inclination"][100:]
    assert rmse_deg(incl) < 1.5 and np.degrees(incl.max()) < 5.0


@pytest.mark.parametrize("algorithm", ALGOS)
def test_vibration_does_not_tilt(algorithm: str) -> None:
    """An engine-like linear (3 m/s²) and angular (0.3 rad/s) vibration at 23–42 Hz, sampled
    at 100 Hz: inclination within 1° RMS without a magnetometer."""
    sim = simulate("vibration", duration=60, rate=100, seed=3)
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    assert rmse_deg(orientation_errors(r.quat, sim.quat)["inclination"][100:]) < 1.0


def _unexplained_steps(q: np.ndarray, gyr: np.ndarray, dt: float) -> np.ndarray:
    """Per sample, how much the published orientation turned beyond what the gyro reading
    explains (rad): the angle between consecutive outputs minus |ω| Δt."""
    d = np.abs(np.einsum("ni,ni->n", q[1:], q[:-1]))
    return 2.0 * np.arccos(np.clip(d, -1.0, 1.0)) - np.linalg.norm(gyr[1:], axis=1) * dt


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("vib_acc", [0.0, 0.3])
def test_slow_turn_never_jumps(algorithm: str, vib_acc: float) -> None:
    """A robot at rest for 5 s, then turning about the vertical at 0.04 rad/s (below what a
    gyro bias may be). ros-bags finding: rest was declared during the turn and the zero-rate
    update turned the yaw by 84° in one sample while its variance dropped. Now no output ever
    turns more than 0.05° beyond what the gyro explains, and the yaw variance grows by the
    rate it should while nothing observes yaw. A rolling robot's vibration (0.3 m/s²) is not
    taken for rest: rest updates only in the first 5 s. (A perfectly smooth turn cannot be
    told from a gyro bias by an IMU alone; it may be taken for rest, which then costs yaw
    rate, never a jump.)"""
    rate = 100.0
    sim = simulate("slow_turn", duration=60, rate=rate, seed=2, vib_acc=vib_acc)
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    jumps = _unexplained_steps(r.quat, sim.gyr, 1 / rate)[int(rate):]  # after convergence
    assert np.degrees(jumps.max()) < 0.05
    yaw_var = r.cov[:, 2, 2]
    assert np.all(np.diff(yaw_var[600:]) > -1e-9)  # nothing observes yaw: it never shrinks
    if vib_acc > 0:
        assert 0 < r.counters["rest_updates"] <= 5 * rate


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("turn_rate", [0.013, 0.04])
def test_a_smooth_slow_turn_after_rest_is_not_taken_for_rest(algorithm: str,
                                                            turn_rate: float) -> None:
    """At rest for 5 s (the bias learned), then a perfectly smooth turn about the vertical at
    0.013 or 0.04 rad/s for 25 s. ros-bags finding (a PhidgetSpatial): such a turn was taken
    for rest and its rate for a bias (vertical bias −0.0002 → +0.0076 rad/s), and the heading
    stopped turning. A bias does not change faster than its random walk: now no zero-rate
    update during the turn, the vertical bias stays within 0.001 rad/s of the truth (0), and
    the heading follows the turn (within 1°)."""
    rate = 100.0
    sim = simulate("slow_turn", duration=30, rate=rate, seed=2, turn_rate=turn_rate)
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    assert 0 < r.counters["rest_updates"] <= 5.1 * rate
    assert np.all(np.abs(r.bias[int(5 * rate):, 2]) < 0.001)
    # 6D: the heading is the start-up heading; the turn is the change of yaw since the start
    yaw, yaw_true = roll_pitch_yaw(r.quat)[:, 2], roll_pitch_yaw(sim.quat)[:, 2]
    d = (yaw - yaw[0]) - (yaw_true - yaw_true[0])
    assert np.degrees(np.abs(np.angle(np.exp(1j * d)))).max() < 1.0


@pytest.mark.parametrize("algorithm", ALGOS)
def test_the_start_of_a_turn_does_not_move_the_bias(algorithm: str) -> None:
    """At rest for 1.5 s (0.5 s of zero-rate updates: the bias not yet sharp), then a turn at
    0.1 rad/s: the rest test's low-passes see it only after some samples; the zero-rate
    update's own χ² gate refuses those (without it the vertical bias went to 0.0085 rad/s, the
    phidgets bag's −0.0073 at the start of its turn). The vertical bias stays within 0.001."""
    sim = simulate("slow_turn", duration=8, rate=100, seed=2, turn_rate=0.1, rest=1.5)
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    assert r.counters["rest_updates"] > 0
    assert np.abs(r.bias[150:, 2]).max() < 0.001


@pytest.mark.parametrize("algorithm", ALGOS)
def test_a_turn_on_bias_beyond_the_prior_is_taken_for_a_bias_at_rest(algorithm: str) -> None:
    """A still sensor whose gyro reads 0.06 / −0.05 / 0.06 rad/s (a cheap IMU's turn-on bias,
    3× the Kalman prior ``gyro_bias_stddev``): rest is detected from the first second
    (``state.REST_BIAS_RANGE``: the rest test takes it for a bias, the first rest raises the
    bias variance so that the zero-rate gate does too) and the bias is learned. Measured
    against the prior alone (no range): the first rest 2.2 s later (683 updates instead of
    900); with the prior 0.01 and no range, on the robot_localization and SparkFun Razor bags,
    none at all (`./run bench ros_bags`)."""
    bias = (0.06, -0.05, 0.06)
    sim = simulate("static", duration=10, rate=100, seed=1, gyro_bias=bias)
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    assert r.counters["rest_updates"] >= 890
    assert np.abs(r.bias[-1] - np.array(bias)).max() < 1e-3


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("use_mag", [True, False])
def test_large_gyro_bias_is_learned_in_motion(algorithm: str, use_mag: bool) -> None:
    """A 0.1 rad/s bias on every axis (learned at rest and in motion, 6D and 9D), on
    slow motion with large tilts: within 0.01 rad/s after 60 s, and the attitude within 2°."""
    sim = simulate("gyro_bias", duration=60, rate=100, seed=4, bias=(0.1, -0.1, 0.1))
    mag = sim.mag if use_mag else None
    r = mkf_ros.estimate(sim.gyr, sim.acc, mag, timestamps=sim.t, algorithm=algorithm)
    assert np.all(np.abs(r.bias[-1] - sim.bias[-1]) < 0.01), r.bias[-1]
    kind = "total" if use_mag else "inclination"
    assert rmse_deg(orientation_errors(r.quat, sim.quat)[kind][3000:]) < 2.0


@pytest.mark.parametrize("algorithm", ALGOS)
def test_a_field_that_changes_for_good_becomes_the_reference(algorithm: str) -> None:
    """Indoors the undisturbed field differs from room to room (tyrex: 10–25 %): at 15 s the
    field changes for good from 50 µT at dip 60° to 40 µT at dip 70°, north unchanged, on slow
    motion. The learned reference used to refuse every later sample (magnitude gate: 4305 of
    the 4500) and the heading coasted on the gyro for the rest of the recording. Now the field,
    consistent while the body turns, becomes the reference within seconds: few refusals, the
    heading right (RMSE < 0.5°) and its variance as with the magnetometer fused."""
    sim = simulate("mag_field_change", duration=60, rate=100, seed=3, gyro_bias=(0, 0, 0.01))
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    refused = r.counters["mag_rejected_norm"]
    assert refused < 600
    head = orientation_errors(r.quat, sim.quat)["heading"]
    assert rmse_deg(head[3000:]) < 0.5
    off = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                           mag_new_time=0.0, mag_new_first_time=0.0)
    assert off.counters["mag_rejected_norm"] > 4000  # what happened without it
    # the heading variance as with the field fused, well below the coasting one's (measured
    # 0.0041 against 0.0149 rad² at the end)
    assert r.cov[-1, 2, 2] < 0.5 * off.cov[-1, 2, 2]


@pytest.mark.parametrize("algorithm", ALGOS)
def test_attached_magnet_does_not_turn_the_heading(algorithm: str) -> None:
    """A magnet attached to the body for the middle 40 % (a 180 µT hard-iron offset, four times
    the Earth's field): the field the body carries along disagrees with the field low-passed
    in the almost inertial frame, so it is not fused; the heading coasts on the gyro (within
    5° RMS through it, never 180° off). Without that consistency test it is dragged tens of
    degrees."""
    sim = simulate("mag_attached", duration=60, rate=100, seed=2)
    a, b = sim.meta["intervals"]["mag_disturbed"][0]
    win = (sim.t >= a) & (sim.t <= b + 5.0)
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    head = orientation_errors(r.quat, sim.quat)["heading"]
    assert rmse_deg(head[win]) < 5.0 and np.degrees(head.max()) < 20.0
    assert r.counters["mag_rejected_inconsistent"] + r.counters["mag_rejected_norm"] > 1000
    off = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm,
                           mag_consistency_tolerance=1000.0, mag_norm_tolerance=1000.0)
    assert rmse_deg(orientation_errors(off.quat, sim.quat)["heading"][win]) > 3 * rmse_deg(
        head[win])


@pytest.mark.parametrize("algorithm", ALGOS)
def test_a_disturbance_that_builds_up_over_seconds_is_refused(algorithm: str) -> None:
    """The Earth's field turned 70° about north over 4 s (faster than the 1 s consistency test
    sees, its magnitude kept, as a phone's system calibration may), held 15 s and turned back:
    the field's steadiness against its 30 s low-pass refuses it, so the heading stays within
    8° RMS of the truth from the disturbance on (measured 4.6°; followed, it is 22° RMS and
    33° at worst)."""
    from mkf_ros.core.quaternion import rotmat_np
    sim = simulate("slow_rotation", duration=80, rate=100, seed=5)
    ramp = np.clip(np.minimum((sim.t - 40.0) / 4.0, (63.0 - sim.t) / 4.0), 0.0, 1.0)
    th = np.radians(70.0) * ramp
    Rs = np.array([rotmat_np(q) for q in sim.quat])
    w = np.einsum("nij,nj->ni", Rs, sim.mag)  # the field in the world frame (ENU)
    c, s = np.cos(th), np.sin(th)
    w = np.stack([c * w[:, 0] + s * w[:, 2], w[:, 1], -s * w[:, 0] + c * w[:, 2]], axis=1)
    mag = np.einsum("nji,nj->ni", Rs, w)
    r = mkf_ros.estimate(sim.gyr, sim.acc, mag, timestamps=sim.t, algorithm=algorithm)
    head = orientation_errors(r.quat, sim.quat)["heading"]
    assert rmse_deg(head[sim.t >= 40.0]) < 8.0
    assert r.counters["mag_rejected_inconsistent"] > 1500


@pytest.mark.parametrize("algorithm", ALGOS)
def test_heading_is_unknown_until_the_magnetometer(algorithm: str) -> None:
    """With use_mag the first output comes before any magnetometer sample (ros-bags finding:
    arbitrary yaw published with a variance of 1e-6 rad²): its yaw variance is that of an
    unknown angle, π²/3, until the first magnetometer sample fixes the heading."""
    sim = simulate("slow_rotation", duration=5, rate=100, seed=1)
    mag = sim.mag.copy()
    mag[:50] = np.nan  # the magnetometer starts half a second late
    r = mkf_ros.estimate(sim.gyr, sim.acc, mag, timestamps=sim.t, algorithm=algorithm)
    world_yaw_var = r.cov[:50, 2, 2]
    np.testing.assert_allclose(world_yaw_var, np.pi ** 2 / 3, rtol=1e-5)
    assert np.all(r.cov[60:, 2, 2] < 0.05)
    assert rmse_deg(orientation_errors(r.quat, sim.quat)["total"][60:]) < 2.0


def test_mukf_failed_step_still_predicts() -> None:
    """A MUKF step whose factorisation fails is counted and still carries the estimate over
    its Δt (it used to return before the prediction: that time was lost while P carried its
    noise): a body turning at 1 rad/s about z turns by 0.01 rad in the failed 10 ms step."""
    from mkf_ros.core.filter import AttitudeFilter, record
    from mkf_ros.core.quaternion import qmul

    f = AttitudeFilter(algorithm="mukf", rest_detection=False)
    w = np.array([0.0, 0.0, 1.0])
    up = np.array([0.0, 0.0, 9.80665])
    f.step(0.0, w, up)
    for _ in range(100):
        f.step(0.01, w, up)
    q0 = f.quaternion
    record(f._st).P[0, 0] = -1.0  # not positive definite: the sigma points cannot be drawn
    f.step(0.01, w, up)
    assert f.counter_dict()["update_failed"] == 1
    d = qmul(f.quaternion, q0 * np.array([1.0, -1.0, -1.0, -1.0]))
    assert 2 * np.arcsin(d[3]) == pytest.approx(0.01, abs=1e-3)
    assert np.all(np.isfinite(f.covariance))


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize(("rate", "counter"), [(500.0, "gyr_rejected_chi2"),
                                               (1e6, "gyr_invalid")])
def test_one_huge_gyro_sample_is_an_outlier(algorithm: str, rate: float, counter: str) -> None:
    """One corrupted gyro sample (1e6 rad/s used to leave the bias at 5.19 rad/s for good):
    within the plausibility limit (1000 rad/s) the gyro's innovation gate skips it, beyond it
    the sample is invalid (plausibility limit); either way the bias and the attitude do not
    notice."""
    sim = simulate("static", duration=10, rate=100, seed=1)
    gyr = sim.gyr.copy()
    gyr[500] = (rate, 0.0, 0.0)
    r = mkf_ros.estimate(gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    clean = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, algorithm=algorithm)
    assert r.counters[counter] == 1
    assert np.all(np.abs(r.bias[-1] - clean.bias[-1]) < 1e-3)
    assert np.degrees(orientation_errors(r.quat, clean.quat)["total"].max()) < 0.1


@pytest.mark.parametrize("algorithm", ALGOS)
def test_an_upset_is_recovered(algorithm: str) -> None:
    """The estimate knocked 60° off (as by a gyro glitch the gate could not tell from motion):
    the gates must not lock the truth out (without the recovery of docs/math.md §9.3 the MUKF
    stayed 63° off after 30 s at rest). Within 10 s at rest the inclination is back within 2°."""
    from mkf_ros.core.filter import AttitudeFilter, record
    from mkf_ros.core.quaternion import q_from_rotvec, qmul

    sim = simulate("static", duration=20, rate=100, seed=5)
    f = AttitudeFilter(algorithm=algorithm)
    incl = []
    for k in range(sim.t.size):
        f.step(0.01 if k else 0.0, sim.gyr[k], sim.acc[k])
        if k == 500:
            f.set_params(chart=f.params.chart)  # MUKF: the mean onto the chart centre
            q = record(f._st).q_c
            q[:] = qmul(q_from_rotvec(np.radians([60.0, 0.0, 0.0])), q.copy())
        incl.append(orientation_errors(f.quaternion[None], sim.quat[k][None])["inclination"][0])
    incl = np.degrees(incl)
    assert incl[501] > 50.0
    assert incl[1500:].max() < 2.0


@pytest.mark.parametrize("algorithm,seed", [(a, s) for a in ALGOS for s in range(4)])
def test_running_does_not_run_away_with_the_bias(algorithm: str, seed: int) -> None:
    """Two minutes of running with the sensor in a pocket (the thigh's swing, its centripetal
    acceleration along fixed body axes, the steps' bounce: `running`), no magnetometer: the
    gyro bias stays within 0.02 rad/s of the truth and the inclination within 6° at every
    sample after the first 10 s. Before the low-pass's dependence on the bias was in its
    measurement model (docs/math.md §9.1) the estimate chased its own bias through the
    low-pass's memory: seed 1 reached 13.8° with the bias 0.125 rad/s off. The partial update
    of the bias matters too: with the full gain (``acc_bias_excess = 0``) seed 1's bias is
    0.022 rad/s off (0.057 with the wider prior of before, ``gyro_bias_stddev = 0.05``, under
    which the MUKF's seed 1 reached 15.6° with its bias 0.029 rad/s off; now 3.5° / 0.006)."""
    sim = simulate("running", duration=120.0, rate=100.0, seed=seed,
                   gyro_bias=(0.005, -0.004, 0.003))
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm)
    incl = np.degrees(orientation_errors(r.quat, sim.quat)["inclination"][1000:])
    bias_err = np.abs(r.bias[1000:] - sim.bias[1000:]).max()
    assert incl.max() < 6.0 and bias_err < 0.02, (incl.max(), bias_err)
    if algorithm == "mekf" and seed == 1:
        full = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm,
                                acc_bias_excess=0.0)
        assert np.abs(full.bias[1000:] - sim.bias[1000:]).max() > 0.02


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("algorithm", ALGOS)
def test_raw_accelerometer_alone_survives_shaking(algorithm: str, seed: int) -> None:
    """``acc_time_constant = 0`` (the raw samples alone, no low-pass) through two minutes of
    hand shaking (`shaking`), no magnetometer: the raw view's variance still takes the recent
    excess power of the magnitude, and the bias's share of the gain with it (docs/math.md
    §9.3), so the inclination stays within 6° at every sample after the first 10 s and the
    bias within 0.01 rad/s. Without them (only this sample's own excess) the shaking's
    acceleration across gravity was fused as gravity and the bias learned from it at full
    gain: 22–146° of tilt, as on BROAD's fast translation trials (30° and 69°)."""
    sim = simulate("shaking", duration=120.0, rate=100.0, seed=seed,
                   gyro_bias=(0.005, -0.004, 0.003))
    r = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm,
                         acc_time_constant=0.0)
    incl = np.degrees(orientation_errors(r.quat, sim.quat)["inclination"][1000:])
    bias_err = np.abs(r.bias[1000:] - sim.bias[1000:]).max()
    assert incl.max() < 6.0 and bias_err < 0.01, (incl.max(), bias_err)


@pytest.mark.parametrize("algorithm", ALGOS)
def test_a_turn_at_speed_is_not_taken_for_a_tilt(algorithm: str) -> None:
    """Laps at 3 m/s (`laps`: half turns of 3 s, up to 0.64 g of centripetal acceleration
    across gravity for seconds), no magnetometer. Left to its defaults (a body that turns in
    place) the filter follows the centripetal acceleration: 5.3° of tilt at the turns' ends
    (3.4° RMS after the first 10 s). Told the speed (``acc_turn_speed = 3``: docs/math.md §9.3)
    the gyro carries the tilt through the turns: the RMS falls by at least two thirds and the
    worst sample stays below 1.5° (0.72° and 1.12°; 1.99° and 2.82° while the term was added
    to each view, not to their blend, with the sample's correlation time); and its published
    3σ tilt still covers the error."""
    sim = simulate("laps", duration=120.0, rate=100.0, seed=2, speed=3.0)
    runs = {v: mkf_ros.estimate(sim.gyr, sim.acc, timestamps=sim.t, algorithm=algorithm,
                                acc_turn_speed=v) for v in (0.0, 3.0)}
    incl = {v: np.degrees(orientation_errors(r.quat, sim.quat)["inclination"][1000:])
            for v, r in runs.items()}
    rms = {v: float(np.sqrt(np.mean(e * e))) for v, e in incl.items()}
    assert incl[0.0].max() > 4.5  # the turns do pull an estimate that ignores them
    assert rms[3.0] < rms[0.0] / 3.0, rms
    assert incl[3.0].max() < 1.5, incl[3.0].max()
    cov = runs[3.0].cov[1000:]  # the published tilt variance, world x and y
    sd = np.degrees(np.sqrt(cov[:, 0, 0] + cov[:, 1, 1]))
    assert np.mean(incl[3.0] <= 3.0 * sd) > 0.99
