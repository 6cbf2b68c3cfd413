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


def _t33(A: np.ndarray) -> tuple:
    return tuple(tuple(float(x) for x in row) for row in A)


def _symmetric_cases() -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    cases = [_spd(rng, 3) * s for s in (1e-6, 1.0, 1e8)]
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    for lams in ((5.0, 5.0, 1.0), (5.0, 1.0, 1.0), (2.0, 2.0, 2.0), (3.0, 0.0, -1.0),
                 (1e9, 1e-3, 1e-9)):
        cases.append(Q @ np.diag(lams) @ Q.T)
    cases += [np.diag([1.0, 7.0, 3.0]), np.zeros((3, 3))]
    return cases


def test_largest_eigenpair_of_a_symmetric_3x3() -> None:
    """Against numpy.linalg.eigh, repeated and zero eigenvalues included."""
    from mkf_ros.core.linalg import largest_eigh33_t

    for A in _symmetric_cases():
        A = 0.5 * (A + A.T)
        lam, v = largest_eigh33_t(_t33(A))
        w = np.linalg.eigvalsh(A)
        scale = max(np.abs(w).max(), 1e-300)
        assert abs(lam - w[-1]) <= 1e-9 * scale
        v = np.array(v)
        assert abs(np.linalg.norm(v) - 1.0) < 1e-12
        np.testing.assert_allclose(A @ v, lam * v, atol=1e-7 * scale)


def test_below_is_never_wrong_and_certain_with_a_margin() -> None:
    """``below33_t(A, t)``: True only if every eigenvalue (numpy.linalg.eigvalsh) is below
    ``t``, False at and above it; True for ``t`` twice the largest, and for a 6D heading's
    covariance (one variance at the cap, two small coupled ones: the cap's fast path) as
    soon as ``t`` exceeds the largest by a relative 1e-9."""
    from mkf_ros.core.linalg import below33_t

    def check(A: np.ndarray, certain_from: float) -> None:
        A = 0.5 * (A + A.T)
        lam = np.linalg.eigvalsh(A)[-1]
        for t in (lam * (1 + 1e-9), lam * (1 + 1e-6), lam * 2, lam, lam * (1 - 1e-9), lam / 2):
            if not t > 0:
                continue
            got = below33_t(_t33(A), t)
            assert not got or lam < t, (A, t)
            assert got or t < lam * certain_from, (lam, t)

    for A in _symmetric_cases():
        if np.linalg.eigvalsh(0.5 * (A + A.T)).min() >= 0:
            check(A, 2.0)
    rng = np.random.default_rng(11)
    for _ in range(300):
        Q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        A = Q @ np.diag([np.pi ** 2 / 3, *10.0 ** rng.uniform(-6, -1, 2)]) @ Q.T
        check(A + 1e-4 * rng.uniform() * _spd(rng, 3) / 3, 1.0 + 1e-9)


def test_eigenvalues_capped_and_the_rest_kept() -> None:
    from mkf_ros.core.linalg import cap_eigenvalues33_t

    for A in _symmetric_cases():
        A = 0.5 * (A + A.T)
        if np.linalg.eigvalsh(A).min() < 0:
            continue  # its contract: a covariance (positive semidefinite)
        cap = 2.5
        C = np.array(cap_eigenvalues33_t(_t33(A), cap))
        w, V = np.linalg.eigh(A)
        expected = V @ np.diag(np.minimum(w, cap)) @ V.T
        scale = max(np.abs(w).max(), 1.0)
        np.testing.assert_allclose(C, expected, atol=1e-8 * scale)
        # positive semidefinite by construction, even below a 10⁹ eigenvalue (a subtraction
        # or congruence along the eigenvector left −10⁻⁸ there)
        np.testing.assert_array_equal(C, C.T)
        assert np.linalg.eigvalsh(C).min() >= -1e-15 * cap


def test_scaling_a_direction_is_a_congruence() -> None:
    """P ← D P Dᵀ, D = I + (s − 1) u uᵀ on the first three rows and columns."""
    from mkf_ros.core.linalg import scale_direction

    rng = np.random.default_rng(3)
    P = _spd(rng, 9)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    D = np.eye(9)
    D[:3, :3] += (0.3 - 1.0) * np.outer(u, u)
    expected = D @ P @ D.T
    scale_direction(P, 9, tuple(u), 0.3)
    np.testing.assert_allclose(P, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(P, P.T)


def test_scaling_a_huge_variance_back_stays_symmetric() -> None:
    """The attitude cap takes a heading variance of 10⁴ rad² (a 10 s step without a heading
    reference) back to π²/3: the result is exactly symmetric, whatever the rounding of the
    large variance (a row pass then a column pass left 1e-11 of the diagonal)."""
    from mkf_ros.core.linalg import scale_direction

    rng = np.random.default_rng(5)
    for _ in range(200):
        B = rng.normal(size=(9, 9))
        P = B @ B.T
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        P[:3, :3] += 1e4 * np.outer(u, u)  # the heading variance along u, then scaled back
        scale_direction(P, 9, tuple(u), float(np.sqrt(3.29 / (u @ P[:3, :3] @ u))))
        np.testing.assert_array_equal(P, P.T)
