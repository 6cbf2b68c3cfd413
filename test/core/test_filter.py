"""AttitudeFilter (mkf_ros.core.filter): output frames and covariance, runtime reconfiguration,
and the interface of compiled front ends."""

from __future__ import annotations

import numpy as np
import pytest
from rest_readings import reading

from mkf_ros.core.filter import AttitudeFilter, record
from mkf_ros.core.frames import FROM_ENU
from mkf_ros.core.quaternion import angle_between, q_from_rotvec, qmul
from mkf_ros.sim import simulate


def test_world_frames() -> None:
    """A level sensor whose x axis points north, at rest: identity in NED (x north, z down) for
    a body frame x forward/y right/z down; in ENU a level x-north body has yaw +90°; NWU yaw 0.
    (REP-103 / REP-145.)"""
    q_enu_flu = q_from_rotvec(np.array([0, 0, np.pi / 2]))  # body FLU, x north
    acc, mag = reading(q_enu_flu)
    out = {}
    for frame in ("enu", "ned", "nwu"):
        f = AttitudeFilter(use_mag=True, world_frame=frame)
        f.step(0.0, np.zeros(3), acc, mag)
        out[frame] = f.quaternion
    assert angle_between(out["enu"], q_enu_flu) < 1e-9
    assert angle_between(out["nwu"], np.array([1.0, 0, 0, 0])) < 1e-9
    # an FRD body (x north, y east, z down) is the identity in NED
    flu_to_frd = np.array([0.0, 1.0, 0.0, 0.0])  # 180° about x
    q_enu_frd = qmul(q_enu_flu, flu_to_frd)
    acc, mag = reading(q_enu_frd)
    f = AttitudeFilter(use_mag=True, world_frame="ned")
    f.step(0.0, np.zeros(3), acc, mag)
    assert angle_between(f.quaternion, np.array([1.0, 0, 0, 0])) < 1e-9
    for frame, qw in FROM_ENU.items():
        assert angle_between(out[frame], qmul(qw, out["enu"])) < 1e-9


@pytest.mark.parametrize("frame", ["enu", "ned", "nwu"])
def test_covariance_is_about_world_axes(frame: str) -> None:
    """Without a magnetometer only yaw — rotation about the world's vertical axis — is
    unobservable: its variance grows while the tilt variances stay small."""
    sim = simulate("slow_rotation", duration=60, rate=100, seed=2)
    f = AttitudeFilter(world_frame=frame)
    covs = []
    for k in range(sim.t.size):
        f.step(0.01 if k else 0.0, sim.gyr[k], sim.acc[k])
        covs.append(f.covariance)
    covs = np.array(covs)
    assert np.all(np.isfinite(covs))
    np.testing.assert_allclose(covs, np.transpose(covs, (0, 2, 1)), atol=1e-15)
    assert np.all(np.linalg.eigvalsh(covs[1:]) > 0)  # never all-zero, positive definite
    vert = 2  # ENU and NWU: z up; NED: z down — the vertical axis is z in all three
    tilt = covs[-1, 0, 0] + covs[-1, 1, 1]
    # the vertical bias is unobservable without a magnetometer: yaw's variance grows by about
    # (gyro_bias_stddev · t)², tilt's stays at the accelerometer's level (measured 17× at 60 s)
    assert covs[-1, vert, vert] > 10 * tilt
    assert covs[-1, vert, vert] > 3 * covs[100, vert, vert]  # grows: yaw drifts with the gyro


def test_covariance_before_initialisation_is_unknown_not_zero() -> None:
    f = AttitudeFilter()
    f.step(0.01, gyr=np.zeros(3))  # no accelerometer yet
    assert not f.initialized
    assert np.all(np.diag(f.covariance) >= np.pi**2 - 1e-9)
    assert f.counter_dict()["before_init"] == 1


@pytest.mark.parametrize("old,new", [({"algorithm": "mukf"}, {"algorithm": "mekf"}),
                                     ({"algorithm": "mekf"}, {"algorithm": "mukf"}),
                                     ({"chart": "rv"}, {"chart": "o"}),
                                     ({"algorithm": "mukf", "chart": "mrp"},
                                      {"chart": "rp", "chart_update": False})])
