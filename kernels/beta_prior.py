"""The online β's prior, constraints and fresh state (Python, once per model).

The prior ``N(β₀, P₀)`` with ``P₀ = P_file + G diag((ρθ₀)²) Gᵀ`` (``G = ∂β/∂θ`` at β₀, θ the physical
parameters), the constraints of a physical drive (7) and the forgetting operators of (2); equation
numbers refer to :mod:`kernels.beta_tracker`.
"""

from __future__ import annotations

import math

import numpy as np

from .beta_layout import (
    C_ARMS,
    C_DIR,
    C_DOWNWEIGHTED,
    C_GATED,
    C_PROJECTED,
    C_QUIET,
    C_REJECTED,
    C_SEEN,
    C_SINCE_FORGET,
    C_SINCE_REBASE,
    C_UPDATES,
    C_VHAT_ARM,
    C_VSIM_ARM,
    FAST_MEMORY,
    FORGET_EVERY,
    L_FORM,
    L_IONE,
    L_ISN,
    L_ISP,
    L_REBASE,
    LAYOUT,
    MIN_SPEED_MAX,
    P_ENABLED,
    P_FASTLAM,
    P_GAIN,
    P_HOLD,
    P_HUBER,
    P_IV,
    P_MINSPEED,
    P_OMEGA,
    P_REJECT,
    P_TS,
    P_WARMUP,
    REBASE_EVERY,
    S_SCALE,
    SETTINGS_FIELDS,
    STATE_FIELDS,
    BetaState,
    beta_state_views,
)
from .feed_drive import FORMS


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


def _jacobian(form, beta0, Ts, g, i_sp, i_sn, i_one) -> tuple[np.ndarray, np.ndarray, float]:
    """``G = ∂β/∂θ`` at β₀ (p×5, central differences; zero columns for the parameters the model has
    no column of), θ₀ = (J, B, d_p, c_n, offset) and the friction scale ``max(d_p, c_n, |offset|, 1 N)``."""
    p = beta0.size
    theta0 = _theta_of_beta(form, beta0, Ts, g, i_sp, i_sn, i_one)
    fscale = max(abs(theta0[2]), abs(theta0[3]), abs(theta0[4]), 1.0)
    G = np.zeros((p, 5))
    for j in _present(i_sp, i_one):
        h = 1e-6 * max(abs(theta0[j]), 1e-3 * fscale if j >= 2 else abs(theta0[j]))
        tp, tm = theta0.copy(), theta0.copy()
        tp[j] += h
        tm[j] -= h
        G[:, j] = (_beta_of_theta(form, tp, Ts, g, p, i_sp, i_sn, i_one)
                   - _beta_of_theta(form, tm, Ts, g, p, i_sp, i_sn, i_one)) / (2 * h)
    return G, theta0, fscale


def _present(i_sp, i_one) -> list[int]:
    """Indices into θ = (J, B, d_p, c_n, offset) of the parameters the model's columns carry (one per column)."""
    return [0, 1] + ([2, 3] if i_sp >= 0 else []) + ([4] if i_one >= 0 else [])


def parameter_basis(form, beta0, Ts, g, i_sp, i_sn, i_one) -> np.ndarray:
    """``[G, G⁻¹]`` (2, p, p): the columns of ``G = ∂β/∂θ`` at β₀ are the directions in β of the
    physical parameters the model has (inertia first), the basis of the forgetting (2)."""
    G = _jacobian(form, beta0, Ts, g, i_sp, i_sn, i_one)[0][:, _present(i_sp, i_one)]
    cond = math.inf
    rows = np.abs(G).max(axis=1)
    if np.all(np.isfinite(G)) and np.all(rows > 0.0):
        cols = np.abs(G / rows[:, None]).max(axis=0)
        if np.all(cols > 0.0):  # scale-free (row and column equilibrated): ~1–3 for drives
            cond = np.linalg.cond(G / rows[:, None] / cols)
    if not cond < 1e8:
        raise ValueError(f"β₀ gives a singular map to the physical parameters (∂β/∂θ, condition {cond:.3g}); "
                         "cannot adapt it")
    return np.stack([G, np.linalg.inv(G)])


