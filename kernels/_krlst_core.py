"""Allocation-free ``@njit`` core of the KRLS-T tracker (method §6, thesis eq. 2.14–2.22).

Reference: kafbox ``lib/krlst.m`` (S. Van Vaerenbergh), back-to-the-prior forgetting.
The public class is :class:`kernels.krlst.KRLST`; this module holds only the numerics.
Kernel values come from :mod:`kernels.covariance` (one formula per kernel).

State
-----
Everything a tracker reads or writes is one :class:`State` (a ``NamedTuple`` of arrays):
the kernel's factor table and lag table, the dictionary, the matrices, the pending and
armed vectors and the scratch. :func:`new_state` is the single definition of every
field's shape and dtype. All fields are views of two base buffers (``float64`` and
``int64``; :func:`new_buffers`, :func:`state_views`). A compiled function takes a ``State``
(``arm(st, x, out)``); Python calls go through ``*_buffers`` twins that take the two
buffers and rebuild the views inside (:func:`state_of`), because numba types and unboxes
each array of a tuple argument separately (~0.1 µs per array, ~2 µs per call for a whole
``State``). Compiled code passes a ``State`` on without reference counting (:func:`unowned`).

Slots and storage
-----------------
The ``M+1`` dictionary positions are *slots*. ``order[:n]`` lists the slots of the ``n``
dictionary elements in the dictionary's logical order (kafbox's order, oldest first),
``order[n:]`` the free slots; ``occ[s]`` is 1 for an occupied slot. A free slot has a zero
row and column in every matrix and zero entries in every vector, so the sweeps run over
the contiguous range ``[0, hw)`` (``hw``: high-water mark of used slots) without gathering.
Adding a basis writes one row/column into a free slot; when a basis is pruned in the same
step the new one takes over its slot (one row/column written instead of one zeroed and one
written). Nothing is shifted and no kernel value is recomputed. Only the pruning ``argmin``
walks the logical order, so ties resolve to the first (oldest) element as Matlab's ``min``.

The symmetric matrices ``Q ≈ K_D⁻¹``, ``Δ = Σ − K_D`` and ``K_D = k(D, D) + ε_j I`` are kept
as strict upper triangles (``Q``, ``D``, ``K``, ``(n8, n8)``, ``n8 = ⌈(M+1)/8⌉·8``) plus
diagonals (``Qd``, ``Dd``, ``Kd``), swept by the 8-lane kernels of
:mod:`kernels._krlst_simd` (half of each matrix per pass; the lanes are explicit, so the
results do not depend on the vector width or on the caller). ``Δ`` instead of ``Σ`` makes the
forgetting ``Σ ← λΣ + (1−λ)K_D`` (2.19) the scaling ``Δ ← λΔ``, which is kept as a scalar:
``Δ = c·D`` with ``c = fst[F_DSC]`` (folded into ``D`` before it underflows), and the ``h``
pass yields ``K_D q`` (needed by ``refine``) along with ``h = Σ q = c·Dq + K_D q``.

Deferred rank-one updates
-------------------------
The rank-one (rank-two with a removal) updates of ``Q`` and ``Δ`` at the end of step ``t``
are stored as *pending* vectors and applied inside the passes of step ``t+1`` (``q = Q k_t``
and ``h = Σq``), so each matrix is swept once per step for them. :func:`predict`
applies pending updates on the fly without writing; ``KRLST`` materialises them for its
``Q``/``Sigma`` properties.

Cost per step at ``M = 100`` (2-core Xeon, numbers from ``benchmarks/krlst_step.py``): the three
sweeps do ~13 multiply–adds per stored matrix entry (``Q``: pending rank-two, ``Q k_t``,
``Q μ_new``, ``Q(k_t − K_D q)``; ``D``: pending rank-one, ``D q``; ``K``: ``K_D q``), ~70 % of the
step; the rest is the ``k_t`` row, the pruning criterion and the row/column writes.

Uniform-grid lag table
----------------------
For a stationary kernel on a scalar time input sampled on a grid of step ``Ts``,
``k(t − t_i)`` depends on the integer lag ``L = (t − t_i)/Ts`` only. With a table
``tab[L] = kernel_value(L·Ts, 0)`` (built once by :func:`build_lag_table`) the ``k_t``
row costs ``n`` lookups instead of ``n`` ``exp``. A lag further than ``1e-6·Ts`` from an
integer falls back to the direct evaluation. A kernel with a squared-exponential envelope is 0
beyond the lag where the envelope falls below the floor of kernel values
(:data:`~kernels.covariance.KERNEL_FLOOR`, 2⁻⁵¹¹: ``≈ σ1·√(2·354)``, 2.8 s for σ1 = 0.1 s; values
below it are 0 on both paths, no subnormal numbers): the table ends there with a ``0.0`` and every
older dictionary entry gets 0 without evaluation (a short REML-tuned σ1 with old entries in the
dictionary once cost 18 µs per sample instead of 5 µs, in ``exp``, ``sin``, the zero-mean kernel's
Bessel series and subnormal arithmetic). Other kernels end at their first 0 or
at ``nmax`` entries, and a lag beyond is evaluated directly. Without a table the row is :func:`kernels.covariance.kernel_row_phased` (one
``exp`` per entry; the sines of periodic factors from each slot's cached phases ``Ph``,
e.g. the spindle angle of ``x = (t, θ)``).

Split step (predict_next / update)
----------------------------------
:func:`learn` is :func:`arm` (steps 1–2: forget, then predict at ``x``) followed by
:func:`update` (steps 3–5, or 6 on the first sample). :func:`arm` writes the forgetting
into the state and keeps everything the update needs ("armed"): ``k_t, q, h`` and
``k_t − K_D q`` in rows of ``P``, ``k_tt, ŷ, γ², σ_f², σ_y²`` in ``fst`` and ``x`` itself in
the free slot ``X[order[n]]`` (where step 3 puts it). The monitor arms on ``x(k+1)`` as
soon as it arrives and publishes the prediction, then calls :func:`update` with the
residual once ``v_m(k+2)`` is known. Arming again without an update re-arms at the new
``x``; the forgetting is then applied once per :func:`arm`. :func:`track` runs
``[update(y_j)] + arm(x_j)`` over a block of arriving samples.

Accuracy of Q: refinement and periodic re-inversion
---------------------------------------------------
kafbox's rank-one update multiplies the current error of ``Q`` by up to ~``|q|²/γ²``
(``γ² ≳ ε_j``) in a single step: with ``ε_j = 1e-6`` ``max|Q K_D − I|`` is ~3e-6
typically and exceeds 1e-5 on ~10 % of the steps (up to ~1e-3), and it is back at
that level ~100 steps after an exact re-inversion, so re-inverting alone cannot hold
it down. With ``ist[I_REFINE]`` the update uses ``q ← q + Q(k_t − K_D q)`` (one step
of iterative refinement; ``K_D q`` comes from the h pass, ``Q(k_t − K_D q)`` shares the
``Q μ_new`` sweep of the pruning criterion) and the error stays ~1e-9. Every
``refresh_every`` steps (0 = never), at the end of :func:`update`, :func:`refresh_inverse`
recomputes ``Q`` from ``K_D`` by a Cholesky factorisation in the dense scratch ``A``; the
new ``Q`` supersedes a pending ``Q`` update.

Named slots
-----------
``ist`` (int64): ``I_*``; ``fst`` (float64): ``F_*`` (the ``F_KTT…F_SY2`` block is the armed
prediction); rows of ``P`` (pending and armed vectors, state): ``P_*``; rows of ``W``
(scratch): ``W_*``. Output buffers: :func:`update`/:func:`learn` write ``O_*`` (``N_OUT``),
:func:`arm`/:func:`predict` write ``A_*`` (``N_ARM``), a row of :func:`track` is ``T_*``
(``N_TRACK``).

Compiled code that runs beside the tracker on the same slots (the shadow means of
:mod:`kernels.beta_tracker`) reads, after :func:`arm`, ``P[P_Q]`` (``q``) and ``P[P_H]`` (``h``;
:func:`update` does not change it) and the armed ``fst[F_YM…F_SY2]``; the new basis goes to the
free slot ``order[n]``; after :func:`update` a reduced step (``O_REDUCED``) leaves it free, a
pruning step (``O_REMOVED ≥ 0``) moves the new basis into the pruned one's slot, which is then
``order[n − 1]``, and frees ``order[n]``. These are part of the layout: keep them when changing it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._krlst_simd import LANES, ROWS, Stream, fmuladd, sweep
from .covariance import KERNEL_FLOOR, envelope_bound, kernel_phases, kernel_row_phased, kernel_value
from .layout import Field, Layout

# ---- ist: integer state ---------------------------------------------------------------------
I_N = 0           # dictionary size n
I_HW = 1          # high-water mark of used slots
I_M = 2           # budget M
I_STEPS = 3       # trained samples (refresh schedule)
I_QPEND = 4       # pending Q update: 0 none, 1 rank-one, 2 rank-one + removal downdate
I_SPEND = 5       # pending Δ rank-one update: 0/1
I_REFRESH = 6     # refresh_every (0 = never)
I_ARMED = 7       # 1 between arm and update
I_REFINE = 8      # 1: refine q before the Q update
N_IST = 9

# ---- fst: float state ------------------------------------------------------------------------
F_LAM = 0         # λ
F_SN2 = 1         # σ² = 1/γ
F_JIT = 2         # ε_j
F_NUM = 3         # num of s0² (2.20)
F_DEN = 4         # den of s0²
F_S02 = 5         # s0² = num/den
F_QSC = 6         # 1/γ² of the pending Q update
F_QBINV = 7       # 1/[Q_new]_rr of the pending removal
F_SC = 8          # 1/(c σ_y²) of the pending Δ update (in units of D)
F_INVTS = 9       # 1/Ts of the lag table (0: none)
F_KTT = 10        # armed k_tt = k(x,x) + ε_j
F_YM = 11         # armed ŷ
F_G2 = 12         # armed γ²
F_SF2 = 13        # armed σ_f²
F_SY2 = 14        # armed σ_y²
F_DSC = 15        # c: Δ = c·D (the forgetting Δ ← λΔ is c ← λc)
N_FST = 16

# ---- P: pending and armed vectors (state) ------------------------------------------------------
P_P = 0           # p = [q; −1] of the pending Q update
P_A = 1           # a = [Q_new]_{:,r} of the pending removal
P_G = 2           # g = [h; σ_f²] of the pending Δ update
P_KT = 3          # armed k_t
P_Q = 4           # armed q = Q k_t
P_H = 5           # armed h = Σ q
P_RES = 6         # armed k_t − K_D q (refine)
N_P = 7

# ---- W: scratch vectors (not state) --------------------------------------------------------------
W_KT = 0          # predict: k_t;  update: the pruning criterion
W_Q = 1           # predict: q
W_H = 2           # predict: h
W_KQ = 3          # K_D q
W_M = 4           # update: μ_new;  predict: √λ μ
W_U = 5           # update: Q μ_new;  refresh: diag of U
W_W = 6           # update: Q (k_t − K_D q);  refresh: diag of Z
N_W = 7

# ---- output buffers ------------------------------------------------------------------------------
O_MEAN = 0        # ŷ (prediction of y before it was seen)
O_SY2 = 1         # σ_y²
O_SF2 = 2         # σ_f²
O_G2 = 3          # γ²
O_REMOVED = 4     # logical index of the pruned basis, −1: none
O_REDUCED = 5     # 1.0: the new sample itself was dropped
O_FILT = 6        # E[f(x) | y] = ŷ + σ_f² (y − ŷ)/σ_y²
O_FILTVAR = 7     # Var[f(x) | y] = σ_f² − σ_f⁴/σ_y²
O_S02 = 8         # s0² after the step
O_SIZE = 9        # n after the step
N_OUT = 10

A_MEAN = 0        # ŷ at the armed x
A_SF2 = 1         # σ_f²
A_SY2 = 2         # σ_y² = sn2 + σ_f²
A_G2 = 3          # γ²
N_ARM = 4

T_NEXT = N_OUT              # track row: [0, N_OUT) the update (NaN when not learned), then the arm
T_S02 = T_NEXT + N_ARM      # s0² after the sample
T_SIZE = T_S02 + 1          # n after the sample
T_LEARNED = T_SIZE + 1      # 1.0 if an update ran
N_TRACK = T_LEARNED + 1

LAG_TOL = 1e-6
_HEADER = 8                 # int buffer: cap, n8, dim, factors, table length (the dims), then the fields

#: every field of :class:`State`: ``cap = M+1`` slots, ``n8 = ⌈cap/8⌉·8``, ``nf`` kernel factors,
#: ``ntab`` lag-table entries; roles: ``state`` is saved by snapshots, ``setting`` is rebuilt from the
#: hyperparameters (kernel spec, lag table), ``scratch`` is not kept
FIELDS = (
    Field("layout", "i8", (_HEADER,), "layout", "cap, n8, dim, nf, ntab"),
    Field("kinds", "i8", ("nf",), "setting", "factor kinds (Kernel.spec)"),
    Field("cols", "i8", ("nf", 2), "setting", "factor columns"),
    Field("order", "i8", ("cap",), "state", "slots in logical order, then the free ones"),
    Field("ist", "i8", (N_IST,), "state", "integer state I_*"),
    Field("params", "f8", ("nf", 3), "setting", "factor parameters"),
    Field("tab", "f8", ("ntab",), "setting", "lag table k(L·Ts)"),
    Field("fst", "f8", (N_FST,), "state", "float state F_*"),
    Field("X", "f8", ("cap", "dim"), "state", "inputs of the slots"),
    Field("Ph", "f8", ("cap", "2 * nf"), "state", "sin, cos of each slot's phase per periodic factor"),
    Field("xph", "f8", ("2 * nf",), "scratch", "phases of a predicted x"),
    Field("Q", "f8", ("n8", "n8"), "state", "strict upper triangle of Q ≈ K_D⁻¹"),
    Field("Qd", "f8", ("n8",), "state", "diagonal of Q"),
    Field("D", "f8", ("n8", "n8"), "state", "strict upper triangle of Δ/c, Δ = Σ − K_D, c = fst[F_DSC]"),
    Field("Dd", "f8", ("n8",), "state", "diagonal of Δ/c"),
    Field("K", "f8", ("n8", "n8"), "state", "strict upper triangle of K_D"),
    Field("Kd", "f8", ("n8",), "state", "diagonal of K_D"),
    Field("mu", "f8", ("n8",), "state", "posterior mean μ"),
    Field("occ", "f8", ("n8",), "state", "1.0 for an occupied slot"),
    Field("P", "f8", (N_P, "n8"), "state", "pending and armed vectors P_*"),
    Field("W", "f8", (N_W, "n8"), "scratch", "scratch vectors W_*"),
    Field("A", "f8", ("n8", "n8"), "scratch", "dense scratch of refresh_inverse"),
)

#: the layout of :class:`State` (float fields padded to 8 doubles, so every matrix row and vector starts
#: on a 64-byte boundary of an aligned buffer; the matrices, then the vectors, at the end)
LAYOUT = Layout("State", __name__, FIELDS, dims=("cap", "n8", "dim", "nf", "ntab"), align=LANES,
                placement=("layout", "kinds", "cols", "order", "ist", "params", "tab", "fst", "X", "Ph", "xph",
                           "Q", "D", "K", "A", "Qd", "Dd", "Kd", "mu", "occ", "P", "W"),
                doc="One tracker's complete state: named views of two base buffers (:data:`FIELDS`).")
State = LAYOUT.tuple

#: fields that are the tracker's state (saved by snapshots); the others are rebuilt
#: from the hyperparameters (layout, kernel spec, lag table) or are scratch
STATE_FIELDS = LAYOUT.names("state")


def _round8(n):
    return (n + LANES - 1) // LANES * LANES


def state_views(fbuf, ibuf) -> State:
    """The :class:`State` of the two base buffers of :func:`new_buffers`, as NumPy views."""
    return LAYOUT.views(fbuf, ibuf)


#: ``state_of(fbuf, ibuf)``: the :class:`State` of the two base buffers inside compiled code, as
#: reference-free views (valid while the buffers are; for compiled code only — from Python, arrays
#: returned by it would not keep the buffers alive: use :func:`state_views`)
state_of = LAYOUT.accessor("state_of", __file__)

#: ``unowned(st)``: ``st`` with reference-free arrays, valid while ``st`` is (compiled code only, as
#: :func:`state_of`). numba increments and decrements the reference count of every array of a ``State``
#: each time it is passed on (~0.2 µs per call for its 22 arrays); the public functions below start
#: with this, and a compiled loop that calls them many times should too.
unowned = LAYOUT.unowned("unowned", __file__)


def _aligned_zeros(n):
    """``n`` zeros starting on a 64-byte boundary (the sweeps load 8 doubles at a time)."""
    raw = np.zeros(n + LANES)
    skip = (-raw.ctypes.data // 8) % LANES
    return raw[skip:skip + n]


def new_buffers(budget: int, dim: int, forgetting: float, sn2: float, jitter: float, grid_step: float | None,
                refresh_every: int, refine: bool, spec: tuple, tab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two base buffers ``(float64, int64)`` of a fresh tracker (see :func:`new_state`)."""
    kinds, params, cols = spec
    cap = budget + 1
    n8 = _round8(cap)
    nf = kinds.shape[0]
    ntab = tab.shape[0]
    fbuf, ibuf = LAYOUT.new_buffers(_aligned_zeros, cap=cap, n8=n8, dim=dim, nf=nf, ntab=ntab)
    st = state_views(fbuf, ibuf)
    st.kinds[:] = kinds
    st.cols[:] = cols
    st.params[:] = params
    st.tab[:] = tab
    st.order[:] = np.arange(cap)
    st.ist[I_M] = budget
    st.ist[I_REFRESH] = refresh_every
    st.ist[I_REFINE] = 1 if refine else 0
    st.fst[F_LAM] = forgetting
    st.fst[F_SN2] = sn2
    st.fst[F_JIT] = jitter
    st.fst[F_INVTS] = 0.0 if not grid_step else 1.0 / grid_step
    st.fst[F_DSC] = 1.0
    return fbuf, ibuf


