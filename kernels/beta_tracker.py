"""Online β: the linear feed-drive parameters estimated jointly with the KRLS-T tracker (method §9).

The model is the PL-ARX regression ``y(k) = v_m(k+1) = βᵀz(k) + f(x(k)) + ε(k)``, ``f ~ GP(0, s0² k)``,
with ``f`` tracked by KRLS-T; this is the recursive counterpart of PL-LSSVM's GLS estimate (method §4)
with the *tracker's* GP. KRLS-T's posterior mean is linear in its targets and nothing else in its state
depends on them, so a *shadow* mean ``M_Z`` (one column per regressor, in the tracker's slots, trained
with the same gains on ``z``) gives, for every β,

    μ(β) = μ_y − M_Z β,   f̂(x | β) = qᵀμ(β)                                                  (1)
    e(k) = ỹ − β̂ᵀz̃,  z̃ = z − ẑ,  ẑ = M_Zᵀq,  E[e²] = R + z̃ᵀPz̃,  R = s0² σ_y² (eq. 2.17/2.20)

and β given the data is recursive least squares on ``(z̃, e)`` weighted by ``1/R`` (tested against the
dense formula ``(Z̃ᵀA⁻¹Z̃)⁻¹ Z̃ᵀA⁻¹ y``). Per learning sample (Λ the information, kept as ``Λ⁻¹``; ζ̃ the
instrument, = z̃ without it):

    g = Λ⁻¹ζ̃,  s = z̃ᵀΛ⁻¹ζ̃,  S = R + s,  ν = e/√S                   gain direction, innovation (3)
    z̃, ζ̃ ← x − (xᵀd/3) d,  d = e_sp + e_sn + e_one                 off the rest direction     (3')
    w = min(1, c/|ν|),  R_w = R/w                                  Huber weight               (4)
    β̂ ← β̂ + g e/(R_w + s),  Λ⁻¹ ← Λ⁻¹ − g (z̃ᵀΛ⁻¹)/(R_w + s)         RLS update                 (5)
    Ψ ← Ψ + ζ̃ζ̃ᵀ R/R_w²,  P = Λ⁻¹ΨΛ⁻ᵀ                               sandwich covariance        (5')
    every m = 16 samples, per physical parameter (G = ∂β/∂θ at β₀, T = G diag(√λ_i^m) G⁻¹,
    S = G diag(√(1 − λ_i^m)) G⁻¹):  Λ ← TᵀΛT + SᵀΛ₀S, Ψ likewise,
    β̂ ← β̂ + Λ⁻¹SᵀΛ₀S(β₀ − β̂)                                      forgetting to N(β₀, P₀)    (2)
    projection onto the physical set when β̂ leaves it                                         (7)
    μ ← μ − M_Z(β̂ − β_trk),  β_trk ← β̂ every 64 samples; in between the
    predictions are corrected exactly by ẑᵀ(β̂ − β_trk)                                        (6)

Why: (6) keeps (1) true, so the published disturbance always goes with the current β̂ and stays
unbiased while β adapts. ``z̃`` is the part of ``z`` the GP cannot predict, so β learns only what is
persistently correlated with it and the tracker keeps what varies fast or periodically. (5) moves β̂
only along excited directions; nothing is learned at rest (``|v_m| ≤ Ω``: stiction), from the first
sample of a run of motion (the Coulomb column steps, the drive's force does not), below ``min_speed``
(:mod:`kernels.low_speed`) or during warm-up. (3') keeps the rest direction — told only by samples at
rest — out of the update. (2) runs on learning samples only, so ``P`` is bounded by ``P₀`` and a
standstill neither learns nor forgets; inertia (memory ``T_J``) and friction (``T_β``) forget at their
own rates because they are excited at different times. The prior ``P₀ = P_file + G diag((ρθ₀)²) Gᵀ``
(:func:`prior_covariance`) bounds how far the parameters may plausibly move. The instrument of the
``v_m`` column is the model's own prediction made before ``v_m`` was seen (recursive IV, Young),
because ``v_m``'s noise is fed back by the loop. The projection (7) (Simon & Chia 2002) keeps β̂ a
physical drive. Measurements behind these choices: ``docs/design-decisions.md``, "Kernels".

Modes: with the re-basing (6) this is *apply*; with ``rebase_every = 0`` (*track*) the tracker's mean
keeps the model file's β and β̂ is only estimated and reported.

The module is split by concern: :mod:`kernels.beta_layout` (the state's field list and slots),
:mod:`kernels.beta_prior` (prior, constraints, a fresh state), :mod:`kernels.linalg_small`,
:mod:`kernels.beta_step` (the compiled step, run by :func:`kernels.online.track_block`),
:mod:`kernels.beta_se` (physical parameters and standard errors); this module is the thin Python API,
:class:`OnlineBeta` (river-style ``learn_one`` / ``predict_one``, snapshot/restore as plain arrays
of :data:`STATE_FIELDS`), and re-exports the names callers use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from . import _krlst_core as core
from ._snapshot import fill_views

# names callers import from here since the module was split by concern
from .beta_layout import (  # noqa: F401, E402
    B_FILTERED,
    B_INNOV,
    B_LEARNED,
    B_NU,
    B_RESID,
    B_VAR,
    B_WEIGHT,
    BOUT,
    C_ARMS,
    C_DOWNWEIGHTED,
    C_GATED,
    C_PROJECTED,
    C_REJECTED,
    C_SEEN,
    C_UPDATES,
    C_VHAT_ARM,
    FORGET_EVERY,
    J_LEARNED,
    JOINT_ROWS,
    L_FORM,
    L_IONE,
    L_ISN,
    L_ISP,
    MIN_SPEED_MAX,
    N_BOUT,
    N_PHYS,
    P_ENABLED,
    P_OMEGA,
    PHYSICAL,
    REBASE_EVERY,
    S_FJN,
    S_FJW,
    S_SCALE,
    SETTINGS_FIELDS,
    STATE_FIELDS,
    BetaState,
    beta_state_of,
    beta_state_views,
)
from .beta_prior import (
    _layout,
    new_beta_buffers,
    parameter_basis,  # noqa: F401, E402
    prior_covariance,
    validate_beta_state,
)
from .beta_se import fast_inertia, physical_of, physical_se, physical_se_buffers
from .beta_step import (
    _forget,  # noqa: F401, E402
    joint_arm,
    joint_arm_buffers,
    joint_update,
    joint_update_buffers,
    rebase_buffers,
    regressor,
    replay_joint,
    replay_joint_rows,
    track_joint,
)

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
    "Rebuilt",
    "JointStep",
    "PHYSICAL",
    "BOUT",
    "STATE_FIELDS",
    "SETTINGS_FIELDS",
]


_POSITIVE = (0.0).__lt__  # x > 0 of a Python float
#: what :func:`_first_broken` found, by its return value (0: nothing)
_BROKEN = (None, "non-finite beta", "non-finite cov", "non-finite psi", "Λ⁻¹ lost its positive diagonal")


@njit(cache=True, nogil=True, inline="always")
def _all_finite(m):
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            if not math.isfinite(m[i, j]):
                return False
    return True


@njit(cache=True, nogil=True)
def _first_broken(beta, cov, psi):
    """The first exact test of :meth:`OnlineBeta.breakdown` that fails, as an index into :data:`_BROKEN`
    (0: none): a non-finite β̂, ``Λ⁻¹``, ``Ψ``, then a diagonal of ``Λ⁻¹`` not positive. One compiled call
    instead of a dozen NumPy reductions: the monitor asks after every block, one sample at 333 Hz."""
    for x in beta:
        if not math.isfinite(x):
            return 1
    if not _all_finite(cov):
        return 2
    if not _all_finite(psi):
        return 3
    for i in range(cov.shape[0]):
        if not cov[i, i] > 0.0:
            return 4
    return 0


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


#: what :meth:`OnlineBeta.reseated` keeps of a replay begun: the new tracker and β state, their scratch
_OWN = ("tracker", "_buf", "state", "_out", "_bout", "_z")


@dataclass(frozen=True)
class Rebuilt:
    """A replay begun by :meth:`OnlineBeta.rebuilt`: the new estimate (tracker and shadow means fed the
    record, not armed), β's learning switch of its fresh buffers, and the ``β_trk`` it replayed with."""

    new: OnlineBeta
    enabled: float
    beta_trk: np.ndarray

    def fits(self, online: OnlineBeta) -> bool:
        """``online`` still has the ``β_trk`` of the replay (*apply* mode rebases it as β is learned)."""
        return bool(np.array_equal(self.beta_trk, online.state.beta_trk))


