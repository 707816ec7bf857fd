"""KRLS-T: kernel recursive least-squares tracker (method §6, thesis §2.2.3, Algorithm 1).

Online Gaussian-process regression of the disturbance ``f`` with a fixed-budget
dictionary and back-to-the-prior forgetting (Van Vaerenbergh, Lázaro-Gredilla and
Santamaría 2012; reference implementation kafbox ``lib/krlst.m``).

Symbols (thesis → code): ``Ω_D``/``K_D`` kernel matrix of the dictionary ``D``;
``Q ≈ K_D⁻¹`` (``K_D`` with ``ε_j`` on the diagonal); posterior ``N(μ, Σ)`` of ``f`` at ``D`` (normalised, i.e.
in units of the signal power ``s0²``); ``σ² = sn2 = 1/γ`` noise-to-signal ratio;
``λ`` forgetting factor; ``M`` budget; ``ε_j`` jitter.

Per sample ``(x, y)`` (method §6):

1. forget, eq. 2.19:     ``Σ ← λΣ + (1−λ)K_D``,  ``μ ← √λ μ``
2. predict, eq. 2.17:    ``q = Q k_t``, ``ŷ = qᵀμ``, ``γ² = k_tt − k_tᵀq``, ``h = Σq``,
   ``σ_f² = γ² + qᵀh``, ``σ_y² = sn2 + σ_f²``
3. update, eq. 2.14–2.15: ``μ, Σ, Q`` grow by the new basis ``x``
4. signal power, eq. 2.20 (with the square): ``s0² = num/den``
5. prune, eq. 2.21–2.22: when ``|D| > M`` or ``γ² < ε_j``
6. initialise, eq. 2.16, on the first sample.

Every ``refresh_every`` steps ``Q`` is recomputed from the cached ``K_D`` (Cholesky);
with ``refine=True`` the ``Q`` update itself is refined, which keeps
``max|Q K_D − I|`` ~1e-9 at ``ε_j = 1e-6`` (kafbox's recursion: ~3e-6, peaks ~1e-3).

Monitor timing (method §6): :meth:`KRLST.predict_next` does steps 1–2 at ``x(k+1)``
in place as soon as it arrives, :meth:`KRLST.update` does steps 3–5 with the residual
once it is known; ``learn_one(x, y)`` is exactly ``predict_next(x)`` then ``update(y)``.
:meth:`KRLST.track_many` runs that pattern over a block in one ``@njit`` call.

The numerics live in :mod:`kernels._krlst_core` (``@njit``, allocation-free); its
:class:`~kernels._krlst_core.State` is what :meth:`KRLST.core_state` hands to compiled loops
that drive the tracker (:func:`kernels.online.track_block`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral, Real
from operator import itemgetter

import numpy as np

from . import _krlst_core as core
from ._snapshot import fill_views
from .covariance import (
    KIND_LOCALLY_PERIODIC,
    KIND_LOCALLY_PERIODIC_ZERO_MEAN,
    KIND_PERIODIC,
    KIND_SE,
    Kernel,
    LocallyPeriodic,
    Periodic,
    Product,
    SquaredExponential,
    ZeroMeanLocallyPeriodic,
)

__all__ = ["KRLST", "Step"]

#: Step / learn_many fields and their slots in the core's ``out`` buffer
_OUT_FIELDS = (("mean", core.O_MEAN), ("sigma_y2", core.O_SY2), ("sigma_f2", core.O_SF2), ("gamma2", core.O_G2),
               ("removed", core.O_REMOVED), ("reduced", core.O_REDUCED), ("filtered", core.O_FILT),
               ("filtered_var", core.O_FILTVAR), ("s02", core.O_S02), ("size", core.O_SIZE))
#: track_many's prediction fields and their slots in the ``out`` of the core's arm
_NEXT_FIELDS = (("next_mean", core.A_MEAN), ("next_sigma_f2", core.A_SF2), ("next_sigma_y2", core.A_SY2),
                ("next_gamma2", core.A_G2))
#: version of the snapshot layout (1: full Q, Σ, K matrices; 2: core.State fields)
SNAPSHOT_LAYOUT = 2
#: what :meth:`KRLST.breakdown` reads of the float state: s0², ŷ, σ_f², k_tt (one list, one C call)
_BREAKDOWN_SCALARS = itemgetter(core.F_S02, core.F_YM, core.F_SF2, core.F_KTT)


@dataclass(frozen=True, slots=True)
class Step:
    """What one :meth:`KRLST.learn_one` call reports (variances normalised: × ``s02`` for signal units).

    Attributes
    ----------
    mean : float
        ``ŷ = qᵀμ``, prediction of ``y`` before it was seen, after forgetting (eq. 2.17).
    sigma_y2 : float
        ``σ_y² = sn2 + σ_f²``, predictive variance of the observation.
    sigma_f2 : float
        ``σ_f² = γ² + qᵀh``, predictive variance of the disturbance ``f(x)``.
    gamma2 : float
        ``γ² = k_tt − k_tᵀ Q k_t``, projection uncertainty of ``x`` on the dictionary.
    removed : int
        0-based dictionary index of the pruned basis (before removal, with the new
        sample appended last); ``-1`` when nothing was pruned.
    reduced : bool
        True when the new sample itself was dropped (reduced update; ``removed == size``).
    filtered : float
        Posterior mean of ``f(x)`` after the update, ``ŷ + σ_f²(y − ŷ)/σ_y²``.
    filtered_var : float
        Its normalised variance ``σ_f² − σ_f⁴/σ_y²``.
    s02 : float
        ``s0²`` after this step (eq. 2.20).
    size : int
        Dictionary size after this step.

    On the first sample (initialisation, eq. 2.16) the prior predictive is reported:
    ``mean = 0``, ``sigma_f2 = gamma2 = k(x,x) + ε_j``.
    """

    mean: float
    sigma_y2: float
    sigma_f2: float
    gamma2: float
    removed: int
    reduced: bool
    filtered: float
    filtered_var: float
    s02: float
    size: int


def _kernel_from_spec(kinds: np.ndarray, params: np.ndarray, cols: np.ndarray) -> Kernel:
    """Rebuild a :class:`Kernel` from the arrays of :meth:`Kernel.spec` (for :meth:`KRLST.restore`)."""
    parts = []
    for kind, p, (start, stop) in zip(kinds.tolist(), params.tolist(), cols.tolist()):
        dims = slice(start, None if stop == -1 else stop)
        if kind == KIND_SE:
            parts.append(SquaredExponential(p[0], dims=dims))
        elif kind == KIND_PERIODIC:
            parts.append(Periodic(p[0], p[1], dims=dims))
        elif kind == KIND_LOCALLY_PERIODIC:
            parts.append(LocallyPeriodic(p[0], p[1], p[2], dims=dims))
        elif kind == KIND_LOCALLY_PERIODIC_ZERO_MEAN:
            parts.append(ZeroMeanLocallyPeriodic(p[0], p[1], p[2], dims=dims))
        else:
            raise ValueError(f"snapshot holds an unknown kernel kind {kind}")
    if not parts:
        raise ValueError("snapshot holds an empty kernel")
    return parts[0] if len(parts) == 1 else Product(*parts)


class KRLST:
    """Kernel recursive least-squares tracker with back-to-the-prior forgetting (method §6).

    Parameters
    ----------
    kernel : Kernel
        Covariance function (method §5), e.g. ``LocallyPeriodic(1.2, 0.495, 1/55)``.
    gamma : float
        Regularisation γ > 0; the noise-to-signal ratio is ``sn2 = 1/γ``.
    forgetting : float
        λ in (0, 1]; 1 means no forgetting (exact GP regression while ``|D| ≤ M``).
    budget : int
        Dictionary size M ≥ 1.
    jitter : float
        ε_j ≥ 0 added to ``k(x, x)``; a sample whose projection uncertainty
        ``γ² < ε_j`` is not added (reduced update).
    grid_step : float, optional
        Sampling period ``Ts`` (s) when ``x`` is the time on a uniform grid and the
        kernel is a function of the time lag (``kernel.is_stationary_1d``). Enables
        a lag lookup table ``k(L·Ts)`` for the ``k_t`` row; inputs off the grid are
        evaluated directly, so results stay correct (the table evaluates the kernel
        at the exact lag ``L·Ts`` instead of the rounded ``t − t_i``).
    refresh_every : int
        Recompute ``Q = K_D⁻¹`` from the cached ``K_D`` (Cholesky, in place) after every
        ``refresh_every``-th step (counting every trained sample); 0 = never. The
        rank-one recursions lose accuracy at a rate ∝ 1/ε_j; see :meth:`inverse_error`.
        One refresh costs ~0.3 ms at M = 100 (~20 steps), ~2 ms at 200, ~20 ms at 400.
    refine : bool
        One step of iterative refinement of ``q`` (``q ← q + Q(k_t − K_D q)``) before the
        ``Q`` update. kafbox's recursion multiplies the error of ``Q`` by up to
        ``~1/γ² ≲ 1/ε_j`` on a step, so with ``ε_j = 1e-6`` ``max|Q K_D − I|`` is ~3e-6
        typically and reaches 1e-4…1e-3 (and no periodic refresh prevents that: the
        error is back within ~100 steps); with ``refine`` it stays ~1e-9. It is needed on
        every step: on a 333 Hz stream ``|q|²/γ²`` exceeds 2e4 on 99 % of them (median
        4e5 at M = 100). ``K_D q`` comes with the ``Σ q`` pass; ``Q(k_t − K_D q)`` costs an
        extra sweep over ``Q`` while the dictionary grows and shares the pruning sweep once
        it is full (~0.2 µs of a ~4 µs step at M = 100). Off by default: the golden vectors
        follow kafbox, whose own ``Q`` error steers its pruning near-ties.

    Examples
    --------
    >>> tracker = KRLST(LocallyPeriodic(1.2, 0.495, 1/55), gamma=5.85, forgetting=0.996, budget=100)
    >>> step = tracker.learn_one(0.0, 0.1)
    >>> mean, var = tracker.predict_one(1 / 333)

    Monitor pattern (train on ``(x(k), v(k))``, then predict ``f(k+1)``):

    >>> mean, sf2, sy2, g2 = tracker.predict_next(2 / 333)   # x(k+1) arrived: arm, publish
    >>> step = tracker.update(0.05)                           # its residual is known: train
    """

    #: default ``refresh_every``: a re-inversion costs ~0.3 ms at M = 100 (~20 ms at
    #: M = 400), ~30 s of a 333 Hz stream apart. It resets the error of ``Q`` (and
    #: bounds any slow growth); the per-step amplification needs ``refine``.
    REFRESH_EVERY = 10000

    #: longest lag table (entries); a kernel that does not decay (pure periodic) stops here
    LAG_TABLE_MAX = 1 << 16

    def __init__(self, kernel: Kernel, gamma: float = 1e4, forgetting: float = 0.999,
                 budget: int = 100, jitter: float = 1e-6, grid_step: float | None = None,
                 refresh_every: int | None = None, refine: bool = False):
        if not isinstance(kernel, Kernel):
            raise ValueError(f"kernel must be a kernels.Kernel, got {type(kernel).__name__}")
        if isinstance(gamma, bool) or not isinstance(gamma, Real) or not (math.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma must be a finite number > 0, got {gamma!r}")
        if (isinstance(forgetting, bool) or not isinstance(forgetting, Real)
                or not (math.isfinite(forgetting) and 0.0 < forgetting <= 1.0)):
            raise ValueError(f"forgetting must be in (0, 1], got {forgetting!r}")
        if isinstance(budget, bool) or not isinstance(budget, Integral) or budget < 1:
            raise ValueError(f"budget must be an integer >= 1, got {budget!r}")
        if isinstance(jitter, bool) or not isinstance(jitter, Real) or not (math.isfinite(jitter) and jitter >= 0):
            raise ValueError(f"jitter must be a finite number >= 0, got {jitter!r}")
        if grid_step is not None:
            if (isinstance(grid_step, bool) or not isinstance(grid_step, Real)
                    or not (math.isfinite(grid_step) and grid_step > 0)):
                raise ValueError(f"grid_step must be None or a finite number > 0, got {grid_step!r}")
            if not kernel.is_stationary_1d:
                raise ValueError(f"grid_step needs a kernel of the time lag; {kernel!r} is not")
            grid_step = float(grid_step)
        if refresh_every is None:
            refresh_every = self.REFRESH_EVERY
        if isinstance(refresh_every, bool) or not isinstance(refresh_every, Integral) or refresh_every < 0:
            raise ValueError(f"refresh_every must be an integer >= 0 (0 = never), got {refresh_every!r}")
        if not isinstance(refine, (bool, np.bool_)):
            raise ValueError(f"refine must be a bool, got {refine!r}")
        self.kernel = kernel
        self.gamma = float(gamma)
        self.forgetting = float(forgetting)
        self.budget = int(budget)
        self.jitter = float(jitter)
        self.grid_step = grid_step
        self.refresh_every = int(refresh_every)
        self.refine = bool(refine)
        self._spec = kernel.spec()
        self._dim = 0
        self._buf = None                    # (float64, int64) base buffers of the core state
        self._st = None                     # core.State: views of self._buf
        self._out = np.zeros(core.N_OUT)
        self._xbuf = None
        self._tab = np.zeros(0)
        if grid_step is not None:
            tab = np.zeros(self.LAG_TABLE_MAX)
            length = core.build_lag_table(*self._spec, grid_step, self.LAG_TABLE_MAX, tab)
            self._tab = tab[:length].copy()

    # ------------------------------------------------------------------ properties
    @property
    def sn2(self) -> float:
        """Noise-to-signal ratio ``σ² = 1/γ``."""
        return 1.0 / self.gamma

    @property
    def size(self) -> int:
        """Current dictionary size ``|D|``."""
        return 0 if self._st is None else int(self._st.ist[core.I_N])

    @property
    def armed(self) -> bool:
        """True between :meth:`predict_next` and :meth:`update` (a prediction waits for its ``y``)."""
        return self._st is not None and bool(self._st.ist[core.I_ARMED])

    @property
    def s02(self) -> float:
        """Signal power ``s0²`` (eq. 2.20); 0 before the first sample."""
        return 0.0 if self._st is None else float(self._st.fst[core.F_S02])

    def _logical(self) -> np.ndarray:
        st = self._st
        return st.order[: st.ist[core.I_N]]

    @property
    def dictionary(self) -> np.ndarray:
        """Dictionary inputs, shape ``(n, d)``, oldest first (a copy)."""
        if self._st is None:
            return np.zeros((0, self._dim))
        return self._st.X[self._logical()].copy()

    @property
    def mu(self) -> np.ndarray:
        """Posterior mean ``μ`` of ``f`` at the dictionary (a copy)."""
        if self._st is None:
            return np.zeros(0)
        return self._st.mu[self._logical()].copy()

    def _materialized(self) -> tuple[np.ndarray, np.ndarray]:
        cap = self.budget + 1
        Qm = np.zeros((cap, cap))
        Sm = np.zeros((cap, cap))
        core.materialize(self._st, Qm, Sm)
        idx = self._logical()
        return Qm[np.ix_(idx, idx)], Sm[np.ix_(idx, idx)]

    @property
    def Sigma(self) -> np.ndarray:
        """Posterior covariance ``Σ`` (normalised) at the dictionary (a copy)."""
        if self._st is None:
            return np.zeros((0, 0))
        return self._materialized()[1]

    @property
    def Q(self) -> np.ndarray:
        """``Q ≈ K_D⁻¹`` (a copy)."""
        if self._st is None:
            return np.zeros((0, 0))
        return self._materialized()[0]

    @property
    def K(self) -> np.ndarray:
        """Cached dictionary kernel matrix ``K_D = k(D, D) + ε_j I`` (a copy)."""
        if self._st is None:
            return np.zeros((0, 0))
        st = self._st
        cap = self.budget + 1
        U = st.K[:cap, :cap]
        full = U + U.T + np.diag(st.Kd[:cap])
        idx = self._logical()
        return full[np.ix_(idx, idx)]

    def inverse_error(self) -> float:
        """``max |Q K_D − I|`` (max-abs norm, ``K_D`` with jitter): drift of ``Q`` from ``K_D⁻¹``.

        Kept small by the periodic re-inversion (``refresh_every``).
        """
        if self._st is None:
            return 0.0
        Q, K = self.Q, self.K
        return float(np.max(np.abs(Q @ K - np.eye(Q.shape[0]))))

    def breakdown(self) -> str | None:
        """Why the state has left what exact arithmetic allows, or None (O(1): a few armed scalars).

        A GP posterior never exceeds its prior: the armed ``σ_f² ≤ k_tt`` (eq. 2.17), with forgetting too
        (``Σ ← λΣ + (1−λ)K_D`` stays ≤ ``K_D``). ``σ_f² > 2 k_tt``, or a non-finite ``s0²``, ``ŷ`` or ``σ_f²``,
        means ``Q ≈ K_D⁻¹`` was lost to roundoff: measured with a jitter ε_j of 0 to 1e-10 on simulated drives
        (σ_f²/k_tt from 13 to 1e127, then NaN), never above 1.0 with ε_j ≥ 1e-9 on the same data. The state
        never recovers by itself."""
        if self._st is None:
            return None
        s02, y_mean, sf2, ktt = _BREAKDOWN_SCALARS(self._st.fst.tolist())
        if not (math.isfinite(s02) and math.isfinite(y_mean) and math.isfinite(sf2)):
            return f"non-finite state (s0² = {s02:.3g}, ŷ = {y_mean:.3g}, σ_f² = {sf2:.3g})"
        if sf2 > 2.0 * ktt:
            return f"posterior variance above the prior (σ_f² = {sf2:.3g} > k_tt = {ktt:.3g})"
        return None

    def get_params(self) -> dict:
        """Hyperparameters (scikit-learn style)."""
        return {"kernel": self.kernel, "gamma": self.gamma, "forgetting": self.forgetting,
                "budget": self.budget, "jitter": self.jitter, "grid_step": self.grid_step,
                "refresh_every": self.refresh_every, "refine": self.refine}

    def __repr__(self) -> str:
        return (f"KRLST({self.kernel!r}, gamma={self.gamma!r}, forgetting={self.forgetting!r}, "
                f"budget={self.budget!r}, jitter={self.jitter!r}, grid_step={self.grid_step!r}, "
                f"refresh_every={self.refresh_every!r}, refine={self.refine!r})")

    # ------------------------------------------------------------------ input checks
    def _as_x(self, x) -> np.ndarray:
        """x as a 1-D float64 array (a float becomes shape (1,)); raises ValueError if non-finite."""
        if isinstance(x, Real) and not isinstance(x, bool):
            xf = float(x)
            if not math.isfinite(xf):
                raise ValueError(f"x must be finite, got {x!r}")
            if self._xbuf is None or self._xbuf.shape[0] != 1:
                self._xbuf = np.empty(1)
            self._xbuf[0] = xf
            xa = self._xbuf
        else:
            xa = np.asarray(x, dtype=np.float64)
            if xa.ndim == 0:
                xa = xa.reshape(1)
            if xa.ndim != 1 or xa.shape[0] == 0:
                raise ValueError(f"x must be a float or a non-empty 1-D array, got shape {xa.shape}")
            if not np.all(np.isfinite(xa)):
                raise ValueError(f"x must be finite, got {xa!r}")
            xa = np.ascontiguousarray(xa)
        if self._dim and xa.shape[0] != self._dim:
            raise ValueError(f"x has dimension {xa.shape[0]}, the tracker was started with {self._dim}")
        return xa

    @staticmethod
    def _as_y(y) -> float:
        try:
            yf = float(y)
        except (TypeError, ValueError):
            raise ValueError(f"y must be a real number, got {y!r}") from None
        if not math.isfinite(yf):
            raise ValueError(f"y must be finite, got {y!r}")
        return yf

    def _start(self, dim: int, x_example: np.ndarray) -> None:
        # lets the kernel reject inputs it cannot read (e.g. a periodic factor on 2 columns)
        self.kernel(x_example.reshape(1, -1))
        self._dim = dim
        self._set_buffers(core.new_buffers(self.budget, dim, self.forgetting, self.sn2, self.jitter,
                                           self.grid_step, self.refresh_every, self.refine, self._spec, self._tab))

    def _set_buffers(self, buf: tuple[np.ndarray, np.ndarray]) -> None:
        self._buf = buf
        self._st = core.state_views(*buf)

    def _step(self) -> Step:
        v = self._out.tolist()
        return Step(v[core.O_MEAN], v[core.O_SY2], v[core.O_SF2], v[core.O_G2], int(v[core.O_REMOVED]),
                    v[core.O_REDUCED] != 0.0, v[core.O_FILT], v[core.O_FILTVAR], v[core.O_S02],
                    int(v[core.O_SIZE]))

    # ------------------------------------------------------------------ learning
    def learn_one(self, x, y) -> Step:
        """Train on one sample (method §6 steps 1–6) and report the step.

        ``x``: float (time) or 1-D array; ``y``: the residual ``v(k)``. A non-finite
        ``x`` or ``y`` raises ``ValueError`` and leaves the state untouched.

        Bit for bit the same as ``predict_next(x)`` followed by ``update(y)``; a
        prediction armed before is discarded (its forgetting stays applied).
        """
        xa = self._as_x(x)
        yf = self._as_y(y)
        if self._st is None:
            self._start(xa.shape[0], xa)
        core.learn_buffers(*self._buf, xa, yf, self._out)
        return self._step()

    def core_state(self, x_example) -> core.State:
        """The :class:`kernels._krlst_core.State` the ``@njit`` core works on (``core.arm(st, x, out)``,
        ``core.update(st, y, out)``), for compiled loops that drive the tracker
        (:func:`kernels.online.track_block`). Starts a new tracker with the input dimension of
        ``x_example`` (a 1-D array) if none is running. The arrays are the tracker's own (not copies)."""
        if self._st is None:
            self._start(x_example.shape[0], x_example)
        return self._st

    def core_buffers(self, x_example) -> tuple[np.ndarray, np.ndarray]:
        """The two base buffers ``(float64, int64)`` behind :meth:`core_state`, for compiled code that
        takes plain arrays and names them inside with ``kernels._krlst_core.state_of(fbuf, ibuf)``
        (two arrays cross the Python/numba boundary instead of the ``State``'s 22)."""
        self.core_state(x_example)
        return self._buf

    def _stream(self, X, y, mask, xname: str, yname: str) -> tuple[np.ndarray, np.ndarray]:
        """Validated contiguous ``(N, d)`` inputs and ``(N,)`` targets; ``y`` must be finite where
        ``mask`` is set (everywhere when ``mask`` is None). Raises ``ValueError`` naming the first bad index."""
        Xa = np.asarray(X, dtype=np.float64)
        if Xa.ndim == 1:
            Xa = Xa.reshape(-1, 1)
        if Xa.ndim != 2:
            raise ValueError(f"{xname} must have shape (N,) or (N, d), got {np.shape(X)}")
        N = Xa.shape[0]
        ya = np.asarray(y, dtype=np.float64)
        if ya.shape != (N,):
            raise ValueError(f"{yname} must have shape ({N},), got {ya.shape}")
        if mask is not None and (mask.shape != (N,) or mask.dtype != np.bool_):
            raise ValueError(f"learn_mask must be a bool array of shape ({N},), got {mask.dtype} {mask.shape}")
        bad_x = ~np.all(np.isfinite(Xa), axis=1)
        if bad_x.any():
            raise ValueError(f"{xname} must be finite; row {int(np.argmax(bad_x))} is not")
        bad_y = ~np.isfinite(ya) if mask is None else mask & ~np.isfinite(ya)
        if bad_y.any():
            where = "" if mask is None else " where learn_mask is set"
            raise ValueError(f"{yname} must be finite{where}; element {int(np.argmax(bad_y))} is not")
        if self._dim and Xa.shape[1] != self._dim:
            raise ValueError(f"{xname} has dimension {Xa.shape[1]}, the tracker was started with {self._dim}")
        return np.ascontiguousarray(Xa), np.ascontiguousarray(ya)

    def learn_many(self, X, y) -> dict[str, np.ndarray]:
        """Train on a whole stream in one ``@njit`` loop; same results as repeated :meth:`learn_one`.

        ``X``: shape ``(N,)`` (times) or ``(N, d)``; ``y``: shape ``(N,)``. Returns a dict
        of 1-D arrays named like the fields of :class:`Step`. Non-finite input raises
        ``ValueError`` (naming the first bad index) before anything is learned.
        """
        Xa, ya = self._stream(X, y, None, "X", "y")
        N = ya.shape[0]
        outs = np.zeros((N, core.N_OUT))
        if N:
            core.learn_many(self.core_state(Xa[0]), Xa, ya, outs)
        res = {name: outs[:, i].copy() for name, i in _OUT_FIELDS}
        res["removed"] = res["removed"].astype(np.int64)
        res["reduced"] = res["reduced"] != 0.0
        res["size"] = res["size"].astype(np.int64)
        return res

    # ------------------------------------------------------------------ split step (monitor)
    def predict_next(self, x) -> tuple[float, float, float, float]:
        """Steps 1–2 at ``x`` *in place*: forget, predict, and arm the update (method §6 timing).

        Returns ``(mean, sigma_f2, sigma_y2, gamma2)``, normalised like :class:`Step`
        (× :attr:`s02` for signal units): the one-step-ahead prediction of ``f(x)``
        (``sigma_f2``) and of the observation (``sigma_y2``). The mean and variances
        are bit-identical to ``predict_one(x, forget=True)`` and to what
        :meth:`learn_one` would report, but the forgetting and the ``k_t, Q k_t, Σ q``
        passes are done here once and reused by :meth:`update`.

        Calling it again before :meth:`update` (e.g. the monitor skips a stale sample)
        is allowed: the tracker forgets again and re-arms at the new ``x``, so the
        forgetting applies once per ``predict_next`` call. On an empty tracker it only
        records ``x`` and returns the prior ``(0, k_tt, sn2 + k_tt, k_tt)``. A
        non-finite ``x`` raises ``ValueError`` and leaves the state untouched.
        """
        xa = self._as_x(x)
        if self._st is None:
            self._start(xa.shape[0], xa)
        out = self._out
        core.arm_buffers(*self._buf, xa, out)
        return float(out[core.A_MEAN]), float(out[core.A_SF2]), float(out[core.A_SY2]), float(out[core.A_G2])

    def update(self, y) -> Step:
        """Steps 3–5 (6 on the first sample) for the ``x`` armed by :meth:`predict_next`.

        ``y``: the residual observed for that ``x``. Returns the :class:`Step` that
        :meth:`learn_one` would have returned. Raises ``RuntimeError`` when nothing is
        armed (no :meth:`predict_next` since the last update) and ``ValueError`` on a
        non-finite ``y`` (the state, armed prediction included, is left untouched).
        """
        yf = self._as_y(y)
        if not self.armed:
            raise RuntimeError("KRLST.update needs an armed prediction: call predict_next(x) first")
        core.update_buffers(*self._buf, yf, self._out)
        return self._step()

    def track_many(self, xs, ys, learn_mask) -> dict[str, np.ndarray]:
        """Monitor block in one ``@njit`` call: per arriving sample ``j``, in order,

        1. if ``learn_mask[j]``: ``update(ys[j])``, ``ys[j]`` being the residual of the
           ``x`` armed before (the previous sample, or the last one of the previous block);
        2. always ``predict_next(xs[j])``.

        Bit-identical to that sequence of :meth:`update` / :meth:`predict_next` calls.

        ``xs``: shape ``(N,)`` or ``(N, d)``; ``ys``: ``(N,)`` (ignored, may be NaN, where
        the mask is False); ``learn_mask``: ``(N,)`` bool. Returns a dict of ``(N,)`` arrays:

        * ``learned`` (bool): an update ran for sample ``j``;
        * the update, named as in :class:`Step`: ``mean, sigma_y2, sigma_f2, gamma2,
          filtered, filtered_var`` (NaN when not learned), ``removed`` (-1 when not
          learned or nothing pruned), ``reduced`` (False when not learned);
        * the new prediction at ``xs[j]``: ``next_mean, next_sigma_f2, next_sigma_y2,
          next_gamma2`` (normalised, as :meth:`predict_next` returns them);
        * ``s02`` and ``size``: the state after sample ``j`` (multiply the normalised
          variances by ``s02``).

        Raises ``ValueError`` (before anything is done) on a non-finite ``xs`` row or a
        non-finite ``ys`` where the mask is set, and ``RuntimeError`` when
        ``learn_mask[0]`` is set but nothing is armed.
        """
        mask = np.asarray(learn_mask)
        Xa, ya = self._stream(xs, ys, mask, "xs", "ys")
        N = Xa.shape[0]
        if N and mask[0] and not self.armed:
            raise RuntimeError("track_many: learn_mask[0] is set but no prediction is armed")
        outs = np.zeros((N, core.N_TRACK))
        if N:
            core.track(self.core_state(Xa[0]), Xa, ya, np.ascontiguousarray(mask), outs)
        learned = outs[:, core.T_LEARNED] != 0.0
        res: dict[str, np.ndarray] = {"learned": learned}
        for name, i in _OUT_FIELDS[:8]:
            res[name] = outs[:, i].copy()
        res["removed"] = np.where(learned, np.nan_to_num(res["removed"], nan=-1.0), -1.0).astype(np.int64)
        res["reduced"] = learned & (res["reduced"] == 1.0)
        for name, i in _NEXT_FIELDS:
            res[name] = outs[:, core.T_NEXT + i].copy()
        res["s02"] = outs[:, core.T_S02].copy()
        res["size"] = outs[:, core.T_SIZE].astype(np.int64)
        return res

    # ------------------------------------------------------------------ prediction
    def predict_one(self, x, noise: bool = True, forget: bool = False) -> tuple[float, float]:
        """Predictive mean and variance at ``x`` (signal units), without learning (eq. 2.17).

        Returns ``(ŷ, s0²·σ_y²)``, or ``(ŷ, s0²·σ_f²)`` with ``noise=False`` (the
        disturbance ``f`` alone). With ``forget=True`` the forgetting of the next
        step is applied virtually, so the mean equals the ``mean`` the next
        :meth:`learn_one` reports for this ``x`` (kafbox's ``evaluate`` does not
        forget: that is the default). Before the first sample: ``(0.0, nan)``
        (``s0²`` is unknown). Does not change the state (an armed prediction stays);
        the monitor's "train, then predict the next" is :meth:`predict_next`.
        """
        xa = self._as_x(x)
        if self._st is None:
            return 0.0, math.nan
        out = self._out
        core.predict_buffers(*self._buf, xa, bool(forget), out)
        s02 = float(self._st.fst[core.F_S02])
        var = out[core.A_SY2] if noise else out[core.A_SF2]
        return float(out[core.A_MEAN]), s02 * float(var)

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, np.ndarray]:
        """The complete state as a plain ``dict[str, np.ndarray]`` (copies; no pickle needed).

        Hyperparameters are 0-d arrays (``grid_step`` 0 for none), the kernel is its
        :meth:`Kernel.spec` arrays, ``state_layout`` is :data:`SNAPSHOT_LAYOUT`. The state
        arrays are the core's :data:`~kernels._krlst_core.STATE_FIELDS` as they are, pending
        rank-one updates, the step counter (refresh schedule) and an armed prediction
        included, so :meth:`restore` continues bit-identically.
        """
        kinds, params, cols = self._spec
        snap = {
            "state_layout": np.array(SNAPSHOT_LAYOUT, dtype=np.int64),
            "gamma": np.array(self.gamma),
            "forgetting": np.array(self.forgetting),
            "budget": np.array(self.budget, dtype=np.int64),
            "jitter": np.array(self.jitter),
            "grid_step": np.array(0.0 if self.grid_step is None else self.grid_step),
            "refresh_every": np.array(self.refresh_every, dtype=np.int64),
            "refine": np.array(self.refine),
            "dim": np.array(self._dim, dtype=np.int64),
            "kernel_kinds": kinds.copy(),
            "kernel_params": params.copy(),
            "kernel_cols": cols.copy(),
        }
        if self._st is not None:
            for name in core.STATE_FIELDS:
                snap[name] = getattr(self._st, name).copy()
        return snap

    @classmethod
    def restore(cls, snap: dict) -> KRLST:
        """Rebuild a tracker from :meth:`snapshot`; raises ``ValueError`` on a malformed snapshot
        (shapes and dtypes against :func:`~kernels._krlst_core.new_state`, then the state's
        invariants, :func:`~kernels._krlst_core.validate_state`).

        Snapshots of layout 1 (full ``Q``, ``Sigma``, ``K`` matrices, written before the
        triangular core; no ``state_layout`` key) are converted, their pending updates
        applied. Those written before ``refresh_every`` and the split step existed
        (shorter ``ist``/``fst``/``P``, no ``refresh_every`` key) get the default
        ``refresh_every`` and no armed prediction.
        """
        try:
            kernel = _kernel_from_spec(np.asarray(snap["kernel_kinds"]), np.asarray(snap["kernel_params"]),
                                       np.asarray(snap["kernel_cols"]))
            grid_step = float(snap["grid_step"])
            refresh_every = int(snap["refresh_every"]) if "refresh_every" in snap else None
            refine = bool(snap["refine"]) if "refine" in snap else False
            tracker = cls(kernel, gamma=float(snap["gamma"]), forgetting=float(snap["forgetting"]),
                          budget=int(snap["budget"]), jitter=float(snap["jitter"]),
                          grid_step=grid_step if grid_step > 0 else None, refresh_every=refresh_every,
                          refine=refine)
            dim = int(snap["dim"])
            layout = int(snap["state_layout"]) if "state_layout" in snap else 1
        except KeyError as exc:
            raise ValueError(f"snapshot is missing {exc.args[0]!r}") from None
        if dim == 0:
            return tracker
        if dim < 0:
            raise ValueError(f"snapshot 'dim' must be >= 0, got {dim}")
        tracker._start(dim, np.zeros(dim))
        st = tracker._st
        fresh_fst = st.fst.copy()
        if layout == 1:
            arrays = _from_layout1(tracker, snap, dim)
        elif layout == SNAPSHOT_LAYOUT:
            arrays = snap
        else:
            raise ValueError(f"snapshot 'state_layout' {layout} is not supported (1 or {SNAPSHOT_LAYOUT})")
        fill_views(st, arrays, core.STATE_FIELDS)
        st.ist[core.I_REFRESH] = tracker.refresh_every
        st.ist[core.I_REFINE] = int(tracker.refine)
        core.validate_state(st)                      # before the compiled code indexes with it
        for slot in (core.F_LAM, core.F_SN2, core.F_JIT, core.F_INVTS):
            if st.fst[slot] != fresh_fst[slot]:
                raise ValueError(f"snapshot 'fst' holds hyperparameters {st.fst[[core.F_LAM, core.F_SN2, core.F_JIT]]}"
                                 " that differ from its own gamma/forgetting/jitter/grid_step entries")
        return tracker


