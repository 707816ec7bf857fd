"""Dense references for the KRLS-T tests (one definition)."""

from __future__ import annotations

import numpy as np


def batch_gp(kernel, X, y, sn2, jitter):
    """Predictive mean and normalised variance of each next point of exact GP regression, by a dense
    Cholesky solve on the first t points (t = 1 … n−1): ``μ_t = k_tᵀ(K + σₙ²I)⁻¹y``,
    ``σ²_t = σₙ² + k_tt − k_tᵀ(K + σₙ²I)⁻¹k_t``."""
    n = len(y)
    K = kernel(X) + jitter * np.eye(n)
    means, variances = [], []
    for t in range(1, n):
        L = np.linalg.cholesky(K[:t, :t] + sn2 * np.eye(t))
        alpha = np.linalg.solve(L.T, np.linalg.solve(L, y[:t]))
        v = np.linalg.solve(L, K[:t, t])
        means.append(K[:t, t] @ alpha)
        variances.append(sn2 + K[t, t] - v @ v)
    return np.array(means), np.array(variances)
