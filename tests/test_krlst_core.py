"""The KRLS-T core's building blocks: state layout, 8-lane sweeps, phase-cached kernel rows, lazy Σ scale."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from gp_reference import batch_gp
from numba import literal_unroll, njit

from kernels import KRLST, LocallyPeriodic, Periodic, Product, SquaredExponential
from kernels import _krlst_core as core
from kernels._krlst_simd import SWEEP_ROWS, Stream, sweep
from kernels.covariance import KERNEL_FLOOR, ZeroMeanLocallyPeriodic, kernel_phases, kernel_row_phased
from kernels.krlst_numpy import NumpyKRLST

TS = 1 / 333


def _stream(n, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    y = 1e-3 * (np.sin(2 * np.pi * 55 * t) + 0.5 * np.sin(2 * np.pi * 110 * t + 0.3))
    return t, y + 1e-4 * rng.standard_normal(n)


def _spindle(n, seed=0, theta0=0.0):
    """x = (t, θ): θ the unwrapped spindle angle (rad) at ~3000 rpm; y periodic in θ (4 teeth)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    theta = theta0 + 2 * np.pi * 50.0 * t + 0.2 * np.sin(2 * np.pi * 0.3 * t)
    y = 1e-3 * (np.sin(4 * theta) + 0.3 * np.sin(8 * theta + 0.5)) + 1e-4 * rng.standard_normal(n)
    return np.column_stack([t, theta]), y


def spindle_kernel():
    return Product(SquaredExponential(0.8, dims=0), Periodic(0.6, 2 * np.pi / 4, dims=1))


# -- State: one layout for Python and compiled code ---------------------------------------------------


@njit
def _fill_compiled(fbuf, ibuf):
    """Write ``1000·(field number) + element index`` into every field through the compiled views."""
    st = core.state_of(fbuf, ibuf)
    k = 0
    for field in literal_unroll(st):
        k += 1
        a = field.reshape(-1)
        for i in range(a.size):
            a[i] = 1000 * k + i
    return k


@pytest.mark.parametrize("budget, dim, kernel, ntab", [(7, 1, LocallyPeriodic(1.0, 0.5, 0.1), 5),
                                                       (100, 2, spindle_kernel(), 0),
                                                       (33, 3, SquaredExponential(1.0), 0)])
