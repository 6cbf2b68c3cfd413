"""Magnetometer calibration (mkf_ros.core.magcal, docs/math.md §10.1) on simulated sensors with a
known hard-iron offset and soft-iron distortion: the fit recovers them, reports its quality and
refuses data that cannot determine them."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from mkf_ros.core.magcal import coverage, fit_ellipsoid, params_yaml
from mkf_ros.core.params import FilterParams
from mkf_ros.sim import simulate

#: a symmetric soft-iron distortion (A is identifiable only up to a rotation: the symmetric one
#: is what the fit returns, docs/math.md §10.1) and a hard-iron offset of the Earth field's size
A_TRUE = np.array([[1.12, 0.06, -0.04], [0.06, 0.91, 0.07], [-0.04, 0.07, 1.03]])
H_TRUE = np.array([32e-6, -41e-6, 18e-6])  # T


def _distorted(scenario: str = "slow_rotation", seed: int = 1, **kw: object
               ) -> tuple[np.ndarray, np.ndarray, float]:
    sim = simulate(scenario, duration=60, rate=50, seed=seed, **kw)  # type: ignore[arg-type]
    m = sim.mag[sim.mag_valid]
    field = float(np.median(np.linalg.norm(m, axis=1)))
    return m @ A_TRUE.T + H_TRUE, m, field


def _unit_det(S: np.ndarray) -> np.ndarray:
    return S / np.cbrt(np.linalg.det(S))


@pytest.mark.parametrize("refine", [True, False])
def test_fit_recovers_offset_and_soft_iron_to_one_percent(refine: bool) -> None:
    raw, true_body, field = _distorted()
    cal = fit_ellipsoid(raw, refine=refine)
    assert np.max(np.abs(cal.offset - H_TRUE)) < 0.01 * field
    # S undoes A up to the scale the calibration keeps: S A ∝ I
    SA = _unit_det(cal.soft_iron @ A_TRUE)
    assert np.max(np.abs(SA - np.eye(3))) < 0.01
    # the calibrated samples are the true body field (scaled to the calibrated magnitude)
    back = cal.apply(raw) * (field / cal.field_magnitude)
    err = np.linalg.norm(back - true_body, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.01 * field
    # quality: the sensor noise (0.5 µT) is about 1 % of 50 µT
    assert cal.rms_relative < 0.02 and cal.coverage > 0.8 and cal.axis_ratio > 1.1


def test_hard_iron_only_recovers_a_magnet_offset() -> None:
    """A magnet on the body is a pure offset: the sphere fit recovers it, S is a multiple of I."""
    sim = simulate("slow_rotation", duration=60, rate=50, seed=5)
    m = sim.mag[sim.mag_valid]
    field = float(np.median(np.linalg.norm(m, axis=1)))
    cal = fit_ellipsoid(m + H_TRUE, soft_iron=False)
    assert np.max(np.abs(cal.offset - H_TRUE)) < 0.01 * field
    S = cal.soft_iron
    np.testing.assert_allclose(S, S[0, 0] * np.eye(3), atol=1e-12)
    assert not cal.soft_iron_fitted and "hard iron only" in cal.summary()
    err = np.linalg.norm(cal.apply(m + H_TRUE) * (field / cal.field_magnitude) - m, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.01 * field


def test_given_field_magnitude_sets_the_scale() -> None:
    raw, true_body, field = _distorted()
    cal = fit_ellipsoid(raw, field_magnitude=field)
    assert cal.field_magnitude == field
    err = np.linalg.norm(cal.apply(raw) - true_body, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.01 * field


def test_undistorted_sensor_gives_identity() -> None:
    sim = simulate("sweep", duration=60, rate=50, seed=2)
    m = sim.mag[sim.mag_valid]
    cal = fit_ellipsoid(m)
    field = float(np.median(np.linalg.norm(m, axis=1)))
    assert np.max(np.abs(cal.offset)) < 0.01 * field
    assert np.max(np.abs(_unit_det(cal.soft_iron) - np.eye(3))) < 0.01


def test_turning_about_one_axis_is_refused_for_coverage() -> None:
    """A level robot turning about the vertical sees a cone of field directions: the ellipsoid
    is undetermined, and the refusal says why."""
    sim = simulate("slow_turn", duration=60, rate=50, seed=3, rest=1.0)
    raw = sim.mag[sim.mag_valid] @ A_TRUE.T + H_TRUE
    with pytest.raises(ValueError, match=r"cover \d+ % of the sphere") as e:
        fit_ellipsoid(raw)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((5, 3)), "at least 20 finite samples"),
    (np.zeros((100, 2)), r"\(N, 3\) array"),
    (np.full((100, 3), np.nan), "at least 20 finite samples"),
])
def test_bad_input_is_one_line_error(bad: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        fit_ellipsoid(bad)


def test_nan_rows_are_dropped() -> None:
    raw, _, field = _distorted()
    with_gaps = np.vstack([raw, np.full((50, 3), np.nan)])
    cal = fit_ellipsoid(with_gaps)
    assert cal.n_samples == len(raw)
    assert np.max(np.abs(cal.offset - H_TRUE)) < 0.01 * field


def test_coverage_of_known_sets() -> None:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20000, 3))
    assert coverage(d) == 1.0
    upper = d[d[:, 2] > 0]
    assert coverage(upper) == pytest.approx(0.5)
    assert coverage(np.tile([[0.0, 0.0, 1.0]], (100, 1))) == pytest.approx(1 / 72)


def test_params_yaml_is_a_ros_params_file_the_filter_accepts() -> None:
    raw, _, _ = _distorted()
    cal = fit_ellipsoid(raw)
    doc = yaml.safe_load(params_yaml(cal))
    values = doc["/**"]["ros__parameters"]
    assert values == cal.params()
    fp = FilterParams(values)  # valid filter parameters (invertible soft iron, in range)
    S = np.reshape(fp.mag_soft_iron, (3, 3))
    h = np.array([fp.mag_bias_x, fp.mag_bias_y, fp.mag_bias_z])
    np.testing.assert_allclose((raw - h) @ S.T, cal.apply(raw))