def forgetting_operators(basis: np.ndarray, lam: float, lam_j: float) -> np.ndarray:
    """``[T, S]`` (2, p, p) of the forgetting (2) over ``m`` learning samples, from ``basis`` =
    :func:`parameter_basis` and the factors ``lam`` = λ_β^m (damping, Coulomb, offset) and ``lam_j`` =
    λ_J^m (inertia, θ_0): ``T = G diag(√λ_i) G⁻¹``, ``S = G diag(√(1 − λ_i)) G⁻¹``."""
    G, Gi = basis
    lams = np.full(G.shape[0], lam)
    lams[0] = lam_j
    return np.stack([G @ np.diag(np.sqrt(lams)) @ Gi, G @ np.diag(np.sqrt(1.0 - lams)) @ Gi])


def prior_covariance(beta0, names, Ts: float, *, gain: float | None = None, beta_cov=None,
                     rel: float = 0.3) -> np.ndarray:
    """``P₀ = P_file + G diag((ρ θ₀)²) Gᵀ`` (:mod:`kernels.beta_tracker`).

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
    G, theta0, fscale = _jacobian(form, beta0, Ts, g, i_sp, i_sn, i_one)
    sd = rel * np.array([theta0[0], theta0[1], fscale, fscale, fscale])
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



def new_beta_buffers(beta0, names, Ts: float, budget: int, *, omega: float = 0.0, gain: float | None = None,
                     P0=None, memory: float = 5.0, inertia_memory: float | None = 10.0, huber: float = 3.0,
                     instrument: bool = True, enabled: bool = True, warmup: int | None = None,
                     rebase_every: int = REBASE_EVERY, reject: float | None = None,
                     hold: float = 0.0, min_speed: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The two base buffers ``(float64, int64)`` of a fresh :class:`BetaState` for a tracker of budget
    ``budget`` (M): β̂ = β₀, P = P₀. ``rebase_every = 0``: never re-base (the *track* mode).
    ``memory``: T_β of the friction parameters (damping, Coulomb, offset), ``inertia_memory``
    the inertia's (None: the same), both in s of learning samples."""
    form, i_sp, i_sn, i_one = _layout(names)
    beta0 = np.asarray(beta0, dtype=np.float64).copy()
    p = beta0.size
    if p != len(tuple(names)):
        raise ValueError(f"beta has {p} entries but beta_names has {len(tuple(names))}")
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
    inertia_memory = memory if inertia_memory is None else inertia_memory
    if not (math.isfinite(inertia_memory) and inertia_memory > 0):
        raise ValueError(f"inertia_memory must be a positive number of seconds, got {inertia_memory!r}")
    if not (math.isfinite(huber) and huber > 0):
        raise ValueError(f"huber must be a positive number of standard deviations, got {huber!r}")
    if reject is not None and not (math.isfinite(reject) and reject > huber):
        raise ValueError(f"reject must be None (off) or a number of standard deviations > huber ({huber}), "
                         f"got {reject!r}")
    if not (math.isfinite(hold) and 0.0 <= hold <= 60.0):
        raise ValueError(f"hold must be in [0, 60] s, got {hold!r}")
    if not (math.isfinite(min_speed) and 0.0 <= min_speed <= MIN_SPEED_MAX):
        raise ValueError(f"min_speed must be in [0, {MIN_SPEED_MAX:g}] m/s, got {min_speed!r}")
    if isinstance(rebase_every, bool) or not isinstance(rebase_every, int) or rebase_every < 0:
        raise ValueError(f"rebase_every must be an integer ≥ 0 (0: never), got {rebase_every!r}")
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 1:
        raise ValueError(f"budget must be an integer ≥ 1, got {budget!r}")
    cons = _constraints(form, beta0, i_sp, i_sn)
    cap = budget + 1
    fbuf, ibuf = LAYOUT.new_buffers(p=p, cap=cap, ncons=cons.shape[0])
    bs = beta_state_views(fbuf, ibuf)
    par = bs.par
    par[P_HUBER] = huber
    par[P_OMEGA] = omega
    par[P_ENABLED] = 1.0 if enabled else 0.0
    par[P_GAIN] = 1.0 if gain is None else float(gain)
    par[P_TS] = Ts
    par[P_IV] = 1.0 if instrument else 0.0
    par[P_WARMUP] = budget if warmup is None else int(warmup)
    par[P_REJECT] = 1e300 if reject is None else reject
    par[P_HOLD] = round(hold / Ts)
    par[P_MINSPEED] = min_speed
    bs.lay[L_FORM] = FORMS.index(form)
    bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE] = i_sp, i_sn, i_one
    bs.lay[L_REBASE] = rebase_every
    bs.beta0[:] = beta0
    bs.info0[:] = info0
    bs.cons[:] = cons
    basis = parameter_basis(form, beta0, Ts, par[P_GAIN], i_sp, i_sn, i_one)
    bs.forget[:] = forgetting_operators(basis, math.exp(-Ts / memory) ** FORGET_EVERY,
                                        math.exp(-Ts / inertia_memory) ** FORGET_EVERY)
    bs.dirj[:] = basis[0][:, 0]                 # ∂β/∂J: the inertia is the first physical parameter
    par[P_FASTLAM] = math.exp(-Ts / FAST_MEMORY)
    bs.beta[:] = beta0
    bs.beta_trk[:] = beta0
    bs.cov[:] = P0
    bs.psi[:] = info0
    bs.sst[S_SCALE] = 1.0
    bs.cnt[C_VHAT_ARM] = -1                     # no velocity prediction stored yet
    bs.cnt[C_VSIM_ARM] = -1                     # no simulated velocity yet
    return fbuf, ibuf


