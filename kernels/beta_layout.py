"""Layout of the online β state: its named slots and the one field list of :class:`BetaState`.

The state is one :class:`BetaState` of named views of two base buffers (``float64``, ``int64``),
generated from :data:`FIELDS` by :class:`kernels.layout.Layout` (:func:`beta_state_views` from
Python, :func:`beta_state_of` inside compiled code), as the KRLS-T core's
:class:`~kernels._krlst_core.State`. Equation numbers refer to :mod:`kernels.beta_tracker`.
"""

from __future__ import annotations

import math

import numpy as np

from .layout import Field, Layout

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
#: slots of ``cnt`` (counters and instrument bookkeeping: state; C_SEEN: samples the β step has seen, the
#: warm-up count, reported as "trained")
(C_UPDATES, C_GATED, C_PROJECTED, C_DOWNWEIGHTED, C_ARMS, C_VHAT_ARM, C_SEEN, C_SINCE_REBASE,
 C_SINCE_FORGET, C_QUIET, C_REJECTED, C_DIR, C_VSIM_ARM) = range(13)
N_CNT = 13
#: slots of ``sst`` (float state): the scale of the stored shadow means, the stored velocity prediction,
#: the velocity the model simulates from the command alone (the velocity-loop instrument, eq. 8), the
#: accumulators of the fast inertia estimate (eq. 9: Σ ζ_J e/R, Σ ζ_J s_J/R, Σ ζ_J²/R, and Σ 1: how full its
#: memory is)
(S_SCALE, S_VHAT, S_VSIM, S_FJN, S_FJD, S_FJV, S_FJW) = range(7)
N_SST = 7
#: share of a full memory (1/(1 − λ)) the fast inertia estimate needs before it is tested: two time
#: constants (4 s of learning samples), so the first seconds of a cut, while the disturbance model is
#: still learning the process, are not read as a payload step
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
#: columns of a row of :func:`kernels.beta_step.track_joint` (``rows[j]``): the one-step prediction of
#: ``f(j)`` made at sample ``j`` and its variance, then the outputs of the update sample ``j`` completed
JOINT_ROWS = ("f_next", "f_next_var", "learned", "nu", "residual", "filtered", "weight")
(J_FNEXT, J_FNEXTVAR, J_LEARNED, J_NU, J_RESID, J_FILTERED, J_WEIGHT) = range(len(JOINT_ROWS))
#: rows of the scratch ``vec``
V_ZT, V_ZETA, V_G, V_TMP, V_BEFORE, V_X, V_ZTR, V_ZETAR, V_SIM = range(9)  # V_BEFORE: the forgetting's step;
N_VEC = 9                      # V_ZTR, V_ZETAR: z̃, ζ̃ off the rest direction; V_SIM: the simulation's regressor
_HEADER = 4                 # int buffer: p, cap, number of constraints, (spare)


#: every field of :class:`BetaState`: ``p`` entries of β, ``cap = M+1`` tracker slots, ``ncons``
#: constraints ``aᵀβ ≤ b``. Roles: ``setting`` fixed for a model (a restored state must hold the same),
#: ``state`` saved by snapshots, ``scratch`` not kept
FIELDS = (
    Field("layout", "i8", (_HEADER,), "layout", "p, cap, number of constraints"),
    Field("lay", "i8", (N_LAY,), "setting", "the column layout and the re-basing interval (L_*)"),
    Field("cnt", "i8", (N_CNT,), "state", "counters (C_*)"),
    Field("piv", "i8", ("p",), "scratch", "LU pivots"),
    Field("par", "f8", (N_PAR,), "setting", "float settings (P_*)"),
    Field("beta0", "f8", ("p",), "setting", "the model file's β"),
    Field("info0", "f8", ("p", "p"), "setting", "Λ₀ = P₀⁻¹"),
    Field("cons", "f8", ("ncons", "p + 1"), "setting", "rows [a, b] of the constraints aᵀβ ≤ b"),
    Field("forget", "f8", (2, "p", "p"), "setting", "T and S of the forgetting (2)"),
    Field("dirj", "f8", ("p",), "setting", "∂β/∂J at β₀, the direction of the inertia (eq. 9)"),
    Field("beta", "f8", ("p",), "state", "β̂"),
    Field("beta_trk", "f8", ("p",), "state", "the β the tracker's mean goes with (re-based to β̂ in apply mode)"),
    Field("cov", "f8", ("p", "p"), "state", "Λ⁻¹, Λ = Σ ζ̃z̃ᵀ/R + prior (rank-one updates)"),
    Field("psi", "f8", ("p", "p"), "state", "Ψ = Σ ζ̃ζ̃ᵀ R/R_w² + prior (P = Λ⁻¹ΨΛ⁻ᵀ)"),
    Field("MZ", "f8", ("cap", "p + 1"), "state", "shadow means of the regressors and the instrument, / sst[S_SCALE]"),
    Field("zhat", "f8", ("p + 1",), "state", "ẑ = M_Zᵀq armed with the tracker"),
    Field("sst", "f8", (N_SST,), "state", "float state (S_*)"),
    Field("info", "f8", ("p", "p"), "scratch", "Λ"),
    Field("lu", "f8", ("p", "p"), "scratch", "LU factors"),
    Field("vec", "f8", (N_VEC, "p"), "scratch", "vectors (V_*)"),
    Field("work", "f8", ("p", "p"), "scratch", "the forgetting's"),
    Field("zx", "f8", ("p + 1",), "scratch", "[z̃; ζ̃_sim], the shadow update's step"),
)
LAYOUT = Layout("BetaState", __name__, FIELDS, dims=("p", "cap", "ncons"),
                doc="State of the online β estimator: named views of two base buffers (:data:`FIELDS`).")
BetaState = LAYOUT.tuple

#: the fields that are the estimator's state (snapshots); the others are settings or scratch
STATE_FIELDS = LAYOUT.names("state")
#: the fields fixed by the model and the settings (a restored state must hold the same)
SETTINGS_FIELDS = LAYOUT.names("setting")


def beta_state_views(fbuf: np.ndarray, ibuf: np.ndarray) -> BetaState:
    """The :class:`BetaState` of the two base buffers, as NumPy views."""
    return LAYOUT.views(fbuf, ibuf)


#: ``beta_state_of(fbuf, ibuf)``: the :class:`BetaState` of the two base buffers inside compiled code,
#: reference-free views (valid while the buffers are; never return them to Python — use
#: :func:`beta_state_views`)
beta_state_of = LAYOUT.accessor("beta_state_of", __file__)
