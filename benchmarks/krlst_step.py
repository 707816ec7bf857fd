"""KRLS-T step latency: the @njit core against a plain NumPy implementation.

    python benchmarks/krlst_step.py [--steps 20000] [--budgets 50 100 200 400]

Streams a 333 Hz locally periodic signal (55 Hz + 110 Hz + noise) through a
tracker with the thesis hyperparameters (σ1 = 1.2, σ2 = 0.495, ψ = 1/55 s,
γ = 5.85, λ = 0.996) after a warm-up that fills the dictionary, so every
measured step predicts, updates and prunes (or does a reduced update).
Each call is timed with ``time.perf_counter_ns``:

* ``core``: one call of ``kernels._krlst_core.learn`` from Python (includes the
  numba dispatch, reported separately as ``dispatch``: an empty @njit call with
  the same arguments);
* ``core+table``: the same with the uniform-grid lag table (``grid_step``);
* ``learn_many``: wall time of the njit loop over the same steps / steps;
* ``numpy``: :class:`benchmarks.krlst_numpy.NumpyKRLST` (fewer steps at large M);
* ``learn_one``: the public Python API, table on.
* ``refine``: ``core+table`` with ``refine=True`` (iterative refinement of the Q update).

Second table, the monitor's per-sample work (train on the previous sample, predict
the next one), table on:

* ``learn+pred``: ``learn_one(x_k, y_k)`` then ``predict_one(x_{k+1}, forget=True)``
  (the old way: the predict passes run twice);
* ``update+next``: ``update(y_k)`` then ``predict_next(x_{k+1})`` (split step);
* ``core l+p`` / ``core u+a``: the same pairs as direct core calls;
* ``track_many``: wall time of ``KRLST.track_many`` over blocks of 32 samples / sample.

Third: ``refresh_inverse`` (one re-inversion of Q) and the k_t row cost per element.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from krlst_numpy import NumpyKRLST  # noqa: E402

from kernels import KRLST, LocallyPeriodic  # noqa: E402
from kernels import _krlst_core as core  # noqa: E402
from kernels.covariance import kernel_row_at, kernel_value  # noqa: E402

TS = 1 / 333
HYPER = dict(gamma=5.85, forgetting=0.996, jitter=1e-6)


def stream(n, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    y = 1e-3 * (np.sin(2 * np.pi * 55 * t) + 0.5 * np.sin(2 * np.pi * 110 * t + 0.3))
    return t, y + 1e-4 * rng.standard_normal(n)


def kernel():
    return LocallyPeriodic(sigma1=1.2, sigma2=0.495, period=1 / 55)


@njit
def _empty(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, y, out):
    out[0] = y


def time_core(M, t, y, warm, steps, grid_step, fn=None, **kw):
    tr = KRLST(kernel(), budget=M, grid_step=grid_step, refresh_every=0, **kw, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    kinds, params, cols = tr._spec
    X, Q, S, K, mu, order, ist, fst, P = tr._state
    W, tab, out = tr._W, tr._tab, tr._out
    fn = core.learn if fn is None else fn
    xs = t[warm:warm + steps].reshape(-1, 1).copy()
    ys = y[warm:warm + steps].copy()
    ns = np.empty(steps, dtype=np.int64)
    pc = time.perf_counter_ns
    for i in range(steps):
        x = xs[i]
        yi = ys[i]
        a = pc()
        fn(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, yi, out)
        ns[i] = pc() - a
    return ns / 1e3


def time_learn_many(M, t, y, warm, steps, grid_step):
    tr = KRLST(kernel(), budget=M, grid_step=grid_step, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    a = time.perf_counter()
    res = tr.learn_many(t[warm:warm + steps], y[warm:warm + steps])
    return (time.perf_counter() - a) / steps * 1e6, float(np.mean(res["reduced"]))


def time_learn_one(M, t, y, warm, steps):
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    ns = np.empty(steps, dtype=np.int64)
    pc = time.perf_counter_ns
    for i in range(steps):
        ti, yi = float(t[warm + i]), float(y[warm + i])
        a = pc()
        tr.learn_one(ti, yi)
        ns[i] = pc() - a
    return ns / 1e3


def time_numpy(M, t, y, warm, steps):
    nk = NumpyKRLST(kernel(), budget=M, **HYPER)
    for i in range(warm):
        nk.learn_one(t[i], y[i])
    ns = np.empty(steps, dtype=np.int64)
    pc = time.perf_counter_ns
    for i in range(steps):
        a = pc()
        nk.learn_one(t[warm + i], y[warm + i])
        ns[i] = pc() - a
    return ns / 1e3


def time_monitor_pairs(M, t, y, warm, steps):
    """µs per monitored sample: old (learn_one + predict_one) vs split (update + predict_next)."""
    pc = time.perf_counter_ns
    res = {}
    # -- public API
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    ns = np.empty(steps, dtype=np.int64)
    for i in range(steps):
        tk, yk, tn = float(t[warm + i]), float(y[warm + i]), float(t[warm + i + 1])
        a = pc()
        tr.learn_one(tk, yk)
        tr.predict_one(tn, noise=False, forget=True)
        ns[i] = pc() - a
    res["learn+pred"] = ns / 1e3
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    tr.predict_next(float(t[warm]))
    ns = np.empty(steps, dtype=np.int64)
    for i in range(steps):
        yk, tn = float(y[warm + i]), float(t[warm + i + 1])
        a = pc()
        tr.update(yk)
        tr.predict_next(tn)
        ns[i] = pc() - a
    res["update+next"] = ns / 1e3
    # -- core calls
    xs = t[warm:warm + steps + 1].reshape(-1, 1).copy()
    ys = y[warm:warm + steps].copy()
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    kinds, params, cols = tr._spec
    X, Q, S, K, mu, order, ist, fst, P = tr._state
    W, tab, out = tr._W, tr._tab, tr._out
    ns = np.empty(steps, dtype=np.int64)
    for i in range(steps):
        x, xn, yi = xs[i], xs[i + 1], ys[i]
        a = pc()
        core.learn(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, yi, out)
        core.predict(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xn, True, out)
        ns[i] = pc() - a
    res["core l+p"] = ns / 1e3
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    X, Q, S, K, mu, order, ist, fst, P = tr._state
    W, tab, out = tr._W, tr._tab, tr._out
    core.arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xs[0], out)
    ns = np.empty(steps, dtype=np.int64)
    for i in range(steps):
        xn, yi = xs[i + 1], ys[i]
        a = pc()
        core.update(X, Q, S, K, mu, order, ist, fst, P, W, yi, out)
        core.arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xn, out)
        ns[i] = pc() - a
    res["core u+a"] = ns / 1e3
    # -- track_many, blocks of 32
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    tr.predict_next(float(t[warm]))
    xb = t[warm + 1:warm + 1 + steps]
    yb = y[warm:warm + steps]
    mask = np.ones(steps, dtype=bool)
    a = time.perf_counter()
    for lo in range(0, steps, 32):
        tr.track_many(xb[lo:lo + 32], yb[lo:lo + 32], mask[lo:lo + 32])
    res["track_many"] = (time.perf_counter() - a) / steps * 1e6
    return res


def time_refresh(M, t, y, warm, reps=20):
    tr = KRLST(kernel(), budget=M, grid_step=TS, refresh_every=0, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    X, Q, S, K, mu, order, ist, fst, P = tr._state
    Q0, ist0 = Q.copy(), ist.copy()
    ns = []
    for _ in range(reps):
        Q[:] = Q0
        ist[:] = ist0
        a = time.perf_counter_ns()
        core.refresh_inverse(Q, K, order, ist, tr._W)
        ns.append(time.perf_counter_ns() - a)
    return np.array(ns) / 1e3


@njit
def _row_loop(kinds, params, cols, X, idx, n, x, out, reps):
    for _ in range(reps):
        kernel_row_at(kinds, params, cols, X, idx, n, x, out)


@njit
def _inline_loop(kinds, params, cols, X, idx, n, x, out, reps):
    s1, s2, psi = params[0, 0], params[0, 1], params[0, 2]
    for _ in range(reps):
        for l in range(n):
            i = idx[l]
            d = X[i, 0] - x[0]
            s = math.sin(math.pi * d / psi)
            out[i] = math.exp(-(d * d) / (2.0 * s1 * s1) - (s * s) / (2.0 * s2 * s2))


@njit
def _value_loop(kinds, params, cols, X, idx, n, x, out, reps):
    for _ in range(reps):
        for l in range(n):
            i = idx[l]
            out[i] = kernel_value(kinds, params, cols, X[i], x)


def time_kernel_row(n=100, reps=20000):
    """ns per k_t element: kernel_row_at vs a hand-inlined LP formula vs per-pair kernel_value(X[i], x)."""
    kinds, params, cols = kernel().spec()
    X = (np.arange(n) * TS).reshape(-1, 1)
    x = np.array([n * TS + 1e-4])
    idx = np.random.default_rng(0).permutation(n).astype(np.int64)
    out = np.empty(n)
    res = {}
    for name, fn in (("kernel_row_at", _row_loop), ("inline", _inline_loop), ("kernel_value(X[i])", _value_loop)):
        fn(kinds, params, cols, X, idx, n, x, out, 1)
        best = np.inf
        for _ in range(5):
            a = time.perf_counter()
            fn(kinds, params, cols, X, idx, n, x, out, reps)
            best = min(best, (time.perf_counter() - a) / (reps * n) * 1e9)
        res[name] = best
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--numpy-steps", type=int, default=3000)
    ap.add_argument("--budgets", type=int, nargs="+", default=[50, 100, 200, 400])
    args = ap.parse_args(argv)

    steps = args.steps
    t, y = stream(4 * max(args.budgets) + 2000 + steps)
    print(f"KRLS-T step latency, µs (median / p99), {steps} timed steps after warm-up; "
          f"LP kernel, 333 Hz, γ={HYPER['gamma']}, λ={HYPER['forgetting']}")
    hdr = (f"{'M':>4} | {'core':>15} | {'core+table':>15} | {'refine':>15} | {'learn_many/step':>15} | "
           f"{'numpy':>15} | {'numpy/core':>10} | {'numpy/table':>11} | {'learn_one':>15} | {'reduced':>7}")
    print(hdr)
    print("-" * len(hdr))
    dispatch = None
    for M in args.budgets:
        warm = 4 * M + 1000
        c = time_core(M, t, y, warm, steps, None)
        ct = time_core(M, t, y, warm, steps, TS)
        cr = time_core(M, t, y, warm, steps, TS, refine=True)
        if dispatch is None:
            dispatch = time_core(M, t, y, warm, steps, TS, fn=_empty)
        lm, red = time_learn_many(M, t, y, warm, steps, TS)
        nsteps = min(steps, args.numpy_steps if M <= 200 else args.numpy_steps // 2)
        npy = time_numpy(M, t, y, warm, nsteps)
        lo = time_learn_one(M, t, y, warm, min(steps, 10000))

        def mp(a):
            return f"{np.median(a):7.2f} /{np.percentile(a, 99):7.2f}"

        print(f"{M:>4} | {mp(c)} | {mp(ct)} | {mp(cr)} | {lm:15.2f} | {mp(npy)} | "
              f"{np.median(npy) / np.median(c):10.1f} | {np.median(npy) / np.median(ct):11.1f} | "
              f"{mp(lo)} | {red:7.2f}")
    print(f"dispatch of an empty @njit call with the same arguments: median {np.median(dispatch):.2f} µs, "
          f"p99 {np.percentile(dispatch, 99):.2f} µs (included in 'core' and 'core+table')")

    def mp(a):
        return f"{np.median(a):7.2f} /{np.percentile(a, 99):7.2f}"

    print()
    print("Monitor step (train on sample k, predict k+1), µs per sample (median / p99), table on")
    hdr = (f"{'M':>4} | {'learn+pred':>15} | {'update+next':>15} | {'ratio':>5} | {'core l+p':>15} | "
           f"{'core u+a':>15} | {'ratio':>5} | {'track_many':>10}")
    print(hdr)
    print("-" * len(hdr))
    for M in args.budgets:
        warm = 4 * M + 1000
        r = time_monitor_pairs(M, t, y, warm, min(steps, 10000))
        print(f"{M:>4} | {mp(r['learn+pred'])} | {mp(r['update+next'])} | "
              f"{np.median(r['learn+pred']) / np.median(r['update+next']):5.2f} | {mp(r['core l+p'])} | "
              f"{mp(r['core u+a'])} | {np.median(r['core l+p']) / np.median(r['core u+a']):5.2f} | "
              f"{r['track_many']:10.2f}")

    print()
    print("refresh_inverse (Q = K_D⁻¹ by Cholesky), µs: " + ", ".join(
        f"M={M}: {np.median(time_refresh(M, t, y, 4 * M + 1000)):.0f}" for M in args.budgets))
    kr = time_kernel_row()
    print("k_t row, ns per element (n = 100, LP kernel, no table): " + ", ".join(f"{k} {v:.1f}" for k, v in kr.items()))


if __name__ == "__main__":
    main()