def test_state_layout_is_shared_by_python_and_compiled_code(budget, dim, kernel, ntab):
    spec = kernel.spec()
    tab = np.linspace(1.0, 0.5, ntab)
    fbuf, ibuf = core.new_buffers(budget, dim, 0.99, 0.1, 1e-6, TS if ntab else None, 0, True, spec, tab)
    st = core.state_views(fbuf, ibuf)
    cap, n8, nf = budget + 1, -(-(budget + 1) // 8) * 8, len(spec[0])
    shapes = {"layout": (8,), "kinds": (nf,), "cols": (nf, 2), "order": (cap,), "ist": (core.N_IST,),
              "params": (nf, 3), "tab": (ntab,), "fst": (core.N_FST,), "X": (cap, dim), "Ph": (cap, 2 * nf),
              "xph": (2 * nf,), "Q": (n8, n8), "Qd": (n8,), "D": (n8, n8), "Dd": (n8,), "K": (n8, n8),
              "Kd": (n8,), "mu": (n8,), "occ": (n8,), "P": (core.N_P, n8), "W": (core.N_W, n8), "A": (n8, n8)}
    assert set(shapes) == set(core.State._fields)
    for name, shape in shapes.items():
        arr = getattr(st, name)
        assert arr.shape == shape, name
        assert arr.dtype == (np.int64 if name in ("layout", "kinds", "cols", "order", "ist") else np.float64)
        assert arr.flags.c_contiguous, name
    np.testing.assert_array_equal(st.kinds, spec[0])
    np.testing.assert_array_equal(st.params, spec[1])
    assert st.ist[core.I_M] == budget and st.fst[core.F_DSC] == 1.0 and st.fst[core.F_INVTS] == (333 if ntab else 0)
    for name in ("Q", "D", "K", "P", "W", "A"):                         # rows start on 64-byte boundaries
        assert getattr(st, name).ctypes.data % 64 == 0
    # the compiled views are the same memory, field by field, and the fields do not overlap
    assert _fill_compiled(fbuf, ibuf) == len(core.State._fields)
    for k, name in enumerate(core.State._fields):
        arr = getattr(st, name).ravel()
        np.testing.assert_array_equal(arr, 1000 * (k + 1) + np.arange(arr.size), err_msg=name)
    np.testing.assert_array_equal(core.new_state(budget, dim, 0.99, 0.1, 1e-6, None, 0, True, spec, tab).occ, 0.0)


# -- 8-lane sweeps over (strict upper triangle, diagonal) storage ---------------------------------------


_SWEEP_W = sweep(Stream(terms=2, scale=True, store=True, vecs=2))
_SWEEP_R = sweep(Stream(vecs=1))


@njit
def _run_sweeps(U, d, c1, x1, c2, x2, lam, t1, z1, t2, z2, n):
    n8 = U.shape[1]
    for j in range(0, n, SWEEP_ROWS):
        _SWEEP_W(j, n8, U, d, c1, x1, c2, x2, lam, t1, z1, t2, z2)


@njit
def _run_read(U, d, t, z, n):
    for j in range(0, n, SWEEP_ROWS):
        _SWEEP_R(j, U.shape[1], U, d, t, z)


@pytest.mark.parametrize("n", [1, 7, 8, 13, 64, 101])
def test_sweep_updates_and_multiplies_a_symmetric_matrix(n):
    rng = np.random.default_rng(n)
    n8 = -(-n // 8) * 8
    S = rng.standard_normal((n, n))
    S = S + S.T
    U = np.zeros((n8, n8))
    U[:n, :n] = np.triu(S, 1)
    d = np.zeros(n8)
    d[:n] = np.diag(S)
    x1, x2, z1, z2 = (np.pad(rng.standard_normal(n), (0, n8 - n)) for _ in range(4))
    t1, t2 = np.zeros(n8), np.zeros(n8)
    c1, c2, lam = 0.7, -1.3, 0.9
    _run_sweeps(U, d, c1, x1, c2, x2, lam, t1, z1, t2, z2, n)
    S_new = lam * (S + c1 * np.outer(x1[:n], x1[:n]) + c2 * np.outer(x2[:n], x2[:n]))
    np.testing.assert_allclose(np.triu(U[:n, :n], 1) + np.triu(U[:n, :n], 1).T + np.diag(d[:n]), S_new,
                               rtol=0, atol=1e-13)
    assert not np.tril(U).any() and not U[:, n:].any()                # lower triangle and padding stay 0
    np.testing.assert_allclose(t1[:n], S_new @ z1[:n], rtol=0, atol=1e-12)
    np.testing.assert_allclose(t2[:n], S_new @ z2[:n], rtol=0, atol=1e-12)
    assert not t1[n:].any()
    t3 = np.zeros(n8)
    _run_read(U, d, t3, z1, n)                                        # read-only sweep of the stored result
    np.testing.assert_array_equal(t3, t1)                             # same lanes, same order: same bits


# -- kernel rows from cached phases ----------------------------------------------------------------------


@pytest.mark.parametrize("kernel, X", [
    (LocallyPeriodic(1.2, 0.495, 1 / 55), np.arange(60)[:, None] * TS + 3.0),
    (LocallyPeriodic(0.05, 0.6, 1 / 55), np.arange(60)[:, None] * TS + 86400.0 * 3),   # three days in
    (Periodic(0.7, 0.3), np.linspace(-5, 5, 40)[:, None]),
    (SquaredExponential(0.4), np.random.default_rng(0).uniform(0, 2, (50, 3))),
    (spindle_kernel(), _spindle(80, theta0=1e6)[0]),                                    # θ ~ 1e6 rad
])
def test_phased_row_matches_the_kernel_formula(kernel, X):
    X = np.ascontiguousarray(X)                                        # C order, as the tracker's
    kinds, params, cols = spec = kernel.spec()
    ph = np.zeros((len(X), 2 * len(kinds)))
    for i, xi in enumerate(X):
        kernel_phases(*spec, np.ascontiguousarray(xi), ph[i])
    w = np.ones(len(X))
    w[3] = 0.0                                                         # a free slot gives 0
    for j in (0, len(X) // 2, len(X) - 1):
        out = np.full(len(X), np.nan)
        kernel_row_phased(kinds, params, cols, X, ph, w, 0, len(X), np.ascontiguousarray(X[j]), ph[j], out)
        ref = kernel(X, X[j:j + 1])[:, 0] * w
        np.testing.assert_allclose(out, ref, rtol=1e-11, atol=1e-300)
        assert out[j] == 1.0 or w[j] == 0.0


# -- the product kernel x = (t, θ) in the tracker ----------------------------------------------------------


@pytest.mark.parametrize("theta0", [0.0, 2.5e6])
def test_spindle_kernel_is_exact_gp_without_forgetting(theta0):
    X, y = _spindle(250, seed=2, theta0=theta0)
    X = X[::3]                                                         # 111 Hz: a well conditioned K_D
    y = y[::3]
    tr = KRLST(spindle_kernel(), gamma=100.0, forgetting=1.0, budget=len(y) + 5, jitter=1e-6)
    res = tr.learn_many(X, y)
    assert tr.size == len(y) and not res["reduced"].any()
    mean, var = batch_gp(spindle_kernel(), X, y, 1 / 100.0, 1e-6)
    np.testing.assert_allclose(res["mean"][1:], mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(res["sigma_y2"][1:], var, rtol=0, atol=1e-8)


def test_spindle_kernel_tracks_like_the_numpy_reference():
    X, y = _spindle(700, seed=3)
    kw = {"gamma": 5.85, "forgetting": 0.996, "budget": 60, "jitter": 1e-6}
    res = KRLST(spindle_kernel(), refine=True, **kw).learn_many(X, y)
    ref = NumpyKRLST(spindle_kernel(), **kw)
    pm = np.array([ref.learn_one(xi, yi) for xi, yi in zip(X, y)])
    assert np.linalg.norm(res["mean"] - pm) <= 1e-3 * np.linalg.norm(pm)
    assert np.sqrt(np.mean((res["mean"][300:] - y[300:]) ** 2)) < 0.3 * np.std(y)   # it tracks


# -- lag table: off-grid inputs fall back to the direct evaluation -------------------------------------------


@njit
def _row(st, x, out):
    st = core.unowned(st)
    kernel_phases(st.kinds, st.params, st.cols, x, st.xph)
    return core._kernel_row(st, x, st.xph, st.ist[core.I_HW], out)


def test_lag_table_falls_back_off_the_grid():
    t, y = _stream(600, seed=5)
    t = t.copy()
    t[::7] += 0.37 * TS                                                # every 7th sample off the grid
    kernel = LocallyPeriodic(1.2, 0.495, 1 / 55)
    tr = KRLST(kernel, gamma=5.85, forgetting=0.996, budget=50, jitter=1e-6, grid_step=TS, refine=True)
    tr.learn_many(t, y)
    st = tr.core_state(t[:1])
    slots = st.order[:tr.size]
    off = np.abs(st.X[slots, 0] / TS - np.round(st.X[slots, 0] / TS)) > 0.1
    assert 0 < off.sum() < tr.size                                     # both kinds in the dictionary
    for x in (600 * TS, 600.37 * TS):                                  # on and off the grid
        kt = np.full(st.Q.shape[0], np.nan)
        ktt = _row(st, np.array([x]), kt)
        assert ktt == 1.0 + 1e-6
        np.testing.assert_allclose(kt[slots], kernel(st.X[slots], np.array([[x]]))[:, 0], rtol=1e-12)
        free = np.setdiff1d(np.arange(len(kt)), slots)
        assert not kt[free].any()
        # the nearest table entry would be far off for the off-grid pairs: the fallback was used
        lag = np.abs(x - st.X[slots, 0]) / TS
        mis = np.abs(lag - np.round(lag)) > 0.1
        assert mis.any()
        nearest = st.tab[np.round(lag[mis]).astype(int)]
        assert np.max(np.abs(nearest - kt[slots][mis])) > 1e-3


@pytest.mark.parametrize("kernel, gamma", [(ZeroMeanLocallyPeriodic(0.1, 5.0, 1 / 55), 500.0),
                                           (LocallyPeriodic(0.1, 0.5, 1 / 55), 5.85)])
def test_lag_table_ends_with_a_zero_tail_where_the_envelope_is_below_the_floor(kernel, gamma):
    """A short σ1 (what REML often picks): the table ends with the zero-tail sentinel; every larger lag is
    below the floor of kernel values, dictionary entries that old get exactly 0 without evaluation, and
    neither the table nor a row holds a value below the floor (no subnormal arithmetic)."""
    tr = KRLST(kernel, gamma=gamma, forgetting=0.998, budget=100, jitter=1e-6, grid_step=TS, refine=True)
    t, y = _stream(6000, seed=4)
    tr.learn_many(t, y)
    st = tr.core_state(t[:1])
    tab = st.tab
    assert tab[-1] == 0.0 and len(tab) < KRLST.LAG_TABLE_MAX
    assert np.all((tab == 0.0) | (np.abs(tab) >= KERNEL_FLOOR))
    beyond = (len(tab) - 1 + np.arange(0, 20000, 7)) * TS
    assert np.all(np.abs(kernel.lag(beyond)) < KERNEL_FLOOR)
    slots = st.order[:tr.size]
    x = t[-1] + TS
    old = (x - st.X[slots, 0]) / TS > len(tab) - 1
    assert old.any() and not old.all()                                  # both kinds in the dictionary
    kt = np.full(st.Q.shape[0], np.nan)
    _row(st, np.array([x]), kt)
    ref = kernel(st.X[slots], np.array([[x]]))[:, 0]
    ref[np.abs(ref) < KERNEL_FLOOR] = 0.0
    np.testing.assert_allclose(kt[slots], ref, rtol=1e-9, atol=1e-12)   # (numpy's formula vs the compiled one)
    assert not np.any(kt[slots][old]) and not np.any((kt != 0.0) & (np.abs(kt) < KERNEL_FLOOR))


# -- Δ = c·D: the forgetting is a scalar, folded back before it underflows -------------------------------


def test_lazy_forgetting_scale_is_folded_and_exact():
    # λ = 0.6: c = λ^k falls below 1e-100 after ~450 steps and is folded into D; no pruning, so the
    # core and kafbox's recursion (NumPy) run the same algorithm and differ by rounding only
    t, y = _stream(1800, seed=6)
    t, y = t[::3], y[::3]
    kw = {"gamma": 5.85, "forgetting": 0.6, "budget": 650, "jitter": 1e-6}
    tr = KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), **kw)
    scales, means = [], []
    for lo in range(0, len(y), 50):
        means.append(tr.learn_many(t[lo:lo + 50], y[lo:lo + 50])["mean"])
        scales.append(tr.core_state(t[:1]).fst[core.F_DSC])
    assert min(scales) >= 1e-100 and any(b > a for a, b in itertools.pairwise(scales))   # folded on the way
    ref = NumpyKRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), **kw)
    pm = np.array([ref.learn_one(ti, yi) for ti, yi in zip(t, y)])
    assert tr.size == len(ref.mu) == len(y)
    np.testing.assert_allclose(np.concatenate(means), pm, rtol=0, atol=1e-7 * np.abs(pm).max())
    np.testing.assert_allclose(tr.Sigma, ref.Sigma, rtol=0, atol=1e-7 * np.abs(ref.Sigma).max())
    np.testing.assert_allclose(tr.mu, ref.mu, rtol=0, atol=1e-7 * np.abs(ref.mu).max())


