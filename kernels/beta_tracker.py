"""Online β: the linear feed-drive parameters estimated jointly with the KRLS-T tracker.

Thesis future work (b), method §2 and §6. The model is the PL-ARX regression

    y(k) = v_m(k+1) = βᵀ z(k) + f(x(k)) + ε(k),      f ~ GP(0, s0² k),

with the disturbance ``f`` tracked by KRLS-T. Offline, PL-LSSVM estimates β by
generalised least squares with the GP covariance (method §4); this module is the
recursive counterpart with the *tracker's* GP (its kernel, γ, forgetting λ, budget M).

Joint recursion (exact for λ = 1 and no pruning)
------------------------------------------------
KRLS-T's posterior mean is linear in its training targets and every other part
of its state (dictionary, ``Q``, ``Σ``, the gains) is independent of them. Next to
the tracker's mean ``μ`` (trained on the residual) keep a *shadow* mean ``M_Z`` —
one column per regressor, in the tracker's slots — trained with the same gains on
the regressors ``z`` themselves (forget ``√λ``, add ``z̃/σ_y² [h; σ_f²]``, drop the
pruned slot). Then, for every β,

    μ(β) = μ_y − M_Z β,          f̂(x | β) = qᵀμ(β)                                   (1)

and the one-step prediction error of the joint model is a difference of GP innovations

    e(k) = y − β̂ᵀz − f̂(x | β̂) = ỹ − β̂ᵀz̃,    z̃ = z − ẑ,  ẑ = M_Zᵀq  (the GP's prediction
    of z from the past, made exactly as the tracker predicts the residual),
    E[e²] = R + z̃ᵀPz̃,   R = s0² σ_y²  (the tracker's predictive variance, eq. 2.17/2.20).

β given the data is recursive least squares on ``(z̃, e)`` weighted by ``1/R`` — the
sequential form of PL-LSSVM's ``(Z̃ᵀA⁻¹Z̃)⁻¹ Z̃ᵀA⁻¹ y`` (tested against that dense
formula). Per trained sample, after the tracker's own update (Λ = information, kept as
``Λ⁻¹`` by rank-one updates; ζ̃ the instrument, = z̃ without it):

    g = Λ⁻¹ζ̃,  s = z̃ᵀΛ⁻¹ζ̃ (≥ 0),  S = R + s,  ν = e/√S      gain direction, innovation  (3)
    z̃, ζ̃ ← x − (xᵀd/3) d,  d = e_sp + e_sn + e_one          off the rest direction      (3')
      (in the update only, when the Coulomb columns and ``one`` are present; ν keeps z̃)
    w = min(1, c/|ν|),  R_w = R/w                           Huber weight                (4)
    β̂ ← β̂ + g e/(R_w + s),  Λ⁻¹ ← Λ⁻¹ − g (z̃ᵀΛ⁻¹)/(R_w + s)   RLS update (Λ += ζ̃z̃ᵀ/R_w) (5)
    Ψ ← Ψ + ζ̃ζ̃ᵀ R/R_w²,   P = Λ⁻¹ Ψ Λ⁻ᵀ                    covariance (sandwich)       (5')
    every m = 16 learning samples, per physical parameter θ_i (G = ∂β/∂θ at β₀; λ_i = λ_J for
    the inertia, λ_β for damping, Coulomb and offset; T = G diag(√λ_i^m) G⁻¹,
    S = G diag(√(1 − λ_i^m)) G⁻¹):
    Λ ← TᵀΛT + SᵀΛ₀S,  Ψ likewise,                              forgetting back to the
    β̂ ← β̂ + Λ⁻¹ SᵀΛ₀S (β₀ − β̂)                               prior N(β₀, P₀)             (2)
    (with λ_J = λ_β: Λ ← λ_β^m Λ + (1 − λ_β^m) Λ₀, the plain exponential forgetting)
    projection onto the physical set when β̂ leaves it                                   (7)
    μ ← μ − M_Z (β̂ − β_trk),  β_trk ← β̂   every 64 samples;  in between every prediction
    and residual is corrected exactly by ẑᵀ(β̂ − β_trk)                                   (6)

(6) keeps (1) true, so the published disturbance (``f_next`` = ŷ − ẑᵀ(β̂ − β_trk), the
filtered ``f``) always goes with the current β̂: no memory of an old β error lingers in
the tracker, and the disturbance estimate stays unbiased while β adapts. The lazy
re-basing, the scale factor that carries the forgetting of ``M_Z`` (``√λ`` per arm on one
scalar instead of the matrix) and the batched forgetting (2) save work (one read and one
update pass over ``M_Z`` per sample). They are exact for the published values; what
differs from a per-sample re-basing is that the tracker's own ``s0²`` and pruning choice
see the residual of a β at most 64 samples old.

Why these choices
-----------------
* **Two time scales without chasing.** ``z̃`` is the part of ``z`` the GP cannot
  predict. What the kernel explains — slow variation within σ1 and the memory of the
  forgetting, the periodic pattern with period ψ — carries no information about β,
  exactly as in the batch GLS: a constant feed (z̃ ≈ 0), a standstill, or a regressor
  that moves with the periodic disturbance teach β nothing. β learns what is
  persistently correlated with the unpredictable part of z; the tracker keeps what
  varies fast or periodically. The price: a drive quantity the kernel can explain
  (a slowly varying force ∝ v, a Coulomb step the tracker absorbs within a sample) is
  weakly determined — its standard error says so.
* **Excitation awareness.** (5) moves β̂ only along ``Λ⁻¹ζ̃`` and adds information only
  in the direction of ``z̃``: an unexcited direction keeps its estimate (exactly, with
  an uncorrelated prior). Nothing is learned while ``|v_m(k)| ≤ Ω`` (the model has no
  static friction: at standstill the force balance is stiction), nor from the first sample of a
  run of motion (out of the dead band or after a reversal: the Coulomb column steps there, which
  the tracker could not foresee, while the drive's real force does not step — stiction before,
  presliding after; learning from that sample reads the step as "less Coulomb friction", measured
  −80 % at 15–20 standard errors on the EMPS drive with its correct model), nor while
  ``|v_m(k)| ≤ min_speed`` when identification found that the friction law does not hold at low
  speed (:mod:`kernels.low_speed`: a Stribeck rise or a gradual Coulomb onset; the samples around
  reversals and starts carry large innovations, and learning from them read the departure as
  friction — EMPS with its own model: damping +25 %, Coulomb −11 % against least squares; with
  min_speed 0.035 m/s damping −8 % ± 20 % (not determined), Coulomb +0.8 %),
  during the tracker's warm-up (M trained samples), on samples the caller does not gate in (stale,
  restarted chain), or when adaptation is off. Optionally (``reject``, off by default)
  not on a sample with a very large ``|ν|`` (an abrupt disturbance the tracker could not
  foresee): that also delays learning after a real parameter step, because a wrong β
  makes ``|ν|`` large too — measured trade-off in :class:`OnlineBeta`.
  Every regressor in motion has ``z_sp + z_sn + z_one = 0`` (−1 in its direction's Coulomb
  column, +1 in ``one``): the *rest direction* ``d`` — the Coulomb asymmetry against the
  offset — is told only by samples at rest, which β does not learn from. The tracker does learn
  them, so ``ẑ`` (its prediction of z from its dictionary) and with it ``z̃`` have a component
  along ``d`` after every rest. Learning from it read the tracker's memory of the rests as a
  split of the friction: on a 250 Hz shaker trial, with the model identified on another seed,
  "coulomb_pos +51 %, coulomb_neg −41 %, offset −48 %" at 6–8 standard errors in the first 8 s.
  (3') takes ``d`` out of the update: the split keeps the model file's values (reported "not
  determined" online), the symmetric Coulomb friction and everything else learn as before.
* **No wind-up.** (2) runs on learning samples only, so a standstill neither learns nor
  forgets. Under excitation the information of a direction is that of the last ~T_β
  seconds of learning; without it Λ relaxes to Λ₀, so ``P`` is bounded by the prior
  ``P₀`` and never grows without limit. Forgetting *back to the prior* (mean and
  covariance, like KRLS-T's own forgetting) also bounds how far a weakly determined
  direction can wander: there β̂ is the posterior of the prior and a few seconds of data.
* **Drift rate trade-off, per parameter.** ``T_β`` (``memory``, default 5 s of learning
  samples) is the drift setting of damping, Coulomb and offset: a parameter drifting linearly at
  rate ``ṙ`` (relative per second) is followed with a lag of about ``1.5 ṙ·T_β`` (measured
  1.4–1.7; part of the excess over ``ṙ·T_β``: the weights ``1/R = 1/(s0²σ_y²)`` fall while the
  tracker's residual under the file's β grows with the drift, so older samples weigh more — a scale
  from the joint innovations instead of ``s0²`` removed a fifth of the excess, but made the first
  seconds overconfident: 32 false reports at the start of the soak stream);
  an excited step decays like ``exp(−t/T_β)``; standard errors scale like ``1/√T_β``. Measured
  through ``feedmon run --from`` on the ``shaker-drift`` trial (friction +30 % in 120 s, 0.25 %/s,
  REML-tuned tracker), largest error from 60 s on over seeds 3, 4, 7: damping 3.3–3.4 % and
  Coulomb 3.8–4.2 % with T_β = 5 s; 5.4–5.5 % and 6.3–6.6 % with 10 s. The inertia has its own
  memory ``T_J`` (``inertia_memory``, default 10 s): friction is excited whenever the axis moves,
  the inertia only while it accelerates — at the feed starts of a machining cycle, every 18 s in
  the soak stream. With one memory for all, 5 s made the inertia rest on the last one or two
  accelerations, with an error heavier-tailed than its standard error: over the 24 h soak stream
  (``benchmarks/soak.py``) it gave 15 false inertia warnings (−4.8 % at 6.0–6.3 standard errors);
  10 s none (largest |z| 4.5). The forgetting (2) is therefore applied in the coordinates of the
  physical parameters, each at its own rate; inertia and friction drift on different time scales
  anyway (a payload changes in steps, friction with temperature and lubrication). A plant known to
  drift faster or slower is served by ``[adaptation] memory`` / ``inertia_memory``.
* **Prior.** ``P₀ = P_file + G diag((ρθ₀)²) Gᵀ``: the model file's covariance of β plus a
  drift allowance ρ (default 0.3, relative, on inertia, damping, Coulomb ± and offset —
  Coulomb and offset relative to the friction scale ``max(d_p, c_n, |offset|, 1 N)`` — mapped
  through ``G = ∂β/∂θ``). Least-squares standard errors in a model file assume white noise
  and are far smaller than the changes the monitor must follow; ρ says how far the
  parameters may plausibly move in the field and is the bound of ``P``.
* **Closed-loop noise.** The measured velocity ``v_m(k)`` is in ``z(k)`` and its noise is
  fed back by the loop and sits in ``ε(k) = n(k+1) − p n(k)``: least squares is biased
  by ``−p σ_n²`` per unit of excitation, which dominates when the excitation is the
  noise itself (constant-feed milling). The instrument of the ``v_m`` column is the
  model's own one-step prediction ``v̂(k) = β̂ᵀz(k−1) + f̂(k−1)`` made before ``v_m(k)`` was
  seen (ζ̃ = ζ − ẑ); the estimate is then recursive IV (Young), consistent under white
  noise, with the sandwich covariance (5'). The force command ``u`` (force-input form)
  is its own instrument: the controller law is unknown to the monitor.
* **Robustness.** The Huber weight (4) bounds one sample's influence to ``c = 3``
  standard deviations (0.3 % of Gaussian samples are touched).
* **Physical constraints** (7): β̂ is projected in the metric of ``P``,
  ``β̂ ← β̂ − P a (aᵀβ̂ − b)/(aᵀPa)`` for each violated ``aᵀβ ≤ b`` (Simon & Chia 2002,
  estimate projection), onto the pole ``p_d ∈ [10⁻⁶, 1 − 10⁻³(1 − p_d0)]``, input gain
  ``β1 ≥ 10⁻³ β1₀`` and Coulomb magnitudes ≥ 0. The output is always a physical drive.

Physical parameters and standard errors (delta method, method §2): with ``b`` the force
gain (``β1`` in force-input form, ``β1/K`` in velocity-loop form) and ``p`` the pole,
``B = (1 − p)/b``, ``J = B Ts/(−ln p)``, ``d_p = β_sp/b``, ``c_n = −β_sn/b``,
``offset = −β_one/b`` and ``Var θ_k = g_kᵀ P g_k`` with the analytic gradient ``g_k = ∂θ_k/∂β``
(:func:`physical_se`). Without the loop gain ``K`` (velocity-loop) ``K = 1`` is used: the
values are then ``J/K, B/K, d/K`` (the caller labels them so).

Modes (``monitor`` settings ``[adaptation] mode``): the recursion above with the re-basing (6)
is *apply* — the published disturbance goes with β̂. With the re-basing off (*track*:
``rebase_every = 0``) the tracker's mean keeps going with the model file's β (β_trk = β₀ for
ever), its predictions are published unchanged, and β̂, P and the innovations of the joint
model are still exact by (1): β is estimated and reported without touching the disturbance.

Wiring (stumpy-style): the state is one :class:`BetaState` of named views of two base buffers
(``float64``, ``int64``; :func:`new_beta_buffers`, :func:`beta_state_views`, and inside compiled
code :func:`beta_state_of`), as the KRLS-T core's :class:`~kernels._krlst_core.State`.
:func:`joint_arm` and :func:`joint_update` replace ``_krlst_core.arm`` / ``update`` in a compiled
loop (:func:`kernels.online.track_block`; the tracker-side contract is listed in
:func:`joint_arm`); :class:`OnlineBeta` is the thin Python API (river-style ``learn_one`` /
``predict_one``), with snapshot/restore as plain arrays (:data:`STATE_FIELDS`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from . import _krlst_core as core
from ._krlst_simd import view
from ._snapshot import fill_views
from .feed_drive import FORMS

__all__ = [
    "BetaState",
    "new_beta_buffers",
    "beta_state_views",
    "beta_state_of",
    "replay_joint",
    "fast_inertia",
    "validate_beta_state",
    "joint_arm",
    "joint_update",
    "track_joint",
    "physical_se",
    "prior_covariance",
    "physical_of",
    "OnlineBeta",
    "JointStep",
    "PHYSICAL",
    "BOUT",
    "STATE_FIELDS",
    "SETTINGS_FIELDS",
]

#: physical parameters reported by :func:`physical_se`, in this order (SI: kg, N·s/m, N, N, N, N)
PHYSICAL = ("inertia", "damping", "coulomb_pos", "coulomb_neg", "coulomb", "offset")
N_PHYS = len(PHYSICAL)

#: slots of ``par`` (settings, fixed for a model)
(P_HUBER, P_OMEGA, P_ENABLED, P_GAIN, P_TS, P_IV, P_WARMUP, P_REJECT, P_HOLD, P_MINSPEED, P_FASTLAM) = range(11)
N_PAR = 11
#: memory (s of learning samples) of the fast inertia estimate (eq. 9): a payload is an abrupt change that
#: shows at the few accelerations after it, which the slow memories average away
FAST_MEMORY = 2.0
#: largest min_speed (m/s) a model may set: beyond any feed drive's speed
MIN_SPEED_MAX = 100.0
#: slots of ``lay`` (integer settings: the column layout and the re-basing interval, 0 = never)
(L_FORM, L_ISP, L_ISN, L_IONE, L_REBASE) = range(5)
N_LAY = 5
#: slots of ``cnt`` (counters and instrument bookkeeping: state)
(C_UPDATES, C_GATED, C_PROJECTED, C_DOWNWEIGHTED, C_ARMS, C_VHAT_ARM, C_TRAINED, C_SINCE_REBASE,
 C_SINCE_FORGET, C_QUIET, C_REJECTED, C_DIR, C_VSIM_ARM) = range(13)
N_CNT = 13
#: slots of ``sst`` (float state): the scale of the stored shadow means, the stored velocity prediction,
#: the velocity the model simulates from the command alone (the velocity-loop instrument, eq. 8), the
#: accumulators of the fast inertia estimate (eq. 9: Σ ζ_J e/R, Σ ζ_J s_J/R, Σ ζ_J²/R, and Σ 1: how full its
#: memory is)
(S_SCALE, S_VHAT, S_VSIM, S_FJN, S_FJD, S_FJV, S_FJW) = range(7)
N_SST = 7
#: share of a full memory (1/(1 − λ)) the fast inertia estimate needs before it is tested: two time
#: constants (4 s of learning samples) — the first seconds of a cut, while the disturbance model is still
#: learning the process, read as a +60 % step at 6–9 standard errors (an air-cut model on
#: milling-spindle-change)
FAST_FILL = 1.0 - math.exp(-2.0)
#: learning samples between two applications of the forgetting (2) (with λ_β^m): keeps the
#: per-sample work at rank-one updates of Λ⁻¹; the forgetting per sample is 1 − λ_β ≈ 3·10⁻⁴
FORGET_EVERY = 16
#: scale floor of the lazily scaled shadow means (renormalised below it)
SCALE_FLOOR = 1e-150
#: default re-basing interval of the *apply* mode (learning samples)
REBASE_EVERY = 64

#: named outputs of :func:`joint_update` (``bout``)
BOUT = ("residual", "innovation", "nu", "variance", "weight", "learned", "filtered", "zt_norm")
(B_RESID, B_INNOV, B_NU, B_VAR, B_WEIGHT, B_LEARNED, B_FILTERED, B_ZTN) = range(len(BOUT))
N_BOUT = len(BOUT)
#: rows of the scratch ``vec``
V_ZT, V_ZETA, V_G, V_TMP, V_BEFORE, V_X, V_ZTR, V_ZETAR, V_SIM = range(9)  # V_BEFORE: the forgetting's step;
N_VEC = 9                      # V_ZTR, V_ZETAR: z̃, ζ̃ off the rest direction; V_SIM: the simulation's regressor
_HEADER = 4                 # int buffer: p, cap, number of constraints, (spare)


class BetaState(NamedTuple):
    """State of the online β estimator: named views of two base buffers (:func:`new_beta_buffers`).

    Settings (fixed for a model; :data:`SETTINGS_FIELDS`): ``lay`` the column layout and the
    re-basing interval (:data:`L_FORM` …), ``par`` float settings (:data:`P_HUBER` …),
    ``beta0`` the model file's β, ``info0`` Λ₀ = P₀⁻¹, ``cons`` rows ``[a, b]`` of the
    constraints ``aᵀβ ≤ b``, ``forget`` the operators ``[T, S]`` of the forgetting (2) over
    :data:`FORGET_EVERY` learning samples (:func:`forgetting_operators`).

    State (:data:`STATE_FIELDS`): ``beta`` β̂ (p,); ``beta_trk`` the β the tracker's mean
    currently goes with (re-based to β̂ every ``lay[L_REBASE]`` learning samples in *apply*
    mode, never in *track* mode; predictions are corrected for the difference exactly);
    ``cov`` Λ⁻¹ with Λ = Σ ζ̃z̃ᵀ/R + prior (p, p; symmetric without instruments), kept by
    rank-one (Sherman–Morrison) updates; ``psi`` Ψ = Σ ζ̃ζ̃ᵀ R/R_w² + prior (the middle of the
    covariance ``P = Λ⁻¹ΨΛ⁻ᵀ``); ``MZ`` the shadow GP means of the regressors in the
    tracker's slots (M+1, p), stored divided by the scale ``sst[S_SCALE]`` (the forgetting
    √λ is applied to that scalar); ``zhat`` ẑ = M_Zᵀq armed with the tracker; ``sst`` the
    scale and the stored velocity prediction v̂; ``cnt`` counters (:data:`C_UPDATES` …).

    Scratch: ``info`` (Λ), ``lu``, ``piv``, ``vec``.
    """

    layout: np.ndarray   # int64 (4,): p, cap, number of constraints
    lay: np.ndarray      # int64 (N_LAY,)
    cnt: np.ndarray      # int64 (N_CNT,)
    piv: np.ndarray      # int64 (p,)
    par: np.ndarray      # float64 (N_PAR,)
    beta0: np.ndarray    # (p,)
    info0: np.ndarray    # (p, p)
    cons: np.ndarray     # (ncons, p + 1)
    forget: np.ndarray   # (2, p, p): T and S of the forgetting (2)
    dirj: np.ndarray     # (p,): ∂β/∂J at β₀, the direction of the inertia (eq. 9)
    beta: np.ndarray     # (p,)
    beta_trk: np.ndarray  # (p,)
    cov: np.ndarray      # (p, p)
    psi: np.ndarray      # (p, p)
    MZ: np.ndarray       # (cap, p + 1): the regressors' and the instrument's
    zhat: np.ndarray     # (p + 1,)
    sst: np.ndarray      # (N_SST,)
    info: np.ndarray     # (p, p) scratch
    lu: np.ndarray       # (p, p) scratch
    vec: np.ndarray      # (N_VEC, p) scratch
    work: np.ndarray     # (p, p) scratch of the forgetting
    zx: np.ndarray       # (p + 1,) scratch: [z̃; ζ̃_sim], the shadow update's step


#: the fields that are the estimator's state (snapshots); the others are settings or scratch
STATE_FIELDS = ("cnt", "beta", "beta_trk", "cov", "psi", "MZ", "zhat", "sst")
#: the fields fixed by the model and the settings (a restored state must hold the same)
SETTINGS_FIELDS = ("lay", "par", "beta0", "info0", "cons", "forget", "dirj")


def _offsets(p, cap, ncons):
    """Start of each field in the base buffers; the last entry of each group is its length."""
    i_lay = _HEADER
    i_cnt = i_lay + N_LAY
    i_piv = i_cnt + N_CNT
    i_end = i_piv + p
    pp = p * p
    f_par = 0
    f_beta0 = f_par + N_PAR
    f_info0 = f_beta0 + p
    f_cons = f_info0 + pp
    f_forget = f_cons + ncons * (p + 1)
    f_dirj = f_forget + 2 * pp
    f_beta = f_dirj + p
    f_btrk = f_beta + p
    f_cov = f_btrk + p
    f_psi = f_cov + pp
    f_mz = f_psi + pp
    f_zhat = f_mz + cap * (p + 1)
    f_sst = f_zhat + p + 1
    f_info = f_sst + N_SST
    f_lu = f_info + pp
    f_vec = f_lu + pp
    f_work = f_vec + N_VEC * p
    f_zx = f_work + pp
    f_end = f_zx + p + 1
    return (i_lay, i_cnt, i_piv, i_end, f_par, f_beta0, f_info0, f_cons, f_forget, f_dirj, f_beta, f_btrk, f_cov,
            f_psi, f_mz, f_zhat, f_sst, f_info, f_lu, f_vec, f_work, f_zx, f_end)


_offsets_nb = njit(cache=True, nogil=True)(_offsets)


def beta_state_views(fbuf: np.ndarray, ibuf: np.ndarray) -> BetaState:
    """The :class:`BetaState` of the two base buffers, as NumPy views."""
    p, cap, ncons = (int(v) for v in ibuf[:3])
    (i_lay, i_cnt, i_piv, i_end, f_par, f_beta0, f_info0, f_cons, f_forget, f_dirj, f_beta, f_btrk, f_cov, f_psi,
     f_mz, f_zhat, f_sst, f_info, f_lu, f_vec, f_work, f_zx, f_end) = _offsets(p, cap, ncons)
    return BetaState(ibuf[:_HEADER], ibuf[i_lay:i_cnt], ibuf[i_cnt:i_piv], ibuf[i_piv:i_end],
                     fbuf[f_par:f_beta0], fbuf[f_beta0:f_info0], fbuf[f_info0:f_cons].reshape(p, p),
                     fbuf[f_cons:f_forget].reshape(ncons, p + 1), fbuf[f_forget:f_dirj].reshape(2, p, p),
                     fbuf[f_dirj:f_beta], fbuf[f_beta:f_btrk], fbuf[f_btrk:f_cov],
                     fbuf[f_cov:f_psi].reshape(p, p), fbuf[f_psi:f_mz].reshape(p, p),
                     fbuf[f_mz:f_zhat].reshape(cap, p + 1), fbuf[f_zhat:f_sst], fbuf[f_sst:f_info],
                     fbuf[f_info:f_lu].reshape(p, p), fbuf[f_lu:f_vec].reshape(p, p),
                     fbuf[f_vec:f_work].reshape(N_VEC, p), fbuf[f_work:f_zx].reshape(p, p), fbuf[f_zx:f_end])


@njit(cache=True, nogil=True, inline="always")
def beta_state_of(fbuf, ibuf):
    """The :class:`BetaState` of the two base buffers inside compiled code: reference-free views
    (valid while the buffers are; never return them to Python — use :func:`beta_state_views`)."""
    p = ibuf[0]
    cap = ibuf[1]
    ncons = ibuf[2]
    (i_lay, i_cnt, i_piv, _, f_par, f_beta0, f_info0, f_cons, f_forget, f_dirj, f_beta, f_btrk, f_cov, f_psi, f_mz,
     f_zhat, f_sst, f_info, f_lu, f_vec, f_work, f_zx, _) = _offsets_nb(p, cap, ncons)
    return BetaState(view(ibuf, 0, (_HEADER,)), view(ibuf, i_lay, (N_LAY,)), view(ibuf, i_cnt, (N_CNT,)),
                     view(ibuf, i_piv, (p,)), view(fbuf, f_par, (N_PAR,)), view(fbuf, f_beta0, (p,)),
                     view(fbuf, f_info0, (p, p)), view(fbuf, f_cons, (ncons, p + 1)), view(fbuf, f_forget, (2, p, p)),
                     view(fbuf, f_dirj, (p,)), view(fbuf, f_beta, (p,)),
                     view(fbuf, f_btrk, (p,)), view(fbuf, f_cov, (p, p)), view(fbuf, f_psi, (p, p)),
                     view(fbuf, f_mz, (cap, p + 1)), view(fbuf, f_zhat, (p + 1,)), view(fbuf, f_sst, (N_SST,)),
                     view(fbuf, f_info, (p, p)), view(fbuf, f_lu, (p, p)), view(fbuf, f_vec, (N_VEC, p)),
                     view(fbuf, f_work, (p, p)), view(fbuf, f_zx, (p + 1,)))


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
    offs = _offsets(p, cap, cons.shape[0])
    fbuf = np.zeros(offs[-1])
    ibuf = np.zeros(offs[3], dtype=np.int64)
    ibuf[:3] = p, cap, cons.shape[0]
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
    if np.any(c[[C_UPDATES, C_GATED, C_PROJECTED, C_DOWNWEIGHTED, C_ARMS, C_TRAINED, C_SINCE_REBASE, C_SINCE_FORGET,
                 C_QUIET, C_REJECTED]] < 0) or c[C_VHAT_ARM] < -1 or c[C_VHAT_ARM] > c[C_ARMS] + 1 \
            or c[C_VSIM_ARM] < -1 or c[C_VSIM_ARM] > c[C_ARMS] + 1:
        raise ValueError("beta 'cnt' holds impossible counters")
    if c[C_DIR] not in (-1, 0, 1):
        raise ValueError("beta 'cnt': the previous sample's direction of motion is not −1, 0 or 1")
    if c[C_SINCE_FORGET] >= FORGET_EVERY or (bs.lay[L_REBASE] > 0 and c[C_SINCE_REBASE] >= bs.lay[L_REBASE]):
        raise ValueError("beta 'cnt': a batched step is overdue (impossible)")


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
    """``out = P a`` with ``P = Λ⁻¹ Ψ Λ⁻ᵀ`` (``bs.cov`` = Λ⁻¹)."""
    p = a.shape[0]
    C = bs.cov
    psi = bs.psi
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += C[j, i] * a[j]
        t1[i] = acc                               # t1 = Λ⁻ᵀ a
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += psi[i, j] * t1[j]
        t2[i] = acc                               # t2 = Ψ Λ⁻ᵀ a
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += C[i, j] * t2[j]
        out[i] = acc                              # out = Λ⁻¹ Ψ Λ⁻ᵀ a


@njit(cache=True, nogil=True)
def _invert(A, out, LU, piv, b, x):
    """out = A⁻¹ (p×p) by LU; False if A is singular."""
    p = A.shape[0]
    if not _lu_factor(A, LU, piv):
        return False
    for c in range(p):
        for i in range(p):
            b[i] = 1.0 if i == c else 0.0
        _lu_solve(LU, piv, b, x)
        for i in range(p):
            out[i, c] = x[i]
    return True


@njit(cache=True, nogil=True)
def _forget(bs):
    """(2) for the last :data:`FORGET_EVERY` learning samples, per physical parameter, with the
    operators ``T``, ``S`` of :func:`forgetting_operators` (:attr:`BetaState.forget`):

        Λ ← TᵀΛT + SᵀΛ₀S,   Ψ ← TᵀΨT + SᵀΛ₀S,   β̂ ← β̂ + Λ_new⁻¹ SᵀΛ₀S (β₀ − β̂),

    i.e. in the coordinates of the physical parameters θ each one is flattened towards the prior
    N(β₀, P₀) at its own rate (``Λ_θ ← DΛ_θD + EΛ₀θE``, ``D = diag(√λ_i^m)``, ``E = √(I − D²)``);
    with λ_J = λ_β it is ``Λ ← λ_β^m Λ + (1 − λ_β^m) Λ₀``."""
    beta = bs.beta
    p = beta.shape[0]
    vec = bs.vec
    info = bs.info
    if not _invert(bs.cov, info, bs.lu, bs.piv, vec[V_TMP], vec[V_X]):   # Λ = (Λ⁻¹)⁻¹
        return
    T = bs.forget[0]
    prior = bs.work
    _congruence(info, T, info, bs.lu)             # Λ ← TᵀΛT
    _congruence(bs.psi, T, bs.psi, bs.lu)         # Ψ ← TᵀΨT
    _congruence(bs.info0, bs.forget[1], prior, bs.lu)   # SᵀΛ₀S
    beta0 = bs.beta0
    d = vec[V_BEFORE]
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += prior[i, j] * (beta0[j] - beta[j])
            info[i, j] += prior[i, j]
            bs.psi[i, j] += prior[i, j]
        d[i] = acc                                # SᵀΛ₀S (β₀ − β̂)
    if not _invert(info, bs.cov, bs.lu, bs.piv, vec[V_TMP], vec[V_X]):
        return
    C = bs.cov
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += C[i, j] * d[j]
        beta[i] += acc


@njit(cache=True, nogil=True)
def _congruence(A, T, out, tmp):
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
def _rows_dot(MZ, q, hw, out):
    """``out = Σ_i q[i] MZ[i, :]`` over the slots ``[0, hw)``; register accumulators for ≤ 6 columns
    (the regressors: e, v_m, −σ_p, −σ_n, 1), so the sweep is not a chain of stores."""
    p = MZ.shape[1]
    if p > 6:
        for j in range(p):
            out[j] = 0.0
        for i in range(hw):
            for j in range(p):
                out[j] += q[i] * MZ[i, j]
        return
    a0 = a1 = a2 = a3 = a4 = a5 = 0.0
    for i in range(hw):
        qi = q[i]
        a0 += qi * MZ[i, 0]
        a1 += qi * MZ[i, 1]
        if p > 2:
            a2 += qi * MZ[i, 2]
            if p > 3:
                a3 += qi * MZ[i, 3]
                if p > 4:
                    a4 += qi * MZ[i, 4]
                    if p > 5:
                        a5 += qi * MZ[i, 5]
    out[0] = a0
    out[1] = a1
    if p > 2:
        out[2] = a2
    if p > 3:
        out[3] = a3
    if p > 4:
        out[4] = a4
    if p > 5:
        out[5] = a5


@njit(cache=True, nogil=True)
def _rows_axpy(MZ, h, c, zt, hw):
    """``MZ[i, :] += c h[i] z̃`` for the slots ``[0, hw)`` (z̃ held in registers for ≤ 6 columns)."""
    p = MZ.shape[1]
    if p > 6:
        for i in range(hw):
            hi = c * h[i]
            for j in range(p):
                MZ[i, j] += zt[j] * hi
        return
    z0 = zt[0]
    z1 = zt[1]
    z2 = zt[2] if p > 2 else 0.0
    z3 = zt[3] if p > 3 else 0.0
    z4 = zt[4] if p > 4 else 0.0
    z5 = zt[5] if p > 5 else 0.0
    for i in range(hw):
        hi = c * h[i]
        MZ[i, 0] += z0 * hi
        MZ[i, 1] += z1 * hi
        if p > 2:
            MZ[i, 2] += z2 * hi
            if p > 3:
                MZ[i, 3] += z3 * hi
                if p > 4:
                    MZ[i, 4] += z4 * hi
                    if p > 5:
                        MZ[i, 5] += z5 * hi



@njit(cache=True, nogil=True)
def joint_arm(st, bs, x, out):
    """Tracker steps 1–2 at ``x`` (``_krlst_core.arm``) and the same on the shadow means.

    ``M_Z ← √λ M_Z`` (the forgetting of μ, eq. 2.19, applied to the scale of the stored
    means) and ``ẑ = M_Zᵀ q`` (the GP's prediction of z at x, eq. 2.17 applied to the
    regressors), armed in ``bs.zhat``. ``out[A_MEAN]`` becomes the prediction of f at x given
    β̂: the tracker's ``ŷ`` (for ``β_trk``, still in ``st.fst[F_YM]``) minus ``ẑᵀ(β̂ − β_trk)``.

    Tracker-side contract (what this relies on in :mod:`kernels._krlst_core`): after ``arm``,
    ``P[P_Q]`` holds ``q = Q k_t`` and ``P[P_H]`` holds ``h = Σ q`` over the slots ``[0, hw)``
    (zero on free slots), ``fst[F_YM], fst[F_SF2], fst[F_SY2]`` the armed ``ŷ, σ_f², σ_y²``
    and ``fst[F_S02]`` the signal power; the new basis goes to the free slot ``order[n]``;
    after ``update`` a reduced step (``O_REDUCED``) leaves that slot free, and a pruning step
    (``O_REMOVED ≥ 0``) moves the new basis into the pruned one's slot ``order[n − 1]`` and
    frees ``order[n]``; μ is stored unscaled in the slots and ``P[P_H]`` is not touched by
    ``update``.
    """
    st = core.unowned(st)
    n = st.ist[core.I_N]
    core.arm(st, x, out)
    bs.cnt[C_ARMS] += 1
    MZ = bs.MZ
    zhat = bs.zhat
    w = zhat.shape[0]                             # the p regressors and the instrument
    for j in range(w):
        zhat[j] = 0.0
    if n == 0:
        return
    hw = st.ist[core.I_HW]
    c = bs.sst[S_SCALE] * math.sqrt(st.fst[core.F_LAM])  # M_Z ← √λ M_Z (on the scale)
    if c < SCALE_FLOOR:
        for i in range(hw):
            for j in range(w):
                MZ[i, j] *= c
        c = 1.0
    bs.sst[S_SCALE] = c
    _rows_dot(MZ, st.P[core.P_Q], hw, zhat)     # Σ q_i M_Z[i, :]
    corr = 0.0
    beta = bs.beta
    btrk = bs.beta_trk
    for j in range(w):
        zhat[j] *= c                              # ẑ = M_Zᵀ q
    for j in range(beta.shape[0]):
        corr += zhat[j] * (beta[j] - btrk[j])
    out[core.A_MEAN] -= corr                      # f̂(x | β̂) = ŷ(β_trk) − ẑᵀ(β̂ − β_trk)


@njit(cache=True, nogil=True)
def rebase(st, bs):
    """Re-express the tracker's mean with β̂: ``μ ← μ − M_Z (β̂ − β_trk)``, ``β_trk ← β̂`` (eq. 6)."""
    beta = bs.beta
    btrk = bs.beta_trk
    MZ = bs.MZ
    p = beta.shape[0]
    d = bs.vec[V_X]
    c = bs.sst[S_SCALE]
    moved = False
    for j in range(p):
        d[j] = c * (beta[j] - btrk[j])
        if d[j] != 0.0:
            moved = True
        btrk[j] = beta[j]
    bs.cnt[C_SINCE_REBASE] = 0
    if not moved:
        return
    mu = st.mu
    for i in range(st.ist[core.I_HW]):
        acc = 0.0
        for j in range(p):
            acc += MZ[i, j] * d[j]
        mu[i] -= acc