def new_state(budget: int, dim: int, forgetting: float, sn2: float, jitter: float, grid_step: float | None,
              refresh_every: int, refine: bool, spec: tuple, tab: np.ndarray) -> State:
    """A fresh :class:`State` for budget ``M``, input dimension ``dim``, the kernel ``spec``
    (:meth:`Kernel.spec`) and lag table ``tab`` (empty for none): the single definition of
    every field's shape and dtype (see :class:`State`)."""
    return state_views(*new_buffers(budget, dim, forgetting, sn2, jitter, grid_step, refresh_every, refine,
                                    spec, tab))


def validate_state(st: State) -> None:
    """Raise ``ValueError`` (naming the field) unless ``st`` holds a state the core can use safely.

    For a state read from outside (a snapshot): the compiled code indexes with ``order``,
    ``ist[I_N]`` and ``ist[I_HW]`` without bounds checks and relies on the layout above
    (free slots, lower triangles and padding zero). Checked: every float finite; ``n ≤ M``,
    ``n ≤ hw ≤ M+1``, ``order`` a permutation with the dictionary below ``hw``, ``occ`` its
    indicator; the pending/armed modes; free slots, lower triangles and padding of ``Q``, ``D``,
    ``K`` zero and ``K_D``'s diagonal positive on the dictionary; ``0 < c ≤ 1``; the phases in
    ``[−1, 1]``; the signal-power accumulators and an armed ``σ_y²`` possible.
    """
    cap, n8 = int(st.layout[0]), int(st.layout[1])
    ist, fst, order = st.ist, st.fst, st.order
    for name in ("fst", "X", "Ph", "Q", "Qd", "D", "Dd", "K", "Kd", "mu", "occ", "P"):
        if not np.isfinite(getattr(st, name)).all():
            raise ValueError(f"state {name!r} holds non-finite values")
    M, n, hw = int(ist[I_M]), int(ist[I_N]), int(ist[I_HW])
    if M != cap - 1:
        raise ValueError(f"state 'ist' budget {M} does not match its {cap} slots")
    if not 0 <= n <= M:
        raise ValueError(f"state 'ist' dictionary size {n} is outside 0…{M}")
    if not n <= hw <= cap:
        raise ValueError(f"state 'ist' high-water mark {hw} is outside {n}…{cap}")
    for name, slot, allowed in (("pending Q update", I_QPEND, (0, 1, 2)), ("pending Σ update", I_SPEND, (0, 1)),
                                ("armed flag", I_ARMED, (0, 1)), ("refine flag", I_REFINE, (0, 1))):
        if int(ist[slot]) not in allowed:
            raise ValueError(f"state 'ist' {name} is {int(ist[slot])}, expected one of {allowed}")
    if ist[I_STEPS] < 0 or ist[I_REFRESH] < 0:
        raise ValueError("state 'ist' step count and refresh interval must be >= 0")
    if not np.array_equal(np.sort(order), np.arange(cap)):
        raise ValueError(f"state 'order' is not a permutation of 0…{cap - 1}")
    used = order[:n]
    if n and int(used.max()) >= hw:
        raise ValueError("state 'order' puts a dictionary element beyond the high-water mark")
    occ = np.zeros(n8)
    occ[used] = 1.0
    if not np.array_equal(st.occ, occ):
        raise ValueError("state 'occ' does not mark exactly the dictionary's slots")
    free = np.setdiff1d(np.arange(n8), used)
    for name, U, d in (("Q", st.Q, st.Qd), ("D", st.D, st.Dd), ("K", st.K, st.Kd)):
        if np.tril(U).any():
            raise ValueError(f"state {name!r} has entries on or below the diagonal (it holds the strict upper triangle)")
        if U[free, :].any() or U[:, free].any() or d[free].any():
            raise ValueError(f"state {name!r} has entries in free slots")
    if n and not (st.Kd[used] > 0.0).all():
        raise ValueError("state 'Kd': the kernel matrix needs a positive diagonal")
    if st.mu[free].any() or st.P[P_P:P_G + 1][:, free].any():
        raise ValueError("state 'mu'/'P' have entries in free slots")
    if st.P[:, cap:].any():
        raise ValueError("state 'P' has entries beyond the slots")
    if np.abs(st.Ph).max(initial=0.0) > 1.0:
        raise ValueError("state 'Ph' holds a sine or cosine outside [-1, 1]")
    if not 0.0 < fst[F_DSC] <= 1.0:
        raise ValueError(f"state 'fst' scale of Σ − K_D is {float(fst[F_DSC])!r}, expected in (0, 1]")
    if fst[F_NUM] < 0.0 or fst[F_S02] < 0.0 or fst[F_DEN] < (1.0 if n else 0.0):
        raise ValueError("state 'fst' signal-power accumulators are impossible")
    if ist[I_ARMED] and n and not fst[F_SY2] > 0.0:
        raise ValueError("state 'fst' armed predictive variance must be > 0")


