"""Dense references for the REML and GLS tests (one definition)."""

import numpy as np


def dense_reml(Z, y, A, intercept=True):
    """Reference REML (b integrated out, s² profiled) with numpy slogdet and dense solves."""
    n = y.size
    Zt = np.column_stack([np.ones(n), Z]) if intercept else Z
    p = Zt.shape[1]
    Ai_Z = np.linalg.solve(A, Zt)
    Ai_y = np.linalg.solve(A, y)
    M = Zt.T @ Ai_Z
    b = np.linalg.solve(M, Zt.T @ Ai_y)
    r = y - Zt @ b
    q = r @ np.linalg.solve(A, r)
    s2 = q / (n - p)
    return -0.5 * ((n - p) * (np.log(2 * np.pi * s2) + 1) + np.linalg.slogdet(A)[1]
                   + np.linalg.slogdet(M)[1] - np.linalg.slogdet(Zt.T @ Zt)[1])


def dense_gls_cov(Z, y, A, intercept=True):
    """Reference GLS covariance ŝ² (Z̃ᵀA⁻¹Z̃)⁻¹ (eq. L3)."""
    n = y.size
    Zt = np.column_stack([np.ones(n), Z]) if intercept else Z
    M = Zt.T @ np.linalg.solve(A, Zt)
    b = np.linalg.solve(M, Zt.T @ np.linalg.solve(A, y))
    r = y - Zt @ b
    s2 = r @ np.linalg.solve(A, r) / (n - Zt.shape[1])
    return s2 * np.linalg.inv(M)