@njit(cache=True, nogil=True)
def joint_update(st, bs, z, y, gate, out, bout):
    """Tracker steps 3–5 with the residual of ``β_trk``, the shadow update, then β (2)–(7).

    ``z``: the regressor ``z(k)`` of the armed sample; ``y = v_m(k+1)``; ``gate``: the
    caller allows learning β from this sample (chain intact, not stale); the warm-up
    (no learning during the first ``warmup`` trained samples, default the budget M) and
    the motion gate ``|v_m(k)| > Ω`` are applied here. ``out`` receives the
    tracker's step (``_krlst_core`` ``O_*`` layout: its filtered value goes with ``β_trk``),
    ``bout`` the named outputs :data:`BOUT` (``filtered`` re-expressed with the new β̂).
    Returns False (nothing done) when no prediction is armed.
    """
    st = core.unowned(st)
    ist = st.ist
    fst = st.fst
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
    n = ist[core.I_N]
    hw = ist[core.I_HW]
    s = st.order[n]                               # the slot the new basis goes to
    sy2 = fst[core.F_SY2]
    sf2 = fst[core.F_SF2]
    s02 = fst[core.F_S02]
    h = st.P[core.P_H]
    btrk = bs.beta_trk
    base = 0.0
    base_trk = 0.0
    shift = 0.0
    for j in range(p):
        base += beta[j] * z[j]
        base_trk += btrk[j] * z[j]
        zt[j] = z[j] - zhat[j]                    # z̃ = z − ẑ
        zeta[j] = zt[j]
        shift += zt[j] * (beta[j] - btrk[j])
    # instrument for the measured velocity (eq. 8). Velocity loop: the velocity the model simulates from
    # the command alone, v_sim(k+1) = β₀ᵀz(v_ref(k), v_sim(k)) — free of the noise and of the disturbance
    # (a cutting force excites v_m at the tooth frequency; its prediction errors must not teach the
    # inertia), with its own shadow mean (column p of M_Z); restarted from v_m after a break of the chain.
    # Force input (u is the loop's reaction to the disturbance too): the model's one-step prediction
    # v̂(k), free of the noise; valid only right after the arm that followed it
    zx = bs.zx
    form_force = bs.lay[L_FORM] == 1
    vsim = z[1]
    if not form_force:
        if cnt[C_VSIM_ARM] == cnt[C_ARMS]:
            vsim = bs.sst[S_VSIM]
        zx[p] = vsim - zhat[p]
        if par[P_IV] != 0.0:
            zeta[1] = zx[p]                       # ζ̃ = ζ − ẑ_ζ with ζ = z, v_m(k) → v_sim(k)
    else:
        zx[p] = 0.0
        if par[P_IV] != 0.0 and cnt[C_VHAT_ARM] == cnt[C_ARMS]:
            zeta[1] = bs.sst[S_VHAT] - zhat[1]    # ζ̃ = ζ − ẑ with ζ = z, v_m(k) → v̂(k)
    for j in range(p):
        zx[j] = zt[j]
    resid_trk = y - base_trk                      # what the tracker trains on (its mean goes with β_trk)
    resid = y - base                              # r = y − β̂ᵀz (eq. 2.13)
    e = resid_trk - fst[core.F_YM] - shift        # e = y − β̂ᵀz − f̂(β̂) = ỹ − β̂ᵀz̃
    bs.sst[S_VHAT] = y - e                        # v̂(k+1) = β̂ᵀz(k) + f̂(k), before seeing y
    cnt[C_VHAT_ARM] = cnt[C_ARMS] + 1
    # shadow means (stored / scale c), the mean part of eq. 2.14 for every regressor column
    inv_sy2 = 1.0 / sy2
    inv_c = 1.0 / bs.sst[S_SCALE]
    w = p + 1
    _rows_axpy(MZ, h, inv_sy2 * inv_c, zx, hw)    # M_Z ← [M_Z; ẑ] + z̃/σ_y² [h; σ_f²]
    for j in range(w):
        MZ[s, j] = (zhat[j] + zx[j] * inv_sy2 * sf2) * inv_c
    core.update(st, resid_trk, out)
    if out[core.O_REDUCED] != 0.0:                # reduced update: the new basis was dropped
        for j in range(w):
            MZ[s, j] = 0.0
    elif out[core.O_REMOVED] >= 0.0:              # pruned: the new basis took the pruned one's slot
        t = st.order[ist[core.I_N] - 1]
        for j in range(w):
            MZ[t, j] = MZ[s, j]
            MZ[s, j] = 0.0
    R = s02 * sy2                                 # R = s0² σ_y²
    bout[B_RESID] = resid
    bout[B_INNOV] = e
    bout[B_VAR] = R
    bout[B_NU] = e / math.sqrt(R) if n > 0 and R > 0.0 else np.nan
    bout[B_WEIGHT] = 1.0
    bout[B_LEARNED] = 0.0
    ztn = 0.0
    for j in range(p):
        ztn += zt[j] * zt[j]
    bout[B_ZTN] = math.sqrt(ztn)
    if par[P_ENABLED] != 0.0 and n > 0 and R > 0.0:
        _beta_step(bs, z, e, R, gate, bout)
    if not form_force:                            # (8) the simulation's next step, with the model file's β₀
        zs = vec[V_SIM]                           # (stable by the validity rules; β̂ would feed back on itself)
        regressor(False, bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE], par[P_OMEGA], z[0], vsim, zs)
        acc = 0.0
        b0 = bs.beta0
        for j in range(p):
            acc += b0[j] * zs[j]
        bs.sst[S_VSIM] = acc
        cnt[C_VSIM_ARM] = cnt[C_ARMS] + 1
    # the filtered f at x(k) given β̂: f_filt(β_trk) − z_filtᵀ(β̂ − β_trk), z_filt = ẑ + σ_f² z̃/σ_y²
    filtered = out[core.O_FILT]
    for j in range(p):
        filtered -= (zhat[j] + sf2 * zt[j] * inv_sy2) * (beta[j] - btrk[j])
    bout[B_FILTERED] = filtered
    every = bs.lay[L_REBASE]
    if every > 0:
        cnt[C_SINCE_REBASE] += 1
        if cnt[C_SINCE_REBASE] >= every:
            rebase(st, bs)                        # (6), amortised: μ ← μ − M_Z (β̂ − β_trk)
    return True


