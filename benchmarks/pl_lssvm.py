"""Benchmark of PL-LSSVM (method §4): Toeplitz path vs the dense KKT solve, and the REML likelihood.

Run: ``python benchmarks/pl_lssvm.py [--sizes 2000 10000 20000 100000] [--dense-max 10000]``

Every case runs in its own subprocess on a simulated thesis case-1-like stream
(``replay/streams.py``: velocity loop, reversals, 55 Hz + 110 Hz shaker). Inside it, after the
data are built and Numba/FFT warmed up on a small case, we record

* ``time``: wall time of one call;
* ``peak RSS Δ``: ``ru_maxrss`` after the call minus before it — the growth of the process's
  peak resident memory caused by the call (includes C/C++ buffers such as FFT work arrays);
* ``tracemalloc``: peak of Python/NumPy allocations during a second call (NumPy arrays are traced,
  FFT-internal buffers are not).

The dense reference builds the (N+1+m)² KKT matrix of eq. 2.9 and calls ``numpy.linalg.solve``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
import tracemalloc

SIGMA1, SIGMA2, GAMMA, PSI = 0.59, 0.42, 50.3, 1 / 55


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _case(kind: str, n: int) -> dict:
    import numpy as np

    from kernels.covariance import LocallyPeriodic
    from kernels.likelihood import log_marginal_likelihood, tune
    from kernels.pl_lssvm import pl_lssvm
    from replay.streams import shaker_stream

    kernel = LocallyPeriodic(SIGMA1, SIGMA2, PSI)
    s = shaker_stream(n + 1, amplitude=10.0, seed=1)
    reg = s.regression()
    Z, y = reg.Z, reg.y
    warm = shaker_stream(3001, amplitude=10.0, seed=2).regression()

    if kind == "toeplitz":
        pl_lssvm(warm.Z, warm.y, kernel, GAMMA, Ts=s.Ts, toeplitz_dense_limit=0)

        def call():
            return pl_lssvm(Z, y, kernel, GAMMA, Ts=s.Ts)
    elif kind == "dense":
        def call():
            m = Z.shape[1]
            scale = np.sqrt(np.sum(Z * Z, axis=0))
            K = np.zeros((n + 1 + m, n + 1 + m))
            K[:n, :n] = kernel(s.x)
            K[np.arange(n), np.arange(n)] += 1.0 / GAMMA
            K[:n, n] = K[n, :n] = 1.0
            K[:n, n + 1:] = Z / scale
            K[n + 1:, :n] = (Z / scale).T
            sol = np.linalg.solve(K, np.concatenate([y, np.zeros(1 + m)]))
            return sol[n + 1:] / scale
    elif kind == "levinson":
        pl_lssvm(warm.Z, warm.y, kernel, GAMMA, Ts=s.Ts, solver="levinson")

        def call():
            return pl_lssvm(Z, y, kernel, GAMMA, Ts=s.Ts, solver="levinson")
    elif kind == "loglik":
        log_marginal_likelihood(warm.Z, warm.y, kernel, GAMMA, s.Ts)

        def call():
            return log_marginal_likelihood(Z, y, kernel, GAMMA, s.Ts)
    elif kind == "loglik-ar":
        log_marginal_likelihood(warm.Z, warm.y, kernel, GAMMA, s.Ts, max_order=2048, tol=0.5)

        def call():
            return log_marginal_likelihood(Z, y, kernel, GAMMA, s.Ts, max_order=2048, tol=0.5)
    elif kind == "tune":
        log_marginal_likelihood(warm.Z, warm.y, kernel, GAMMA, s.Ts)

        def call():
            return tune(Z, y, s.Ts, PSI)
    else:
        raise ValueError(kind)

    rss0 = _maxrss_mb()
    t0 = time.perf_counter()
    out = call()
    elapsed = time.perf_counter() - t0
    rss1 = _maxrss_mb()
    info = {"kind": kind, "n": n, "seconds": elapsed, "rss_delta_mb": rss1 - rss0}
    if kind in ("toeplitz", "levinson", "loglik", "loglik-ar"):
        tracemalloc.start()
        call()
        info["tracemalloc_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    if kind in ("toeplitz", "levinson"):
        info.update(solver=out.solver, iterations=out.iterations,
                    beta_err=float(np.max(np.abs(out.beta[:2] - s.beta[:2]) / s.beta[:2])))
    elif kind == "dense":
        info["beta"] = out.tolist()
    elif kind == "tune":
        info.update(sigma1=out.sigma1, sigma2=out.sigma2, gamma=out.gamma, evaluations=out.evaluations)
    return info


def _run(kind: str, n: int) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--case", kind, str(n)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"kind": kind, "n": n, "error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2000, 10000, 20000, 100000])
    ap.add_argument("--dense-max", type=int, default=10000, help="largest N for the dense KKT reference")
    ap.add_argument("--levinson-max", type=int, default=30000, help="largest N for the O(N²) Levinson path")
    ap.add_argument("--tune-n", type=int, default=10000)
    ap.add_argument("--emps", help="folder with DATA_EMPS*.mat: time 'feedmon identify' on them (default $FEEDMON_EMPS_DIR)")
    ap.add_argument("--case", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        print(json.dumps(_case(args.case[0], int(args.case[1]))))
        return 0

    print(f"PL-LSSVM, LocallyPeriodic(σ1={SIGMA1}, σ2={SIGMA2}, ψ=1/55), γ={GAMMA}; each case in a fresh subprocess")
    print("peak RSS Δ = ru_maxrss growth during the call; tracemalloc = peak traced NumPy/Python allocations\n")
    header = (f"{'N':>7} | {'solver':<20} {'iters':>5} {'time s':>8} {'RSS Δ MB':>9} {'trace MB':>9} "
              f"{'β1,2 err %':>10} | {'dense s':>8} {'dense MB':>9} {'speed-up':>9}")
    print(header)
    print("-" * len(header))
    for n, kind in [(n, k) for n in args.sizes for k in ("toeplitz", "levinson")]:
        if kind == "levinson" and n > args.levinson_max:
            continue
        t = _run(kind, n)
        d = _run("dense", n) if n <= args.dense_max and kind == "toeplitz" else None
        if "error" in t:
            print(f"{n:>7} | error: {t['error']}")
            continue
        line = (f"{n:>7} | {t['solver']:<20} {t['iterations']:>5} {t['seconds']:>8.3f} {t['rss_delta_mb']:>9.1f} "
                f"{t['tracemalloc_mb']:>9.1f} {100 * t['beta_err']:>10.4f} | ")
        if d is None:
            line += f"{'—':>8} {'—':>9} {'—':>9}"
        elif "error" in d:
            line += f"dense error: {d['error']}"
        else:
            line += f"{d['seconds']:>8.2f} {d['rss_delta_mb']:>9.0f} {d['seconds'] / t['seconds']:>8.0f}×"
        print(line, flush=True)

    n = args.tune_n
    print(f"\nREML likelihood and tuning at N = {n}")
    for kind, label in (("loglik", "log_marginal_likelihood, exact (Levinson whitening)"),
                        ("loglik-ar", "log_marginal_likelihood, order ≤ 2048 (kernels.levinson)"),
                        ("tune", "tune (5 starts + Nelder–Mead, exact REML, 30 evaluations)")):
        r = _run(kind, n)
        if "error" in r:
            print(f"  {label:<58} error: {r['error']}")
            continue
        extra = ""
        if kind == "tune":
            extra = (f"  → σ1={r['sigma1']:.3g} s, σ2={r['sigma2']:.3g}, γ={r['gamma']:.3g}, "
                     f"{r['evaluations']} evaluations")
        mem = f", RSS Δ {r['rss_delta_mb']:.1f} MB"
        print(f"  {label:<58} {r['seconds']:8.3f} s{mem}{extra}", flush=True)

    folder = args.emps or os.environ.get("FEEDMON_EMPS_DIR")
    if not folder:
        print("\n'feedmon identify' on EMPS: give --emps DIR or set FEEDMON_EMPS_DIR")
        return 0
    print("\n'feedmon identify' on the EMPS trials, no flags (import once, then one subprocess each)")
    for mat, rate in (("DATA_EMPS.mat", 333), ("DATA_EMPS.mat", 1000), ("DATA_EMPS_PULSES.mat", 333),
                      ("DATA_EMPS_PULSES.mat", 1000)):
        r = _emps(os.path.join(folder, mat), rate)
        print(f"  {mat:<22} {rate:>5} Hz  {r}", flush=True)
    return 0


def _emps(mat: str, rate: int) -> str:
    import tempfile

    if not os.path.isfile(mat):
        return f"not found: {mat}"
    with tempfile.TemporaryDirectory() as tmp:
        trial = os.path.join(tmp, "t.mcap")
        feedmon = [sys.executable, "-m", "feedmon"]
        subprocess.run([*feedmon, "import", "emps", mat, "-o", trial, "--rate", str(rate)], check=True,
                       capture_output=True)
        t0 = time.perf_counter()
        proc = subprocess.run([*feedmon, "identify", trial, "--json", "--dry-run"], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode not in (0, 1):
            return f"error: {proc.stderr.strip().splitlines()[-1]}"
        doc = json.loads(proc.stdout)
        kernels = sum(1 for c in doc["candidates"] if c["method"] == "pl_lssvm")
        return (f"{wall:6.1f} s wall (Numba compiled), chosen {doc['chosen']}, {kernels} kernel candidates, "
                f"ψ {doc['period']['value'] and round(doc['period']['value'], 5)} ({doc['period']['source']})")


if __name__ == "__main__":
    raise SystemExit(main())
