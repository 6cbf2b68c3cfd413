"""The estimator node's calibration services (mkf_ros.ros.calibration, docs/math.md §10), called
from a client node as a user would: ``~/calibrate_gyro`` measures a known gyro bias at rest and
applies it, refuses when the sensor moves; ``~/calibrate_mag/start`` + ``finish`` recover a known
hard- and soft-iron distortion and apply it as parameters; both under rclpy's single-threaded
executor and the EventsExecutor."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from rosharness import Harness, imu_msg, recording_messages
from std_srvs.srv import Trigger

from mkf_ros.sim import simulate

RATE = 100.0
BIAS = np.array([0.012, -0.021, 0.0075])  # rad/s
A_TRUE = np.array([[1.10, 0.05, -0.03], [0.05, 0.92, 0.06], [-0.03, 0.06, 1.04]])
H_TRUE = np.array([25e-6, -30e-6, 15e-6])  # T


class Client:
    """Calls a Trigger service of the estimator and feeds messages until it answers."""

    def __init__(self, h: Harness, name: str) -> None:
        self.h = h
        self.cli = h.cli.create_client(Trigger, h.est.get_fully_qualified_name() + "/" + name)
        assert self.cli.wait_for_service(timeout_sec=10.0), name

    def call(self, feed: Callable[[int], list[Any]] | None = None, chunks: int = 20) -> Any:
        fut = self.cli.call_async(Trigger.Request())
        for k in range(chunks if feed else 0):
            if fut.done():
                break
            self.h.send(feed(k))
        return self.h.wait(fut, timeout=20.0)


def _rest_feed(gyr: Callable[[np.ndarray], np.ndarray], acc: Callable[[np.ndarray], np.ndarray],
               seed: int = 0) -> Callable[[int], list[Any]]:
    """Chunks of 0.5 s of IMU messages; ``gyr(t)``/``acc(t)`` give the signal at stamps t."""
    rng = np.random.default_rng(seed)

    def feed(k: int) -> list[Any]:
        t = 100.0 + (k * 50 + np.arange(50)) / RATE
        g = gyr(t) + rng.normal(scale=0.004, size=(len(t), 3))
        a = acc(t) + rng.normal(scale=0.03, size=(len(t), 3))
        return [imu_msg(float(s), gi, ai) for s, gi, ai in zip(t, g, a, strict=True)]
    return feed


def _still_acc(t: np.ndarray) -> np.ndarray:
    return np.tile([0.0, 0.0, 9.80665], (len(t), 1))


def _bias(t: np.ndarray) -> np.ndarray:
    return np.tile(BIAS, (len(t), 1))


@pytest.fixture(params=["single", "events"])
def est(request: pytest.FixtureRequest, harness: Callable[..., Harness],
        monkeypatch: pytest.MonkeyPatch) -> Harness:
    """The harness under rclpy's SingleThreadedExecutor and under the EventsExecutor."""
    monkeypatch.setenv("MKF_TEST_EXECUTOR", request.param)
    return harness({"gyro_calibration_duration": 1.5})


def test_gyro_calibration_measures_and_applies_the_bias(est: Harness) -> None:
    res = Client(est, "calibrate_gyro").call(_rest_feed(_bias, _still_acc))
    assert res.success, res.message
    got = np.array(est.get("gyro_offset_x", "gyro_offset_y", "gyro_offset_z"))
    # 150 samples of 0.004 rad/s noise: σ of the mean 3.3e-4; 5σ
    np.testing.assert_allclose(got, BIAS, atol=1.7e-3)
    assert "gyro bias" in res.message and "σ" in res.message
    assert f"{got[0]:.6f}" in res.message
    # from now on the filter (and imu/data's angular_velocity) sees the corrected gyro
    n = len(est.out)
    est.send(_rest_feed(_bias, _still_acc, seed=1)(10))
    w = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z]
                  for m in est.out[n:]])
    assert len(w) >= 40
    np.testing.assert_allclose(w.mean(axis=0), 0.0, atol=2e-3)


def test_gyro_calibration_refuses_motion(est: Harness) -> None:
    def turning(t: np.ndarray) -> np.ndarray:
        return BIAS + 0.3 * np.sin(2 * np.pi * 0.7 * t)[:, None] * np.array([1.0, 0.0, 0.0])

    res = Client(est, "calibrate_gyro").call(_rest_feed(turning, _still_acc))
    assert not res.success
    assert "moved" in res.message and "gyro x" in res.message
    assert est.get("gyro_offset_x", "gyro_offset_y", "gyro_offset_z") == [0.0, 0.0, 0.0]


def test_gyro_calibration_refuses_a_shaken_accelerometer(est: Harness) -> None:
    def shaken(t: np.ndarray) -> np.ndarray:
        return _still_acc(t) + 1.5 * np.sin(2 * np.pi * 3.0 * t)[:, None] * np.array(
            [0.0, 1.0, 0.0])

    res = Client(est, "calibrate_gyro").call(_rest_feed(_bias, shaken))
    assert not res.success and "accelerometer" in res.message


def _distorted(scenario: str, **kw: Any) -> Any:
    sim = simulate(scenario, duration=40, rate=50, seed=6, **kw)
    return dataclasses.replace(sim, mag=sim.mag @ A_TRUE.T + H_TRUE)


def test_mag_calibration_recovers_and_applies_the_distortion(est: Harness) -> None:
    sim = _distorted("slow_rotation")
    field = float(np.nanmedian(np.linalg.norm(sim.mag @ np.linalg.inv(A_TRUE).T
                                              - H_TRUE @ np.linalg.inv(A_TRUE).T, axis=1)))
    start = Client(est, "calibrate_mag/start").call()
    assert start.success, start.message
    est.send(recording_messages(sim))
    res = Client(est, "calibrate_mag/finish").call()
    assert res.success, res.message
    assert "coverage" in res.message and "applied" in res.message
    h = np.array(est.get("mag_bias_x", "mag_bias_y", "mag_bias_z"))
    assert np.max(np.abs(h - H_TRUE)) < 0.01 * field
    S = np.reshape(est.get("mag_soft_iron")[0], (3, 3))
    SA = S @ A_TRUE
    np.testing.assert_allclose(SA / np.cbrt(np.linalg.det(SA)), np.eye(3), atol=0.01)


def test_mag_calibration_refuses_poor_coverage(est: Harness) -> None:
    sim = _distorted("slow_turn", rest=1.0)
    assert Client(est, "calibrate_mag/start").call().success
    est.send(recording_messages(sim))
    res = Client(est, "calibrate_mag/finish").call()
    assert not res.success and "sphere" in res.message and "\n" not in res.message
    assert est.get("mag_bias_x", "mag_bias_y", "mag_bias_z") == [0.0, 0.0, 0.0]


def test_mag_finish_without_start_is_refused(est: Harness) -> None:
    res = Client(est, "calibrate_mag/finish").call()
    assert not res.success and "calibrate_mag/start" in res.message


def test_calibration_parameters_are_validated(est: Harness) -> None:
    r = est.set(gyro_calibration_duration=-1.0)
    assert not r[0].successful and "gyro_calibration_duration" in r[0].reason
    r = est.set(gyro_offset_z=0.01)
    assert r[0].successful
    assert est.get("gyro_offset_z") == [0.01]
