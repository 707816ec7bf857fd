"""How far the order-m likelihood of ``feedmon identify`` lies from the exact REML, on the reference trials.

Run: ``python benchmarks/identify_accuracy.py [--emps DIR] [--out DIR]``

For every kernel candidate identify evaluated (tuned at order ≤ 2048, evaluated at order ≤ 8192 with the
stop criterion of :mod:`kernels.levinson`), the same hyperparameters are evaluated again with the exact
Levinson REML (``max_order=None, tol=0``) on the same regression (gate, samples left out, spindle
stretches). Printed per candidate: the order used, the log-likelihood difference (order-m − exact), the
largest difference of a β entry in its exact standard errors, and the time of one exact evaluation.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TRIALS = [("milling-incdec", 40.0, 1), ("shaker-constant", 40.0, 1), ("milling-spindle-change", 40.0, 1),
          ("shaker-control", 40.0, 1)]


def _simulated(out: Path) -> list[Path]:
    paths = []
    for scenario, duration, seed in TRIALS:
        path = out / f"{scenario}-{duration:g}s-{seed}.mcap"
        if not path.exists():
            subprocess.run([sys.executable, "-m", "feedmon", "simulate", scenario, "-o", str(path), "--duration",
                            str(duration), "--seed", str(seed)], check=True, capture_output=True)
        paths.append(path)
    return paths


def _emps(folder: Path, out: Path) -> list[Path]:
    paths = []
    for mat, rate in (("DATA_EMPS.mat", 333), ("DATA_EMPS.mat", 1000), ("DATA_EMPS_PULSES.mat", 333)):
        path = out / f"{Path(mat).stem}-{rate}.mcap"
        if not path.exists():
            subprocess.run([sys.executable, "-m", "feedmon", "import", "emps", str(folder / mat), "-o", str(path),
                            "--rate", str(rate)], check=True, capture_output=True)
        paths.append(path)
    return paths


def _compare(path: Path) -> list[str]:
    from feedio.mcapio import read_trial
    from kernels.likelihood import reml_terms
    from monitor.identify import identify
    from monitor.identify.regression import build_regression

    trial = read_trial(path)
    ident = identify(trial)
    exo = trial.v_ref if ident.form == "velocity-loop" else trial.u
    reg = build_regression(ident.form, trial.v_meas, exo, ident.Ts, omega=None, coulomb=None,
                           spindle_rpm=trial.spindle_rpm, notes=[], delay=ident.delay)
    gate = reg.process.active if reg.nuisance else None
    rows = []
    for cand in ident.candidates:
        if cand.method != "pl_lssvm":
            continue
        start = time.perf_counter()
        exact = reml_terms(reg.Z_id, reg.y, cand.kernel_object, cand.gamma, ident.Ts, names=reg.id_names,
                           phase=cand.phase, gate=gate, keep=reg.keep)
        seconds = time.perf_counter() - start
        se = np.sqrt(np.maximum(np.diag(exact.beta_cov), 1e-300))
        dbeta = float(np.max(np.abs(np.asarray(cand.theta) - exact.beta) / se))
        rows.append(f"{path.stem:28s} {cand.label[:44]:44s} {cand.order:6d} {cand.log_likelihood - exact.log_likelihood:+9.2f} "
                    f"{dbeta:8.3f} {seconds:7.2f}s  {'chosen' if cand is ident.chosen else ''}")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--emps", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"),
                    help="folder of DATA_EMPS.mat and DATA_EMPS_PULSES.mat (left out when absent)")
    ap.add_argument("--out", default="/tmp/feedmon-identify-accuracy", help="folder for the trial files")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    paths = _simulated(out)
    if (Path(args.emps) / "DATA_EMPS.mat").is_file():
        paths += _emps(Path(args.emps), out)
    print(f"{'trial':28s} {'candidate':44s} {'order':>6s} {'Δℓ':>9s} {'Δβ/se':>8s} {'exact':>8s}")
    for path in paths:
        for row in _compare(path):
            print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
