"""Small dense linear algebra for the kernels: Cholesky factor and solve (docs/math.md §8 item 16).

Written out because numba's ``np.linalg`` needs SciPy's LAPACK and these matrices are ≤ 21×21.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline


@jit_inline
def cholesky_into(a: np.ndarray, L: np.ndarray, o: int, n: int) -> bool:
    """Lower Cholesky factor ``L`` with ``a = L Lᵀ`` of the ``n × n`` diagonal blocks at rows and
    columns ``o … o + n − 1``, in place (``L`` may be ``a``: only its lower triangle is read;
    the upper one is zeroed). False if ``a`` is not positive definite (``L`` is then
    incomplete)."""
    for j in range(o, o + n):
        s = a[j, j]
        for k in range(o, j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:  # also catches NaN
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, o + n):
            s = a[i, j]
            for k in range(o, j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(o, j):
            L[i, j] = 0.0
    return True


@jit
def cholesky(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """Lower Cholesky factor ``L`` with ``a = L Lᵀ``; ``ok`` is False if ``a`` is not PD."""
    n = a.shape[0]
    L = np.zeros((n, n))
    ok = cholesky_into(a, L, 0, n)
    return L, ok


@jit_inline
def cho_solve_into(L: np.ndarray, n: int, x: np.ndarray, m: int) -> None:
    """Solve ``(L Lᵀ) X = B`` in place: ``x`` holds ``B`` (its first ``m`` columns are
    right-hand sides) in its first ``n`` rows on entry and ``X`` on return; ``L`` is ``n × n``
    lower (leading block)."""
    for i in range(n):  # forward: L Z = B, all columns at once (row-major friendly)
        for k in range(i):
            lik = L[i, k]
            for c in range(m):
                x[i, c] -= lik * x[k, c]
        inv = 1.0 / L[i, i]
        for c in range(m):
            x[i, c] *= inv
    for i in range(n - 1, -1, -1):  # backward: Lᵀ X = Z
        for k in range(i + 1, n):
            lki = L[k, i]
            for c in range(m):
                x[i, c] -= lki * x[k, c]
        inv = 1.0 / L[i, i]
        for c in range(m):
            x[i, c] *= inv


@jit
def cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``(L Lᵀ) X = B`` for a matrix ``B`` (columns are right-hand sides)."""
    x = b.copy()
    cho_solve_into(L, b.shape[0], x, x.shape[1])
    return x


@jit
def copy_into(dst: np.ndarray, src: np.ndarray) -> None:
    """``dst[:] = src`` for vectors (written out: numba compiles a slice assignment with its
    shape check and the formatting of its error message, seconds of compile time)."""
    for i in range(dst.shape[0]):
        dst[i] = src[i]


@jit
def copy_block(dst: np.ndarray, r0: int, c0: int, src: np.ndarray, transpose: bool) -> None:
    """``dst[r0:r0+n, c0:c0+m] = src`` (``src.T`` with ``transpose``) for the ``n × m`` ``src``
    (``m × n`` transposed); written out like :func:`copy_into`."""
    n, m = src.shape
    for i in range(n):
        for j in range(m):
            if transpose:
                dst[r0 + j, c0 + i] = src[i, j]
            else:
                dst[r0 + i, c0 + j] = src[i, j]


@jit_inline
def symmetrize_leading(P: np.ndarray, n: int) -> None:
    """``P ← ½(P + Pᵀ)`` on the leading ``n × n`` block, in place."""
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s


@jit_inline
def mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for small dense matrices."""
    n, k = a.shape
    m = b.shape[1]
    c = np.zeros((n, m))
    for i in range(n):
        for p in range(k):
            aip = a[i, p]
            if aip != 0.0:
                for j in range(m):
                    c[i, j] += aip * b[p, j]
    return c


@jit_inline
def mmt(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ bᵀ`` for small dense matrices."""
    n, k = a.shape
    m = b.shape[0]
    c = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for p in range(k):
                s += a[i, p] * b[j, p]
            c[i, j] = s
    return c


@jit
def mv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``a @ v`` for a small matrix and vector."""
    n, k = a.shape
    r = np.zeros(n)
    for i in range(n):
        s = 0.0
        for p in range(k):
            s += a[i, p] * v[p]
        r[i] = s
    return r


@jit
def mtv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``aᵀ @ v`` for a small matrix and vector."""
    k, n = a.shape
    r = np.zeros(n)
    for p in range(k):
        vp = v[p]
        for i in range(n):
            r[i] += a[p, i] * vp
    return r


@jit_inline
def congruence(a: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``a p aᵀ``."""
    return mmt(mm(a, p), a)


# Loop versions of np.eye / np.outer / np.cross: numba compiles those NumPy functions slowly
# (seconds each, measured), which would make the first start of every program slow.
@jit
def eye(n: int, s: float = 1.0) -> np.ndarray:
    """``s`` times the identity matrix."""
    r = np.zeros((n, n))
    for i in range(n):
        r[i, i] = s
    return r


@jit
def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b``."""
    return np.array((a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]))


@jit_inline
def mul33_t(A: tuple, B: tuple) -> tuple:
    """``A B`` for 3×3 tuples of rows."""
    return (_row_times33_t(A[0], B), _row_times33_t(A[1], B), _row_times33_t(A[2], B))


@jit_inline
def _row_times33_t(a: tuple, B: tuple) -> tuple:
    """Row vector ``a`` (3) times the 3×3 ``B`` (tuple of rows)."""
    return (a[0] * B[0][0] + a[1] * B[1][0] + a[2] * B[2][0],
            a[0] * B[0][1] + a[1] * B[1][1] + a[2] * B[2][1],
            a[0] * B[0][2] + a[1] * B[1][2] + a[2] * B[2][2])


@jit_inline
def transpose33_t(A: tuple) -> tuple:
    """``Aᵀ`` for a 3×3 tuple of rows."""
    return ((A[0][0], A[1][0], A[2][0]), (A[0][1], A[1][1], A[2][1]),
            (A[0][2], A[1][2], A[2][2]))


@jit_inline
def congruence33_t(A: tuple, B: tuple) -> tuple:
    """``A B Aᵀ`` for 3×3 tuples of rows."""
    return mul33_t(A, mul33_t(B, transpose33_t(A)))