# -- named slots -------------------------------------------------------------------------------------------


def test_named_slots_are_distinct_and_dense():
    for names, size in ((("I_N", "I_HW", "I_M", "I_STEPS", "I_QPEND", "I_SPEND", "I_REFRESH", "I_ARMED",
                          "I_REFINE"), core.N_IST),
                        (("O_MEAN", "O_SY2", "O_SF2", "O_G2", "O_REMOVED", "O_REDUCED", "O_FILT", "O_FILTVAR",
                          "O_S02", "O_SIZE"), core.N_OUT),
                        (("A_MEAN", "A_SF2", "A_SY2", "A_G2"), core.N_ARM),
                        (("P_P", "P_A", "P_G", "P_KT", "P_Q", "P_H", "P_RES"), core.N_P)):
        assert sorted(getattr(core, n) for n in names) == list(range(size))
    fst = [v for k, v in vars(core).items() if k.startswith("F_")]
    assert sorted(fst) == list(range(core.N_FST))
    assert (core.T_NEXT, core.T_S02, core.T_SIZE, core.T_LEARNED, core.N_TRACK) == (10, 14, 15, 16, 17)


# -- a state read from outside is checked before the compiled code indexes with it ----------------------


def _snapshot():
    t, y = _stream(300, seed=8)
    tr = KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), gamma=5.85, forgetting=0.996, budget=20, jitter=1e-6, refine=True)
    tr.learn_many(t[:-1], y[:-1])
    tr.predict_next(t[-1])
    return tr.snapshot(), tr


