"""Zero false alarms over a series of good parts: the process monitors on ``feedmon simulate milling-part
--parts N`` (material, spindle speed ±5 %, feed override ±5 %, spindle phase varied per part; 20 s each).

Usage::

    python benchmarks/process_series.py                  # 200 parts (≈ 1.1 h of cutting; ~25 min here)
    python benchmarks/process_series.py --parts 50 --reference 10
    python benchmarks/process_series.py --parts 21 --reference 0 --wear 0.01 --wear-history   # the wear alarm

The axis is identified as a user does it, once, on part 0 with ``feedmon identify`` and no options
(``--truth-model``: the simulator's true β instead); every part is then run through
``feedmon run --from … --monitors`` (impulse, tooth) — parts 1 … N−1 out of sample; with ``--reference K`` a
reference is learned from the first K parts (``feedmon reference learn``) and the rest are also judged
against it (envelope); with ``--wear-history`` every run appends to one wear history (``--wear REL``: a series whose
force grows by REL per part). Prints one line per part as it goes (alarms, if any) and a table at the end:
parts, hours of cutting, alarms per monitor.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feedio.mcapio import iter_blocks, read_trial  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--reference", type=int, default=10, metavar="K", help="learn a reference from K parts (0: none)")
    ap.add_argument("--work", default=None, help="keep the files here (default: a temporary folder)")
    ap.add_argument("--truth-model", action="store_true", help="monitor with the true β, not a model identified on part 0")
    ap.add_argument("--wear", type=float, default=None, metavar="REL", help="tool wear: force +REL per part")
    ap.add_argument("--wear-history", action="store_true", help="judge the wear trend across the parts")
    args = ap.parse_args()
    from monitor.model_file import save_model, truth_model

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        if len(list(work.glob("part-*.mcap"))) != args.parts:  # a kept --work folder with the series: reused
            subprocess.run([sys.executable, "-m", "feedmon.cli", "simulate", "milling-part", "--parts", str(args.parts),
                            "-o", str(work), "--seed", str(args.seed), "--created", "2024-05-01T08:00:00Z",
                            *(["--wear", str(args.wear)] if args.wear is not None else [])],
                           check=True, cwd=ROOT, capture_output=True)
        parts = sorted(work.glob("part-*.mcap"))
        if args.truth_model:
            save_model(truth_model(read_trial(parts[0]).meta, period=1 / 50, budget=100), work / "m.model.toml")
        else:
            subprocess.run([sys.executable, "-m", "feedmon.cli", "identify", str(parts[0]), "-o",
                            str(work / "m.model.toml")], check=True, cwd=ROOT, capture_output=True)
        print(f"simulated {len(parts)} parts in {time.perf_counter() - t0:.0f} s", flush=True)
        counts: Counter[str] = Counter()
        seconds = 0.0
        ref = None
        for i, part in enumerate(parts):
            out = work / f"out-{i:04d}.mcap"
            extra = ["--reference", str(ref)] if ref is not None else []
            extra += ["--wear-history", str(work / "wear.json")] if args.wear_history else []
            subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--from", str(part), "--model",
                            str(work / "m.model.toml"), "-o", str(out), "--monitors", *extra],
                           check=True, cwd=ROOT, capture_output=True)
            alarms = [a for _, a in iter_blocks(out, None, ("alarm",))]
            seconds += float(read_trial(part).t[-1])
            counts.update(f"{a.monitor}:{a.kind}" for a in alarms)
            print(f"part {i:4d}: {len(alarms)} alarm(s) "
                  + "; ".join(f"{a.kind} t={a.t:.3f} {a.value:.3g}/{a.limit:.3g}" for a in alarms), flush=True)
            if args.reference and i + 1 == args.reference:
                ref = work / "part.ref.json"
                subprocess.run([sys.executable, "-m", "feedmon.cli", "reference", "learn",
                                *(str(work / f"out-{j:04d}.mcap") for j in range(args.reference)), "-o", str(ref)],
                               check=True, cwd=ROOT, capture_output=True)
        print("| parts | cutting h | with reference | alarms | by monitor |")
        print("|---:|---:|---:|---:|---|")
        print(f"| {len(parts)} | {seconds / 3600:.2f} | {max(0, len(parts) - args.reference) if args.reference else 0} "
              f"| {sum(counts.values())} | {dict(counts) or '—'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