@njit(cache=True, nogil=True)
def _beta_step(bs, z, e, R, gate, bout):
    """Steps (2)–(5) and (7) for one trained sample (``e``: innovation given β̂, ``R = s0²σ_y²``)."""
    beta = bs.beta
    par = bs.par
    cnt = bs.cnt
    vec = bs.vec
    C = bs.cov
    p = beta.shape[0]
    zt = vec[V_ZT]
    zeta = vec[V_ZETA]
    g = vec[V_G]
    row = vec[V_TMP]
    cnt[C_TRAINED] += 1
    omega = par[P_OMEGA]
    vk = z[1]
    d = 1 if vk > omega else (-1 if vk < -omega else 0)   # direction of motion (0: dead band)
    # learn only in motion, and not from the first sample of a run of motion (module docstring)
    learn = gate and cnt[C_TRAINED] > par[P_WARMUP] and d != 0 and d == cnt[C_DIR] and abs(vk) > par[P_MINSPEED]
    cnt[C_DIR] = d
    # ---- (3) gain direction and the normalised innovation ---------------------------------------
    ztg = _gain_direction(C, zt, zeta, g, row)
    Sfull = R + ztg                               # S = R + z̃ᵀ P z̃
    nu = e / math.sqrt(Sfull)
    bout[B_VAR] = Sfull
    bout[B_NU] = nu
    # redescending cut: |ν| ≥ reject — an abrupt disturbance the tracker could not foresee;
    # learn nothing from it (nor, with hold > 0, from the ``hold`` samples after it)
    if abs(nu) >= par[P_REJECT]:
        cnt[C_QUIET] = 0
    else:
        cnt[C_QUIET] += 1
    if learn and (abs(nu) >= par[P_REJECT] or cnt[C_QUIET] <= par[P_HOLD]):
        learn = False
        cnt[C_REJECTED] += 1
    if not learn:
        cnt[C_GATED] += 1
        return
    if bs.lay[L_ISP] >= 0 and bs.lay[L_IONE] >= 0:
        # (3') a moving sample says nothing about the rest direction d = e_sp + e_sn + e_one (zᵀd = 0 for
        # every z in motion); z̃ = z − ẑ has a component along d only through the tracker's memory of
        # samples at rest, which β does not learn from: learn with z̃, ζ̃ off d (module docstring)
        zt = _off_rest(zt, vec[V_ZTR], bs.lay)
        zeta = _off_rest(zeta, vec[V_ZETAR], bs.lay)
        ztg = _gain_direction(C, zt, zeta, g, row)
    # ---- (4) Huber weight, (5) update ------------------------------------------------------------
    c = par[P_HUBER]
    w = 1.0
    if abs(nu) > c:
        w = c / abs(nu)
        cnt[C_DOWNWEIGHTED] += 1
    # (9) the fast inertia estimate: δ = Σ ζ_J e/R ÷ Σ ζ_J s_J/R over a memory of FAST_MEMORY, with
    # s_J = z̃ᵀ∂β/∂J and ζ_J = ζ̃ᵀ∂β/∂J — an instrumental-variable estimate of the inertia's change since β̂,
    # unweighted: the samples that carry an abrupt change are the ones Huber's weight would discount
    sj = 0.0
    cj = 0.0
    dirj = bs.dirj
    for i in range(p):
        sj += zt[i] * dirj[i]
        cj += zeta[i] * dirj[i]
    sst = bs.sst
    lf = par[P_FASTLAM]
    sst[S_FJN] = lf * sst[S_FJN] + cj * e / R
    sst[S_FJD] = lf * sst[S_FJD] + cj * sj / R
    sst[S_FJV] = lf * sst[S_FJV] + cj * cj / R
    sst[S_FJW] = lf * sst[S_FJW] + 1.0
    Rw = R / w
    den = 1.0 / (Rw + ztg)
    coef = e * den
    meat = (w * e / R) ** 2                       # empirical score² (Huber–White sandwich); model-based: R/R_w²
    psi = bs.psi
    for i in range(p):
        beta[i] += g[i] * coef                    # β̂ ← β̂ + Λ⁻¹ζ̃ e / (R_w + z̃ᵀΛ⁻¹ζ̃)
        gi = g[i] * den
        for j in range(p):
            C[i, j] -= gi * row[j]                # Λ⁻¹ ← Λ⁻¹ − Λ⁻¹ζ̃ z̃ᵀΛ⁻¹ / (R_w + z̃ᵀΛ⁻¹ζ̃)   (Λ += ζ̃z̃ᵀ/R_w)
            psi[i, j] += zeta[i] * zeta[j] * meat  # Ψ ← Ψ + ζ̃ ζ̃ᵀ R / R_w²
    cnt[C_SINCE_FORGET] += 1
    if cnt[C_SINCE_FORGET] >= FORGET_EVERY:
        _forget(bs)                               # (2) for the last FORGET_EVERY learning samples
        cnt[C_SINCE_FORGET] = 0
    # ---- (7) physical constraints -------------------------------------------------------------
    viol = False
    cons = bs.cons
    for r in range(cons.shape[0]):
        a = -cons[r, p]
        for j in range(p):
            a += cons[r, j] * beta[j]
        if a > 0.0:
            viol = True
    if viol:
        cnt[C_PROJECTED] += _project(bs, zeta, g, row, vec[V_X])
    bout[B_WEIGHT] = w
    bout[B_LEARNED] = 1.0
    cnt[C_UPDATES] += 1


