"""Monitor step per sample with and without online β and health (target: at most +30 %).

    python benchmarks/monitor_step.py                         # this tree: adaptation off / track / apply / default
    python benchmarks/monitor_step.py --baseline /work/main   # and a tree without online β and health

What is timed: :meth:`monitor.estimator.AxisEstimator.process` — the monitor's whole per-block
work below the transport (the compiled loop :func:`kernels.online.track_block` plus the Python
around it: columns in, the EstimateBlock out, health messages) — on a 60 s shaker trial at 333 Hz
(``feedmon simulate shaker-constant``), model = the trial's true β with the tracker defaults
(λ 0.998, M 100, thesis kernel), in blocks of 1 sample (one message per sample, the live latency
case) and of 100. Process CPU time (waiting for a loaded CPU is not counted; the disturbance search's
worker thread is), after a warm-up
pass; every configuration runs in its own subprocess, interleaved, ``--repeats`` times; the table
gives the median µs per sample and the median of the paired ratios against the baseline
(``--baseline``'s tree, else this tree with adaptation off — which still runs the health
statistics, so it is not "without").

A third column, *cold*, times single-sample blocks the way the live monitor meets them: each call
after a 3 ms pause (the period at 333 Hz) and after 8 MB of other memory traffic (what the sinks,
Zenoh's threads and the rest of the machine do meanwhile), median per call over 1000 calls. The
difference to the first column is the cost of cold caches, which the monitor's *estimate* stage
(``feedmon status``, ``monitor_latency.py``) pays on every message.

The machine may be shared: compare the same-run ratios, and run it more than once.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, {root!r})
from feedio import schema as S
from feedio.mcapio import read_trial
from monitor.model_file import AxisModel, TrackerConfig
from monitor.estimator import AxisEstimator
try:
    from monitor.online_settings import LocallyPeriodicKernel
    kern = LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=1 / 55)
except ImportError:  # a baseline tree from before the typed kernel union
    kern = {{"type": "locally_periodic", "sigma1": 1.2, "sigma2": 0.495, "period": 1 / 55}}
tr = read_trial({trial!r})
m = tr.meta
model = AxisModel(machine=m.machine, axis=m.axis, form=m.form, Ts=m.Ts, beta=list(m.truth.beta), omega=m.truth.omega,
                  coulomb=m.truth.coulomb, loop_gain=m.loop_gain,
                  tracker=TrackerConfig(kernel=kern, gamma=5.85, forgetting=0.998, budget=100))
mode = {mode!r}
if mode is not None:
    import msgspec
    from monitor.online_settings import OnlineSettings, Adaptation
    model.online = OnlineSettings(adaptation=Adaptation(mode=mode))
out = {{}}
for size in (1, 100):
    blocks = [S.SampleBlock(machine=m.machine, axis=m.axis, seq=i, t=tr.t[i:i + size].tolist(),
                            v_ref=tr.v_ref[i:i + size].tolist(), v_meas=tr.v_meas[i:i + size].tolist())
              for i in range(0, tr.t.size, size)]
    est = AxisEstimator(model)
    for b in blocks[: max(1, len(blocks) // 10)]:   # warm-up (JIT, caches)
        est.process(b)
    est = AxisEstimator(model)
    take = getattr(est, "take_health", lambda: None)
    clock = time.process_time
    t0 = clock()
    for b in blocks:
        est.process(b)
        take()
    out[size] = (clock() - t0) / tr.t.size * 1e6
    if size == 1:                                   # cold: a pause and other memory traffic before each call
        junk = np.zeros(2 ** 20)
        spent = []
        for b in blocks[-1000:]:
            time.sleep(0.003)
            junk += 1.0
            c0 = clock()
            est.process(b)
            take()
            spent.append(clock() - c0)
        out["cold"] = float(np.median(spent)) * 1e6
print(json.dumps(out))
"""


def _trial(path: Path) -> None:
    sys.path.insert(0, str(ROOT))
    from replay.scenarios import load_scenario
    from replay.simulator import simulate, write_trial

    write_trial(simulate(load_scenario("shaker-constant", duration=60.0), seed=7), path)


def _measure(tree: Path, trial: Path, mode: str | None, cache: str) -> dict[str, float]:
    code = _CHILD.format(root=str(tree), trial=str(trial), mode=mode)
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)  # never write a cache into another tree
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True,
                         cwd=str(tree))
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", default=None, metavar="TREE", help="a checkout without online β and health")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    configs = [("off", ROOT, "off"), ("track", ROOT, "track"), ("apply", ROOT, "apply"), ("default", ROOT, None)]
    if args.baseline:
        configs.insert(0, ("baseline", Path(args.baseline).resolve(), None))
    res: dict[str, list[dict[str, float]]] = {name: [] for name, _, _ in configs}
    with tempfile.TemporaryDirectory(prefix="feedmon-step-") as d:
        trial = Path(d) / "trial.mcap"
        _trial(trial)
        caches = {str(tree): tempfile.mkdtemp(dir=d) for _, tree, _ in configs}
        for r in range(args.repeats + 1):          # the first round fills the caches (not counted)
            for name, tree, mode in configs:
                got = _measure(tree, trial, mode, caches[str(tree)])
                if r:
                    res[name].append(got)
    ref = "baseline" if args.baseline else "off"
    print(f"AxisEstimator.process, µs per sample (process CPU, median of {args.repeats}); ratio = paired median "
          f"against '{ref}'")
    print(f"{'configuration':<12} | {'1 sample/block':>15} | {'ratio':>6} | {'100 samples/block':>18} | {'ratio':>6} | "
          f"{'1 sample, cold':>15} | {'ratio':>6}")
    print("-" * 97)
    for name, _, _ in configs:
        cells = []
        for size in ("1", "100", "cold"):
            a = np.array([x[size] for x in res[name] if size in x])
            b = np.array([x[size] for x in res[ref] if size in x])
            if a.size == 0 or a.size != b.size:     # a baseline tree without the cold column
                cells += [f"{'—':>15}", f"{'—':>6}"]
                continue
            cells += [f"{np.median(a):15.2f}", f"{np.median(a / b):6.3f}"]
        print(f"{name:<12} | {cells[0]} | {cells[1]} | {cells[2]:>18} | {cells[3]} | {cells[4]} | {cells[5]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