@njit(cache=True, nogil=True)
def build_lag_table(kinds, params, cols, step, nmax, tab):
    """``tab[L] = k(L·Ts)`` for ``L < nmax`` (0 below :data:`~kernels.covariance.KERNEL_FLOOR`, as the
    direct evaluation); returns the length.

    A kernel with a squared-exponential envelope stays below the floor at every lag from the one where
    its bound ``B·exp(−d²/(2σ²))`` (:func:`~kernels.covariance.envelope_bound`) falls below it: the
    table ends there with one ``0.0``, the *zero tail* sentinel —
    :func:`_kernel_row` then takes every lag beyond the table as 0 instead of evaluating it. Any other
    kernel stops at its first 0 (lags beyond are evaluated directly) or at ``nmax`` entries; such a
    table never ends with ``0.0``."""
    env, bound = envelope_bound(kinds, params)     # |k(d)| ≤ bound · exp(−d²/(2 env²))
    x0 = np.zeros(1)
    x1 = np.zeros(1)
    for L in range(nmax):
        d = L * step
        if env < math.inf and bound * math.exp(-(d * d) / (2.0 * env * env)) < KERNEL_FLOOR:
            tab[L] = 0.0                           # the zero tail
            return L + 1
        x1[0] = d
        v = kernel_value(kinds, params, cols, x1, x0)
        if abs(v) < KERNEL_FLOOR:
            v = 0.0
        if v == 0.0 and env == math.inf:
            return L
        tab[L] = v
    L = nmax
    while L > 0 and tab[L - 1] == 0.0:             # only the sentinel may end a table with 0.0
        L -= 1
    return L