@njit(cache=True, nogil=True, inline="always")
def _gain_direction(C, zt, zeta, g, row):
    """Eq. (3): ``g = Λ⁻¹ζ̃``, ``row = z̃ᵀΛ⁻¹`` (into ``g``, ``row``; ``C`` holds Λ⁻¹); returns
    ``s = z̃ᵀΛ⁻¹ζ̃`` clipped at 0 (``= z̃ᵀPz̃`` without instrument)."""
    p = g.shape[0]
    s = 0.0
    for i in range(p):
        gi = 0.0
        ri = 0.0
        for j in range(p):
            gi += C[i, j] * zeta[j]               # g = Λ⁻¹ ζ̃
            ri += zt[j] * C[j, i]                 # rowᵀ = z̃ᵀ Λ⁻¹
        g[i] = gi
        row[i] = ri
        s += zt[i] * gi                           # z̃ᵀ Λ⁻¹ ζ̃
    return s if s > 0.0 else 0.0


@njit(cache=True, nogil=True, inline="always")
def _off_rest(x, out, lay):
    """``out = x − (xᵀd/3) d`` with ``d = e_sp + e_sn + e_one`` (the rest direction); returns ``out``."""
    isp, isn, ione = lay[L_ISP], lay[L_ISN], lay[L_IONE]
    for j in range(x.shape[0]):
        out[j] = x[j]
    m = (x[isp] + x[isn] + x[ione]) / 3.0
    out[isp] -= m
    out[isn] -= m
    out[ione] -= m
    return out


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
def track_joint(fbuf, ibuf, bfbuf, bibuf, X, e, v, gate, resume, out, bout, zbuf, rows):
    """Offline loop over one uninterrupted stream (benchmarks, tests): at sample ``j ≥ 1`` update
    with ``(z(j−1), v(j))`` (β learns where ``gate[j]``), then arm at ``X[j]`` (the tracker input,
    ``(n, d)``).

    ``resume``: sample 0 is the last sample of the previous call, already armed (its row
    is left NaN). ``rows[j]`` (≥ 7 columns): ``[f_next, f_next_var, learned, nu, residual,
    filtered, weight]`` — the one-step prediction of ``f(j)`` (signal units) made at sample
    ``j``, then the outputs of the update that sample ``j`` completed.
    """
    st = core.unowned(core.state_of(fbuf, ibuf))
    bs = beta_state_of(bfbuf, bibuf)
    form_force = bs.lay[L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE]
    omega = bs.par[P_OMEGA]
    for j in range(X.shape[0]):
        r = rows[j]
        for c in range(r.shape[0]):
            r[c] = np.nan
        if j > 0:
            regressor(form_force, i_sp, i_sn, i_one, omega, e[j - 1], v[j - 1], zbuf)
            if joint_update(st, bs, zbuf, v[j], gate[j], out, bout):
                r[2] = bout[B_LEARNED]
                r[3] = bout[B_NU]
                r[4] = bout[B_RESID]
                r[5] = bout[B_FILTERED]
                r[6] = bout[B_WEIGHT]
        if j == 0 and resume:
            continue
        was_empty = st.ist[core.I_N] == 0
        joint_arm(st, bs, X[j], out)
        r[0] = out[core.A_MEAN]
        r[1] = np.nan if was_empty else out[core.A_SF2] * st.fst[core.F_S02]


