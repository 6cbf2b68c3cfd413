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


@jit_inline
def cross_t(a: tuple, b: tuple) -> tuple:
    """``a × b`` for 3-tuples."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


#: The zero 3-vector and the 3×3 zero matrix as a tuple of rows.
ZERO3 = (0.0, 0.0, 0.0)
ZERO33 = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


@jit_inline
def cross33_t(v: tuple, S: tuple) -> tuple:
    """``[v]× S`` for a 3-tuple ``v`` and a 3×3 tuple of rows ``S``: column ``j`` is
    ``v × S[:, j]``."""
    c = transpose33_t(S)
    return transpose33_t((cross_t(v, c[0]), cross_t(v, c[1]), cross_t(v, c[2])))


@jit_inline
def orthogonal_unit_t(x: tuple) -> tuple:
    """A unit vector orthogonal to the non-zero 3-tuple ``x``: ``x`` × the axis least aligned
    with it, normalised."""
    k = 0
    if abs(x[1]) < abs(x[k]):
        k = 1
    if abs(x[2]) < abs(x[k]):
        k = 2
    c = cross_t(x, (1.0 if k == 0 else 0.0, 1.0 if k == 1 else 0.0, 1.0 if k == 2 else 0.0))
    n = np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    return (c[0] / n, c[1] / n, c[2] / n)


@jit
def largest_eigh33_t(A: tuple) -> tuple[float, tuple]:
    """The largest eigenvalue of a symmetric 3×3 ``A`` (tuple of rows) and a unit eigenvector
    of it: the eigenvalue in closed form (the trigonometric solution of the characteristic
    cubic), the vector as the longest cross product of two rows of ``A − λ I`` (for a
    repeated largest eigenvalue, a unit vector orthogonal to the one non-zero row; for
    ``A = λ I``, the x axis)."""
    a00, a11, a22 = A[0][0], A[1][1], A[2][2]
    a01, a02, a12 = 0.5 * (A[0][1] + A[1][0]), 0.5 * (A[0][2] + A[2][0]), 0.5 * (A[1][2] + A[2][1])
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    lam = q
    if p2 > 0.0:
        p = np.sqrt(p2 / 6.0)
        b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
        b01, b02, b12 = a01 / p, a02 / p, a12 / p
        r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                   + b02 * (b01 * b12 - b11 * b02))
        lam = q + 2.0 * p * np.cos(np.arccos(max(-1.0, min(1.0, r))) / 3.0)
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best = (1.0, 0.0, 0.0)
    n_best = 0.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        c = cross_t(u, v)
        n = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        if n > n_best:
            best, n_best = c, n
    scale = max(abs(a00), abs(a11), abs(a22), abs(a01), abs(a02), abs(a12), 1e-300)
    if n_best <= (1e-12 * scale * scale) ** 2:  # rank ≤ 1: the largest eigenvalue repeats
        row = r0
        for rr in (r1, r2):
            if rr[0] ** 2 + rr[1] ** 2 + rr[2] ** 2 > row[0] ** 2 + row[1] ** 2 + row[2] ** 2:
                row = rr
        nr = row[0] ** 2 + row[1] ** 2 + row[2] ** 2
        if nr <= (1e-12 * scale) ** 2:
            return lam, (1.0, 0.0, 0.0)
        return lam, orthogonal_unit_t(row)
    n = np.sqrt(n_best)
    return lam, (best[0] / n, best[1] / n, best[2] / n)


@jit_inline
def below33_t(A: tuple, t: float) -> bool:
    """Whether every eigenvalue of the symmetric 3×3 ``A`` (tuple of rows) is certainly below
    ``t`` (> 0), without an eigenvalue: the roots of ``det(x I − M)``, ``M = t I − A``, are all
    positive iff its coefficients alternate in sign (its roots are real: Descartes), i.e. iff
    ``tr M``, the sum of ``M``'s principal 2×2 minors and ``det M`` are positive. Each is asked
    to be so by a margin (``1e-12 t^k``, far above their rounding, ~1e-15 t^k), so that True
    leaves no doubt: ``λ_max < t`` by more than a closed-form eigenvalue's rounding, and a
    caller decides as :func:`largest_eigh33_t` would. False: not certain (compute it)."""
    m00, m11, m22 = t - A[0][0], t - A[1][1], t - A[2][2]
    m01, m02, m12 = -0.5 * (A[0][1] + A[1][0]), -0.5 * (A[0][2] + A[2][0]), \
        -0.5 * (A[1][2] + A[2][1])
    e = 1e-12 * t
    if not m00 + m11 + m22 > e:
        return False
    c11, c22 = m11 * m22 - m12 * m12, m00 * m22 - m02 * m02
    if not c11 + c22 + m00 * m11 - m01 * m01 > e * t:
        return False
    return m00 * c11 - m01 * (m01 * m22 - m12 * m02) + m02 * (m01 * m12 - m11 * m02) > e * t * t


@jit_inline
def none_above33_t(C: tuple, t: float) -> bool:
    """The quick test before an eigenvalue: no eigenvalue of the positive semidefinite 3×3
    ``C`` exceeds ``t`` because its trace does not (every eigenvalue is at most the trace), or
    certainly none does (:func:`below33_t`). False: compute it. A 6D heading sits at the cap
    for good, where the trace never passes and the eigenvalue cost ~14 % of a step."""
    return C[0][0] + C[1][1] + C[2][2] <= t or below33_t(C, t)


@jit_inline
def psd33_t(C: tuple) -> bool:
    """Whether the symmetric 3×3 ``C`` is positive semidefinite: every principal minor ≥ 0
    (Sylvester's criterion for semidefiniteness), as computed."""
    a, b, c = C[0][0], C[1][1], C[2][2]
    d, e, f = C[0][1], C[0][2], C[1][2]
    if a < 0.0 or b < 0.0 or c < 0.0:
        return False
    if a * b < d * d or a * c < e * e or b * c < f * f:
        return False
    return a * (b * c - f * f) - d * (d * c - f * e) + e * (d * f - b * e) >= 0.0


@jit_inline
def scale_direction(P: np.ndarray, n: int, u: tuple, s: float) -> None:
    """``P ← D P Dᵀ`` with ``D = I + (s − 1) u uᵀ`` on rows and columns 0–2 of the leading
    ``n × n`` block (``u`` unit): the variance along ``u`` times ``s²``, every correlation
    with it scaled alike (a congruence: ``P`` stays PSD). Each entry is computed once, from
    the upper triangle, and mirrored: symmetric by construction. (A row pass then a column
    pass in place left the attitude block asymmetric by the rounding of the variance before
    the scaling: 1e-11 of the diagonal after the cap took a 10 s step's heading variance back
    to π²/3, found by the long property profile.)"""
    f = s - 1.0
    a = (P[0, 0] * u[0] + P[0, 1] * u[1] + P[0, 2] * u[2],  # a = P u (the block as it was)
         P[0, 1] * u[0] + P[1, 1] * u[1] + P[1, 2] * u[2],
         P[0, 2] * u[0] + P[1, 2] * u[1] + P[2, 2] * u[2])
    ff = f * f * (u[0] * a[0] + u[1] * a[1] + u[2] * a[2])
    for i in range(3):  # the block: P + f (u aᵀ + a uᵀ) + f² (uᵀ P u) u uᵀ
        for j in range(i, 3):
            v = P[i, j] + f * (u[i] * a[j] + a[i] * u[j]) + ff * u[i] * u[j]
            P[i, j] = v
            P[j, i] = v
    for j in range(3, n):  # the correlations: rows 0–2 of D P, mirrored
        t = f * (u[0] * P[0, j] + u[1] * P[1, j] + u[2] * P[2, j])
        for i in range(3):
            v = P[i, j] + u[i] * t
            P[i, j] = v
            P[j, i] = v


@jit
def cap_eigenvalues33_t(C: tuple, cap: float) -> tuple:
    """The symmetric positive semidefinite 3×3 ``C`` with its eigenvalues clamped to
    ``[0, cap]``: rebuilt as ``Σ λₖ vₖ vₖᵀ`` from its eigenpairs (the largest from
    :func:`largest_eigh33_t`, the other two in closed form in the plane orthogonal to it), so
    that the result is positive semidefinite by construction. A subtraction
    ``C − (λ − cap) v vᵀ`` or a congruence along ``v`` is not: at λ ≈ 10⁹ the rounding of
    either left eigenvalues of −10⁻⁸. ``C`` itself when no eigenvalue exceeds ``cap`` (the
    trace bounds them, or :func:`none_above33_t`: the quick case) and it is positive
    semidefinite (:func:`psd33_t`). A symmetric ``C`` that is not (a state covariance whose
    attitude block is rounded indefinite next to a rate variance 10⁹ times larger) is rebuilt
    alike, its negative eigenvalues set to 0."""
    psd = psd33_t(C)
    if psd and none_above33_t(C, cap):
        return C
    lam, v = largest_eigh33_t(C)
    if psd and not lam > cap:
        return C
    # an orthonormal basis (e, h) of the plane orthogonal to v; C e and C h (C symmetric)
    e = orthogonal_unit_t(v)
    h = cross_t(v, e)
    Ce, Ch = _row_times33_t(e, C), _row_times33_t(h, C)
    b11 = e[0] * Ce[0] + e[1] * Ce[1] + e[2] * Ce[2]
    b22 = h[0] * Ch[0] + h[1] * Ch[1] + h[2] * Ch[2]
    b12 = 0.5 * (e[0] * Ch[0] + e[1] * Ch[1] + e[2] * Ch[2]
                 + h[0] * Ce[0] + h[1] * Ce[1] + h[2] * Ce[2])
    m = 0.5 * (b11 + b22)
    d = np.sqrt(0.25 * (b11 - b22) ** 2 + b12 * b12)
    l2, l3 = m + d, m - d
    x, y = b12, l2 - b11  # eigenvector of l2 in (e, h): the longer of two equivalent forms
    x2, y2 = l2 - b22, b12
    if x2 * x2 + y2 * y2 > x * x + y * y:
        x, y = x2, y2
    n = np.sqrt(x * x + y * y)
    if n > 0.0:
        x, y = x / n, y / n
    else:
        x, y = 1.0, 0.0
    u = (x * e[0] + y * h[0], x * e[1] + y * h[1], x * e[2] + y * h[2])
    w = cross_t(v, u)
    l1 = min(max(lam, 0.0), cap)
    l2 = min(max(l2, 0.0), cap)
    l3 = min(max(l3, 0.0), cap)
    c00 = l1 * v[0] * v[0] + l2 * u[0] * u[0] + l3 * w[0] * w[0]
    c11 = l1 * v[1] * v[1] + l2 * u[1] * u[1] + l3 * w[1] * w[1]
    c22 = l1 * v[2] * v[2] + l2 * u[2] * u[2] + l3 * w[2] * w[2]
    c01 = l1 * v[0] * v[1] + l2 * u[0] * u[1] + l3 * w[0] * w[1]
    c02 = l1 * v[0] * v[2] + l2 * u[0] * u[2] + l3 * w[0] * w[2]
    c12 = l1 * v[1] * v[2] + l2 * u[1] * u[2] + l3 * w[1] * w[2]
    return ((c00, c01, c02), (c01, c11, c12), (c02, c12, c22))
