"""Synthetic feed-drive streams from the exact discrete model (method §1), for the tests and benchmarks of
the estimators: ``y = Zβ + f + ε`` holds exactly, so an estimator is checked against the very β and f
that made the data, as arrays. (:mod:`replay.simulator` makes trial files instead: the closed loop with
the friction on the true velocity and measurement noise, scenarios, drifting constants; its data satisfy
the model exactly only without noise.)

The simulated plant is the exact ZOH recursion of method §1,

    v_m(k+1) = (p_d − K_d) v_m(k) + K_d v_r(k) − b (T_f(k) + T_c(k)) + ε(k)      (velocity loop)
    v_m(k+1) = p_d v_m(k) + b (u(k) − offset) − b (T_f(k) + T_c(k)) + ε(k)        (force input)

with ``b = K_d/K = (1 − p_d)/B``, Coulomb friction ``T_f = d_p`` above ``+Ω`` and
``d_n`` below ``−Ω`` (on the measured velocity, as in the regressors) and a
disturbance force ``T_c`` (N). ``ε`` is white equation noise. So ``y = Zβ + f + ε``
holds exactly with ``f(k) = −b T_c(k)`` and the true β from
:func:`kernels.feed_drive.physical_to_beta`.

Default physical parameters give the thesis case-1 numbers (Table 4.2):
``Ts = 1/333 s``, ``J = 100 kg``, ``B = 100 N·s/m`` → ``p_d = 0.99700``,
``b = 3.0e-5 m/s/N``; ``K = 27 817 N·s/m`` → ``β ≈ [0.834, 0.163, …]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels.feed_drive import physical_to_beta, regressors

TS = 1.0 / 333.0
INERTIA = 100.0  # kg
DAMPING = 100.0  # N·s/m
GAIN = 0.834 * DAMPING / (1.0 - np.exp(-DAMPING * TS / INERTIA))  # K so that K_d = 0.834
COULOMB_POS = 20.0  # N
COULOMB_NEG = 25.0  # N
OMEGA = 1e-3  # m/s dead band


@dataclass(frozen=True)
class Stream:
    """One simulated trial and its truth."""

    form: str
    Ts: float
    t: np.ndarray  # sample times (s), t[k] = k Ts
    v_meas: np.ndarray  # m/s
    exogenous: np.ndarray  # v_ref (m/s) or u (N)
    force: np.ndarray  # disturbance force T_c (N)
    beta: np.ndarray  # true β (exact ZOH)
    f: np.ndarray  # true disturbance in velocity units, aligned with y: f(k) = −b T_c(k)
    b: float  # K_d/K (m/s per N)
    omega: float
    coulomb: bool

    def regression(self):
        """``Regression`` of the trial (``Z`` has N−1 rows)."""
        kw = {"v_ref": self.exogenous} if self.form == "velocity-loop" else {"u": self.exogenous}
        return regressors(self.form, self.v_meas, omega=self.omega, coulomb=self.coulomb, **kw)

    @property
    def x(self) -> np.ndarray:
        """Sample times of the regression rows ``t[0 … N−2]``."""
        return self.t[:-1]


def reference_trajectory(n: int, Ts: float = TS, *, seed: int = 0, reversals: bool = True,
                         vmax: float = 0.1) -> np.ndarray:
    """Identification trajectory: trapezoidal moves between random speed levels with dwells at rest.

    Levels alternate in sign when ``reversals`` (speed reversals through the dead band),
    otherwise all are positive. Accelerations 0.2–2 m/s², holds 0.1–0.6 s, rests 0.05–0.2 s.
    """
    rng = np.random.default_rng(seed)
    v = np.zeros(n)
    k = int(rng.integers(10, 40))
    current = 0.0
    sign = 1.0
    while k < n:
        level = sign * rng.uniform(0.15, 1.0) * vmax
        if reversals:
            sign = -sign
        acc = rng.uniform(0.2, 2.0)
        steps = max(1, int(abs(level - current) / (acc * Ts)))
        ramp = np.linspace(current, level, steps + 1)[1:]
        hold = np.full(int(rng.uniform(0.1, 0.6) / Ts), level)
        back = np.linspace(level, 0.0, steps + 1)[1:] if rng.random() < 0.6 else np.empty(0)
        rest = np.zeros(int(rng.uniform(0.05, 0.2) / Ts)) if back.size else np.empty(0)
        seg = np.concatenate([ramp, hold, back, rest])
        m = min(seg.size, n - k)
        v[k:k + m] = seg[:m]
        k += m
        current = seg[-1]
    return v


def shaker_force(t, amplitude: float = 60.0, frequency: float = 55.0, harmonic: float = 0.35,
                 phase: float = 0.3, sweep: bool = False) -> np.ndarray:
    """Shaker disturbance force (N): ``a(t)(sin(2π f t + φ) + h sin(4π f t + 2φ + 0.7))``.

    ``sweep`` makes the amplitude vary slowly (thesis trial #3).
    """
    t = np.asarray(t, dtype=np.float64)
    a = amplitude * (1.0 + 0.4 * np.sin(2 * np.pi * 0.15 * t)) if sweep else amplitude
    w = 2 * np.pi * frequency * t
    return a * (np.sin(w + phase) + harmonic * np.sin(2 * w + 2 * phase + 0.7))


def simulate(n: int = 2500, *, form: str = "velocity-loop", Ts: float = TS, inertia: float = INERTIA,
             damping: float = DAMPING, gain: float = GAIN, coulomb_pos: float = COULOMB_POS,
             coulomb_neg: float = COULOMB_NEG, offset: float = 0.0, omega: float = OMEGA,
             coulomb: bool = True, reversals: bool = True, force=None, noise: float = 2e-5,
             seed: int = 0) -> Stream:
    """Simulate ``n`` samples of the exact discrete closed loop (module docstring).

    ``force``: disturbance force array (N) of length ``n``, a callable of ``t``, or None (none).
    For the force-input form the command is a PI-like velocity controller output
    ``u = K (v_r − v_m) + 0.3 K v_r`` recomputed from the measured velocity each sample,
    so ``u`` is correlated with the disturbance like a recorded command.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) * Ts
    v_ref = reference_trajectory(n, Ts, seed=seed, reversals=reversals)
    if force is None:
        tc = np.zeros(n)
    elif callable(force):
        tc = np.asarray(force(t), dtype=np.float64)
    else:
        tc = np.asarray(force, dtype=np.float64)
    p_d = np.exp(-damping * Ts / inertia)
    b = (1.0 - p_d) / damping
    K_d = gain * b
    d_p, d_n = coulomb_pos, -coulomb_neg
    if not coulomb:
        d_p = d_n = 0.0
    eps = noise * rng.standard_normal(n)
    v = np.zeros(n)
    u = np.zeros(n)
    for k in range(n - 1):
        vk = v[k]
        tf = d_p if vk > omega else (d_n if vk < -omega else 0.0)
        if form == "velocity-loop":
            v[k + 1] = (p_d - K_d) * vk + K_d * v_ref[k] - b * (tf + tc[k]) + eps[k]
        else:
            u[k] = gain * (v_ref[k] - vk) + 0.3 * gain * v_ref[k] + damping * v_ref[k]
            v[k + 1] = p_d * vk + b * (u[k] - offset) - b * (tf + tc[k]) + eps[k]
    if form != "velocity-loop":
        u[n - 1] = gain * (v_ref[n - 1] - v[n - 1]) + 0.3 * gain * v_ref[n - 1] + damping * v_ref[n - 1]
    beta = physical_to_beta(form, Ts, inertia, damping, gain=gain if form == "velocity-loop" else None,
                            coulomb_pos=coulomb_pos, coulomb_neg=coulomb_neg, offset=offset, coulomb=coulomb)
    return Stream(form=form, Ts=Ts, t=t, v_meas=v, exogenous=v_ref if form == "velocity-loop" else u,
                  force=tc, beta=beta, f=-b * tc[:-1], b=b, omega=omega, coulomb=coulomb)


def shaker_stream(n: int = 2500, *, amplitude: float = 60.0, noise: float = 2e-5, seed: int = 0,
                  sweep: bool = False, **kw) -> Stream:
    """Thesis case-1-like trial: velocity loop, reversals, 55 Hz (+110 Hz) shaker force."""
    return simulate(n, force=lambda t: shaker_force(t, amplitude, sweep=sweep), noise=noise, seed=seed, **kw)