# ---- k_t ----------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _off_table(dl, top, zero_tail):
    """The table cannot give ``k`` at the lag ``dl`` (grid steps): off the grid within the table, or beyond
    a table without zero tail (NaN: True). Branch-free, so that the row loop vectorises."""
    inside = dl <= top
    return (inside & (abs(dl - np.floor(dl + 0.5)) > LAG_TOL)) | ((not inside) & (not (zero_tail & (dl > top))))


@njit(cache=True, nogil=True, inline="always")
def _kernel_row(st, x, xph, hw, kt):
    """``k_t = k(D, x)`` into the slots of ``kt`` (zeros elsewhere, up to ``hw8``); returns ``k_tt = k(x,x) + ε_j``."""
    hw8 = (hw + LANES - 1) // LANES * LANES
    tab = st.tab
    ntab = tab.shape[0]
    invts = st.fst[F_INVTS]
    if invts > 0.0 and ntab > 0:
        X = st.X
        occ = st.occ
        x0 = x[0]
        top = ntab - 1.0
        zero_tail = tab[ntab - 1] == 0.0               # k = 0 beyond the table (build_lag_table)
        nbad = 0
        # nearest table entry; beyond the table tab[top], 0 in a zero tail (NaN: a valid index, and
        # evaluated directly below)
        for i in range(hw):
            dl = abs(x0 - X[i, 0]) * invts             # lag in grid steps
            nbad += _off_table(dl, top, zero_tail) & (occ[i] != 0.0)
            kt[i] = np.floor((dl if dl <= top else top) + 0.5)
        for i in range(hw):
            kt[i] = occ[i] * tab[np.int64(kt[i])]      # k(L Ts), computed once
        if nbad:                                       # off the grid, or beyond a table without zero tail: direct
            for i in range(hw):
                dl = abs(x0 - X[i, 0]) * invts
                if occ[i] != 0.0 and _off_table(dl, top, zero_tail):
                    kernel_row_phased(st.kinds, st.params, st.cols, X, st.Ph, occ, i, i + 1, x, xph, kt)
        ktt = tab[0]
    else:
        kernel_row_phased(st.kinds, st.params, st.cols, st.X, st.Ph, st.occ, 0, hw, x, xph, kt)
        ktt = 1.0                                      # k(x, x): every kernel is normalised (Kernel.diag)
    for i in range(hw, hw8):
        kt[i] = 0.0
    return ktt + st.fst[F_JIT]                         # k_tt = k(x, x) + ε_j


# ---- sweeps (kernels._krlst_simd) ----------------------------------------------------------------

_Q2_W = sweep(Stream(terms=2, store=True))            # Q ← Q + (sc p) pᵀ − (binv a) aᵀ;  Q k
_Q1_W = sweep(Stream(terms=1, store=True))            # Q ← Q + (sc p) pᵀ;  Q k
_Q2_R = sweep(Stream(terms=2))
_Q1_R = sweep(Stream(terms=1))
_Q0_R = sweep(Stream())                                # Q k
_QQ_R = sweep(Stream(vecs=2))                          # Q m, Q r
_S1_W = sweep(Stream(terms=1, store=True), Stream())   # D ← D − (cs g) gᵀ;  D q, K q
_S1_R = sweep(Stream(terms=1), Stream())
_S0_R = sweep(Stream(), Stream())


@njit(cache=True, nogil=True, inline="always")
def _sweep_q(st, hw, kt, q, write):
    """``q = Q k_t`` (2.17), applying the pending update of ``Q`` on the way (written back when ``write``):
    ``Q ← [[Q,0],[0,0]] + p pᵀ/γ²`` (2.15), then ``− a aᵀ/[Q_new]_rr`` for a removal (2.22)."""
    hw8 = (hw + LANES - 1) // LANES * LANES
    for i in range(hw8):
        q[i] = 0.0
    mode = st.ist[I_QPEND]
    sc = st.fst[F_QSC]
    nb = -st.fst[F_QBINV]
    p = st.P[P_P]
    a = st.P[P_A]
    Q = st.Q
    Qd = st.Qd
    for j in range(0, hw, ROWS):
        if mode == 2:
            if write:
                _Q2_W(j, hw8, Q, Qd, sc, p, nb, a, q, kt)
            else:
                _Q2_R(j, hw8, Q, Qd, sc, p, nb, a, q, kt)
        elif mode == 1:
            if write:
                _Q1_W(j, hw8, Q, Qd, sc, p, q, kt)
            else:
                _Q1_R(j, hw8, Q, Qd, sc, p, q, kt)
        else:
            _Q0_R(j, hw8, Q, Qd, q, kt)
    if write:
        st.ist[I_QPEND] = 0


