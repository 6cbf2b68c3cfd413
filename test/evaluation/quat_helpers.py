"""Quaternion helpers shared by the dataset and scoring tests (plain NumPy, independent of
the code under test)."""

from __future__ import annotations

import math

import numpy as np


def canon(q: np.ndarray) -> np.ndarray:
    """Unit quaternions with w ≥ 0 (q and −q are the same rotation)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def random_quats(n: int, seed: int) -> np.ndarray:
    return canon(np.random.default_rng(seed).normal(size=(n, 4)))


def quat_z(angle: float) -> np.ndarray:
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])
