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
"""

from __future__ import annotations

import argparse
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


def time_core(M, t, y, warm, steps, grid_step, fn=None):
    tr = KRLST(kernel(), budget=M, grid_step=grid_step, **HYPER)
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
    tr = KRLST(kernel(), budget=M, grid_step=grid_step, **HYPER)
    tr.learn_many(t[:warm], y[:warm])
    a = time.perf_counter()
    res = tr.learn_many(t[warm:warm + steps], y[warm:warm + steps])
    return (time.perf_counter() - a) / steps * 1e6, float(np.mean(res["reduced"]))


def time_learn_one(M, t, y, warm, steps):
    tr = KRLST(kernel(), budget=M, grid_step=TS, **HYPER)
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
    hdr = (f"{'M':>4} | {'core':>15} | {'core+table':>15} | {'learn_many/step':>15} | "
           f"{'numpy':>15} | {'numpy/core':>10} | {'numpy/table':>11} | {'learn_one':>15} | {'reduced':>7}")
    print(hdr)
    print("-" * len(hdr))
    dispatch = None
    for M in args.budgets:
        warm = 4 * M + 1000
        c = time_core(M, t, y, warm, steps, None)
        ct = time_core(M, t, y, warm, steps, TS)
        if dispatch is None:
            dispatch = time_core(M, t, y, warm, steps, TS, fn=_empty)
        lm, red = time_learn_many(M, t, y, warm, steps, TS)
        nsteps = min(steps, args.numpy_steps if M <= 200 else args.numpy_steps // 2)
        npy = time_numpy(M, t, y, warm, nsteps)
        lo = time_learn_one(M, t, y, warm, min(steps, 10000))

        def mp(a):
            return f"{np.median(a):7.2f} /{np.percentile(a, 99):7.2f}"

        print(f"{M:>4} | {mp(c)} | {mp(ct)} | {lm:15.2f} | {mp(npy)} | "
              f"{np.median(npy) / np.median(c):10.1f} | {np.median(npy) / np.median(ct):11.1f} | "
              f"{mp(lo)} | {red:7.2f}")
    print(f"dispatch of an empty @njit call with the same arguments: median {np.median(dispatch):.2f} µs, "
          f"p99 {np.percentile(dispatch, 99):.2f} µs (included in 'core' and 'core+table')")


if __name__ == "__main__":
    main()