def test_runtime_switch_is_continuous(old: dict, new: dict) -> None:
    """Switching algorithm, chart or chart update mid-stream keeps the estimate and its
    covariance: no jump, no re-convergence."""
    sim = simulate("slow_rotation", duration=10, rate=100, seed=4)
    f = AttitudeFilter(use_mag=True, **old)
    g = AttitudeFilter(use_mag=True, **old)
    half = sim.t.size // 2
    for k in range(half):
        for h in (f, g):
            h.step(0.01 if k else 0.0, sim.gyr[k], sim.acc[k], sim.mag[k])
    q_before, c_before = f.quaternion, f.covariance
    f.set_params(**new)
    assert angle_between(f.quaternion, q_before) < 1e-12
    np.testing.assert_allclose(f.covariance, c_before, rtol=1e-9, atol=1e-15)
    for k in range(half, sim.t.size):
        f.step(0.01, sim.gyr[k], sim.acc[k], sim.mag[k])
        g.step(0.01, sim.gyr[k], sim.acc[k], sim.mag[k])
    # after the switch the new filter tracks as well as the unswitched one
    assert np.degrees(angle_between(f.quaternion, sim.quat[-1])) < 1.0
    assert np.degrees(angle_between(f.quaternion, g.quaternion)) < 0.5


def test_invalid_parameter_change_changes_nothing() -> None:
    f = AttitudeFilter(chart="mrp")
    with pytest.raises(ValueError, match="chart must be one of"):
        f.set_params(chart="euler")
    with pytest.raises(ValueError, match=r"gyro_noise must be in \["):
        f.set_params(gyro_noise=-1.0)
    with pytest.raises(ValueError, match="unknown filter parameter 'gain'"):
        f.set_params(gain=0.1)
    assert f.params.chart == "mrp" and f.params.gyro_noise == 0.01


def test_run_advances_the_filter_like_step_calls() -> None:
    """``run`` (the batch loop of estimate()) and one ``step`` per sample give the same
    orientations and leave the filter in the same state (counters included)."""
    s = simulate("wiener", duration=3.0, rate=100.0, mag_rate=25.0, seed=3)
    dt = 0.01
    dts = np.full(len(s.gyr), dt)
    batch, single = (AttitudeFilter(use_mag=True, estimate_gyro_bias=True) for _ in range(2))
    out = batch.run(dts, s.gyr, s.acc, s.mag)
    for k in range(len(dts)):
        single.step(dt, s.gyr[k], s.acc[k], s.mag[k])
        np.testing.assert_allclose(out.quat[k], single.quaternion, atol=1e-12)
        np.testing.assert_allclose(out.cov[k], single.covariance, atol=1e-12)
    assert batch.counter_dict() == single.counter_dict()
    np.testing.assert_allclose(batch.bias, single.bias, atol=1e-12)


def test_kernel_interface_reads_what_the_properties_say() -> None:
    """The accessors a compiled front end uses (mkf_ros.stream.kernel) read the same values as
    the filter's public properties and parameters."""
    from mkf_ros.core import filter as kf

    s = simulate("wiener", duration=3.0, rate=100.0, mag_rate=25.0, seed=5)
    f = AttitudeFilter(use_mag=True, estimate_gyro_bias=True, max_dt=0.2, gravity=9.79)
    assert not kf.is_initialized(record(f.kernel_arrays().st))
    for k in range(len(s.gyr)):
        f.step(0.01 if k != 150 else 0.5, s.gyr[k], s.acc[k], s.mag[k])  # one gap
    cfg, st, cnt, _ = (record(a) for a in f.kernel_arrays())
    assert kf.gravity(cfg) == 9.79 and kf.max_dt(cfg) == 0.2 and kf.uses_mag(cfg)
    assert kf.is_initialized(st) == f.initialized is True
    assert kf.heading_fixed(cfg, st) == f.heading_initialized is True
    assert kf.gap_count(cnt) == f.counter_dict()["gaps"] == 1
    np.testing.assert_array_equal([kf.rate(st, i) for i in range(3)], f.omega)
    np.testing.assert_array_equal([kf.bias(st, i) for i in range(3)], f.bias)
    np.testing.assert_allclose(np.sqrt([kf.bias_variance(cfg, st, i) for i in range(3)]),
                               f.bias_std, rtol=1e-15)
    np.testing.assert_array_equal(
        [[kf.rate_covariance(st, i, j) for j in range(3)] for i in range(3)],
        f.state_covariance[3:6, 3:6])
    f.set_params(estimate_gyro_bias=False, use_mag=False)
    cfg, st, *_ = (record(a) for a in f.kernel_arrays())
    assert [kf.bias_variance(cfg, st, i) for i in range(3)] == [0.0, 0.0, 0.0]
    assert not kf.uses_mag(cfg)
    assert kf.heading_fixed(cfg, st) == f.heading_initialized is False


def test_split_input_is_kept_across_parameter_changes() -> None:
    """The rest test's split-input flag (set by the stream adapter) survives set_params, which
    rebuilds the configuration."""
    f = AttitudeFilter()
    f.set_split_input(True)
    f.set_params(gyro_noise=0.02)
    assert record(f.kernel_arrays().cfg).split_input
    f.set_split_input(False)
    f.set_params(gyro_noise=0.03)
    assert not record(f.kernel_arrays().cfg).split_input