@njit(cache=True, nogil=True, inline="always")
def _sweep_sigma(st, hw, c, q, h, kq, write):
    """``h = Σ q`` after the forgetting ``Σ ← λΣ + (1−λ)K_D`` (2.19) and ``kq = K_D q``.

    With ``Δ = Σ − K_D = c·D`` the forgetting is ``c ← λc`` (the caller passes the new ``c``), so the
    sweep only applies the pending part of 2.14, ``D ← D − g gᵀ/(c σ_y²)`` (written back when
    ``write``), and ``h = c·(D q) + K_D q``. When ``c`` falls below 1e-100 it is folded into ``D``.
    """
    hw8 = (hw + LANES - 1) // LANES * LANES
    D = st.D
    Dd = st.Dd
    if write and c < 1e-100:                      # keep D finite: D ← c D, c ← 1
        for j in range(hw):
            for i in range(j, hw8):
                D[j, i] *= c
            Dd[j] *= c
        st.fst[F_SC] *= c
        c = 1.0
    if write:
        st.fst[F_DSC] = c
    for i in range(hw8):
        h[i] = 0.0
        kq[i] = 0.0
    spend = st.ist[I_SPEND]
    ncs = -st.fst[F_SC]
    g = st.P[P_G]
    K = st.K
    Kd = st.Kd
    for j in range(0, hw, ROWS):
        if spend:
            if write:
                _S1_W(j, hw8, D, Dd, ncs, g, h, q, K, Kd, kq, q)
            else:
                _S1_R(j, hw8, D, Dd, ncs, g, h, q, K, Kd, kq, q)
        else:
            _S0_R(j, hw8, D, Dd, h, q, K, Kd, kq, q)
    for i in range(hw8):
        h[i] = c * h[i] + kq[i]                   # h = Σ q = c D q + K_D q
    if write:
        st.ist[I_SPEND] = 0


@njit(cache=True, nogil=True, inline="always")
def _sweep_qq(st, hw, m, r_, u, w):
    """``u = Q m`` and ``w = Q r`` in one read-only sweep (``Q`` has no pending update)."""
    hw8 = (hw + LANES - 1) // LANES * LANES
    for i in range(hw8):
        u[i] = 0.0
        w[i] = 0.0
    for j in range(0, hw, ROWS):
        _QQ_R(j, hw8, st.Q, st.Qd, u, m, w, r_)


