"""Online β: the linear feed-drive parameters estimated jointly with the KRLS-T tracker.

Thesis future work (b), method §2 and §6. The model is the PL-ARX regression

    y(k) = v_m(k+1) = βᵀ z(k) + f(x(k)) + ε(k),      f ~ GP(0, s0² k),

with the disturbance ``f`` tracked by KRLS-T. Offline, PL-LSSVM estimates β by
generalised least squares with the GP covariance (method §4); this module is the
recursive counterpart, so the online β has the same meaning as the offline one.

Joint recursion (exact for λ = 1 and no pruning)
------------------------------------------------
KRLS-T's posterior mean is linear in its training targets and every other part
of its state (dictionary, ``Q``, ``Σ``, the gains) is independent of them. Train
the tracker on the residual ``r = y − βᵀz`` and keep, next to its mean ``μ``, a
*shadow* mean ``M_Z`` (one column per regressor, in the tracker's slots) trained
with the same gains on the regressors ``z`` themselves. Then for every β

    μ(β) = μ_y − M_Z β,         f̂(x) = qᵀμ(β),                              (1)

and the one-step prediction error of the joint model splits into GP innovations

    e(k) = y − β̂ᵀz − qᵀμ = ỹ − β̂ᵀz̃,     z̃(k) = z(k) − M_Zᵀ q   (ẑ: the GP's
    prediction of z from the past, exactly as the tracker predicts the residual),

    E[e²] = R + z̃ᵀ P z̃,         R = s0² σ_y²  (the tracker's predictive variance).

β given the data is then ordinary recursive least squares on ``(z̃, e)`` weighted
by ``1/R`` — the sequential form of PL-LSSVM's ``(Z̃ᵀA⁻¹Z̃)⁻¹ Z̃ᵀA⁻¹ y``. Per
trained sample, in information form (``Λ = P⁻¹``), after the tracker's update:

    Λ ← λ_β Λ + (1 − λ_β) Λ₀                        forgetting back to the prior     (2)
    g = Λ⁻¹ z̃,   S = R + z̃ᵀ g,   ν = e / √S          gain direction, innovation      (3)
    w = min(1, c/|ν|),  R_w = R / w,  S_w = R_w + z̃ᵀg  Huber weight                   (4)
    δ = g e / S_w,   β̂ ← β̂ + δ,   Λ ← Λ + z̃ z̃ᵀ / R_w   Kalman/RLS update             (5)
    μ ← μ − M_Z δ                                   re-express f̂ with the new β      (6)

and (5) is followed by a projection onto the physical set when β̂ leaves it (7).
Step (6) keeps (1) true, so the disturbance estimate is always the one that goes
with the current β̂: no memory of an old β error lingers in the tracker, and the
filtered and predicted disturbances stay unbiased while β adapts.

Why these choices
-----------------
* **Two time scales without chasing.** ``z̃`` is the part of ``z`` the GP cannot
  predict. What the kernel explains — slow variation within σ1, the periodic
  pattern with period ψ — carries no information about β, exactly as in the
  batch GLS: a constant feed (z̃ ≈ 0 for the pole and damping columns), a standstill,
  or a regressor that moves with the periodic disturbance teach β nothing, and
  β cannot absorb the disturbance. β learns from what is persistently correlated
  with the unpredictable part of z; the tracker keeps what varies fast or periodically.
* **Excitation awareness.** The update (5) moves β̂ only along ``Λ⁻¹ z̃`` and adds
  information only in the direction of ``z̃``; unexcited directions keep their
  estimate. In addition nothing is learned while ``|v_m(k)| ≤ Ω`` (the model has no
  static friction: at standstill the force balance is stiction, which the PL-ARX
  model does not describe), during the tracker's warm-up, on stale/restarted
  samples, or when adaptation is off.
* **No wind-up.** (2) forgets *information* toward the prior information ``Λ₀``
  with time constant ``T_β`` (``λ_β = exp(−Ts/T_β)``); the mean is not moved by
  forgetting. In a direction without excitation ``P`` relaxes to ``P₀`` — bounded
  by the prior, never growing without limit — and in an excited direction ``P``
  settles to the information of the last ~T_β seconds of data: ``P ≈ (Σ λ_β^i z̃z̃ᵀ/R)⁻¹``.
* **Drift rate trade-off.** ``T_β`` (``memory``) is the documented drift setting:
  a parameter drifting linearly at rate ``ṙ`` (relative per second) is followed with
  a lag of about ``ṙ·T_β`` (the mean age of the data), a step is followed with an
  error decaying like ``exp(−t/T_β)`` once excited, and the standard errors scale like
  ``1/√T_β``. Short memories track faster and report larger standard errors.
* **Prior.** ``P₀ = P_file + G diag((ρ θ₀)²) Gᵀ``: the model file's covariance of β
  plus a *drift allowance* ``ρ`` (relative, on the physical parameters θ₀ =
  inertia, damping, Coulomb ±, offset, mapped through the Jacobian ``G = ∂β/∂θ``).
  The model file's least-squares standard errors are far smaller than the
  parameter changes the monitor must follow (they assume white noise); ρ says how
  far parameters may plausibly move in the field (default 30 %). ``P₀`` is also the
  bound the covariance returns to without excitation.
* **Robustness.** The Huber weight (4) bounds the influence of one sample with a
  large normalised innovation (a disturbance edge the tracker did not foresee, a
  glitch) to ``c`` standard deviations (``c = 3``: 0.3 % of Gaussian samples are
  touched).
* **Physical constraints** (7): the estimate is projected in the ``Λ`` metric,
  ``β̂ ← β̂ − Λ⁻¹a (aᵀβ̂ − b)/(aᵀΛ⁻¹a)`` for each violated ``aᵀβ ≤ b`` (Simon & Chia
  2002, estimate projection), onto pole ``p_d ∈ [p_min, p_max]`` with
  ``p_max = 1 − 10⁻³(1 − p_d0)`` and ``p_min = 10⁻⁶``, input gain
  ``β1 ≥ 10⁻³ β1₀`` and Coulomb magnitudes ≥ 0. The output is always a physical drive.

Physical parameters and standard errors (delta method, method §2): with ``b`` the
force gain (``β1`` in force-input form, ``β1/K`` in velocity-loop form) and ``p`` the
pole, ``B = (1 − p)/b``, ``J = B Ts/(−ln p)``, ``d_p = β_sp/b``, ``c_n = −β_sn/b``,
``offset = −β_one/b`` and ``Cov θ = G P Gᵀ`` with the analytic Jacobian
``G = ∂θ/∂β`` (:func:`physical_se`). Without the loop gain ``K`` (velocity-loop)
``K = 1`` is used: the values are then ``J/K, B/K, d/K`` (and flagged so by the caller).

Wiring (stumpy-style): :func:`joint_arm` and :func:`joint_update` are drop-in
replacements for ``_krlst_core.arm`` / ``update`` in a compiled loop; they keep
``M_Z`` in step with the tracker (the tracker-side contract is listed in
:func:`joint_arm`). :class:`OnlineBeta` is the thin Python API (river-style
``learn_one`` / ``predict_one``), snapshot/restore as plain arrays.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from . import _krlst_core as core
from .feed_drive import FORMS

__all__ = [
    "BetaState",
    "new_beta_state",
    "joint_arm",
    "joint_update",
    "track_joint",
    "physical_se",
    "prior_covariance",
    "OnlineBeta",
    "JointStep",
    "PHYSICAL",
    "BOUT",
]

#: physical parameters reported by :func:`physical_se`, in this order (SI: kg, N·s/m, N, N, N, N)
PHYSICAL = ("inertia", "damping", "coulomb_pos", "coulomb_neg", "coulomb", "offset")
N_PHYS = len(PHYSICAL)

#: slots of ``par`` (float settings and small state)
(P_LAMBDA, P_HUBER, P_OMEGA, P_ENABLED, P_GAIN, P_TS, P_IV, P_VHAT, P_WARMUP) = range(9)
N_PAR = 9
#: slots of ``cnt`` (counters, column layout, instrument bookkeeping)
(C_UPDATES, C_GATED, C_PROJECTED, C_DOWNWEIGHTED, C_FORM, C_ISP, C_ISN, C_IONE, C_ARMS,
 C_VHAT_ARM, C_TRAINED) = range(11)
N_CNT = 11

#: named outputs of :func:`joint_update` (``bout``)
BOUT = ("residual", "innovation", "nu", "variance", "weight", "learned", "filtered", "zt_norm")
(B_RESID, B_INNOV, B_NU, B_VAR, B_WEIGHT, B_LEARNED, B_FILTERED, B_ZTN) = range(len(BOUT))
N_BOUT = len(BOUT)
#: rows of the scratch ``vec``
V_ZT, V_ZETA, V_G, V_TMP, V_BEFORE, V_X = range(6)


class BetaState(NamedTuple):
    """State of the online β estimator (plain arrays; Numba passes it as one argument).

    ``beta`` β̂ (p,); ``info`` Λ = Σ ζ̃z̃ᵀ/R + prior (p, p; symmetric without instruments);
    ``psi`` Ψ = Σ ζ̃ζ̃ᵀ R/R_w² + prior (the middle of the covariance ``P = Λ⁻¹ΨΛ⁻ᵀ``);
    ``info0`` Λ₀ = P₀⁻¹; ``beta0`` the model file's β; ``MZ`` the shadow GP means of the
    regressors in the tracker's slots (M+1, p); ``zhat`` ẑ = M_Zᵀq armed with the tracker;
    ``cons`` rows ``[a, b]`` of the constraints ``aᵀβ ≤ b``; ``par`` settings and the stored
    velocity prediction (:data:`P_LAMBDA` …); ``cnt`` counters and the column layout
    (:data:`C_UPDATES` …); ``lu``, ``piv``, ``vec`` scratch.
    """

    beta: np.ndarray
    info: np.ndarray
    psi: np.ndarray
    info0: np.ndarray
    beta0: np.ndarray
    MZ: np.ndarray
    zhat: np.ndarray
    cons: np.ndarray
    par: np.ndarray
    cnt: np.ndarray
    lu: np.ndarray
    piv: np.ndarray
    vec: np.ndarray


# ---------------------------------------------------------------------------------------------
# prior and constraints (Python, once)
# ---------------------------------------------------------------------------------------------
def _layout(names) -> tuple[str, int, int, int]:
    names = tuple(names)
    if len(names) < 2 or names[1] != "v_meas" or names[0] not in ("u", "v_ref"):
        raise ValueError(f"beta_names must start with ('u' | 'v_ref', 'v_meas'), got {names!r}")
    known = {"u", "v_ref", "v_meas", "-sigma_p", "-sigma_n", "one"}
    bad = [n for n in names if n not in known]
    if bad:
        raise ValueError(f"beta_names holds unknown column(s) {bad!r}; known: {sorted(known)}")
    form = "force-input" if names[0] == "u" else "velocity-loop"
    i_sp = names.index("-sigma_p") if "-sigma_p" in names else -1
    i_sn = names.index("-sigma_n") if "-sigma_n" in names else -1
    i_one = names.index("one") if "one" in names else -1
    if (i_sp < 0) != (i_sn < 0):
        raise ValueError("beta_names must hold both Coulomb columns or neither")
    return form, i_sp, i_sn, i_one


def _check_physical(form, beta) -> None:
    b1 = beta[0]
    pd = beta[1] if form == "force-input" else beta[0] + beta[1]
    if not (b1 > 0.0 and 0.0 < pd < 1.0):
        raise ValueError(f"β gives pole p_d = {pd:.6g} and input gain β1 = {b1:.6g}; a physical drive needs "
                         "0 < p_d < 1 and β1 > 0")


def _theta_of_beta(form, beta, Ts, gain, i_sp, i_sn, i_one) -> np.ndarray:
    """(J, B, d_p, c_n, offset) from β (zeros for absent columns)."""
    b = beta[0] if form == "force-input" else beta[0] / gain
    p = beta[1] if form == "force-input" else beta[0] + beta[1]
    B = (1.0 - p) / b
    J = B * Ts / (-math.log(p))
    dp = beta[i_sp] / b if i_sp >= 0 else 0.0
    cn = -beta[i_sn] / b if i_sn >= 0 else 0.0
    off = -beta[i_one] / b if i_one >= 0 else 0.0
    return np.array([J, B, dp, cn, off])


def _beta_of_theta(form, theta, Ts, gain, p_len, i_sp, i_sn, i_one) -> np.ndarray:
    J, B, dp, cn, off = theta
    pd = math.exp(-B * Ts / J)
    b = (1.0 - pd) / B
    beta = np.zeros(p_len)
    if form == "force-input":
        beta[0], beta[1] = b, pd
    else:
        Kd = gain * b
        beta[0], beta[1] = Kd, pd - Kd
    if i_sp >= 0:
        beta[i_sp] = b * dp
        beta[i_sn] = -b * cn
    if i_one >= 0:
        beta[i_one] = -b * off
    return beta


def prior_covariance(beta0, names, Ts: float, *, gain: float | None = None, beta_cov=None,
                     rel: float = 0.3) -> np.ndarray:
    """``P₀ = P_file + G diag((ρ θ₀)²) Gᵀ`` (module docstring, "Prior").

    ``beta_cov``: the model file's covariance of β (p×p), or its standard errors (p,),
    or None. ``rel`` = ρ, the relative drift allowance on inertia, damping, Coulomb
    and offset; the Coulomb/offset allowance is relative to the force scale
    ``max(d_p, c_n, |offset|, 1 N)`` so that a zero offset still may move.
    """
    form, i_sp, i_sn, i_one = _layout(names)
    beta0 = np.asarray(beta0, dtype=np.float64)
    p = beta0.size
    if p != len(names):
        raise ValueError(f"beta has {p} entries but beta_names has {len(names)}")
    if not (math.isfinite(rel) and 0.0 < rel <= 10.0):
        raise ValueError(f"prior allowance rel must be in (0, 10], got {rel!r}")
    g = 1.0 if gain is None else float(gain)
    _check_physical(form, beta0)
    theta0 = _theta_of_beta(form, beta0, Ts, g, i_sp, i_sn, i_one)
    fscale = max(abs(theta0[2]), abs(theta0[3]), abs(theta0[4]), 1.0)
    sd = rel * np.array([theta0[0], theta0[1], fscale, fscale, fscale])
    G = np.zeros((p, 5))
    for j in range(5):
        if (j in (2, 3) and i_sp < 0) or (j == 4 and i_one < 0):
            continue
        h = 1e-6 * max(abs(theta0[j]), 1e-3 * fscale if j >= 2 else abs(theta0[j]))
        tp, tm = theta0.copy(), theta0.copy()
        tp[j] += h
        tm[j] -= h
        G[:, j] = (_beta_of_theta(form, tp, Ts, g, p, i_sp, i_sn, i_one)
                   - _beta_of_theta(form, tm, Ts, g, p, i_sp, i_sn, i_one)) / (2 * h)
    P0 = G @ np.diag(sd * sd) @ G.T
    if beta_cov is not None:
        C = np.asarray(beta_cov, dtype=np.float64)
        if C.shape == (p,):
            C = np.diag(C * C)
        if C.shape != (p, p) or not np.all(np.isfinite(C)):
            raise ValueError(f"beta covariance must be finite, shape ({p},) (standard errors) or ({p}, {p})")
        P0 = P0 + 0.5 * (C + C.T)
    # a column no physical parameter maps to (none today) still gets a finite prior
    diag = np.diag(P0).copy()
    floor = 1e-12 * max(float(np.max(diag)), 1e-300)
    return P0 + np.diag(np.where(diag < floor, floor, 0.0))


def _constraints(form, beta0, i_sp, i_sn) -> np.ndarray:
    """Rows ``[a, b]`` of ``aᵀβ ≤ b``: pole in [1e-6, 1 − 1e-3(1 − p0)], β1 ≥ 1e-3 β1₀, Coulomb ≥ 0."""
    p = beta0.size
    pole_vec = np.zeros(p)
    if form == "force-input":
        pole_vec[1] = 1.0
    else:
        pole_vec[0] = pole_vec[1] = 1.0
    p0 = float(pole_vec @ beta0)
    rows = [np.r_[pole_vec, 1.0 - 1e-3 * (1.0 - p0)], np.r_[-pole_vec, -1e-6]]
    a = np.zeros(p)
    a[0] = -1.0
    rows.append(np.r_[a, -1e-3 * beta0[0]])
    if i_sp >= 0:
        a = np.zeros(p)
        a[i_sp] = -1.0          # β_sp = b d_p ≥ 0
        rows.append(np.r_[a, 0.0])
        a = np.zeros(p)
        a[i_sn] = 1.0           # β_sn = −b c_n ≤ 0
        rows.append(np.r_[a, 0.0])
    return np.array(rows)


def new_beta_state(beta0, names, Ts: float, budget: int, *, omega: float = 0.0, gain: float | None = None,
                   P0=None, memory: float = 10.0, huber: float = 3.0, instrument: bool = True,
                   enabled: bool = True, warmup: int | None = None) -> BetaState:
    """A fresh :class:`BetaState` for a tracker of budget ``budget`` (M): β̂ = β₀, P = P₀."""
    form, i_sp, i_sn, i_one = _layout(names)
    beta0 = np.asarray(beta0, dtype=np.float64).copy()
    p = beta0.size
    if P0 is None:
        P0 = prior_covariance(beta0, names, Ts, gain=gain)
    P0 = np.asarray(P0, dtype=np.float64)
    if P0.shape != (p, p):
        raise ValueError(f"P0 must have shape ({p}, {p}), got {P0.shape}")
    try:
        info0 = np.linalg.inv(np.linalg.cholesky(P0))
    except np.linalg.LinAlgError:
        raise ValueError("the prior covariance P0 is not positive definite") from None
    info0 = info0.T @ info0
    info0 = 0.5 * (info0 + info0.T)
    if not (math.isfinite(memory) and memory > 0):
        raise ValueError(f"memory must be a positive number of seconds, got {memory!r}")
    if not (math.isfinite(huber) and huber > 0):
        raise ValueError(f"huber must be a positive number of standard deviations, got {huber!r}")
    par = np.zeros(N_PAR)
    par[P_LAMBDA] = math.exp(-Ts / memory)
    par[P_HUBER] = huber
    par[P_OMEGA] = omega
    par[P_ENABLED] = 1.0 if enabled else 0.0
    par[P_GAIN] = 1.0 if gain is None else float(gain)
    par[P_TS] = Ts
    par[P_IV] = 1.0 if instrument else 0.0
    par[P_VHAT] = np.nan
    par[P_WARMUP] = budget if warmup is None else int(warmup)
    cnt = np.zeros(N_CNT, dtype=np.int64)
    cnt[C_FORM] = FORMS.index(form)
    cnt[C_ISP], cnt[C_ISN], cnt[C_IONE] = i_sp, i_sn, i_one
    cnt[C_VHAT_ARM] = -1
    return BetaState(beta=beta0, info=info0.copy(), psi=info0.copy(), info0=info0, beta0=beta0.copy(),
                     MZ=np.zeros((budget + 1, p)), zhat=np.zeros(p),
                     cons=_constraints(form, beta0, i_sp, i_sn), par=par, cnt=cnt,
                     lu=np.zeros((p, p)), piv=np.zeros(p, dtype=np.int64), vec=np.zeros((6, p)))


# ---------------------------------------------------------------------------------------------
# compiled step
# ---------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _lu_factor(A, LU, piv):
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
def _lu_solve(LU, piv, b, x):
    """x = A⁻¹ b from :func:`_lu_factor`."""
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
def _lu_solve_t(LU, piv, b, x):
    """x = A⁻ᵀ b from :func:`_lu_factor` (Aᵀ = Uᵀ Lᵀ P)."""
    p = LU.shape[0]
    for i in range(p):
        acc = b[i]
        for k in range(i):
            acc -= LU[k, i] * x[k]
        x[i] = acc / LU[i, i]
    for i in range(p - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, p):
            acc -= LU[k, i] * x[k]
        x[i] = acc
    for k in range(p - 1, -1, -1):
        m = piv[k]
        if m != k:
            t = x[k]
            x[k] = x[m]
            x[m] = t


@njit(cache=True, nogil=True)
def _cov_apply(bs, a, out, t1, t2):
    """``out = P a`` with ``P = Λ⁻¹ Ψ Λ⁻ᵀ`` (``bs.lu`` must hold the LU of Λ)."""
    p = a.shape[0]
    _lu_solve_t(bs.lu, bs.piv, a, t1)             # t1 = Λ⁻ᵀ a
    psi = bs.psi
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += psi[i, j] * t1[j]
        t2[i] = acc                               # t2 = Ψ Λ⁻ᵀ a
    _lu_solve(bs.lu, bs.piv, t2, out)             # out = Λ⁻¹ Ψ Λ⁻ᵀ a


@njit(cache=True, nogil=True)
def _project(bs, a, pa, t1, t2):
    """Estimate projection (7) onto ``aᵀβ ≤ b`` in the metric of ``P``; returns the number of projections."""
    beta = bs.beta
    cons = bs.cons
    p = beta.shape[0]
    count = 0
    for _sweep in range(3):
        moved = False
        for c in range(cons.shape[0]):
            viol = -cons[c, p]
            for j in range(p):
                viol += cons[c, j] * beta[j]      # aᵀβ − b
            if viol <= 0.0:
                continue
            for j in range(p):
                a[j] = cons[c, j]
            _cov_apply(bs, a, pa, t1, t2)         # P a
            den = 0.0
            for j in range(p):
                den += a[j] * pa[j]               # aᵀ P a
            if not den > 0.0:
                continue
            for j in range(p):
                beta[j] -= pa[j] * viol / den     # β ← β − P a (aᵀβ − b)/(aᵀ P a)
            moved = True
            count += 1
        if not moved:
            break
    return count


@njit(cache=True, nogil=True)
def joint_arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, out, bs):
    """Tracker steps 1–2 at ``x`` (``_krlst_core.arm``) and the same on the shadow means.

    ``M_Z ← √λ M_Z`` (the forgetting of μ, eq. 2.19) and ``ẑ = M_Zᵀ q`` (the GP's prediction
    of z at x, eq. 2.17 applied to the regressors), armed in ``bs.zhat``.

    Tracker-side contract (what this relies on in the core): after ``arm``, ``P[4]`` holds
    ``q = Q k_t`` over the slots ``[0, hw)`` and ``P[5]`` holds ``h = Σ q``; ``fst`` holds
    ``λ, ŷ, σ_f², σ_y²`` of the armed prediction; after ``update`` a pruned slot sits at
    ``order[n]``; ``μ`` and ``M_Z`` share the slots.
    """
    n = ist[core.I_N]
    core.arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, out)
    bs.cnt[C_ARMS] += 1
    MZ = bs.MZ
    zhat = bs.zhat
    p = zhat.shape[0]
    for j in range(p):
        zhat[j] = 0.0
    if n == 0:
        return
    hw = ist[core.I_HW]
    sl = math.sqrt(fst[core.F_LAM])
    q = P[4]
    for i in range(hw):
        qi = q[i]
        for j in range(p):
            m = sl * MZ[i, j]                     # M_Z ← √λ M_Z
            MZ[i, j] = m
            zhat[j] += qi * m                     # ẑ = M_Zᵀ q


@njit(cache=True, nogil=True)
def joint_update(X, Q, S, K, mu, order, ist, fst, P, W, z, y, gate, out, bs, bout):
    """Tracker steps 3–5 with the residual of the current β̂, the shadow update, then β (2)–(7).

    ``z``: the regressor ``z(k)`` of the armed sample; ``y = v_m(k+1)``; ``gate``: the
    caller allows learning β from this sample (chain intact, not stale); the warm-up
    (no learning during the first ``warmup`` trained samples, default the budget M) and
    the motion gate ``|v_m(k)| > Ω`` are applied here. ``out`` receives the
    tracker's step (``_krlst_core`` layout), ``bout`` the named outputs :data:`BOUT`
    (``filtered`` already re-expressed with the new β̂). Returns False (nothing done)
    when no prediction is armed.
    """
    if ist[core.I_ARMED] == 0:
        return False
    beta = bs.beta
    MZ = bs.MZ
    zhat = bs.zhat
    par = bs.par
    cnt = bs.cnt
    vec = bs.vec
    p = beta.shape[0]
    zt = vec[V_ZT]
    zeta = vec[V_ZETA]
    g = vec[V_G]
    tmp = vec[V_TMP]
    before = vec[V_BEFORE]
    xx = vec[V_X]
    n = ist[core.I_N]
    hw = ist[core.I_HW]
    s = order[n]                                  # the slot the new basis goes to
    sy2 = fst[core.F_SY2]
    sf2 = fst[core.F_SF2]
    s02 = fst[core.F_S02]
    h = P[5]
    base = 0.0
    for j in range(p):
        base += beta[j] * z[j]
        zt[j] = z[j] - zhat[j]                    # z̃ = z − ẑ
        zeta[j] = zt[j]
    # instrument for the measured velocity: the model's prediction v̂(k) made one step earlier
    # (independent of the noise of v_m(k) and v_m(k+1)); valid only right after the arm that followed it
    if par[P_IV] != 0.0 and cnt[C_VHAT_ARM] == cnt[C_ARMS] and math.isfinite(par[P_VHAT]):
        zeta[1] = par[P_VHAT] - zhat[1]           # ζ̃ = ζ − ẑ with ζ = z, v_m(k) → v̂(k)
    resid = y - base                              # r = y − β̂ᵀz (eq. 2.13)
    e = resid - fst[core.F_YM]                    # e = y − β̂ᵀz − f̂ = ỹ − β̂ᵀz̃
    par[P_VHAT] = base + fst[core.F_YM]           # v̂(k+1) = β̂ᵀz(k) + f̂(k), before seeing y
    cnt[C_VHAT_ARM] = cnt[C_ARMS] + 1
    # shadow means, the mean part of eq. 2.14 for every regressor column
    inv_sy2 = 1.0 / sy2
    for j in range(p):
        ej = zt[j] * inv_sy2
        for i in range(hw):
            MZ[i, j] += ej * h[i]                 # M_Z ← [M_Z; ẑ] + z̃/σ_y² [h; σ_f²]
        MZ[s, j] = zhat[j] + ej * sf2
    core.update(X, Q, S, K, mu, order, ist, fst, P, W, resid, out)
    if out[5] != 0.0:                             # reduced update: the new basis was dropped
        for j in range(p):
            MZ[s, j] = 0.0
    elif out[4] >= 0.0:                           # basis pruned: its slot now sits at order[n]
        sr = order[n]
        for j in range(p):
            MZ[sr, j] = 0.0
    filtered = out[6]
    R = s02 * sy2                                 # R = s0² σ_y²
    bout[B_RESID] = resid
    bout[B_INNOV] = e
    bout[B_VAR] = R
    bout[B_NU] = e / math.sqrt(R) if n > 0 and R > 0.0 else np.nan
    bout[B_WEIGHT] = 1.0
    bout[B_LEARNED] = 0.0
    bout[B_FILTERED] = filtered
    ztn = 0.0
    for j in range(p):
        ztn += zt[j] * zt[j]
    bout[B_ZTN] = math.sqrt(ztn)
    if par[P_ENABLED] == 0.0 or n == 0 or not R > 0.0:
        return True
    cnt[C_TRAINED] += 1
    omega = par[P_OMEGA]
    vk = z[1]
    learn = gate and cnt[C_TRAINED] > par[P_WARMUP] and (vk > omega or vk < -omega)
    info = bs.info
    psi = bs.psi
    if learn:
        # ---- (2) forgetting back to the prior N(β₀, P₀), on learning samples only ----------------
        lam = par[P_LAMBDA]
        info0 = bs.info0
        beta0 = bs.beta0
        for i in range(p):
            acc = 0.0
            for j in range(p):
                acc += info0[i, j] * (beta0[j] - beta[j])
                info[i, j] = lam * info[i, j] + (1.0 - lam) * info0[i, j]   # Λ ← λ_β Λ + (1−λ_β) Λ₀
                psi[i, j] = lam * psi[i, j] + (1.0 - lam) * info0[i, j]     # Ψ likewise
            tmp[i] = (1.0 - lam) * acc            # (1−λ_β) Λ₀ (β₀ − β̂)
    if not _lu_factor(info, bs.lu, bs.piv):
        return True
    for j in range(p):
        before[j] = beta[j]
    if learn:
        _lu_solve(bs.lu, bs.piv, tmp, g)
        for j in range(p):
            beta[j] += g[j]                       # β̂ ← Λ⁻¹(λ_β Λ_old β̂ + (1−λ_β) Λ₀ β₀)
            e -= zt[j] * g[j]                     # the innovation that goes with it
    # ---- (3) gain direction and the normalised innovation ---------------------------------------
    _lu_solve(bs.lu, bs.piv, zeta, g)             # g = Λ⁻¹ ζ̃
    ztg = 0.0
    for j in range(p):
        ztg += zt[j] * g[j]                       # z̃ᵀ Λ⁻¹ ζ̃ (= z̃ᵀ P z̃ without instrument)
    if ztg < 0.0:
        ztg = 0.0
    Sfull = R + ztg                               # S = R + z̃ᵀ P z̃
    nu = e / math.sqrt(Sfull)
    bout[B_VAR] = Sfull
    bout[B_NU] = nu
    if not learn:
        cnt[C_GATED] += 1
        return True
    # ---- (4) Huber weight, (5) update ------------------------------------------------------------
    c = par[P_HUBER]
    w = 1.0
    if abs(nu) > c:
        w = c / abs(nu)
        cnt[C_DOWNWEIGHTED] += 1
    Rw = R / w
    coef = e / (Rw + ztg)
    for j in range(p):
        beta[j] += g[j] * coef                    # β̂ ← β̂ + Λ⁻¹ζ̃ e / (R_w + z̃ᵀΛ⁻¹ζ̃)
    inv_rw = 1.0 / Rw
    meat = R * inv_rw * inv_rw
    for i in range(p):
        for j in range(p):
            info[i, j] += zeta[i] * zt[j] * inv_rw   # Λ ← Λ + ζ̃ z̃ᵀ / R_w
            psi[i, j] += zeta[i] * zeta[j] * meat    # Ψ ← Ψ + ζ̃ ζ̃ᵀ R / R_w²
    # ---- (7) physical constraints -------------------------------------------------------------
    viol = False
    cons = bs.cons
    for r in range(cons.shape[0]):
        a = -cons[r, p]
        for j in range(p):
            a += cons[r, j] * beta[j]
        if a > 0.0:
            viol = True
    if viol and _lu_factor(info, bs.lu, bs.piv):
        cnt[C_PROJECTED] += _project(bs, zeta, g, tmp, xx)
    # ---- (6) re-express the tracker's mean with the new β̂: μ ← μ − M_Z δ -------------------------
    for j in range(p):
        tmp[j] = beta[j] - before[j]              # δ
    hwn = ist[core.I_HW]
    for i in range(hwn):
        acc = 0.0
        for j in range(p):
            acc += MZ[i, j] * tmp[j]
        mu[i] -= acc
    # filtered f at x(k) with the new β̂: f_filt − z_filtᵀ δ, z_filt = ẑ + σ_f² z̃/σ_y²
    zf = 0.0
    for j in range(p):
        zf += (zhat[j] + sf2 * zt[j] * inv_sy2) * tmp[j]
    bout[B_FILTERED] = filtered - zf
    bout[B_WEIGHT] = w
    bout[B_LEARNED] = 1.0
    cnt[C_UPDATES] += 1
    return True


@njit(cache=True, nogil=True)
def regressor(form_force, i_sp, i_sn, i_one, omega, e, v, z):
    """``z(k)`` of method §2 into ``z``: ``[e, v, −σ_p(v), −σ_n(v), 1]`` with the columns present."""
    z[0] = e
    z[1] = v
    if i_sp >= 0:
        z[i_sp] = -1.0 if v > omega else 0.0
        z[i_sn] = -1.0 if v < -omega else 0.0
    if i_one >= 0:
        z[i_one] = 1.0


@njit(cache=True, nogil=True)
def track_joint(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, bs, t, e, v, gate,
                resume, out, bout, xbuf, zbuf, rows):
    """Offline loop over one uninterrupted stream (benchmarks, tests): at sample ``j ≥ 1`` update
    with ``(z(j−1), v(j))`` (β learns where ``gate[j]``), then arm at ``t[j]``.

    ``resume``: sample 0 is the last sample of the previous call, already armed (its row
    is left NaN). ``rows[j]`` (≥ 7 columns): ``[f_next, f_next_var, learned, nu, residual,
    filtered, weight]`` — the one-step prediction of ``f(j)`` (signal units) made at sample
    ``j``, then the outputs of the update that sample ``j`` completed.
    """
    p = zbuf.shape[0]
    form_force = bs.cnt[C_FORM] == 1
    i_sp, i_sn, i_one = bs.cnt[C_ISP], bs.cnt[C_ISN], bs.cnt[C_IONE]
    omega = bs.par[P_OMEGA]
    for j in range(t.shape[0]):
        r = rows[j]
        for c in range(r.shape[0]):
            r[c] = np.nan
        if j > 0:
            regressor(form_force, i_sp, i_sn, i_one, omega, e[j - 1], v[j - 1], zbuf)
            if joint_update(X, Q, S, K, mu, order, ist, fst, P, W, zbuf, v[j], gate[j], out, bs, bout):
                r[2] = bout[B_LEARNED]
                r[3] = bout[B_NU]
                r[4] = bout[B_RESID]
                r[5] = bout[B_FILTERED]
                r[6] = bout[B_WEIGHT]
        if j == 0 and resume:
            continue
        xbuf[0] = t[j]
        was_empty = ist[core.I_N] == 0
        joint_arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xbuf, out, bs)
        r[0] = out[0]
        r[1] = np.nan if was_empty else out[1] * fst[core.F_S02]
    return p


@njit(cache=True, nogil=True)
def physical_se(bs, theta, se, cov_work):
    """θ = (J, B, d_p, c_n, (d_p + c_n)/2, offset) of β̂ and their standard errors (delta method).

    ``cov_work`` (:data:`N_PHYS` + 2, p) scratch. Absent columns give NaN. Returns False when β̂ is not a
    physical drive (cannot happen after the projection; guards restored states).
    """
    beta = bs.beta
    p = beta.shape[0]
    form_force = bs.cnt[C_FORM] == 1
    i_sp, i_sn, i_one = bs.cnt[C_ISP], bs.cnt[C_ISN], bs.cnt[C_IONE]
    K = bs.par[P_GAIN]
    Ts = bs.par[P_TS]
    for k in range(N_PHYS):
        theta[k] = np.nan
        se[k] = np.nan
    if form_force:
        b = beta[0]
        pd = beta[1]
        db0 = 1.0
    else:
        b = beta[0] / K
        pd = beta[0] + beta[1]
        db0 = 1.0 / K
    if not (b > 0.0 and 0.0 < pd < 1.0):
        return False
    Lg = -math.log(pd)
    B = (1.0 - pd) / b
    J = B * Ts / Lg
    # gradients w.r.t. β (rows of G): ∂θ/∂β = ∂θ/∂b ∂b/∂β + ∂θ/∂p ∂p/∂β + direct terms
    G = cov_work[:N_PHYS]
    for k in range(N_PHYS):
        for j in range(p):
            G[k, j] = 0.0
    dp_d0 = 1.0 if not form_force else 0.0       # ∂p/∂β1 (velocity-loop p = β1 + β2)
    dp_d1 = 1.0                                   # ∂p/∂β2
    # rows: value, ∂/∂b, ∂/∂p
    theta[0] = J                                  # J = B Ts / (−ln p)
    G[0, 0] = (-J / b) * db0 + Ts * (-Lg / b + B / pd) / (Lg * Lg) * dp_d0
    G[0, 1] = Ts * (-Lg / b + B / pd) / (Lg * Lg) * dp_d1
    theta[1] = B                                  # B = (1 − p) / b
    G[1, 0] = (-B / b) * db0 + (-1.0 / b) * dp_d0
    G[1, 1] = (-1.0 / b) * dp_d1
    if i_sp >= 0:
        dpos = beta[i_sp] / b                     # d_p = β_sp / b
        cneg = -beta[i_sn] / b                    # c_n = −β_sn / b
        theta[2] = dpos
        G[2, 0] = (-dpos / b) * db0
        G[2, i_sp] = 1.0 / b
        theta[3] = cneg
        G[3, 0] = (-cneg / b) * db0
        G[3, i_sn] = -1.0 / b
        theta[4] = 0.5 * (dpos + cneg)
        for j in range(p):
            G[4, j] = 0.5 * (G[2, j] + G[3, j])
    if i_one >= 0:
        off = -beta[i_one] / b                    # offset = −β_one / b
        theta[5] = off
        G[5, 0] = (-off / b) * db0
        G[5, i_one] = -1.0 / b
    # Var θ_k = g_kᵀ P g_k,  P = Λ⁻¹ Ψ Λ⁻ᵀ
    if not _lu_factor(bs.info, bs.lu, bs.piv):
        return True
    x = cov_work[N_PHYS]
    gk = cov_work[N_PHYS + 1]                     # cov_work: (N_PHYS + 2, p)
    t1 = bs.vec[V_TMP]
    t2 = bs.vec[V_X]
    for k in range(N_PHYS):
        if not math.isfinite(theta[k]):
            continue
        for j in range(p):
            gk[j] = G[k, j]
        _cov_apply(bs, gk, x, t1, t2)
        v = 0.0
        for j in range(p):
            v += gk[j] * x[j]
        se[k] = math.sqrt(v) if v > 0.0 else 0.0
    return True


# ---------------------------------------------------------------------------------------------
# Python API
# ---------------------------------------------------------------------------------------------
class JointStep(NamedTuple):
    """What :meth:`OnlineBeta.learn_one` reports (signal units: m/s, (m/s)²).

    ``residual`` ``r = y − β̂ᵀz`` the tracker trained on; ``innovation`` ``e = r − f̂``;
    ``nu`` ``e/√S`` (the health input); ``variance`` ``S``; ``weight`` the Huber weight;
    ``learned`` β was updated; ``filtered`` the disturbance at the trained x given the new
    β̂; ``removed``/``reduced`` as :class:`kernels.krlst.Step`.
    """

    residual: float
    innovation: float
    nu: float
    variance: float
    weight: float
    learned: bool
    filtered: float
    removed: int
    reduced: bool


class OnlineBeta:
    """Online β joined to a KRLS-T tracker (module docstring); river-style API.

    Parameters
    ----------
    tracker : kernels.KRLST
        The disturbance tracker (fresh: nothing learned yet); its forgetting, budget and kernel
        define what the disturbance may explain. This object drives it from now on.
    beta0, names : sequence
        Model-file β and its column names (:func:`kernels.feed_drive.beta_names`, the
        constant ``one`` may end them in both forms).
    Ts : float
        Sampling period (s).
    omega : float
        Coulomb dead band Ω (m/s): no learning while ``|v_m(k)| ≤ Ω``.
    gain : float, optional
        Velocity-loop gain K (N·s/m); without it physical values are ``J/K, B/K, d/K``.
    beta_cov : array, optional
        Model-file covariance (p×p) or standard errors (p,) of β.
    allowance : float
        ρ, the relative drift allowance of the prior (default 0.3).
    memory : float
        T_β (s of learning samples), the forgetting time constant (default 10 s).
    huber : float
        Huber threshold c (standard deviations, default 3).
    instrument : bool
        Use the model's one-step velocity prediction as the instrument of the measured
        velocity (default True: removes the bias of noise that the velocity loop feeds back).
    enabled : bool
        False: β stays at β₀ (the joint bookkeeping still runs; ``nu`` is the tracker's).
    warmup : int, optional
        Trained samples before β learns (default: the tracker's budget).

    Examples
    --------
    >>> ob = OnlineBeta(KRLST(LocallyPeriodic(1.2, 0.495, 1/55), gamma=300, forgetting=0.998, budget=100),
    ...                 beta0, ("v_ref", "v_meas", "-sigma_p", "-sigma_n"), 1/333, omega=5e-4, gain=83300)
    >>> f_next, f_var = ob.predict_one(t[0])          # arm at x(0)
    >>> step = ob.learn_one(z0, v_meas[1])             # residual of step 0 known: learn
    """

    def __init__(self, tracker, beta0, names, Ts: float, *, omega: float = 0.0, gain: float | None = None,
                 beta_cov=None, allowance: float = 0.3, memory: float = 10.0, huber: float = 3.0,
                 instrument: bool = True, enabled: bool = True, warmup: int | None = None):
        from .krlst import KRLST

        if not isinstance(tracker, KRLST):
            raise ValueError(f"tracker must be a kernels.KRLST, got {type(tracker).__name__}")
        if tracker.size:
            raise ValueError("the tracker must be fresh: the shadow means start with an empty dictionary")
        if not (math.isfinite(Ts) and Ts > 0):
            raise ValueError(f"Ts must be a positive number of seconds, got {Ts!r}")
        if not (math.isfinite(omega) and omega >= 0):
            raise ValueError(f"omega must be a finite number ≥ 0 (m/s), got {omega!r}")
        if gain is not None and not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"gain must be None or a positive number (N·s/m), got {gain!r}")
        self.names = tuple(names)
        self.form = _layout(self.names)[0]
        self.Ts = float(Ts)
        self.gain = gain
        self.tracker = tracker
        self.P0 = prior_covariance(beta0, self.names, Ts, gain=gain, beta_cov=beta_cov, rel=allowance)
        self.state = new_beta_state(beta0, self.names, Ts, tracker.budget, omega=omega, gain=gain, P0=self.P0,
                                    memory=memory, huber=huber, instrument=instrument, enabled=enabled,
                                    warmup=warmup)
        self._xbuf = np.zeros(1)
        self._out = np.zeros(core.N_OUT)
        self._bout = np.zeros(N_BOUT)
        self._z = np.zeros(len(self.names))
        self._cw = np.zeros((N_PHYS + 2, len(self.names)))
        self.prior_se = self._physical_of(self.P0)[1]

    # ------------------------------------------------------------------ state views
    @property
    def beta(self) -> np.ndarray:
        """β̂ (a copy)."""
        return self.state.beta.copy()

    @property
    def covariance(self) -> np.ndarray:
        """``P = Λ⁻¹ Ψ Λ⁻ᵀ`` (a copy)."""
        Li = np.linalg.inv(self.state.info)
        return Li @ self.state.psi @ Li.T

    @property
    def counters(self) -> dict[str, int]:
        c = self.state.cnt
        return {"updates": int(c[C_UPDATES]), "gated": int(c[C_GATED]), "projected": int(c[C_PROJECTED]),
                "downweighted": int(c[C_DOWNWEIGHTED]), "trained": int(c[C_TRAINED])}

    def _physical_of(self, P) -> tuple[np.ndarray, np.ndarray]:
        st = self.state
        probe = st._replace(info=np.linalg.inv(P), psi=np.linalg.inv(P), lu=st.lu.copy(), vec=st.vec.copy())
        theta, se = np.zeros(N_PHYS), np.zeros(N_PHYS)
        physical_se(probe, theta, se, self._cw)
        return theta, se

    def physical(self) -> dict[str, tuple[float, float]]:
        """``{name: (value, standard error)}`` per :data:`PHYSICAL` (delta method; NaN when the model
        has no such column). Without the loop gain (velocity-loop) the values are over K."""
        theta, se = np.zeros(N_PHYS), np.zeros(N_PHYS)
        physical_se(self.state, theta, se, self._cw)
        return {k: (float(a), float(b)) for k, a, b in zip(PHYSICAL, theta, se)}

    # ------------------------------------------------------------------ steps
    def regressor(self, exo: float, v: float) -> np.ndarray:
        """``z(k)`` for the command ``exo`` (v_ref or u) and measured velocity ``v`` (a copy)."""
        c = self.state.cnt
        regressor(c[C_FORM] == 1, c[C_ISP], c[C_ISN], c[C_IONE], self.state.par[P_OMEGA], float(exo), float(v), self._z)
        return self._z.copy()

    def predict_one(self, x) -> tuple[float, float]:
        """Arm the tracker at ``x`` (forget, predict): the one-step prediction of the disturbance at
        ``x`` given β̂ and its variance (signal units; NaN variance before the first sample)."""
        self._xbuf[0] = float(x)
        if not math.isfinite(self._xbuf[0]):
            raise ValueError(f"x must be finite, got {x!r}")
        was_empty = self.tracker.size == 0
        joint_arm(*self.tracker.core_arrays(self._xbuf), self._xbuf, self._out, self.state)
        var = math.nan if was_empty else float(self._out[1]) * self.tracker.s02
        return float(self._out[0]), var

    def learn_one(self, z, y: float, *, gate: bool = True) -> JointStep:
        """Learn from the regressor ``z`` of the armed sample and ``y = v_m(k+1)``."""
        za = np.ascontiguousarray(z, dtype=np.float64)
        if za.shape != (len(self.names),) or not np.all(np.isfinite(za)) or not math.isfinite(y):
            raise ValueError(f"z must be {len(self.names)} finite values and y finite; got z={z!r}, y={y!r}")
        if not self.tracker.armed:
            raise RuntimeError("learn_one needs an armed prediction: call predict_one(x) first")
        arrs = self.tracker.core_arrays(self._xbuf)
        joint_update(*arrs[3:13], za, float(y), bool(gate), self._out, self.state, self._bout)
        b = self._bout
        return JointStep(float(b[B_RESID]), float(b[B_INNOV]), float(b[B_NU]), float(b[B_VAR]), float(b[B_WEIGHT]),
                         bool(b[B_LEARNED]), float(b[B_FILTERED]), int(self._out[4]), bool(self._out[5]))

    def track(self, t, exo, v, gate=None) -> dict[str, np.ndarray]:
        """One uninterrupted stream in one compiled loop (the monitor's order: at sample ``j ≥ 1`` learn
        from ``(z(j−1), v(j))``, then arm at ``t[j]``). Continues a stream when the tracker is armed
        (then ``t[0]`` must be the armed sample). Returns ``f_next`` (prediction of f(j) made at j),
        ``f_next_var``, ``learned``, ``nu``, ``residual``, ``filtered``, ``weight`` per sample."""
        t = np.ascontiguousarray(t, dtype=np.float64)
        exo = np.ascontiguousarray(exo, dtype=np.float64)
        v = np.ascontiguousarray(v, dtype=np.float64)
        n = t.size
        if exo.shape != (n,) or v.shape != (n,):
            raise ValueError(f"t, exo, v must have the same length; got {t.shape}, {exo.shape}, {v.shape}")
        for name, a in (("t", t), ("exo", exo), ("v", v)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite; element {int(np.argmax(~np.isfinite(a)))} is not")
        g = np.ones(n, dtype=np.bool_) if gate is None else np.ascontiguousarray(gate, dtype=np.bool_)
        rows = np.zeros((n, 7))
        resume = self.tracker.armed
        track_joint(*self.tracker.core_arrays(self._xbuf), self.state, t, exo, v, g, resume, self._out,
                    self._bout, self._xbuf, self._z, rows)
        return {"f_next": rows[:, 0], "f_next_var": rows[:, 1], "learned": rows[:, 2] == 1.0, "nu": rows[:, 3],
                "residual": rows[:, 4], "filtered": rows[:, 5], "weight": rows[:, 6]}

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, np.ndarray]:
        """The β state as plain arrays (copies); persist it together with ``tracker.snapshot()``
        taken at the same moment (the shadow means live in the tracker's slots)."""
        return {f"beta.{k}": np.array(v, copy=True) for k, v in self.state._asdict().items()}

    def restore(self, snap: dict, tracker) -> None:
        """Continue from :meth:`snapshot` with the tracker restored from the same moment."""
        parts = {}
        for k, cur in self.state._asdict().items():
            key = f"beta.{k}"
            if key not in snap:
                raise ValueError(f"beta snapshot is missing {key!r}")
            arr = np.array(snap[key], dtype=cur.dtype, copy=True)
            if arr.shape != cur.shape:
                raise ValueError(f"beta snapshot {key!r} has shape {arr.shape}, expected {cur.shape} "
                                 "(another model or budget)")
            if arr.dtype.kind == "f" and k not in ("par",) and not np.all(np.isfinite(arr)):
                raise ValueError(f"beta snapshot {key!r} holds non-finite values")
            parts[k] = arr
        if tracker.budget + 1 != parts["MZ"].shape[0]:
            raise ValueError("the tracker's budget does not match the beta snapshot")
        self.state = BetaState(**parts)
        self.tracker = tracker
