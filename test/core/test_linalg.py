"""Small dense linear algebra of the kernels (mkf_ros/core/linalg.py) against NumPy."""

from __future__ import annotations

import numpy as np

from mkf_ros.core.linalg import cho_solve, cho_solve_into, cholesky, cholesky_into


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def test_cholesky_and_solve() -> None:
    rng = np.random.default_rng(1)
    S = _spd(rng, 7)
    L, ok = cholesky(S)
    assert ok
    np.testing.assert_allclose(L, np.linalg.cholesky(S), rtol=1e-12, atol=1e-12)
    B = rng.normal(size=(7, 3))
    np.testing.assert_allclose(cho_solve(L, B), np.linalg.solve(S, B), rtol=1e-10)
    bad = S.copy()
    bad[3, 3] = -1.0
    assert not cholesky(bad)[1]


def test_cholesky_into_a_diagonal_block_in_place() -> None:
    """The MUKF factors blockdiag(P, Q) block by block into one matrix, the second in place."""
    rng = np.random.default_rng(2)
    P, Q = _spd(rng, 6), _spd(rng, 3)
    L = np.full((9, 9), np.nan)
    assert cholesky_into(P, L, 0, 6)
    L[6:, 6:] = Q
    assert cholesky_into(L, L, 6, 3)
    np.testing.assert_allclose(L[:6, :6], np.linalg.cholesky(P), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(L[6:, 6:], np.linalg.cholesky(Q), rtol=1e-12, atol=1e-12)
    assert np.isnan(L[6:, :6]).all() and np.isnan(L[:6, 6:]).all()  # nothing else touched


def test_cho_solve_into_leading_rows() -> None:
    """Only the first n rows of the right-hand side are solved (the rest are left alone)."""
    rng = np.random.default_rng(3)
    S = _spd(rng, 4)
    L = np.zeros((6, 6))
    assert cholesky_into(S, L, 0, 4)
    X = rng.normal(size=(6, 5))
    want = np.linalg.solve(S, X[:4])
    rest = X[4:].copy()
    cho_solve_into(L, 4, X, X.shape[1])
    np.testing.assert_allclose(X[:4], want, rtol=1e-10)
    np.testing.assert_array_equal(X[4:], rest)
