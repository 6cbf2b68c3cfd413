"""Hypothesis strategies shared by the core tests (imported as a plain module: test/ has no
__init__.py, so every test file name must be unique across the tree)."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


@st.composite
def unit_quaternions(draw: st.DrawFn) -> np.ndarray:
    """Unit quaternions, any sign, avoiding degenerate tiny draws."""
    v = np.array([draw(finite) for _ in range(4)])
    n = np.linalg.norm(v)
    if n < 1e-3:
        v = np.array([1.0, 0.0, 0.0, 0.0])
        n = 1.0
    return v / n


@st.composite
def vectors(draw: st.DrawFn, scale: float = 1.0) -> np.ndarray:
    return scale * np.array([draw(finite) for _ in range(3)])
