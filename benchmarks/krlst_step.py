"""KRLS-T step latency: the ``@njit`` core against the NumPy reference, measured in one run.

    python benchmarks/krlst_step.py [--steps 4000] [--numpy-steps 1500]

Streams after a warm-up that fills the dictionary, so every measured step predicts,
updates and prunes (or does a reduced update); γ = 5.85, λ = 0.996, ε_j = 1e-6 (thesis):

* time kernel: ``LocallyPeriodic(σ1=1.2, σ2=0.495, ψ=1/55 s)`` on ``t`` at 333 Hz (55 Hz +
  110 Hz + noise), lag table on;
* spindle kernel: ``Product(SquaredExponential(1.2, dims=0), Periodic(0.495, 2π/4, dims=1))``
  on ``x = (t, θ)``, θ the cumulative spindle angle (rad) at ~3000 rpm with a slow speed
  ripple, ψ one tooth of a 4-tooth cutter; the disturbance is periodic in θ.

Rows (µs per sample, median and p99 over the timed samples):

* ``split step``: the monitor's split step, core ``update(y_k)`` then ``arm(x_{k+1})``
  (``refine=True`` as the monitor runs it), two calls from Python per sample
  (``KRLST.update`` / ``KRLST.predict_next`` make the same two calls);
* ``… compiled``: the same two calls inside a compiled loop, as ``kernels.online.track_block``
  runs them (chunks of 20 samples timed, the loop given the two base buffers; p99 is of the
  chunk means);
* ``step M=400``: one ``learn`` (arm + update) from Python, lag table on, ``refine=False``
  (kafbox's recursion) and ``refine=True``.

The NumPy column is :class:`kernels.krlst_numpy.NumpyKRLST` (kafbox's algorithm in
whole-array NumPy) on the same stream and kernel, measured in the same run, and the
ratio is NumPy median / core median. The machine may be shared: compare medians and
same-run ratios, and run it more than once.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numba import njit

from kernels import KRLST, LocallyPeriodic, Periodic, Product, SquaredExponential
from kernels import _krlst_core as core
from kernels.krlst_numpy import NumpyKRLST

TS = 1 / 333
HYPER = {"gamma": 5.85, "forgetting": 0.996, "jitter": 1e-6}
CHUNK = 20


def time_stream(n, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    y = 1e-3 * (np.sin(2 * np.pi * 55 * t) + 0.5 * np.sin(2 * np.pi * 110 * t + 0.3))
    return t.reshape(-1, 1), y + 1e-4 * rng.standard_normal(n)


def spindle_stream(n, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    theta = 2 * np.pi * 50.0 * t + 0.2 * np.sin(2 * np.pi * 0.3 * t)        # 3000 rpm, slow ripple
    y = 1e-3 * (np.sin(4 * theta) + 0.3 * np.sin(8 * theta + 0.5))
    return np.column_stack([t, theta]), y + 1e-4 * rng.standard_normal(n)


def time_kernel():
    return LocallyPeriodic(sigma1=1.2, sigma2=0.495, period=1 / 55)


def spindle_kernel():
    return Product(SquaredExponential(1.2, dims=0), Periodic(0.495, 2 * np.pi / 4, dims=1))


def _warm(kernel, X, y, M, grid_step, refine):
    tr = KRLST(kernel, budget=M, grid_step=grid_step, refresh_every=0, refine=refine, **HYPER)
    warm = 4 * M + 1000
    tr.learn_many(X[:warm], y[:warm])
    return tr, warm


def time_split_calls(kernel, X, y, M, grid_step, steps):
    """µs per sample: ``update(y_k)`` then ``arm(x_{k+1})``, two Python calls."""
    tr, w = _warm(kernel, X, y, M, grid_step, True)
    tr.predict_next(X[w])
    fbuf, ibuf = tr.core_buffers(X[0])
    out = np.zeros(core.N_OUT)
    ns = np.empty(steps, dtype=np.int64)
    pc = time.perf_counter_ns
    update, arm = core.update_buffers, core.arm_buffers
    for i in range(steps):
        yk, xn = y[w + i], X[w + i + 1]
        a = pc()
        update(fbuf, ibuf, yk, out)
        arm(fbuf, ibuf, xn, out)
        ns[i] = pc() - a
    return ns / 1e3


@njit(nogil=True)
def _split_loop(fbuf, ibuf, xs, ys, out):
    st = core.state_of(fbuf, ibuf)
    for i in range(ys.shape[0]):
        core.update(st, ys[i], out)
        core.arm(st, xs[i], out)


def time_split_compiled(kernel, X, y, M, grid_step, steps):
    """µs per sample of the same two calls in a compiled loop (means of CHUNK samples)."""
    tr, w = _warm(kernel, X, y, M, grid_step, True)
    tr.predict_next(X[w])
    fbuf, ibuf = tr.core_buffers(X[0])
    out = np.zeros(core.N_OUT)
    _split_loop(fbuf, ibuf, X[w + 1:w + 1], y[w:w], out)
    means = []
    pc = time.perf_counter_ns
    for i in range(0, steps - CHUNK + 1, CHUNK):
        xs, ys = X[w + 1 + i:w + 1 + i + CHUNK], y[w + i:w + i + CHUNK]
        a = pc()
        _split_loop(fbuf, ibuf, xs, ys, out)
        means.append((pc() - a) / CHUNK)
    return np.array(means) / 1e3


def time_learn(kernel, X, y, M, grid_step, refine, steps):
    """µs per ``learn`` (arm + update) call from Python."""
    tr, w = _warm(kernel, X, y, M, grid_step, refine)
    fbuf, ibuf = tr.core_buffers(X[0])
    out = np.zeros(core.N_OUT)
    ns = np.empty(steps, dtype=np.int64)
    pc = time.perf_counter_ns
    learn = core.learn_buffers
    for i in range(steps):
        x, yi = X[w + i], y[w + i]
        a = pc()
        learn(fbuf, ibuf, x, yi, out)
        ns[i] = pc() - a
    return ns / 1e3


def time_numpy(kernel, X, y, M, steps):
    nk = NumpyKRLST(kernel, budget=M, **HYPER)
    warm = 4 * M + 1000
    for i in range(warm):
        nk.learn_one(X[i], y[i])
    ns = np.empty(steps, dtype=np.int64)
    pc = time.perf_counter_ns
    for i in range(steps):
        a = pc()
        nk.learn_one(X[warm + i], y[warm + i])
        ns[i] = pc() - a
    return ns / 1e3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=4000, help="timed samples per core row")
    ap.add_argument("--numpy-steps", type=int, default=1500, help="timed samples of the NumPy reference at M=100")
    args = ap.parse_args(argv)
    steps = args.steps
    n = 4 * 400 + 1000 + steps + 2
    Xt, yt = time_stream(n)
    Xs, ys = spindle_stream(n)
    tk, sk = time_kernel(), spindle_kernel()

    np_t100 = time_numpy(tk, Xt, yt, 100, args.numpy_steps)
    np_s100 = time_numpy(sk, Xs, ys, 100, args.numpy_steps)
    np_t400 = time_numpy(tk, Xt, yt, 400, max(args.numpy_steps // 5, 50))
    rows = [
        ("split step M=100, time kernel", time_split_calls(tk, Xt, yt, 100, TS, steps), np_t100, "≤ 6 µs, ≥ 60×", 6.0),
        ("  … compiled loop", time_split_compiled(tk, Xt, yt, 100, TS, steps), np_t100, "", None),
        ("split step M=100, spindle kernel", time_split_calls(sk, Xs, ys, 100, None, steps), np_s100,
         "≤ 6 µs, ≥ 60×", 6.0),
        ("  … compiled loop", time_split_compiled(sk, Xs, ys, 100, None, steps), np_s100, "", None),
        ("step M=400, time kernel", time_learn(tk, Xt, yt, 400, TS, False, steps // 4), np_t400, "≤ 60 µs", 60.0),
        ("  … refine=True", time_learn(tk, Xt, yt, 400, TS, True, steps // 4), np_t400, "", None),
    ]
    print("KRLS-T step, µs per sample (median / p99); NumPy reference measured in the same run")
    hdr = f"{'measure':<34} | {'median':>8} | {'p99':>8} | {'NumPy':>8} | {'ratio':>6} | {'target':<14} | met"
    print(hdr)
    print("-" * len(hdr))
    for name, a, ref, target, limit in rows:
        med, p99, nmed = np.median(a), np.percentile(a, 99), np.median(ref)
        ratio = nmed / med
        met = ""
        if limit is not None:
            met = "yes" if med <= limit and (limit > 10 or ratio >= 60) else "no"
        print(f"{name:<34} | {med:8.2f} | {p99:8.2f} | {nmed:8.1f} | {ratio:5.0f}× | {target:<14} | {met}")


if __name__ == "__main__":
    main()