def _free_slot(snap):
    n = int(snap["ist"][core.I_N])
    return int(snap["order"][n])


@pytest.mark.parametrize("corrupt, message", [
    (lambda s: s["ist"].__setitem__(core.I_N, 10**9), "dictionary size"),
    (lambda s: s["ist"].__setitem__(core.I_HW, 10**6), "high-water mark"),
    (lambda s: s["ist"].__setitem__(core.I_QPEND, 7), "pending Q update"),
    (lambda s: s["order"].__setitem__(0, s["order"][1]), "permutation"),
    (lambda s: s["Q"].__setitem__((5, 2), 1.0), "below the diagonal"),
    (lambda s: s["K"].__setitem__((0, _free_slot(s)) if _free_slot(s) > 0 else (_free_slot(s), 1), 0.5),
     "free slots"),
    (lambda s: s["occ"].__setitem__(_free_slot(s), 1.0), "'occ'"),
    (lambda s: s["D"].__setitem__((0, 3), np.nan), "non-finite"),
    (lambda s: s["fst"].__setitem__(core.F_DSC, 0.0), "scale"),
    (lambda s: s["fst"].__setitem__(core.F_SY2, -1.0), "armed predictive variance"),
    (lambda s: s["fst"].__setitem__(core.F_LAM, 0.5), "hyperparameters"),
    (lambda s: s["Ph"].__setitem__((0, 0), 3.0), "'Ph'"),
])
def test_restore_refuses_an_inconsistent_state(corrupt, message):
    snap, _tr = _snapshot()
    KRLST.restore(snap)                                               # the intact one is fine
    bad = {k: v.copy() for k, v in snap.items()}
    corrupt(bad)
    with pytest.raises(ValueError, match=message):
        KRLST.restore(bad)


