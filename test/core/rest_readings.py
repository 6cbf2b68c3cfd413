"""Noise-free readings of a body at rest, shared by the sensor-layer and filter tests (imported
as a plain module: test/ has no __init__.py)."""

from __future__ import annotations

import numpy as np

from mkf_ros.core.quaternion import rotmat

G = 9.80665
MAG_ENU = np.array([0.0, 20e-6, -40e-6])  # north and down


def reading(q_enu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free accelerometer and magnetometer readings of a body at rest with attitude q."""
    R = rotmat(q_enu)
    return R.T @ np.array([0.0, 0.0, G]), R.T @ MAG_ENU
