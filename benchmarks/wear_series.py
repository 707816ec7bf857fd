"""The wear alarm across parts (M7) on part series with known truth: at which part a tool-wear series alarms,
and how many false alarms a nominal series raises.

Usage::

    python benchmarks/wear_series.py                          # 20 s parts, seeds 1-5: 200 nominal parts, wear 1 %/part
    python benchmarks/wear_series.py --parts 200 --seeds 1 2 3 --duration 3

Each part of ``milling-part`` (material, spindle speed ±5 %, feed override ±5 %, spindle phase varied) is
simulated; its per-section statistics come from the true force (:func:`replay.parts.truth_sections`, the form
the monitor's :meth:`~monitor.process_monitor.AxisProcessMonitor.finish` gives) and go through the wear
monitor (:class:`monitor.process_monitor.wear.WearMonitor`, default settings) part by part, as
``feedmon run --wear-history`` does. Prints, per seed, the first part that alarms in the wear series, the
false alarms (parts with any ``wear`` alarm) in the nominal series and the part-to-part spread of the mean
force per section.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from monitor.process_monitor.settings import WearSettings  # noqa: E402
from monitor.process_monitor.wear import WearMonitor  # noqa: E402
from replay import parts as PT  # noqa: E402
from replay import scenarios as SC  # noqa: E402
from replay.simulator import simulate  # noqa: E402


def series(n_parts: int, seed: int, wear: float, duration: float | None, settings: WearSettings):
    """(index of the first part with a wear alarm or None, parts with an alarm, mean forces per section)."""
    sc = SC.load_scenario("milling-part")
    if duration is not None:
        sc["duration"] = duration
    mon = WearMonitor(settings)
    first, alarmed, forces = None, 0, {}
    for var in PT.part_variations(sc, n_parts, seed=seed, wear_per_part=wear):
        res = simulate(PT.part_scenario(sc, var), seed=var.seed)
        secs = PT.truth_sections(res)
        for s in secs:
            forces.setdefault(s["program_line"], []).append(s["mean_force_N"])
        alarms = mon.add_run("m", "x", secs, f"part-{var.index}", "", (0, 0.0))
        if alarms:
            alarmed += 1
            first = var.index if first is None else first
    return first, alarmed, forces


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", type=int, default=200, help="parts of the nominal series")
    ap.add_argument("--wear-parts", type=int, default=30, help="parts of the wear series")
    ap.add_argument("--wear", type=float, default=0.01, help="relative force increase per part")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--duration", type=float, default=None, help="part length in s (default: the scenario's 20 s)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        settings = WearSettings(history=str(Path(d) / "unused.json"))
        print(f"defaults: window {settings.window}, min_parts {settings.min_parts}, sensitivity {settings.sensitivity:g}, "
              f"min_rise {settings.min_rise:.0%}, statistic {settings.statistic}")
        t0 = time.perf_counter()
        total = 0
        for seed in args.seeds:
            first, _, _ = series(args.wear_parts, seed, args.wear, args.duration, settings)
            _, false, forces = series(args.parts, seed, 0.0, args.duration, settings)
            total += false
            spread = ", ".join(f"L{k} {np.std(v) / np.mean(v):.3f}" for k, v in sorted(forces.items())
                               if abs(np.mean(v)) >= settings.cut_min_N)
            print(f"seed {seed}: wear {args.wear:+.0%}/part alarms at part {first}; nominal {args.parts} parts: {false} "
                  f"part(s) with a wear alarm; spread of the mean force per part: {spread}", flush=True)
        print(f"{len(args.seeds)} seeds: {total} false alarms in {len(args.seeds) * args.parts} nominal parts "
              f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