@njit
def _split_from_buffers(fbuf, ibuf, ys, xs, out):
    st = core.state_of(fbuf, ibuf)
    for j in range(ys.shape[0]):
        core.update(st, ys[j], out)
        core.arm(st, xs[j], out)


def test_core_buffers_drive_the_same_tracker():
    # a compiled loop given the two base buffers works on the tracker's own state
    t, y = _stream(400, seed=9)
    kw = {"gamma": 5.85, "forgetting": 0.996, "budget": 30, "jitter": 1e-6, "grid_step": TS, "refine": True}
    a = KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), **kw)
    b = KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), **kw)
    for tr in (a, b):
        tr.learn_many(t[:200], y[:200])
        tr.predict_next(t[200])
    _split_from_buffers(*a.core_buffers(t[:1]), y[200:399], t[201:400].reshape(-1, 1), np.zeros(core.N_OUT))
    for j in range(200, 399):
        b.update(y[j])
        b.predict_next(t[j + 1])
    sa, sb = a.snapshot(), b.snapshot()
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key], err_msg=key)


def test_core_survives_non_finite_inputs_that_bypass_the_checks():
    # defence in depth: the classes refuse non-finite x; the compiled core itself must not index
    # out of its arrays with one (it gives NaN or 0 kernel values, never a crash)
    t, y = _stream(200, seed=10)
    tr = KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), gamma=5.85, forgetting=0.996, budget=30, jitter=1e-6,
               grid_step=TS, refine=True)
    tr.learn_many(t, y)
    st = tr.core_state(t[:1])
    for bad in (np.nan, np.inf, -np.inf, 1e300):
        kt = np.zeros(st.Q.shape[0])
        _row(st, np.array([bad]), kt)
        assert np.all(np.isnan(kt) | (kt == 0.0)), bad