@njit(cache=True, nogil=True)
def replay_joint(fbuf, ibuf, bfbuf, bibuf, X, exo, v, target, x_now, out, bout, zbuf):
    """Rebuild a fresh tracker and its shadow means from recorded samples: for each ``k``, arm at
    ``X[k]`` and learn ``(z(exo[k], v[k]), target[k])`` without learning β (the caller has switched
    β's learning off), then arm at ``x_now``. The samples need not be consecutive: each carries its
    own regressor and target (``target[k] = v_m`` of the sample after ``k``)."""
    st = core.unowned(core.state_of(fbuf, ibuf))
    bs = beta_state_of(bfbuf, bibuf)
    form_force = bs.lay[L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE]
    omega = bs.par[P_OMEGA]
    for k in range(X.shape[0]):
        joint_arm(st, bs, X[k], out)
        regressor(form_force, i_sp, i_sn, i_one, omega, exo[k], v[k], zbuf)
        joint_update(st, bs, zbuf, target[k], False, out, bout)
    joint_arm(st, bs, x_now, out)


@njit(cache=True, nogil=True)
def joint_arm_buffers(fbuf, ibuf, bfbuf, bibuf, x, out):
    """:func:`joint_arm` on the base buffers of the tracker and of the β state."""
    joint_arm(core.state_of(fbuf, ibuf), beta_state_of(bfbuf, bibuf), x, out)


