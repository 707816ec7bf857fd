"""Benchmark: estimate latency of a live ``feedmon run`` with and without a status-query flood.

Usage::

    python benchmarks/status_flood.py                # 3 rounds of 8 s quiet + 8 s flooded
    python benchmarks/status_flood.py --quick        # 1 round of 4 s + 4 s
    python benchmarks/status_flood.py --unprotected  # the same without status cache and rate limit

One monitor subprocess (MCAP and Rerun sinks off), one sample per message at 333 Hz, the latency
publisher send → estimate arrival measured in this process (same clock). Alternating periods:
*quiet* (only the samples) and *flood* (a second session asks ``<prefix>/monitor/status`` at
``--qps`` queries per second, default 1000, without reading the replies). The monitor serves
status from a cache rebuilt at most every ``status_refresh_s`` and rate-limits replies
(``status_rate``), so the flood should cost the estimator little. Prints p50/p99/max per period,
the monitor process' CPU use per period (/proc; steadier than latency on a busy machine) and the
median p99 ratio flood/quiet; on a shared machine compare ratios within one run.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from monitor_latency import PREFIX, Harness, Monitor, Stream, _model, _pct, _trial

from feedio import transport as T
from feedio.transport import query_status


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (Linux /proc), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Flood:
    """``qps`` status queries per second from its own session, replies ignored."""

    def __init__(self, endpoint: str, qps: float):
        self.session = T.open_session(connect=endpoint)
        self.qps = qps
        self.on = threading.Event()
        self.stop = threading.Event()
        self.sent = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        key = T.status_key(PREFIX)
        batch = 10
        while not self.stop.is_set():
            if not self.on.wait(0.1):
                continue
            t0 = time.perf_counter()
            for _ in range(batch):
                self.session.get(key, timeout=0.5)
            self.sent += batch
            left = batch / self.qps - (time.perf_counter() - t0)
            if left > 0:
                time.sleep(left)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.session.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--qps", type=float, default=1000.0, help="status queries per second in the flood")
    p.add_argument("--seconds", type=float, default=None, help="length of each period (default 8, quick 4)")
    p.add_argument("--rounds", type=int, default=None, help="quiet+flood rounds (default 3, quick 1)")
    p.add_argument("--unprotected", action="store_true",
                   help="for comparison: status rebuilt for every query, no rate limit "
                        "(--limit status_refresh_s=0 --limit status_rate=100000 --limit status_burst=1000000)")
    args = p.parse_args(argv)
    seconds = args.seconds or (4.0 if args.quick else 8.0)
    rounds = args.rounds or (1 if args.quick else 3)
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        _trial(work / "trial.mcap", 20.0)
        _model(work / "trial.mcap", work / "z.model.toml")
        stream = Stream(work / "trial.mcap")
        extra = ["--limit", "status_refresh_s=0", "--limit", "status_rate=100000", "--limit",
                 "status_burst=1000000"] if args.unprotected else []
        mon = Monitor(work, extra)
        rows = []
        try:
            with T.open_session(connect=mon.endpoint) as session:
                h = Harness(session, stream)
                flood = Flood(mon.endpoint, args.qps)
                h.run(333.0, 2.0, 1)  # warm-up: JIT, dictionary fills
                time.sleep(0.5)
                for r in range(rounds):
                    for kind in ("quiet", "flood"):
                        if kind == "flood":
                            flood.on.set()
                            time.sleep(0.5)  # the flood is under way
                        first = stream.next
                        sent0 = flood.sent
                        cpu0, wall0 = cpu_seconds(mon.proc.pid), time.perf_counter()
                        n, t_end = h.run(333.0, seconds, 1)
                        cpu = (cpu_seconds(mon.proc.pid) - cpu0) / (time.perf_counter() - wall0) * 100.0
                        qps = (flood.sent - sent0) / max(1e-9, seconds)
                        flood.on.clear()
                        deadline = time.perf_counter() + 5
                        while h.est_samples < first + n and time.perf_counter() < deadline:
                            time.sleep(0.05)
                        lat = h.latencies_us(range(first, first + n))
                        rows.append((r, kind, *_pct(lat), n - lat.size, qps, cpu))
                        time.sleep(0.5)
                flood.close()
                time.sleep(1.0)  # tokens come back: our own query is answered
                st = query_status(session, PREFIX, 10.0)[0]
                h.close()
        finally:
            mon.stop()
    print(f"{'round':>5} {'period':>6} {'p50 µs':>9} {'p99 µs':>9} {'max µs':>9} {'lost':>5} {'queries/s':>10} "
          f"{'monitor CPU %':>14}")
    for r, kind, p50, p99, mx, lost, qps, cpu in rows:
        print(f"{r:>5} {kind:>6} {p50:>9.0f} {p99:>9.0f} {mx:>9.0f} {lost:>5} {qps:>10.0f} {cpu:>14.1f}")
    quiet = np.array([x[3] for x in rows if x[1] == "quiet"])
    loud = np.array([x[3] for x in rows if x[1] == "flood"])
    print(f"median p99: quiet {np.median(quiet):.0f} µs, flood {np.median(loud):.0f} µs, "
          f"ratio {np.median(loud) / np.median(quiet):.2f}")
    cq = np.median([x[7] for x in rows if x[1] == "quiet"])
    cf = np.median([x[7] for x in rows if x[1] == "flood"])
    print(f"median monitor CPU: quiet {cq:.1f} %, flood {cf:.1f} % (+{cf - cq:.1f} points for the flood)")
    print(f"status queries: {st['status']['served']} answered, {st['status']['refused']} refused (rate limit "
          f"{st['limits']['status_rate']:g}/s, burst {st['limits']['status_burst']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
