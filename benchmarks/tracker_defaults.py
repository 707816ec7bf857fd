"""Tracker defaults from measurements: one-step disturbance prediction per setting.

    python benchmarks/tracker_defaults.py            # the table of the report (~5 min)

For each data set the KRLS-T tracker runs on the residual ``v(k) = v_m(k+1) − βᵀz(k)`` in the
monitor's order (train on the previous sample, then predict the next: ``KRLST.track_many``)
and ``force_next`` (row j, the prediction of f(j) made when sample j arrived, in N) is
compared with the true force of sample j — the documented alignment:

* ``pulses`` — real EMPS: β by least squares on DATA_EMPS.mat, run on DATA_EMPS_PULSES.mat
  (PD-law force as the command, the pulse force as truth), all samples; ``per`` = the worst
  RMS over the 1 s periods 2…24 (the same edges, different periods: not tuned to one period).
* simulated trials (``replay.simulator``, no recorder glitches, true β): milling-incdec,
  -inc, -dec (steady cutting: full engagement), shaker-constant, -sweep (shaker on, from 0.5 s
  after it switched on), ``*-fine`` (10 kHz plant, anti-alias decimation: β only nominal),
  ``*-noisy`` (10× measurement noise). RMS error in N over those samples.

Settings: ``thesis`` = Table 4.5 (σ1 1.2 s, σ2 0.495, γ 5.85), ``reml`` = σ1, σ2, γ tuned by
REML on the data set's own identification trial (:func:`kernels.likelihood.tune`, what
``feedmon identify --tune`` writes; for the pulses: tuned on DATA_EMPS.mat, not on the
pulses), a few untuned alternatives; λ per sample at 333 Hz; M = 100.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from kernels import KRLST, LocallyPeriodic
from kernels.feed_drive import regressors
from kernels.least_squares import least_squares
from kernels.likelihood import tune
from replay import scenarios as SC
from replay.importers import load_emps
from replay.simulator import simulate_scenario


def force_next(t, resid, b, hp, period, Ts) -> np.ndarray:
    trk = KRLST(LocallyPeriodic(hp[0], hp[1], period), gamma=hp[2], forgetting=hp[3], budget=100, jitter=1e-6,
                grid_step=Ts, refine=True)
    n = t.size
    ys = np.r_[np.nan, resid[: n - 1]]
    out = trk.track_many(t, ys, np.r_[False, np.ones(n - 1, bool)])
    return -out["next_mean"] / b


def datasets():
    folder = os.environ.get("FEEDMON_EMPS_DIR", "/work/shared/data/emps")
    from monitor.identify import dead_band

    emps = load_emps(f"{folder}/DATA_EMPS.mat")
    om = dead_band(emps.v_meas)
    reg = regressors("force-input", emps.v_meas, u=emps.u, omega=om)
    ls = least_squares(reg.Z, reg.y, names=reg.names)
    Ts = float(emps.meta.Ts)
    tu = tune(reg.Z, reg.y, Ts, 1.0, names=reg.names)
    pulses = load_emps(f"{folder}/DATA_EMPS_PULSES.mat")
    rp = regressors("force-input", pulses.v_meas, u=pulses.u, omega=om)
    sel = np.ones(pulses.t.size, bool)
    yield ("pulses", pulses.t, rp.y - rp.Z @ ls.beta, ls.beta[0], pulses.truth_force, sel, 1.0, float(pulses.meta.Ts),
           (tu.sigma1, tu.sigma2, tu.gamma))
    specs = [("milling-incdec", {}, False), ("milling-inc", {}, False), ("milling-dec", {}, False),
             ("shaker-constant", {}, False), ("shaker-sweep", {}, False),
             ("milling-incdec", {}, True), ("shaker-constant", {}, True),
             ("milling-incdec", {"v_meas_std": 2e-5}, False), ("shaker-constant", {"v_meas_std": 5e-5}, False)]
    for name, noise, fine in specs:
        cfg = {"noise": {"glitch_rate": 0.0, **noise}}
        res = simulate_scenario(name, seed=0, config=cfg, fine=fine)
        m = res.meta
        beta = np.asarray(m.truth.beta)
        reg = regressors(m.form, res.v_meas, v_ref=res.v_ref, omega=m.truth.omega, coulomb=m.truth.coulomb)
        sc = m.truth.scenario
        milling = name.startswith("milling")
        period = 0.02 if milling else 1 / 55
        if milling:
            sel = SC.engagement(sc, res.t) >= 1.0
        else:
            d = sc["disturbance"]
            sel = (res.t >= d["start"] * sc["duration"] + 0.5) & (res.t < d["stop"] * sc["duration"])
        tu = tune(reg.Z, reg.y, m.Ts, period, names=reg.names)
        label = name + ("-fine" if fine else "") + ("-noisy" if noise else "")
        yield (label, res.t, reg.y - reg.Z @ beta, beta[0] / m.loop_gain, res.force, sel, period, m.Ts,
               (tu.sigma1, tu.sigma2, tu.gamma))


SETTINGS = [
    ("thesis", None, 0.996), ("thesis", None, 0.998),
    ("reml", None, 0.996), ("reml", None, 0.998), ("reml", None, 0.999),
    ("untuned γ 1000", (1.2, 0.495, 1000.0), 0.996), ("untuned γ 1000", (1.2, 0.495, 1000.0), 0.998),
    ("untuned γ 300", (3.0, 0.25, 300.0), 0.998),
]


def main() -> int:
    t0 = time.perf_counter()
    data = list(datasets())
    print(f"data sets and REML: {time.perf_counter() - t0:.0f} s")
    for label, *_rest, hp in data:
        print(f"  REML {label:22s} σ1 {hp[0]:.3g} s, σ2 {hp[1]:.3g}, γ {hp[2]:.4g}")
    head = f"{'setting':16s} {'λ':>6s} | {'pulses RMS/r [worst period]':>30s} | " + " | ".join(f"{d[0][:14]:>14s}" for d in data[1:])
    print(head)
    print("-" * len(head))
    for name, fixed, lam in SETTINGS:
        cells = []
        for label, t, resid, b, force, sel, period, Ts, reml in data:
            hp = (1.2, 0.495, 5.85) if name == "thesis" else (reml if name == "reml" else fixed)
            fn = force_next(t, resid, b, (*hp, lam), period, Ts)
            err = fn - force
            if label == "pulses":
                r = float(np.corrcoef(fn, force)[0, 1])
                per = max(math.sqrt(np.mean(err[(t >= k) & (t < k + 1)] ** 2)) for k in range(2, 24))
                cells.append(f"{math.sqrt(np.mean(err ** 2)):6.2f} N {r:.4f} [{per:5.1f}]")
            else:
                cells.append(f"{math.sqrt(np.mean(err[sel] ** 2)):12.2f} N")
        print(f"{name:16s} {lam:6.4f} | {cells[0]:>30s} | " + " | ".join(f"{c:>14s}" for c in cells[1:]), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