@njit(cache=True, nogil=True)
def joint_update_buffers(fbuf, ibuf, bfbuf, bibuf, z, y, gate, out, bout):
    """:func:`joint_update` on the base buffers of the tracker and of the β state."""
    return joint_update(core.state_of(fbuf, ibuf), beta_state_of(bfbuf, bibuf), z, y, gate, out, bout)


@njit(cache=True, nogil=True)
def rebase_buffers(fbuf, ibuf, bfbuf, bibuf):
    """:func:`rebase` on the base buffers."""
    rebase(core.state_of(fbuf, ibuf), beta_state_of(bfbuf, bibuf))


@njit(cache=True, nogil=True)
def physical_se_buffers(bfbuf, bibuf, theta, se, cov_work):
    """:func:`physical_se` on the base buffers of the β state."""
    return physical_se(beta_state_of(bfbuf, bibuf), theta, se, cov_work)


@njit(cache=True, nogil=True)
def fast_inertia(bs, J):
    """The fast inertia estimate (eq. 9) ``J + δ`` and its standard error, ``J`` the slow estimate
    (kg, or kg over K); NaN when the last ``FAST_MEMORY`` seconds of motion held no acceleration, and in
    the force-input form: there the command is the loop's reaction to the disturbance too, so no
    instrument free of it exists, and a disturbance step reads as an inertia step over a few samples."""
    sst = bs.sst
    d = sst[S_FJD]
    if bs.lay[L_FORM] == 1 or not (d != 0.0 and math.isfinite(J)):
        return np.nan, np.nan
    if sst[S_FJW] * (1.0 - bs.par[P_FASTLAM]) < FAST_FILL:   # not yet FAST_FILL of a full memory
        return np.nan, np.nan
    return J + sst[S_FJN] / d, math.sqrt(max(sst[S_FJV], 0.0)) / abs(d)