@njit(cache=True, nogil=True, inline="always")
def _dot(a, b, n):
    """``Σ_{i<n} a_i b_i`` in a fixed order (8 lanes, as the sweeps; ``n`` a multiple of 8)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    for i in range(0, n, LANES):
        s0 = fmuladd(a[i], b[i], s0)
        s1 = fmuladd(a[i + 1], b[i + 1], s1)
        s2 = fmuladd(a[i + 2], b[i + 2], s2)
        s3 = fmuladd(a[i + 3], b[i + 3], s3)
        s4 = fmuladd(a[i + 4], b[i + 4], s4)
        s5 = fmuladd(a[i + 5], b[i + 5], s5)
        s6 = fmuladd(a[i + 6], b[i + 6], s6)
        s7 = fmuladd(a[i + 7], b[i + 7], s7)
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


# ---- steps 1–2: arm ------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def arm(st, x, out):
    """Steps 1–2 at ``x``, in place ("predict_next"): forget, predict, keep what the update needs.

    ``out[A_*] = ŷ, σ_f², σ_y², γ²`` (normalised). On an empty dictionary only ``x`` and
    ``k_tt`` are kept and the prior predictive ``0, k_tt, sn2 + k_tt, k_tt`` is reported.
    Arming again before :func:`update` forgets once more and predicts at the new ``x``.
    """
    _arm(unowned(st), x, out)


@njit(cache=True, nogil=True, inline="always")
def _arm(st, x, out):
    """:func:`arm` on an unowned state. (The helpers are inlined: numba increments and decrements
    the reference count of each of a ``State``'s arrays at every call boundary.)"""
    ist = st.ist
    fst = st.fst
    n = ist[I_N]
    hw = ist[I_HW]
    lam = fst[F_LAM]
    sn2 = fst[F_SN2]
    s = st.order[n]                               # free slot: where step 3 puts x
    for c in range(x.shape[0]):
        st.X[s, c] = x[c]
    xph = st.Ph[s]
    kernel_phases(st.kinds, st.params, st.cols, x, xph)
    ist[I_ARMED] = 1
    if n == 0:
        ktt = kernel_value(st.kinds, st.params, st.cols, x, x) + fst[F_JIT]   # k = k(x, x) + ε_j
        _armed(fst, out, ktt, 0.0, ktt, ktt, sn2 + ktt)
        return
    hw8 = (hw + LANES - 1) // LANES * LANES
    kt = st.P[P_KT]
    q = st.P[P_Q]
    h = st.P[P_H]
    mu = st.mu

    # ---- 1. forget, μ part (2.19); the Σ part is the λ of the Δ sweep --------------------------
    sl = math.sqrt(lam)
    for i in range(hw8):
        mu[i] = sl * mu[i]                        # μ ← √λ μ

    # ---- 2. predict (2.17) -----------------------------------------------------------------------
    ktt = _kernel_row(st, x, xph, hw, kt)         # k_t = k(D, x),  k_tt = k(x, x) + ε_j
    _sweep_q(st, hw, kt, q, True)                 # q = Q k_t
    y_mean = _dot(q, mu, hw8)                     # ŷ = qᵀ μ
    gamma2 = ktt - _dot(kt, q, hw8)               # γ² = k_tt − k_tᵀ q
    gamma2 = max(gamma2, 0.0)
    kq = st.W[W_KQ]
    _sweep_sigma(st, hw, lam * fst[F_DSC], q, h, kq, True)   # Σ ← λΣ + (1−λ)K_D;  h = Σ q, K_D q
    if ist[I_REFINE] != 0:
        res = st.P[P_RES]
        for i in range(hw8):
            res[i] = kt[i] - kq[i]                # k_t − K_D q, for the refinement of q
    sf2 = gamma2 + _dot(q, h, hw8)                # σ_f² = γ² + qᵀ h
    sf2 = max(sf2, 0.0)
    _armed(fst, out, ktt, y_mean, gamma2, sf2, sn2 + sf2)   # σ_y² = sn2 + σ_f²


@njit(cache=True, nogil=True, inline="always")
def _armed(fst, out, ktt, y_mean, gamma2, sf2, sy2):
    fst[F_KTT] = ktt
    fst[F_YM] = y_mean
    fst[F_G2] = gamma2
    fst[F_SF2] = sf2
    fst[F_SY2] = sy2
    out[A_MEAN] = y_mean
    out[A_SF2] = sf2
    out[A_SY2] = sy2
    out[A_G2] = gamma2


# ---- steps 3–6: update -------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _init(st, y, out):
    """Step 6, eq. 2.16 (first sample, armed): ``Q = 1/k``, ``μ = y k/(k+sn2)``, ``Σ = k − k²/(k+sn2)``."""
    fst = st.fst
    ist = st.ist
    sn2 = fst[F_SN2]
    k = fst[F_KTT]                                # k = k(x, x) + ε_j  (x is in X[order[0]])
    s = st.order[0]
    st.Kd[s] = k                                  # K_D = k
    st.Qd[s] = 1.0 / k                            # Q = 1 / k
    st.mu[s] = y * k / (k + sn2)                  # μ = y k / (k + sn2)
    st.Dd[s] = -(k * k / (k + sn2)) / fst[F_DSC]  # Σ = k − k² / (k + sn2),  Δ = Σ − K_D = c D
    st.occ[s] = 1.0
    fst[F_NUM] = y * y / (k + sn2)                # num = y² / (k + sn2)
    fst[F_DEN] = 1.0                              # den = 1
    fst[F_S02] = fst[F_NUM] / fst[F_DEN]          # s0² = num / den
    ist[I_N] = 1
    ist[I_HW] = s + 1
    ist[I_STEPS] += 1
    # report the prior predictive of this first sample (kafbox writes zeros on this row)
    _write_out(out, y, 0.0, sn2 + k, k, k, -1.0, 0.0, fst[F_S02], 1)


@njit(cache=True, nogil=True, error_model="numpy")
def _criterion(u, q, Qd, sc, pm, hw8, crit):
    """``crit_i = |[Q_new μ_new]_i / [Q_new]_ii|`` for all slots at once (so that it vectorises; a
    free slot gives 0/0 = NaN, which no comparison picks); returns the smallest."""
    for i in range(hw8):
        qii = Qd[i] + sc * (q[i] * q[i])          # [Q_new]_ii
        qmu = u[i] + sc * (q[i] * pm)             # [Q_new μ_new]_i
        crit[i] = abs(qmu / qii)                  # |[Q μ]_i / Q_ii|, MSE pruning criterion
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = np.inf
    for i in range(0, hw8, LANES):                # min is exact in any order: 8 independent chains
        m0 = min(m0, crit[i])
        m1 = min(m1, crit[i + 1])
        m2 = min(m2, crit[i + 2])
        m3 = min(m3, crit[i + 3])
        m4 = min(m4, crit[i + 4])
        m5 = min(m5, crit[i + 5])
        m6 = min(m6, crit[i + 6])
        m7 = min(m7, crit[i + 7])
    return min(min(min(m0, m1), min(m2, m3)), min(min(m4, m5), min(m6, m7)))


@njit(cache=True, nogil=True, inline="always")
def _update(st, y, out):
    """Steps 3–5 for ``n ≥ 1`` from the armed prediction (eq. 2.14, 2.15, 2.20–2.22)."""
    ist = st.ist
    fst = st.fst
    order = st.order
    n = ist[I_N]
    hw = ist[I_HW]
    M = ist[I_M]
    lam = fst[F_LAM]
    jit = fst[F_JIT]
    P = st.P
    kt = P[P_KT]
    q = P[P_Q]
    h = P[P_H]
    p = P[P_P]
    a = P[P_A]
    g = P[P_G]
    m = st.W[W_M]
    u = st.W[W_U]
    mu = st.mu
    ktt = fst[F_KTT]
    y_mean = fst[F_YM]
    gamma2 = fst[F_G2]
    sf2 = fst[F_SF2]
    sy2 = fst[F_SY2]
    err = y - y_mean
    e = err / sy2                                 # (y − ŷ) / σ_y²
    cs = 1.0 / sy2

    # ---- 4. signal power (2.20, with the square) ---------------------------------------------------
    fst[F_NUM] += lam * err * err / sy2           # num ← num + λ (y − ŷ)² / σ_y²
    fst[F_DEN] += lam                             # den ← den + λ
    fst[F_S02] = fst[F_NUM] / fst[F_DEN]          # s0² = num / den

    # ---- 3. posterior of f at [D; x] (2.14), μ part -----------------------------------------------
    s = order[n]                                  # free slot for the new basis (x is there)
    hwn = hw if s < hw else s + 1
    hw8 = (hwn + LANES - 1) // LANES * LANES
    for i in range(hw8):
        m[i] = mu[i] + e * h[i]                   # μ_new = [μ; ŷ] + (y − ŷ)/σ_y² [h; σ_f²]
    m[s] = y_mean + e * sf2

    # ---- 5. which basis to prune (2.21–2.22) ---------------------------------------------------------
    r = -1                                        # logical index to remove, -1: none
    g2q = gamma2                                  # γ² of the Q update (refined below)
    prune = n + 1 > M
    refine = ist[I_REFINE] != 0
    if not (gamma2 >= jit and gamma2 > 0.0):
        r = n                                     # roundoff guard: drop the new sample (also γ² = 0 with
                                                  # ε_j = 0, and a NaN γ² of a damaged state)
    elif prune or refine:
        # u = Q μ_new (row/column s of Q is zero); with refine also w = Q (k_t − K_D q), one
        # step of iterative refinement for the Q update: q ← q + w, γ² ← k_tt − k_tᵀ q. Without
        # it the update multiplies the error of Q by up to ~|q|²/γ² ≲ 1/ε_j (kafbox's recursion).
        # (ŷ, γ², σ² reported and the μ, Σ updates keep the unrefined q, as kafbox.)
        w = st.W[W_W]
        if prune and refine:
            _sweep_qq(st, hwn, m, P[P_RES], u, w)
        elif prune:
            _sweep_q(st, hwn, m, u, False)        # (no pending Q update: arm applied it)
        else:
            _sweep_q(st, hwn, P[P_RES], w, False)
        if refine:
            for i in range(hw8):
                w[i] = q[i] + w[i]                # refined q
            g2r = ktt - _dot(kt, w, hw8)
            if g2r > 0.0:
                g2q = g2r
                for i in range(hw8):
                    q[i] = w[i]
    if r < 0 and prune:
        # criterion on Q_new = [[Q,0],[0,0]] + p pᵀ/γ², p = [q; −1], without forming Q_new:
        #   [Q_new μ_new]_i = [Q μ_new]_i + p_i (pᵀ μ_new)/γ²,  [Q_new]_ii = Q_ii + p_i²/γ²
        sc = 1.0 / g2q
        q[s] = -1.0
        pm = _dot(q, m, hw8)                      # pᵀ μ_new
        crit = st.W[W_KT]
        best = _criterion(u, q, st.Qd, sc, pm, hw8, crit)
        for l in range(n + 1):                    # order[n] == s: the new sample is last
            if crit[order[l]] == best:            # first minimum, as Matlab's min
                r = l
                break
        if r < 0:
            r = n                                 # no finite criterion (a damaged state): drop the new
                                                  # sample rather than grow beyond the budget's slots
        q[s] = 0.0

    if r == n:
        # ---- reduced update: Q stays as before step 3, x is not added ---------------------------
        for i in range(hw8):
            mu[i] = m[i]                          # μ ← μ + (y − ŷ)/σ_y² h
            g[i] = h[i]                           # Σ ← Σ − h hᵀ/σ_y²   (pending)
        mu[s] = 0.0
        g[s] = 0.0
        _free_slot(st, s)                         # the slot stays free
        fst[F_SC] = cs / fst[F_DSC]
        ist[I_SPEND] = 1
        ist[I_STEPS] += 1
        _write_out(out, y, y_mean, sy2, sf2, gamma2, float(n), 1.0, fst[F_S02], n)
        return

    # ---- 3. update (2.14, 2.15): append x to D ------------------------------------------------------
    for i in range(hw8):
        mu[i] = mu[i] + e * h[i]                  # μ ← μ_new
        g[i] = h[i]
        p[i] = q[i]
    sc = 1.0 / g2q
    if r < 0:
        t = s                                     # the new basis stays in slot s
        ist[I_QPEND] = 1                          # Q ← [[Q,0],[0,0]] + p pᵀ/γ²  (pending)
        n_new = n + 1
        removed = -1.0
    else:
        # ---- 5. prune r (2.21–2.22); the new basis takes its slot ---------------------------------------
        t = order[r]
        Q = st.Q
        p[s] = -1.0
        for i in range(t):                        # a = [Q_new]_{:, r},  Q_new = [[Q,0],[0,0]] + p pᵀ/γ²
            a[i] = Q[i, t] + sc * (p[i] * p[t])
            Q[i, t] = 0.0                         # (row and column t of Q become those of the new basis: 0)
        a[t] = st.Qd[t] + sc * (p[t] * p[t])
        for i in range(t + 1, hw8):
            a[i] = Q[t, i] + sc * (p[i] * p[t])
            Q[t, i] = 0.0
        st.Qd[t] = 0.0
        fst[F_QBINV] = 1.0 / a[t]                 # Q ← Q_new[−r,−r] − a aᵀ/[Q_new]_rr  (pending)
        a[t] = a[s]                               # the new basis moves from slot s to t
        a[s] = 0.0
        p[s] = 0.0
        mu[s] = 0.0
        g[s] = 0.0
        for c in range(st.X.shape[1]):
            st.X[t, c] = st.X[s, c]
        for c in range(st.Ph.shape[1]):
            st.Ph[t, c] = st.Ph[s, c]
        _free_slot(st, s)
        for l in range(r, n - 1):                 # drop r from the logical order, the new basis last
            order[l] = order[l + 1]
        order[n - 1] = t
        order[n] = s
        ist[I_QPEND] = 2
        n_new = n
        removed = float(r)
    K, D = st.K, st.D
    ic = 1.0 / fst[F_DSC]
    for i in range(t):                            # K_D ← [[K_D, k_t], [k_tᵀ, k_tt]]  (row/column t)
        K[i, t] = kt[i]                           # Δ ← [[Δ, h − k_t], [·, σ_f² − k_tt]] ...
        D[i, t] = (h[i] - kt[i]) * ic
    for i in range(t + 1, hw8):
        K[t, i] = kt[i]
        D[t, i] = (h[i] - kt[i]) * ic
    st.Kd[t] = ktt
    st.Dd[t] = (sf2 - ktt) * ic
    mu[t] = y_mean + e * sf2
    g[t] = sf2                                    # ... − g gᵀ/σ_y²,  g = [h; σ_f²]  (pending)
    p[t] = -1.0                                   # p = [q; −1]
    st.occ[t] = 1.0
    fst[F_SC] = cs * ic
    ist[I_SPEND] = 1
    fst[F_QSC] = sc
    ist[I_N] = n_new
    ist[I_HW] = hwn
    ist[I_STEPS] += 1
    _write_out(out, y, y_mean, sy2, sf2, gamma2, removed, 0.0, fst[F_S02], n_new)


@njit(cache=True, nogil=True, inline="always")
def _free_slot(st, s):
    """Zero the input, phases and occupancy of slot ``s``."""
    for c in range(st.X.shape[1]):
        st.X[s, c] = 0.0
    for c in range(st.Ph.shape[1]):
        st.Ph[s, c] = 0.0
    st.occ[s] = 0.0


@njit(cache=True, nogil=True, inline="always")
def _write_out(out, y, y_mean, sy2, sf2, gamma2, removed, reduced, s02, n):
    out[O_MEAN] = y_mean
    out[O_SY2] = sy2
    out[O_SF2] = sf2
    out[O_G2] = gamma2
    out[O_REMOVED] = removed
    out[O_REDUCED] = reduced
    out[O_FILT] = y_mean + sf2 * (y - y_mean) / sy2    # E[f(x) | y] = ŷ + σ_f² (y − ŷ)/σ_y²
    out[O_FILTVAR] = sf2 - sf2 * sf2 / sy2             # Var[f(x) | y] = σ_f² − σ_f⁴/σ_y²
    out[O_S02] = s02
    out[O_SIZE] = n


@njit(cache=True, nogil=True, inline="always")
def _k_at(st, i, j):
    """``K_D`` entry of slots ``i, j`` from the (strict upper, diagonal) storage."""
    if i == j:
        return st.Kd[i]
    return st.K[i, j] if i < j else st.K[j, i]


@njit(cache=True, nogil=True)
def refresh_inverse(st):
    """:func:`_refresh_inverse` (see there) on ``st``."""
    return _refresh_inverse(unowned(st))


@njit(cache=True, nogil=True)
def _refresh_inverse(st):
    """``Q ← K_D⁻¹`` from the cached ``K_D`` by Cholesky; False (``Q`` untouched) if not PD.

    Works in the dense scratch ``A`` in the dictionary's logical order, with row-wise axpys
    only (contiguous, so LLVM vectorises them without reassociation; ~``n³/2`` multiply-adds):

    1. ``K_D = Uᵀ U`` (upper ``U`` in ``A``'s upper triangle), diagonal copied to ``W[W_U]``;
    2. ``Z = U⁻ᵀ = L⁻¹`` row by row into ``A``'s strict lower triangle, diagonal in ``W[W_W]``;
    3. ``K_D⁻¹ = Zᵀ Z`` accumulated into ``A``'s upper triangle (``U`` is no longer needed);
    4. scattered into ``Q``'s (strict upper, diagonal) storage. The pending update of ``Q``
       is dropped. A pivot ``≤ 0`` (``K_D`` numerically singular, e.g. ``ε_j = 0`` and a
       repeated input) leaves ``Q`` and its pending update as they were.
    """
    n = st.ist[I_N]
    order = st.order
    A = st.A
    ud = st.W[W_U]
    zd = st.W[W_W]
    # ---- 1. Cholesky K_D = Uᵀ U (right-looking, row axpys) ----------------------------------------
    for i in range(n):
        si = order[i]
        for j in range(i, n):
            A[i, j] = _k_at(st, si, order[j])
    for k in range(n):
        d = A[k, k]
        if not d > 0.0:
            return False
        ukk = math.sqrt(d)
        A[k, k] = ukk
        ud[k] = ukk
        for j in range(k + 1, n):
            A[k, j] = A[k, j] / ukk
        for i in range(k + 1, n):
            c = A[k, i]
            for j in range(i, n):
                A[i, j] -= c * A[k, j]
    # ---- 2. Z = L⁻¹ (L = Uᵀ): row i solves Σ_k L[i,k] Z[k,:] = e_i -----------------------------------
    for i in range(n):
        for j in range(i):
            A[i, j] = 0.0                         # row i of Z accumulates here (strict lower)
        for k in range(i):
            c = A[k, i]                           # L[i, k]
            for j in range(k):
                A[i, j] -= c * A[k, j]            # − L[i, k] Z[k, j]
            A[i, k] -= c * zd[k]
        uii = ud[i]
        for j in range(i):
            A[i, j] = A[i, j] / uii
        zd[i] = 1.0 / uii
    # ---- 3. K_D⁻¹ = Zᵀ Z = Σ_k Z[k,:]ᵀ Z[k,:] into the upper triangle --------------------------------
    for a in range(n):
        for b in range(a, n):
            A[a, b] = 0.0
    for k in range(n):
        for a in range(k):
            c = A[k, a]                           # Z[k, a]
            for b in range(a, k):
                A[a, b] += c * A[k, b]            # row a of K_D⁻¹, columns a..k−1
            A[a, k] += c * zd[k]
        A[k, k] += zd[k] * zd[k]
    # ---- 4. scatter --------------------------------------------------------------------------------
    Q = st.Q
    for a in range(n):
        sa = order[a]
        st.Qd[sa] = A[a, a]
        for b in range(a + 1, n):
            sb = order[b]
            if sa < sb:
                Q[sa, sb] = A[a, b]
            else:
                Q[sb, sa] = A[a, b]
    st.ist[I_QPEND] = 0
    return True


@njit(cache=True, nogil=True)
def update(st, y, out):
    """Steps 3–5 (or 6 on the first sample) with the armed prediction; False if nothing is armed.

    ``out[O_*]``. After the step, every ``refresh_every`` steps, ``Q`` is recomputed from ``K_D``.
    """
    return _update_step(unowned(st), y, out)


@njit(cache=True, nogil=True, inline="always")
def _update_step(st, y, out):
    """:func:`update` on an unowned state."""
    ist = st.ist
    if ist[I_ARMED] == 0:
        return False
    ist[I_ARMED] = 0
    if ist[I_N] == 0:
        _init(st, y, out)
    else:
        _update(st, y, out)
    every = ist[I_REFRESH]
    if every > 0 and ist[I_STEPS] % every == 0:
        _refresh_inverse(st)
    return True


@njit(cache=True, nogil=True)
def learn(st, x, y, out):
    """One sample: :func:`arm` at ``x`` then :func:`update` with ``y`` (steps 1–5, or 6 first)."""
    st = unowned(st)
    arm(st, x, out)
    update(st, y, out)


@njit(cache=True, nogil=True)
def learn_many(st, xs, ys, outs):
    """:func:`learn` over a stream; ``outs[t]`` receives the ``out`` row of sample ``t``."""
    st = unowned(st)
    for t in range(ys.shape[0]):
        learn(st, xs[t], ys[t], outs[t])


@njit(cache=True, nogil=True)
def track(st, xs, ys, learn_mask, outs):
    """Monitor block: for each arriving sample ``j`` in order, ``update(ys[j])`` if
    ``learn_mask[j]`` (``ys[j]``: the residual of the previously armed ``x``), then
    ``arm(xs[j])``.

    ``outs[j]`` (width :data:`N_TRACK`): ``[0, N_OUT)`` the ``out`` of the update (NaN when
    not learned), ``[T_NEXT, T_NEXT + N_ARM)`` the new prediction (``A_*``), ``T_S02`` s0²,
    ``T_SIZE`` n after sample ``j``, ``T_LEARNED`` 1.0 if an update ran (mask set and armed).
    """
    st = unowned(st)
    for j in range(xs.shape[0]):
        o = outs[j]
        learned = False
        if learn_mask[j]:
            learned = update(st, ys[j], o)
        if not learned:
            for c in range(N_OUT):
                o[c] = np.nan
        arm(st, xs[j], o[T_NEXT:T_NEXT + N_ARM])
        o[T_S02] = st.fst[F_S02]
        o[T_SIZE] = st.ist[I_N]
        o[T_LEARNED] = 1.0 if learned else 0.0


@njit(cache=True, nogil=True)
def predict(st, x, forget, out):
    """:func:`_predict` (see there) on ``st``."""
    _predict(unowned(st), x, forget, out)


@njit(cache=True, nogil=True, inline="always")
def _predict(st, x, forget, out):
    """``ŷ, σ_f², σ_y², γ²`` at ``x`` from the current state (2.17) into ``out[A_*]``; state untouched.

    With ``forget`` the forgetting (2.19) of the next step is applied virtually, so the
    numbers are bit-identical to what the next :func:`learn` reports for ``x``.
    """
    ist = st.ist
    fst = st.fst
    hw = ist[I_HW]
    hw8 = (hw + LANES - 1) // LANES * LANES
    lam = fst[F_LAM] if forget else 1.0
    W = st.W
    kt = W[W_KT]
    q = W[W_Q]
    h = W[W_H]
    xph = st.xph
    kernel_phases(st.kinds, st.params, st.cols, x, xph)
    ktt = _kernel_row(st, x, xph, hw, kt)
    _sweep_q(st, hw, kt, q, False)
    sl = math.sqrt(lam)
    mu = W[W_M]
    for i in range(hw8):
        mu[i] = sl * st.mu[i]
    y_mean = _dot(q, mu, hw8)
    gamma2 = ktt - _dot(kt, q, hw8)
    gamma2 = max(gamma2, 0.0)
    kq = W[W_KQ]
    _sweep_sigma(st, hw, lam * fst[F_DSC], q, h, kq, False)
    sf2 = gamma2 + _dot(q, h, hw8)
    sf2 = max(sf2, 0.0)
    out[A_MEAN] = y_mean
    out[A_SF2] = sf2
    out[A_SY2] = fst[F_SN2] + sf2
    out[A_G2] = gamma2


@njit(cache=True, nogil=True)
def materialize(st, Qout, Sout):
    """Full ``Q`` and ``Σ = K_D + c D`` over the slots ``[0, hw)`` with the pending updates applied (no forgetting)."""
    st = unowned(st)
    ist = st.ist
    fst = st.fst
    hw = ist[I_HW]
    p = st.P[P_P]
    a = st.P[P_A]
    g = st.P[P_G]
    sc = fst[F_QSC]
    nb = -fst[F_QBINV]
    ncs = -fst[F_SC]
    mode = ist[I_QPEND]
    spend = ist[I_SPEND]
    for j in range(hw):
        for i in range(j, hw):
            if i == j:
                v = st.Qd[j]
                w = st.Dd[j]
                k = st.Kd[j]
            else:
                v = st.Q[j, i]
                w = st.D[j, i]
                k = st.K[j, i]
            if mode >= 1:
                v = fmuladd(sc * p[j], p[i], v)
            if mode == 2:
                v = fmuladd(nb * a[j], a[i], v)
            if spend:
                w = fmuladd(ncs * g[j], g[i], w)
            w = k + fst[F_DSC] * w
            Qout[j, i] = v
            Qout[i, j] = v
            Sout[j, i] = w
            Sout[i, j] = w


# ---- Python entry points: the two base buffers instead of a State (see the module docstring) -----

@njit(cache=True, nogil=True)
def arm_buffers(fbuf, ibuf, x, out):
    """:func:`arm` on ``state_of(fbuf, ibuf)``."""
    _arm(state_of(fbuf, ibuf), x, out)


@njit(cache=True, nogil=True)
def update_buffers(fbuf, ibuf, y, out):
    """:func:`update` on ``state_of(fbuf, ibuf)``."""
    return _update_step(state_of(fbuf, ibuf), y, out)


@njit(cache=True, nogil=True)
def learn_buffers(fbuf, ibuf, x, y, out):
    """:func:`learn` on ``state_of(fbuf, ibuf)``."""
    learn(state_of(fbuf, ibuf), x, y, out)


@njit(cache=True, nogil=True)
def predict_buffers(fbuf, ibuf, x, forget, out):
    """:func:`predict` on ``state_of(fbuf, ibuf)``."""
    _predict(state_of(fbuf, ibuf), x, forget, out)
