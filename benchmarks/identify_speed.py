"""Benchmark of ``feedmon identify`` on records of any length: wall time and peak memory, medians.

Run: ``python benchmarks/identify_speed.py [--repeats 3] [--cases milling-40s shaker-10min milling-10min
shaker-1h milling-1h] [--out DIR]``

Each case simulates its trial once (``feedmon simulate``, cached in ``--out``), then runs the command a user
runs — ``feedmon identify TRIAL --dry-run --json``: reading, every candidate tuned, the fits, the checks
and the self-check — in a fresh subprocess per repeat, and records

* ``wall``: its wall time (median over the repeats; min and max beside it);
* ``cpu``: user + system time of the subprocess (two threads tune at once);
* ``peak RSS``: the subprocess's ``ru_maxrss``;
* the chosen model and its errors against the simulated truth (inertia, damping, Coulomb friction).

The targets (issue: 40 s milling ≤ 15 s, 10 min ≤ 30 s, 1 h ≤ 3 min and ≤ 2 GB) are printed beside the
figures; the machine's other load is not controlled (state it next to the figures).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: case → (scenario, duration s, seed, target s)
CASES = {
    "milling-40s": ("milling-incdec", 40.0, 1, 15.0),
    "shaker-10min": ("shaker-constant", 600.0, 2, 30.0),
    "milling-10min": ("milling-incdec", 600.0, 2, 30.0),
    "shaker-1h": ("shaker-constant", 3600.0, 3, 180.0),
    "milling-1h": ("milling-incdec", 3600.0, 3, 180.0),
}
MEMORY_TARGET_MB = 2048.0


def _trial(out: Path, scenario: str, duration: float, seed: int) -> Path:
    path = out / f"{scenario}-{duration:g}s-{seed}.mcap"
    if not path.exists():
        subprocess.run([sys.executable, "-m", "feedmon", "simulate", scenario, "-o", str(path), "--duration",
                        str(duration), "--seed", str(seed)], check=True, capture_output=True)
    return path


def _measure(path: Path) -> dict:
    """One subprocess, its own resource usage (``wait4``)."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "feedmon", "identify", str(path), "--dry-run", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    chunks = []
    while True:
        block = proc.stdout.read(1 << 16)
        if not block:
            break
        chunks.append(block)
    err = proc.stderr.read().decode(errors="replace")
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    text = b"".join(chunks).decode()
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "rss_mb": usage.ru_maxrss / 1024.0,
            "doc": json.loads(text) if text.strip() else {}, "code": os.waitstatus_to_exitcode(status),
            "err": err[-500:]}


def _errors(doc: dict) -> str:
    errs = (doc.get("truth") or {}).get("model_physical_error") or {}
    return ", ".join(f"{k} {100 * v:+.2f} %" for k, v in errs.items() if k in ("inertia", "damping", "coulomb"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--out", default="/tmp/feedmon-identify-bench", help="folder for the simulated trials")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{'case':15s} {'samples':>9s} {'wall median (min–max)':>24s} {'target':>7s} {'cpu':>7s} "
          f"{'peak RSS':>9s}  chosen; errors against the truth")
    failed = False
    for name in args.cases:
        scenario, duration, seed, target = CASES[name]
        path = _trial(out, scenario, duration, seed)
        runs = [_measure(path) for _ in range(args.repeats)]
        walls = [r["wall"] for r in runs]
        last = runs[-1]
        doc = last["doc"]
        chosen = doc.get("chosen") or f"refused ({doc.get('error')})"
        model = doc.get("pl_lssvm") if doc.get("chosen") == "pl_lssvm" else doc.get("ls")
        label = chosen if not model else f"{chosen} {model.get('kernel') or ''}".strip()
        med = statistics.median(walls)
        rss = max(r["rss_mb"] for r in runs)
        ok = med <= target and rss <= MEMORY_TARGET_MB and last["code"] == 0
        failed |= not ok
        n = int(round(duration * 333.0))
        print(f"{name:15s} {n:9d} {med:8.1f} s ({min(walls):.1f}–{max(walls):.1f}) {target:6.0f}s "
              f"{statistics.median(r['cpu'] for r in runs):6.1f}s {rss:7.0f} MB  {label}; {_errors(doc)}"
              + ("" if ok else "  ← above target" if last["code"] == 0 else f"  ← exit {last['code']}: {last['err']}"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