def _from_layout1(tracker: KRLST, snap: dict, dim: int) -> dict[str, np.ndarray]:
    """The :data:`~kernels._krlst_core.STATE_FIELDS` of a layout-1 snapshot (full ``Q``, ``Sigma``,
    ``K``; pending rank-one updates in ``P`` rows 0–2 and ``ist[4:6]``), pending updates applied."""
    cap = tracker.budget + 1
    shapes = {"X": ((cap, dim), np.float64), "Q": ((cap, cap), np.float64),
              "Sigma": ((cap, cap), np.float64), "K": ((cap, cap), np.float64),
              "mu": ((cap,), np.float64), "order": ((cap,), np.int64),
              "ist": ((core.N_IST,), np.int64), "fst": ((15,), np.float64),
              "P": ((core.N_P, cap), np.float64)}
    # the format before refresh_every / predict_next: fewer entries, zero-padded
    old = {"ist": (6,), "fst": (10,), "P": (3, cap)}
    a = {}
    for name, (shape, dtype) in shapes.items():
        if name not in snap:
            raise ValueError(f"snapshot is missing {name!r}")
        arr = np.array(snap[name], dtype=dtype, copy=True)
        if name in old and arr.shape == old[name] and "refresh_every" not in snap:
            padded = np.zeros(shape, dtype=dtype)
            padded[tuple(slice(0, k) for k in arr.shape)] = arr
            arr = padded
        if arr.shape != shape:
            raise ValueError(f"snapshot {name!r} has shape {arr.shape}, expected {shape}")
        a[name] = arr
    ist, fst, P = a["ist"], a["fst"], a["P"]
    p, pa, g = P[core.P_P], P[core.P_A], P[core.P_G]
    Q, S, K = a["Q"], a["Sigma"], a["K"]
    if ist[core.I_QPEND] >= 1:
        Q = Q + fst[core.F_QSC] * np.outer(p, p)
    if ist[core.I_QPEND] == 2:
        Q = Q - fst[core.F_QBINV] * np.outer(pa, pa)
    if ist[core.I_SPEND]:
        S = S - fst[core.F_SC] * np.outer(g, g)
    st = tracker._st
    n8 = st.Q.shape[0]
    fst = np.concatenate([fst, [1.0]])            # c of Δ = c·D
    out = {"X": a["X"], "order": a["order"], "fst": fst}
    ist = ist.copy()
    ist[core.I_QPEND] = 0
    ist[core.I_SPEND] = 0
    out["ist"] = ist
    for name, full in (("Q", Q), ("D", S - K), ("K", K)):
        upper = np.zeros((n8, n8))
        upper[:cap, :cap] = np.triu(full, 1)
        diag = np.zeros(n8)
        diag[:cap] = np.diag(full)
        out[name], out[name + "d"] = upper, diag
    out["mu"] = np.pad(a["mu"], (0, n8 - cap))
    n = int(ist[core.I_N])
    if not 0 <= n <= tracker.budget:
        raise ValueError(f"snapshot dictionary size {n} is outside [0, {tracker.budget}]")
    occ = np.zeros(n8)
    occ[a["order"][:n]] = 1.0
    out["occ"] = occ
    Pn = np.zeros_like(st.P)
    Pn[core.P_KT:core.P_RES + 1, :cap] = P[core.P_KT:core.P_RES + 1]   # armed vectors
    out["P"] = Pn
    Ph = np.zeros_like(st.Ph)
    kinds, params, cols = tracker._spec
    used = list(a["order"][:n]) + ([a["order"][n]] if ist[core.I_ARMED] and n < cap else [])
    for s in used:
        core.kernel_phases(kinds, params, cols, np.ascontiguousarray(a["X"][s]), Ph[s])
    out["Ph"] = Ph
    return out
