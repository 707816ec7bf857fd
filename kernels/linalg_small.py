"""Small dense linear algebra for compiled code (p×p, p ≤ 6: the online β's matrices).

Hand-written loops instead of LAPACK: numba's ``np.linalg`` allocates and checks on every call, which
costs more than the arithmetic at this size, and these run inside the allocation-free step.
"""

from __future__ import annotations

from numba import njit

__all__ = ["lu_factor", "lu_solve", "invert", "congruence"]


@njit(cache=True, nogil=True)
def lu_factor(A, LU, piv):
    """LU factorisation with partial pivoting of the p×p matrix A (``PA = LU``); False if singular."""
    p = A.shape[0]
    for i in range(p):
        for j in range(p):
            LU[i, j] = A[i, j]
    for k in range(p):
        m = k
        big = abs(LU[k, k])
        for i in range(k + 1, p):
            if abs(LU[i, k]) > big:
                big = abs(LU[i, k])
                m = i
        if not big > 0.0:
            return False
        piv[k] = m
        if m != k:
            for j in range(p):
                t = LU[k, j]
                LU[k, j] = LU[m, j]
                LU[m, j] = t
        inv = 1.0 / LU[k, k]
        for i in range(k + 1, p):
            f = LU[i, k] * inv
            LU[i, k] = f
            for j in range(k + 1, p):
                LU[i, j] -= f * LU[k, j]
    return True


@njit(cache=True, nogil=True)
def lu_solve(LU, piv, b, x):
    """x = A⁻¹ b from :func:`lu_factor`."""
    p = LU.shape[0]
    for i in range(p):
        x[i] = b[i]
    for k in range(p):
        m = piv[k]
        if m != k:
            t = x[k]
            x[k] = x[m]
            x[m] = t
    for i in range(p):
        acc = x[i]
        for k in range(i):
            acc -= LU[i, k] * x[k]
        x[i] = acc
    for i in range(p - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, p):
            acc -= LU[i, k] * x[k]
        x[i] = acc / LU[i, i]


@njit(cache=True, nogil=True)
def invert(A, out, LU, piv, b, x):
    """out = A⁻¹ (p×p) by LU; False if A is singular."""
    p = A.shape[0]
    if not lu_factor(A, LU, piv):
        return False
    for c in range(p):
        for i in range(p):
            b[i] = 1.0 if i == c else 0.0
        lu_solve(LU, piv, b, x)
        for i in range(p):
            out[i, c] = x[i]
    return True

@njit(cache=True, nogil=True)
def congruence(A, T, out, tmp):
    """out = Tᵀ A T (p×p; ``out`` may be ``A``; ``tmp`` scratch, aliasing none of them)."""
    p = A.shape[0]
    for i in range(p):
        for j in range(p):
            acc = 0.0
            for k in range(p):
                acc += A[i, k] * T[k, j]
            tmp[i, j] = acc                       # A T
    for i in range(p):
        for j in range(p):
            acc = 0.0
            for k in range(p):
                acc += T[k, i] * tmp[k, j]
            out[i, j] = acc                       # Tᵀ (A T)
