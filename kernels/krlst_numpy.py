"""Plain vectorised NumPy KRLS-T (kafbox ``krlst.m`` port): the speed baseline of
``benchmarks/krlst_step.py`` and an independent reference for the tests.

Same algorithm as :mod:`kernels._krlst_core` (method §6: forget, predict, update, s0²,
prune, with the cached ``K_D`` updated by one row/column), written the way one would in
NumPy: whole-array expressions, ``np.block``/``np.delete`` reallocation, the kernel row from
:class:`kernels.Kernel` (NumPy path), full matrices, no refinement, no numba.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NumpyKRLST"]


class NumpyKRLST:
    """kafbox's KRLS-T with back-to-the-prior forgetting, eq. 2.14–2.22.

    After each :meth:`learn_one`, ``removed`` is the 0-based index of the pruned basis (-1:
    none; the new sample is last) and ``criterion_gap`` the relative gap between the two
    smallest pruning criteria ``|[Qμ]_i/Q_ii|`` (``inf`` when the criterion was not used):
    how near the pruning decision was to a tie.
    """

    def __init__(self, kernel, gamma, forgetting, budget, jitter=1e-6):
        self.kernel = kernel
        self.sn2 = 1.0 / gamma
        self.lam = forgetting
        self.M = budget
        self.jitter = jitter
        self.dict = None
        self.removed = -1
        self.criterion_gap = np.inf

    def learn_one(self, x, y):
        """Train on ``(x, y)``; returns the prediction ``ŷ`` made before ``y`` was seen."""
        x = np.atleast_1d(np.asarray(x, dtype=float))[None, :]
        sn2, lam, jit = self.sn2, self.lam, self.jitter
        self.removed, self.criterion_gap = -1, np.inf
        if self.dict is None:
            k = self.kernel(x)[0, 0] + jit
            self.dict = x
            self.K = np.array([[k]])
            self.Q = np.array([[1.0 / k]])
            self.mu = np.array([y * k / (k + sn2)])
            self.Sigma = np.array([[k - k * k / (k + sn2)]])
            self.num, self.den = y * y / (k + sn2), 1.0
            self.s02 = self.num / self.den
            return 0.0
        # 1. forget
        self.Sigma = lam * self.Sigma + (1 - lam) * self.K
        self.mu = np.sqrt(lam) * self.mu
        # 2. predict
        kt = self.kernel(self.dict, x)[:, 0]
        ktt = self.kernel(x)[0, 0] + jit
        q = self.Q @ kt
        y_mean = q @ self.mu
        gamma2 = max(ktt - kt @ q, 0.0)
        h = self.Sigma @ q
        sf2 = max(gamma2 + q @ h, 0.0)
        sy2 = sn2 + sf2
        # 3. update
        Qold = self.Q
        p = np.append(q, -1.0)
        m = len(q)
        self.Q = np.pad(self.Q, ((0, 1), (0, 1))) + np.outer(p, p) / gamma2 if gamma2 > 0 else self.Q
        g = np.append(h, sf2)
        self.mu = np.append(self.mu, y_mean) + (y - y_mean) / sy2 * g
        self.Sigma = np.block([[self.Sigma, h[:, None]], [h[None, :], np.array([[sf2]])]]) - np.outer(g, g) / sy2
        self.K = np.block([[self.K, kt[:, None]], [kt[None, :], np.array([[ktt]])]])
        self.dict = np.vstack([self.dict, x])
        m += 1
        # 4. s0²
        self.num += lam * (y - y_mean) ** 2 / sy2
        self.den += lam
        self.s02 = self.num / self.den
        # 5. prune
        if m > self.M or gamma2 < jit:
            if gamma2 < jit:
                r = m - 1
            else:
                crit = np.abs((self.Q @ self.mu) / np.diag(self.Q))
                r = int(np.argmin(crit))
                two = np.partition(crit, 1)[:2]
                self.criterion_gap = (two[1] - two[0]) / two[1]
            if r == m - 1:
                self.Q = Qold
            else:
                Qs = np.delete(self.Q[:, r], r)
                self.Q = np.delete(np.delete(self.Q, r, 0), r, 1) - np.outer(Qs, Qs) / self.Q[r, r]
            self.mu = np.delete(self.mu, r)
            self.Sigma = np.delete(np.delete(self.Sigma, r, 0), r, 1)
            self.K = np.delete(np.delete(self.K, r, 0), r, 1)
            self.dict = np.delete(self.dict, r, 0)
            self.removed = r
        return y_mean