def validate_beta_state(bs: BetaState, fresh: BetaState, occupied: np.ndarray) -> None:
    """Raise ``ValueError`` (naming the field) unless ``bs`` — e.g. read from a state file — holds a
    state the compiled code can use: the settings equal ``fresh``'s (a fresh state of the same
    model and settings), every number finite, β̂ a physical drive (the constraints hold), ``P``
    positive on its diagonal and at most 100× the prior's, the shadow means of the free slots of
    the tracker (``occupied[s]`` = 0) zero and the others of a plausible size, the scale in
    (0, 1], the counters possible."""
    for name in SETTINGS_FIELDS + ("layout",):
        if not np.array_equal(getattr(bs, name), getattr(fresh, name)):
            raise ValueError(f"beta {name!r} differs from this model's settings")
    for name in STATE_FIELDS:
        if not np.all(np.isfinite(getattr(bs, name))):
            raise ValueError(f"beta {name!r} holds non-finite values")
    p = bs.beta.size
    viol = bs.cons[:, :p] @ bs.beta - bs.cons[:, p]
    if np.any(viol > 1e-9 * (1.0 + np.abs(bs.cons[:, p]))):
        raise ValueError("beta 'beta' is not a physical drive (a constraint of the pole, gain or Coulomb is violated)")
    with np.errstate(over="ignore", invalid="ignore"):  # a damaged file: inf/NaN fail the test below
        P = bs.cov @ bs.psi @ bs.cov.T
    P0 = np.linalg.inv(bs.info0)
    d, d0 = np.diag(P), np.diag(P0)
    if not (np.all(d > 0.0) and np.all(d <= 100.0 * d0)):
        raise ValueError("beta 'cov'/'psi': the covariance of β is not positive or far beyond its prior")
    occ = np.asarray(occupied, dtype=bool)[: bs.MZ.shape[0]]
    if occ.shape[0] != bs.MZ.shape[0]:
        raise ValueError("beta 'MZ' does not match the tracker's slots")
    if np.any(bs.MZ[~occ] != 0.0):
        raise ValueError("beta 'MZ' has entries in free slots of the tracker")
    if not 0.0 < bs.sst[S_SCALE] <= 1.0:
        raise ValueError(f"beta 'sst' scale is {float(bs.sst[S_SCALE])!r}, expected in (0, 1]")
    if np.max(np.abs(bs.MZ), initial=0.0) * bs.sst[S_SCALE] > 1e9 or np.max(np.abs(bs.zhat), initial=0.0) > 1e9:
        raise ValueError("beta 'MZ'/'zhat': implausibly large shadow means")
    c = bs.cnt
    if np.any(c[[C_UPDATES, C_GATED, C_PROJECTED, C_DOWNWEIGHTED, C_ARMS, C_SEEN, C_SINCE_REBASE, C_SINCE_FORGET,
                 C_QUIET, C_REJECTED]] < 0) or c[C_VHAT_ARM] < -1 or c[C_VHAT_ARM] > c[C_ARMS] + 1 \
            or c[C_VSIM_ARM] < -1 or c[C_VSIM_ARM] > c[C_ARMS] + 1:
        raise ValueError("beta 'cnt' holds impossible counters")
    if c[C_DIR] not in (-1, 0, 1):
        raise ValueError("beta 'cnt': the previous sample's direction of motion is not −1, 0 or 1")
    if c[C_SINCE_FORGET] >= FORGET_EVERY or (bs.lay[L_REBASE] > 0 and c[C_SINCE_REBASE] >= bs.lay[L_REBASE]):
        raise ValueError("beta 'cnt': a batched step is overdue (impossible)")