class OnlineBeta:
    """Online β joined to a KRLS-T tracker (:mod:`kernels.beta_tracker`); river-style API.

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
        The inertia's (default 10 s; None: ``memory``): the inertia is excited only while the axis
        accelerates, so it needs a longer memory than friction.
    huber : float
        Huber threshold c (standard deviations, default 3).
    reject, hold : float, optional
        A sample with ``|ν| ≥ reject`` teaches nothing, nor do the ``hold`` seconds after one.
        Off by default (None): a wrong β makes ``|ν|`` large too, so the rule delays the
        learning after a real parameter step (the trade-off measured: ``docs/design-decisions.md``).
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
                "trained": int(c[C_SEEN])}

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
        rows = np.zeros((n, len(JOINT_ROWS)))
        if n == 0:
            return {k: rows[:, i] for i, k in enumerate(JOINT_ROWS)}
        resume = self.tracker.armed
        track_joint(*self._core(X[0]), *self._buf, X, exo, v, g, resume, self._out, self._bout, self._z, rows)
        self._x = X[-1].copy()
        out = {k: rows[:, i] for i, k in enumerate(JOINT_ROWS)}
        out["learned"] = rows[:, J_LEARNED] == 1.0
        return out

    def breakdown(self) -> str | None:
        """Why the β recursion has left what exact arithmetic allows, or None: a non-finite β̂ or
        covariance factor, or ``Λ⁻¹`` or ``P = Λ⁻¹ΨΛ⁻ᵀ`` no longer positive on the diagonal (roundoff in
        the rank-one updates on nearly collinear regressors). The recursion never recovers by itself."""
        st = self.state
        bad = _first_broken(st.beta, st.cov, st.psi)
        if bad:
            return _BROKEN[bad]
        # NumPy's product, not a compiled loop: its rounding decides a diagonal at zero (NaN is not > 0)
        if not all(map(_POSITIVE, (st.cov @ st.psi @ st.cov.T).diagonal().tolist())):
            return "the covariance of β lost its positive diagonal"
        return None

    def reseated(self, tracker, X, exo, v, target, x_now, *, begun: Rebuilt | None = None) -> OnlineBeta:
        """This β estimate joined to another (fresh) tracker — a new disturbance model: the tracker and
        its shadow means are rebuilt from recorded samples (:func:`replay_joint`, β not learning), then
        β̂, its covariance, the instrument's prediction and the counters are carried over. In *apply*
        mode the tracker learns the residual of the current ``β_trk``.

        ``begun``: the first part of the record already replayed (:meth:`rebuilt`, e.g. on another
        thread); ``X, exo, v, target`` are then the samples recorded after it. The result is the same as
        one call on the whole record, provided ``β_trk`` is still the one it replayed with
        (:meth:`Rebuilt.fits`)."""
        if begun is None:
            if tracker.size:
                raise ValueError("reseated needs a fresh tracker")
            begun = self.rebuilt(tracker, X[:0], exo[:0], v[:0], target[:0])
        elif begun.new.tracker is not tracker or not begun.fits(self):
            raise ValueError("reseated: the replay begun is of another tracker or another β_trk")
        new = begun.new
        own = {k: new.__dict__[k] for k in _OWN}
        new.__dict__.update(self.__dict__)        # what this estimate is now, but for the replayed parts
        new.__dict__.update(own)
        bs, old = new.state, self.state
        if x_now is None:                         # nothing accepted yet: nothing to replay or arm at
            new._x = None
        else:
            xn = np.ascontiguousarray(np.atleast_1d(np.asarray(x_now, dtype=np.float64)))
            Xa = np.ascontiguousarray(np.asarray(X, dtype=np.float64).reshape(len(target), xn.size))
            replay_joint(*tracker.core_buffers(xn), *new._buf, Xa, np.ascontiguousarray(exo, dtype=np.float64),
                         np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(target, dtype=np.float64),
                         xn, new._out, new._bout, new._z)
            new._x = xn
        bs.par[P_ENABLED] = begun.enabled
        for name in ("beta", "cov", "psi"):
            getattr(bs, name)[:] = getattr(old, name)
        bs.sst[S_FJN:S_FJW + 1] = old.sst[S_FJN:S_FJW + 1]   # the fast inertia estimate goes on
        arms, vhat_arm = bs.cnt[C_ARMS], bs.cnt[C_VHAT_ARM]
        bs.cnt[:] = old.cnt
        bs.cnt[C_ARMS], bs.cnt[C_VHAT_ARM] = arms, vhat_arm   # the instrument's v̂: the new tracker's
        return new

    def rebuilt(self, tracker, X, exo, v, target) -> Rebuilt:
        """The first part of :meth:`reseated`: a fresh ``tracker`` and its shadow means fed the recorded
        samples (:func:`replay_joint_rows`, β not learning, the residual of this estimate's ``β_trk``),
        not armed, nothing carried over. It reads only ``β_trk`` and the settings of this estimate, so it
        may run on another thread while the estimate goes on (the replay of a long record is tens of
        milliseconds that no sample should wait for)."""
        if tracker.size:
            raise ValueError("rebuilt needs a fresh tracker")
        new = OnlineBeta.__new__(OnlineBeta)
        new.__dict__.update(self.__dict__)
        new.tracker = tracker
        new._buf = new_beta_buffers(self._beta0, self.names, self.Ts, tracker.budget, **self._kw)
        new.state = beta_state_views(*new._buf)
        new._out = np.zeros(core.N_OUT)
        new._bout = np.zeros(N_BOUT)
        new._z = np.zeros(len(self.names))
        bs = new.state
        beta_trk = self.state.beta_trk.copy()     # (the replay may rebase the new one)
        bs.beta_trk[:] = beta_trk
        enabled = float(bs.par[P_ENABLED])
        bs.par[P_ENABLED] = 0.0
        n = len(target)
        if n:
            X = np.asarray(X, dtype=np.float64).reshape(n, -1)
            Xa = np.ascontiguousarray(X)
            replay_joint_rows(*tracker.core_buffers(np.ascontiguousarray(Xa[0])), *new._buf, Xa,
                              np.ascontiguousarray(exo, dtype=np.float64), np.ascontiguousarray(v, dtype=np.float64),
                              np.ascontiguousarray(target, dtype=np.float64), new._out, new._bout, new._z)
        return Rebuilt(new, enabled, beta_trk)

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
