"""The KRLS-T core's state: named slots, the field list of :class:`State` and its checks.

Everything a tracker reads or writes is one :class:`State`, a ``NamedTuple`` of views of two base
buffers (``float64`` and ``int64``), generated from :data:`FIELDS` (:class:`kernels.layout.Layout`):
:func:`new_buffers` / :func:`state_views` from Python, :func:`state_of` inside compiled code. A compiled
function takes a ``State`` (``arm(st, x, out)``); Python calls go through ``*_buffers`` twins that take
the two buffers and rebuild the views inside, because numba unboxes each array of a tuple argument
separately. Compiled code passes a ``State`` on without reference counting (:func:`unowned`).

Slots and storage
-----------------
The ``M+1`` dictionary positions are *slots*. ``order[:n]`` lists the slots of the ``n`` dictionary
elements in the dictionary's logical order (kafbox's order, oldest first), ``order[n:]`` the free
slots; ``occ[s]`` is 1 for an occupied slot. A free slot has a zero row and column in every matrix and
zero entries in every vector, so the sweeps run over the contiguous range ``[0, hw)`` (``hw``:
high-water mark of used slots) without gathering. Adding a basis writes one row/column into a free
slot; when a basis is pruned in the same step the new one takes over its slot. Nothing is shifted and
no kernel value is recomputed. Only the pruning ``argmin`` walks the logical order, so ties resolve to
the first (oldest) element as Matlab's ``min``.

The symmetric matrices ``Q ≈ K_D⁻¹``, ``Δ = Σ − K_D`` and ``K_D = k(D, D) + ε_j I`` are kept as strict
upper triangles (``Q``, ``D``, ``K``, ``(n8, n8)``, ``n8 = ⌈(M+1)/8⌉·8``) plus diagonals (``Qd``, ``Dd``,
``Kd``), swept by the 8-lane kernels of :mod:`kernels._krlst_simd` (the lanes are explicit, so the
results do not depend on the vector width or on the caller). ``Δ`` instead of ``Σ`` makes the
forgetting ``Σ ← λΣ + (1−λ)K_D`` (2.19) the scaling ``Δ ← λΔ``, kept as a scalar: ``Δ = c·D`` with
``c = fst[F_DSC]`` (folded into ``D`` before it underflows).

Named slots
-----------
``ist`` (int64): ``I_*``; ``fst`` (float64): ``F_*`` (the ``F_KTT…F_SY2`` block is the armed
prediction); rows of ``P`` (pending and armed vectors, state): ``P_*``; rows of ``W`` (scratch):
``W_*``. Output buffers: ``update``/``learn`` write ``O_*`` (``N_OUT``), ``arm``/``predict`` write
``A_*`` (``N_ARM``), a row of ``track`` is ``T_*`` (``N_TRACK``).

Compiled code that runs beside the tracker on the same slots (the shadow means of
:mod:`kernels.beta_step`) reads, after ``arm``, ``P[P_Q]`` (``q``) and ``P[P_H]`` (``h``; ``update``
does not change it) and the armed ``fst[F_YM…F_SY2]``; the new basis goes to the free slot
``order[n]``; after ``update`` a reduced step (``O_REDUCED``) leaves it free, a pruning step
(``O_REMOVED ≥ 0``) moves the new basis into the pruned one's slot, which is then ``order[n − 1]``,
and frees ``order[n]``. These are part of the layout: keep them when changing it.
"""

from __future__ import annotations

import numpy as np

from ._krlst_simd import LANES
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
#: each time it is passed on; the core's public functions start with this, and a compiled loop that
#: calls them many times should too.
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