@njit(cache=True, nogil=True)
def physical_se(bs, theta, se, cov_work):
    """θ = (J, B, d_p, c_n, (d_p + c_n)/2, offset) of β̂ and their standard errors (delta method).

    ``cov_work`` (:data:`N_PHYS` + 2, p) scratch. Absent columns give NaN. Returns False when β̂ is not a
    physical drive (cannot happen after the projection; guards restored states).
    """
    beta = bs.beta
    p = beta.shape[0]
    form_force = bs.lay[L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE]
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
        vm = 0.0
        for j in range(p):
            v += gk[j] * x[j]                     # the sandwich gᵀΛ⁻¹ΨΛ⁻ᵀg
            vm += gk[j] * t1[j]                   # the model-based gᵀΛ⁻¹g (t1 = Λ⁻ᵀg)
        # the larger of the two: the sandwich of a few effective samples is too small (the first seconds
        # of the real EMPS drive: a damping 'drift' of 8 standard errors at 3 s that was gone at 5 s)
        v = max(v, vm)
        se[k] = math.sqrt(v) if v > 0.0 else 0.0
    return True


# ---------------------------------------------------------------------------------------------
# Python API
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# Python API
# ---------------------------------------------------------------------------------------------
def physical_of(beta, names, Ts: float, P, *, gain: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Physical parameters (:data:`PHYSICAL`) of ``beta`` and their standard errors for the β
    covariance ``P`` (delta method, :func:`physical_se`), e.g. the model file's values and
    standard errors for the health reference. NaN for columns the model does not have."""
    form = _layout(names)[0]
    beta = np.asarray(beta, dtype=np.float64)
    _check_physical(form, beta)
    P = np.asarray(P, dtype=np.float64)
    p = beta.size
    if P.shape != (p, p) or not np.all(np.isfinite(P)):
        raise ValueError(f"P must be a finite ({p}, {p}) covariance")
    fbuf, ibuf = new_beta_buffers(beta, names, Ts, 1, gain=gain, P0=np.eye(p))
    probe = beta_state_views(fbuf, ibuf)
    Ps = 0.5 * (P + P.T)
    probe.cov[:] = Ps                             # P = Λ⁻¹ Ψ Λ⁻ᵀ with Λ⁻¹ = P, Ψ = P⁺
    probe.psi[:] = np.linalg.pinv(Ps, hermitian=True)
    theta, se = np.zeros(N_PHYS), np.zeros(N_PHYS)
    physical_se_buffers(fbuf, ibuf, theta, se, np.zeros((N_PHYS + 2, p)))
    return theta, se


class JointStep(NamedTuple):
    """What :meth:`OnlineBeta.learn_one` reports (signal units: m/s, (m/s)²).

    ``residual`` ``r = y − β̂ᵀz``; ``innovation`` ``e = r − f̂``; ``nu`` ``e/√S`` (the health
    input); ``variance`` ``S``; ``weight`` the Huber weight; ``learned`` β was updated;
    ``filtered`` the disturbance at the trained x given the new β̂; ``removed``/``reduced`` as
    :class:`kernels.krlst.Step`.
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
    min_speed : float
        No learning while ``|v_m(k)| ≤ min_speed`` either (m/s, default 0): below it the model's
        friction law does not hold (:mod:`kernels.low_speed`).
    gain : float, optional
        Velocity-loop gain K (N·s/m); without it physical values are ``J/K, B/K, d/K``.
    beta_cov : array, optional
        Model-file covariance (p×p) or standard errors (p,) of β.
    allowance : float
        ρ, the relative drift allowance of the prior (default 0.3).
    memory : float
        T_β (s of learning samples), the forgetting time constant of the friction parameters —
        damping, Coulomb, offset (default 5 s).
    inertia_memory : float, optional
        The inertia's (default 10 s; None: ``memory``). Module docstring, "Drift rate trade-off".
    huber : float
        Huber threshold c (standard deviations, default 3).
    reject, hold : float, optional
        A sample with ``|ν| ≥ reject`` teaches nothing, nor do the ``hold`` seconds after one.
        Off by default (None): a wrong β makes ``|ν|`` large too, so the rule delays the
        learning after a real parameter step (measured: payload step detected after 7 s instead
        of 1 s with the REML tracker at reject = 8; 20 s with a 0.1 s hold); it halves what β
        takes from an abrupt 300 N disturbance (0.4 % instead of 1.3 %).
    instrument : bool
        Use the model's one-step velocity prediction as the instrument of the measured
        velocity (default True: removes the bias of noise that the velocity loop feeds back).
    enabled : bool
        False: β stays at β₀ (the joint bookkeeping still runs; ``nu`` is the tracker's).
    warmup : int, optional
        Trained samples before β learns (default: the tracker's budget).
    rebase_every : int
        Re-base the tracker's mean to β̂ every so many trained samples (*apply*, default 64);
        0: never (*track*: the published disturbance keeps the model file's β).

    Examples
    --------
    >>> ob = OnlineBeta(KRLST(LocallyPeriodic(1.2, 0.495, 1/55), gamma=300, forgetting=0.998, budget=100),
    ...                 beta0, ("v_ref", "v_meas", "-sigma_p", "-sigma_n"), 1/333, omega=5e-4, gain=83300)
    >>> f_next, f_var = ob.predict_one(t[0])          # arm at x(0)
    >>> step = ob.learn_one(z0, v_meas[1])             # residual of step 0 known: learn
    """

    def __init__(self, tracker, beta0, names, Ts: float, *, omega: float = 0.0, gain: float | None = None,
                 beta_cov=None, allowance: float = 0.3, memory: float = 5.0, inertia_memory: float | None = 10.0,
                 huber: float = 3.0, reject: float | None = None, hold: float = 0.0, instrument: bool = True,
                 enabled: bool = True, warmup: int | None = None, rebase_every: int = REBASE_EVERY,
                 min_speed: float = 0.0):
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
        self._kw = dict(omega=omega, gain=gain, P0=self.P0, memory=memory, inertia_memory=inertia_memory,
                        huber=huber, instrument=instrument,
                        enabled=enabled, warmup=warmup, reject=reject, hold=hold, rebase_every=rebase_every,
                        min_speed=min_speed)
        self._beta0 = np.asarray(beta0, dtype=np.float64).copy()
        self._buf = new_beta_buffers(self._beta0, self.names, Ts, tracker.budget, **self._kw)
        self.state = beta_state_views(*self._buf)
        self._x = None
        self._out = np.zeros(core.N_OUT)
        self._bout = np.zeros(N_BOUT)
        self._z = np.zeros(len(self.names))
        self._cw = np.zeros((N_PHYS + 2, len(self.names)))
        self.prior_se = physical_of(self._beta0, self.names, Ts, self.P0, gain=gain)[1]

    # ------------------------------------------------------------------ state views
    @property
    def beta(self) -> np.ndarray:
        """β̂ (a copy)."""
        return self.state.beta.copy()

    @property
    def covariance(self) -> np.ndarray:
        """``P = Λ⁻¹ Ψ Λ⁻ᵀ`` (a copy)."""
        Li = self.state.cov
        return Li @ self.state.psi @ Li.T

    @property
    def counters(self) -> dict[str, int]:
        c = self.state.cnt
        return {"updates": int(c[C_UPDATES]), "gated": int(c[C_GATED]), "projected": int(c[C_PROJECTED]),
                "downweighted": int(c[C_DOWNWEIGHTED]), "rejected": int(c[C_REJECTED]),
                "trained": int(c[C_TRAINED])}

    def physical(self) -> dict[str, tuple[float, float]]:
        """``{name: (value, standard error)}`` per :data:`PHYSICAL` (delta method; NaN when the model
        has no such column). Without the loop gain (velocity-loop) the values are over K."""
        theta, se = np.zeros(N_PHYS), np.zeros(N_PHYS)
        physical_se_buffers(*self._buf, theta, se, self._cw)
        return {k: (float(a), float(b)) for k, a, b in zip(PHYSICAL, theta, se)}

    @property
    def shadow_means(self) -> np.ndarray:
        """``M_Z`` of the regressors in the tracker's slots, in signal units (a copy)."""
        return self.state.MZ[:, :len(self.names)] * self.state.sst[S_SCALE]

    @property
    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """The two base buffers of :attr:`state`, for compiled loops (:func:`kernels.online.track_block`)."""
        return self._buf

    def _core(self, x_example) -> tuple[np.ndarray, np.ndarray]:
        return self.tracker.core_buffers(x_example)

    def rebase(self) -> None:
        """Re-express the tracker's mean with the current β̂ now (done every ``rebase_every`` samples)."""
        if self._x is None:
            return
        rebase_buffers(*self._core(self._x), *self._buf)

    # ------------------------------------------------------------------ steps
    def regressor(self, exo: float, v: float) -> np.ndarray:
        """``z(k)`` for the command ``exo`` (v_ref or u) and measured velocity ``v`` (a copy)."""
        lay = self.state.lay
        regressor(lay[L_FORM] == 1, lay[L_ISP], lay[L_ISN], lay[L_IONE], self.state.par[P_OMEGA], float(exo),
                  float(v), self._z)
        return self._z.copy()

    def _as_x(self, x) -> np.ndarray:
        xa = np.ascontiguousarray(np.atleast_1d(np.asarray(x, dtype=np.float64)))
        if xa.ndim != 1 or not np.all(np.isfinite(xa)):
            raise ValueError(f"x must be finite (a float or a 1-D array), got {x!r}")
        return xa

    def predict_one(self, x) -> tuple[float, float]:
        """Arm the tracker at ``x`` (forget, predict): the one-step prediction of the disturbance at
        ``x`` given β̂ and its variance (signal units; NaN variance before the first sample)."""
        xa = self._as_x(x)
        was_empty = self.tracker.size == 0
        joint_arm_buffers(*self._core(xa), *self._buf, xa, self._out)
        self._x = xa
        var = math.nan if was_empty else float(self._out[core.A_SF2]) * self.tracker.s02
        return float(self._out[core.A_MEAN]), var

    def learn_one(self, z, y: float, *, gate: bool = True) -> JointStep:
        """Learn from the regressor ``z`` of the armed sample and ``y = v_m(k+1)``."""
        za = np.ascontiguousarray(z, dtype=np.float64)
        if za.shape != (len(self.names),) or not np.all(np.isfinite(za)) or not math.isfinite(y):
            raise ValueError(f"z must be {len(self.names)} finite values and y finite; got z={z!r}, y={y!r}")
        if not self.tracker.armed or self._x is None:
            raise RuntimeError("learn_one needs an armed prediction: call predict_one(x) first")
        joint_update_buffers(*self._core(self._x), *self._buf, za, float(y), bool(gate), self._out, self._bout)
        b = self._bout
        return JointStep(float(b[B_RESID]), float(b[B_INNOV]), float(b[B_NU]), float(b[B_VAR]), float(b[B_WEIGHT]),
                         bool(b[B_LEARNED]), float(b[B_FILTERED]), int(self._out[core.O_REMOVED]),
                         bool(self._out[core.O_REDUCED]))

    def track(self, t, exo, v, gate=None) -> dict[str, np.ndarray]:
        """One uninterrupted stream in one compiled loop (the monitor's order: at sample ``j ≥ 1`` learn
        from ``(z(j−1), v(j))``, then arm at ``t[j]``; ``t`` the tracker inputs, ``(n,)`` times or
        ``(n, d)``). Continues a stream when the tracker is armed (then ``t[0]`` must be the armed
        sample). Returns ``f_next`` (prediction of f(j) made at j), ``f_next_var``, ``learned``,
        ``nu``, ``residual``, ``filtered``, ``weight`` per sample."""
        X = np.asarray(t, dtype=np.float64)
        X = np.ascontiguousarray(X.reshape(-1, 1) if X.ndim == 1 else X)
        exo = np.ascontiguousarray(exo, dtype=np.float64)
        v = np.ascontiguousarray(v, dtype=np.float64)
        n = X.shape[0]
        if X.ndim != 2 or exo.shape != (n,) or v.shape != (n,):
            raise ValueError(f"t, exo, v must have the same length; got {X.shape}, {exo.shape}, {v.shape}")
        for name, a in (("t", X), ("exo", exo), ("v", v)):
            if not np.all(np.isfinite(a)):
                bad = int(np.argmax(~np.isfinite(a.reshape(n, -1)).any(axis=1)))
                raise ValueError(f"{name} must be finite; element {bad} is not")
        g = np.ones(n, dtype=np.bool_) if gate is None else np.ascontiguousarray(gate, dtype=np.bool_)
        rows = np.zeros((n, 7))
        if n == 0:
            return {k: rows[:, i] for i, k in enumerate(("f_next", "f_next_var", "learned", "nu", "residual",
                                                         "filtered", "weight"))}
        resume = self.tracker.armed
        track_joint(*self._core(X[0]), *self._buf, X, exo, v, g, resume, self._out, self._bout, self._z, rows)
        self._x = X[-1].copy()
        return {"f_next": rows[:, 0], "f_next_var": rows[:, 1], "learned": rows[:, 2] == 1.0, "nu": rows[:, 3],
                "residual": rows[:, 4], "filtered": rows[:, 5], "weight": rows[:, 6]}

    def breakdown(self) -> str | None:
        """Why the β recursion has left what exact arithmetic allows, or None: a non-finite β̂ or
        covariance factor, or ``Λ⁻¹`` or ``P = Λ⁻¹ΨΛ⁻ᵀ`` no longer positive on the diagonal (roundoff in
        the rank-one updates on nearly collinear regressors). The recursion never recovers by itself."""
        st = self.state
        for name in ("beta", "cov", "psi"):
            if not np.all(np.isfinite(getattr(st, name))):
                return f"non-finite {name}"
        if not np.all(np.diag(st.cov) > 0.0):
            return "Λ⁻¹ lost its positive diagonal"
        if not np.all(np.diag(st.cov @ st.psi @ st.cov.T) > 0.0):
            return "the covariance of β lost its positive diagonal"
        return None

    def reseated(self, tracker, X, exo, v, target, x_now) -> OnlineBeta:
        """This β estimate joined to another (fresh) tracker — a new disturbance model: the tracker and
        its shadow means are rebuilt from recorded samples (:func:`replay_joint`, β not learning), then
        β̂, its covariance, the instrument's prediction and the counters are carried over. In *apply*
        mode the tracker learns the residual of the current ``β_trk``."""
        if tracker.size:
            raise ValueError("reseated needs a fresh tracker")
        new = OnlineBeta.__new__(OnlineBeta)
        new.__dict__.update(self.__dict__)
        new.tracker = tracker
        new._buf = new_beta_buffers(self._beta0, self.names, self.Ts, tracker.budget, **self._kw)
        new.state = beta_state_views(*new._buf)
        new._out = np.zeros(core.N_OUT)
        new._bout = np.zeros(N_BOUT)
        new._z = np.zeros(len(self.names))
        bs, old = new.state, self.state
        bs.beta_trk[:] = old.beta_trk
        enabled = bs.par[P_ENABLED]
        bs.par[P_ENABLED] = 0.0
        if x_now is None:                         # nothing accepted yet: nothing to replay or arm at
            new._x = None
        else:
            xn = np.ascontiguousarray(np.atleast_1d(np.asarray(x_now, dtype=np.float64)))
            Xa = np.ascontiguousarray(np.asarray(X, dtype=np.float64).reshape(len(target), xn.size))
            replay_joint(*tracker.core_buffers(xn), *new._buf, Xa, np.ascontiguousarray(exo, dtype=np.float64),
                         np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(target, dtype=np.float64),
                         xn, new._out, new._bout, new._z)
            new._x = xn
        bs.par[P_ENABLED] = enabled
        for name in ("beta", "cov", "psi"):
            getattr(bs, name)[:] = getattr(old, name)
        bs.sst[S_FJN:S_FJW + 1] = old.sst[S_FJN:S_FJW + 1]   # the fast inertia estimate goes on
        arms, vhat_arm = bs.cnt[C_ARMS], bs.cnt[C_VHAT_ARM]
        bs.cnt[:] = old.cnt
        bs.cnt[C_ARMS], bs.cnt[C_VHAT_ARM] = arms, vhat_arm   # the instrument's v̂: the new tracker's
        return new

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, np.ndarray]:
        """The β state (:data:`STATE_FIELDS`) as plain arrays (copies); persist it together with
        ``tracker.snapshot()`` taken at the same moment (the shadow means live in the tracker's slots)."""
        return {f"beta.{k}": np.array(getattr(self.state, k), copy=True) for k in STATE_FIELDS}

    def restore(self, snap: dict, tracker) -> None:
        """Continue from :meth:`snapshot` with the tracker restored from the same moment; raises
        ``ValueError`` naming the entry (shape, dtype, :func:`validate_beta_state`) and leaves this
        object as it was."""
        if tracker.budget != self.tracker.budget:
            raise ValueError(f"the tracker's budget {tracker.budget} does not match this estimator's "
                             f"{self.tracker.budget}")
        buf = new_beta_buffers(self._beta0, self.names, self.Ts, tracker.budget, **self._kw)
        bs = beta_state_views(*buf)
        fill_views(bs, snap, STATE_FIELDS, prefix="beta.", what="beta snapshot")
        occ = np.zeros(tracker.budget + 1)
        if tracker.size or tracker.armed:
            st = tracker.core_state(np.zeros(tracker.dictionary.shape[1]))
            occ = st.occ[: tracker.budget + 1]
        validate_beta_state(bs, beta_state_views(*new_beta_buffers(self._beta0, self.names, self.Ts, tracker.budget,
                                                                    **self._kw)), occ)
        self._buf = buf
        self.state = bs
        self.tracker = tracker
        self._x = None
        if tracker.armed:
            st = tracker.core_state(np.zeros(tracker.dictionary.shape[1]))
            self._x = st.X[st.order[st.ist[core.I_N]]].copy()
