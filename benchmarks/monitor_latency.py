"""Benchmark of the live monitor (``feedmon run``) and the offline path (``feedmon run --from``): the
table of its targets — measure, the figure before the performance work, the target, this run
(docs/benchmarks.md).

Usage::

    python benchmarks/monitor_latency.py            # everything (~4 min)
    python benchmarks/monitor_latency.py --quick    # shorter runs (~2 min)
    python benchmarks/monitor_latency.py --only latency|rate|offline|multi

Measures, with a real ``feedmon run`` subprocess on loopback (MCAP and Rerun sinks on unless
``--sinks``):

1. **Latency at 333 Hz**, one sample per message: publisher send → estimate arrival at a
   subscriber, both in this process (same clock), p50/p99/max in µs; the monitor's own figure
   (sample received → estimate published) and its stages (queue, decode, estimate, encode,
   publish; then the sinks) from its status; the CPU the monitor process and its sink processes
   spent per message (from ``/proc``, a figure the machine's load does not inflate as much).
2. **Highest sustained input rate**: one axis streamed in blocks (``--block``, default 50
   samples) at increasing rates; a rate is *sustained* when the monitor estimates every sample,
   nothing is dropped (input queue, estimator, sinks) and the last estimate arrives within
   ``--lag`` s (default 0.5) of the last send. Estimates the monitor published but this process
   did not receive (Zenoh drops them, congestion control DROP, when the subscriber falls behind —
   here on the same two cores) are shown, not counted as monitor drops.
3. **Offline throughput** of ``run --from`` on a 120 s simulated trial (one axis; median of
   ``--repeat`` runs after a warm-up), with the share of the KRLS-T loop (measured in this process
   on the same blocks) and the CPU per sample.
4. **Several axes offline**: a 2-axis trial, one process (``jobs=1``) against one worker process
   per axis (``jobs=2``), alternating, medians, same-run ratio; the two files must be identical
   byte for byte.

The machine's load average is printed with the table: on a shared machine quote medians and
same-run ratios.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feedio import schema as S  # noqa: E402
from feedio import transport as T  # noqa: E402
from feedio.transport import query_status  # noqa: E402

PREFIX = "feedmon-bench"

#: the figures before the performance work (2026-11-22, quiet machine, one run) and the targets
BEFORE = {
    "monitor": "p50 319 µs, p99 1.1 ms, max 4.6 ms",
    "e2e": "p50 735 µs, p99 3.3 ms, max 13 ms",
    "rate": "20,000 samples/s",
    "offline": "50,000–75,000 samples/s",
    "multi": "—",
}
TARGET = {
    "monitor": "p50 ≤ 100 µs, p99 ≤ 400 µs",
    "e2e": "p99 ≤ 1.5 ms",
    "rate": "≥ 50,000 samples/s",
    "offline": "≥ 150,000 samples/s",
    "multi": "≥ 1.7× one process, identical",
}


class _Seq(msgspec.Struct):
    seq: int
    t: list[float]


_dec = msgspec.json.Decoder(_Seq)


def _trial(path: Path, duration: float, seed: int = 7, scenario: str = "shaker-constant") -> None:
    from replay.scenarios import load_scenario
    from replay.simulator import simulate, write_trial

    write_trial(simulate(load_scenario(scenario, duration=duration), seed=seed), path)


def _model(trial: Path, path: Path, budget: int | None = None, axis: str | None = None) -> None:
    """The trial's true β and the thesis tracker (budget 100 unless given; a smaller dictionary is what the
    monitor around the tracker sustains) in a model file, for axis ``axis`` (default the trial's)."""
    from dataclasses import replace

    from feedio.mcapio import read_trial
    from monitor.model_file import save_model, truth_model

    model = truth_model(read_trial(trial).meta, budget=100 if budget is None else budget)
    save_model(replace(model, axis=model.axis if axis is None else axis), path)


class Stream:
    """The trial's samples as an endless stream (seq and t continue across passes)."""

    def __init__(self, trial: Path):
        from feedio.mcapio import read_trial

        tr = read_trial(trial)
        self.machine, self.axis = tr.machine, tr.axis
        self.t, self.v_ref, self.v_meas = tr.t, tr.v_ref, tr.v_meas
        self.n = len(tr.t)
        self.Ts = tr.Ts
        self.next = 0  # global seq

    def block(self, n: int) -> S.SampleBlock:
        seq = self.next
        idx = np.arange(seq, seq + n)
        k, i = np.divmod(idx, self.n)
        t = self.t[i] + k * (self.n * self.Ts)
        self.next += n
        return S.SampleBlock(machine=self.machine, axis=self.axis, seq=seq, t=t.tolist(),
                             v_ref=self.v_ref[i].tolist(), v_meas=self.v_meas[i].tolist())


def _cpu_seconds(pid: int) -> float:
    """CPU time (user + system, s) of a process from /proc (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


class Monitor:
    def __init__(self, work: Path, extra: list[str]):
        self.endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
        cmd = [sys.executable, "-m", "feedmon.cli", "run", "--model", str(work / "z.model.toml"), "--fresh",
               "--state-dir", str(work / "state"), "--listen", self.endpoint, "--prefix", PREFIX, *extra]
        self.proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, cwd=ROOT)
        self.lines: list[str] = []
        ready = threading.Event()

        def read():
            for line in self.proc.stderr:
                self.lines.append(line)
                if "listening on" in line:
                    ready.set()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(60) or self.proc.poll() is not None:
            raise SystemExit("monitor did not start:\n" + "".join(self.lines))

    def cpu(self) -> tuple[float, float]:
        """(CPU s of the monitor process, of its child processes: the sinks)."""
        return _cpu_seconds(self.proc.pid), sum(_cpu_seconds(c) for c in _children(self.proc.pid))

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(120)


class Harness:
    """Publisher of samples + subscriber of estimates in this process."""

    def __init__(self, session, stream: Stream):
        self.stream = stream
        self.pub = session.declare_publisher(T.samples_key(PREFIX, stream.machine, stream.axis),
                                             congestion_control=zenoh.CongestionControl.BLOCK,
                                             encoding=zenoh.Encoding.APPLICATION_JSON, express=True)
        self.sent: dict[int, float] = {}  # first seq of a block -> send time
        self.arrived: dict[int, float] = {}
        self.last_arrival = 0.0
        self.est_samples = 0
        self.sub = session.declare_subscriber(T.disturbance_key(PREFIX, stream.machine, stream.axis), self._on_est)
        T.wait_for_matching(self.pub, 10.0)

    def _on_est(self, sample) -> None:
        now = time.perf_counter()
        e = _dec.decode(sample.payload.to_bytes())
        self.arrived[e.seq] = now
        self.est_samples += len(e.t)
        self.last_arrival = now

    def run(self, rate: float, seconds: float, block: int) -> tuple[int, float]:
        """Send ``block``-sample messages at ``rate`` samples/s for ``seconds``; returns (samples, end time)."""
        n_msgs = max(1, int(round(rate * seconds / block)))
        period = block / rate
        payloads = []
        for _ in range(n_msgs):
            b = self.stream.block(block)
            payloads.append((b.seq, S.encode(b)))
        start = time.perf_counter() + 0.05
        for j, (seq, data) in enumerate(payloads):
            due = start + j * period
            wait = due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)  # no spinning: on a 2-core machine it would steal the monitor's CPU
            self.sent[seq] = time.perf_counter()
            self.pub.put(data)
        return n_msgs * block, time.perf_counter()

    def latencies_us(self, seqs) -> np.ndarray:
        return np.array([(self.arrived[s] - self.sent[s]) * 1e6 for s in seqs if s in self.arrived])

    def close(self):
        self.sub.undeclare()
        self.pub.undeclare()


def _pct(x: np.ndarray) -> tuple[float, float, float]:
    if x.size == 0:
        return (float("nan"),) * 3
    p50, p99 = np.percentile(x, [50, 99])
    return float(p50), float(p99), float(x.max())


def _sink_args(work: Path, sinks: str, tag: str) -> list[str]:
    out = []
    if sinks in ("both", "mcap"):
        out += ["--mcap", str(work / f"{tag}.mcap")]
    if sinks in ("both", "rerun"):
        out += ["--rrd", str(work / f"{tag}.rrd")]
    return out


def _axis_status(session, stream: Stream) -> dict:
    st = query_status(session, PREFIX, 5.0)[0]
    return st, st["axes"][f"{stream.machine}/{stream.axis}"]


def bench_latency(work: Path, stream: Stream, seconds: float, sinks: str = "both") -> dict:
    mon = Monitor(work, _sink_args(work, sinks, "lat"))
    try:
        with T.open_session(connect=mon.endpoint) as session:
            h = Harness(session, stream)
            h.run(333.0, 2.0, 1)  # warm-up: JIT, dictionary fills (not measured)
            time.sleep(0.5)
            first = stream.next
            cpu0 = mon.cpu()
            n, _ = h.run(333.0, seconds, 1)
            cpu1 = mon.cpu()
            deadline = time.perf_counter() + 5
            while h.est_samples < first + n and time.perf_counter() < deadline:
                time.sleep(0.05)
            lat = h.latencies_us(range(first, first + n))
            status, a = _axis_status(session, stream)
            h.close()
    finally:
        rc = mon.stop()
    return {"e2e": _pct(lat), "lost": n - lat.size, "n": n, "status": a["latency_us"], "drops": a["dropped_total"],
            "stages": a.get("stages_us", {}), "sinks": {s["name"]: s["dropped"] for s in status["sinks"]}, "rc": rc,
            "cpu": ((cpu1[0] - cpu0[0]) / n * 1e6, (cpu1[1] - cpu0[1]) / n * 1e6)}


def bench_rate(work: Path, stream: Stream, rates: list[float], seconds: float, block: int, lag: float,
               sinks: str = "both") -> list[dict]:
    mon = Monitor(work, _sink_args(work, sinks, "rate"))
    rows = []
    try:
        with T.open_session(connect=mon.endpoint) as session:
            h = Harness(session, stream)
            h.run(5000.0, 1.0, block)  # warm-up
            time.sleep(1.0)
            for rate in rates:
                _, a0 = _axis_status(session, stream)
                target_mon = a0["estimates_out"]
                target = h.est_samples
                n, t_end = h.run(rate, seconds, block)
                target += n
                target_mon += n
                deadline = t_end + 30.0
                a = a0
                while time.perf_counter() < deadline:  # until the monitor has estimated everything
                    st, a = _axis_status(session, stream)
                    if a["estimates_out"] >= target_mon and h.est_samples >= target - n // 20:
                        break
                    time.sleep(0.05)
                time.sleep(0.2)  # estimates still on their way
                st, a = _axis_status(session, stream)
                lost = target - h.est_samples  # published, not received here (Zenoh DROP towards a slow subscriber)
                done = a["estimates_out"] >= target_mon
                caught_up = h.last_arrival - t_end if done else float("inf")
                drops = a["dropped_total"] + st["input"]["queue_full"] + sum(s["dropped"] for s in st["sinks"])
                ok = drops == 0 and done and caught_up <= lag
                rows.append({"rate": rate, "lag": caught_up, "drops": drops, "ok": ok, "lost": lost,
                             "sinks": {s["name"]: s["dropped"] for s in st["sinks"]}})
                if not ok:
                    break
                time.sleep(0.3)
            h.close()
    finally:
        mon.stop()
    return rows


def _tracker_us(trial: Path, model: Path) -> float:
    """µs per sample spent in the compiled loop (``track_block``) on the trial's blocks, in this process."""
    from kernels import online
    from monitor.axes import load_axes
    from monitor.offline import _merged_blocks
    from monitor.pipeline import Pipeline

    axes = load_axes([model])
    names = [f"{m}/{a}" for m, a in axes]
    blocks = [b for _, _, kind, _, b in _merged_blocks(str(trial), names) if kind == "samples"]
    pipe = Pipeline(axes)
    orig, spent = online.track_block, [0.0]

    def timed(*a):
        t0 = time.perf_counter()
        try:
            return orig(*a)
        finally:
            spent[0] += time.perf_counter() - t0

    online.track_block = timed
    try:
        for b in blocks:
            pipe.estimate(b)
    finally:
        online.track_block = orig
    return spent[0] / sum(len(b.t) for b in blocks) * 1e6


def bench_offline(work: Path, repeat: int) -> dict:
    from monitor.axes import load_axes
    from monitor.offline import run_offline

    trial, model = work / "long.mcap", work / "z.model.toml"
    run_offline(trial, work / "warm.mcap", load_axes([model]))  # warm-up
    rates, cpus = [], []
    for _ in range(repeat):
        c0 = time.process_time()
        res = run_offline(trial, work / "offline.mcap", load_axes([model]))
        cpus.append((time.process_time() - c0) / res.samples * 1e6)
        rates.append(res.rate)
    return {"samples": res.samples, "rate": statistics.median(rates), "rates": rates,
            "cpu_us": statistics.median(cpus), "tracker_us": _tracker_us(trial, model)}


def bench_multi(work: Path, repeat: int) -> dict:
    """A 2-axis trial through ``run --from`` with one process and with one worker per axis (command
    line, as a user runs it), alternating."""
    cmd = [sys.executable, "-m", "feedmon.cli", "run", "--from", str(work / "two.mcap"), "--model",
           str(work / "x.model.toml"), "--model", str(work / "y.model.toml")]
    import re

    times: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(repeat):
        for jobs in (1, 2):
            out = work / f"two-{jobs}.mcap"
            r = subprocess.run(cmd + ["-o", str(out), "--jobs", str(jobs)], capture_output=True, text=True, cwd=ROOT)
            if r.returncode != 0:
                raise SystemExit(r.stderr)
            # the run's own time (what run_offline measures: reading, estimating, writing; not the imports)
            times[jobs].append(float(re.search(r" in ([0-9.]+) s ", r.stdout).group(1)))
    same = (work / "two-1.mcap").read_bytes() == (work / "two-2.mcap").read_bytes()
    one, two = statistics.median(times[1]), statistics.median(times[2])
    return {"one": one, "two": two, "ratio": one / two, "same": same, "times": times}


def _two_axis_trial(work: Path, duration: float) -> None:
    """Axes X and Y (two simulated shaker trials, seeds 1 and 2) in one file, interleaved in time."""
    from feedio.mcapio import TrialWriter, iter_blocks, read_trial

    for name, seed in (("x", 1), ("y", 2)):
        _trial(work / f"{name}.mcap", duration, seed)
        _model(work / f"{name}.mcap", work / f"{name}.model.toml", axis=name.upper())
    metas, items = [], []
    for name in ("x", "y"):
        tr = read_trial(work / f"{name}.mcap")
        metas.append(msgspec.structs.replace(tr.meta, axis=name.upper()))
        for kind, b in iter_blocks(work / f"{name}.mcap", kinds=("samples", "truth")):
            items.append((float(b.t[-1]), name.upper(), kind, b))
    items.sort(key=lambda x: (x[0], x[1]))
    with TrialWriter(work / "two.mcap", metas, start="2024-05-01T08:00:00Z") as w:
        for _, axis, kind, b in items:
            if kind == "samples":
                w.write_samples(msgspec.structs.replace(b, axis=axis))
            else:
                w.write_truth(b, metas[0].machine, axis)


def _loadavg() -> str:
    return Path("/proc/loadavg").read_text().split()[0]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="shorter runs")
    p.add_argument("--seconds", type=float, default=None, help="latency run length at 333 Hz (default 10, quick 4)")
    p.add_argument("--block", type=int, default=50, help="samples per message in the rate test (default 50)")
    p.add_argument("--lag", type=float, default=0.5, help="max catch-up lag for a sustained rate (s)")
    p.add_argument("--sinks", choices=("both", "mcap", "rerun", "none"), default="both",
                   help="sinks of the monitor under test (default both)")
    p.add_argument("--only", choices=("latency", "rate", "offline", "multi"), default=None, help="run one part only")
    p.add_argument("--budget", type=int, default=None, help="dictionary budget M of the model (default 100)")
    p.add_argument("--repeat", type=int, default=None, help="offline runs per figure (default 3, quick 2)")
    p.add_argument("--rates", default="10000,20000,30000,40000,50000,60000,80000",
                   help="input rates to try (samples/s)")
    args = p.parse_args(argv)
    seconds = args.seconds or (4.0 if args.quick else 10.0)
    repeat = args.repeat or (2 if args.quick else 3)
    rates = [float(r) for r in args.rates.split(",")]
    part = args.only
    lat = rows = off = multi = None
    load0 = _loadavg()
    with tempfile.TemporaryDirectory(prefix="feedmon-bench-") as d:
        work = Path(d)
        _trial(work / "trial.mcap", 30.0 if args.quick else 60.0)
        _model(work / "trial.mcap", work / "z.model.toml", args.budget)
        stream = Stream(work / "trial.mcap")
        if part in (None, "latency"):
            print(f"[bench] latency at 333 Hz for {seconds:g} s (sinks: {args.sinks}) ...", file=sys.stderr)
            lat = bench_latency(work, stream, seconds, args.sinks)
        if part in (None, "rate"):
            print(f"[bench] sustained rate, blocks of {args.block} (sinks: {args.sinks}) ...", file=sys.stderr)
            rows = bench_rate(work, stream, rates, 2.0 if args.quick else 3.0, args.block, args.lag, args.sinks)
        if part in (None, "offline"):
            print("[bench] offline --from, one axis ...", file=sys.stderr)
            _trial(work / "long.mcap", 60.0 if args.quick else 120.0, seed=3)
            off = bench_offline(work, repeat)
        if part in (None, "multi"):
            print("[bench] offline --from, two axes, one process vs one worker per axis ...", file=sys.stderr)
            _two_axis_trial(work, 60.0 if args.quick else 120.0)
            multi = bench_multi(work, repeat)

    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"feedmon monitor benchmark (loopback, sinks: {args.sinks}"
                    f"{'' if args.budget is None else f', budget M = {args.budget}'}; load average {load0} → "
                    f"{_loadavg()} on {os.cpu_count()} cores)")
    for c in ("measure", "before", "target", "this run"):
        t.add_column(c)
    if lat is not None:
        s = lat["status"]
        t.add_row("inside the monitor, receive → published", BEFORE["monitor"], TARGET["monitor"],
                  f"p50 {s['p50']:,.0f} µs, p99 {s['p99']:,.0f} µs, max {s['max']:,.0f} µs")
        t.add_row("  by stage, p50 / p99 µs", "", "",
                  ", ".join(f"{k} {v['p50']:,.0f}/{v['p99']:,.0f}" for k, v in lat["stages"].items()))
        p50, p99, mx = lat["e2e"]
        t.add_row("send → estimate received, 333 Hz, 1 sample/message, sinks on", BEFORE["e2e"], TARGET["e2e"],
                  f"p50 {p50:,.0f} µs, p99 {p99:,.0f} µs, max {mx:,.0f} µs ({lat['n']} samples, {lat['lost']} "
                  "without an estimate seen)")
        t.add_row("  CPU per message: monitor process / sink processes", "", "",
                  f"{lat['cpu'][0]:,.0f} µs / {lat['cpu'][1]:,.0f} µs; drops: estimator {lat['drops']}, "
                  f"sinks {lat['sinks']}")
    if rows is not None:
        best = max((r["rate"] for r in rows if r["ok"]), default=0.0)
        t.add_row(f"highest sustained input, blocks of {args.block}, no drops", BEFORE["rate"], TARGET["rate"],
                  f"{best:,.0f} samples/s")
        for r in rows:
            lost = f", {r['lost']} estimates lost in transit" if r["lost"] else ""
            t.add_row(f"  input {r['rate']:,.0f} samples/s", "", "",
                      f"{'kept up' if r['ok'] else 'FELL BEHIND'}: lag {r['lag']:.3f} s, drops {r['drops']} "
                      f"{r['sinks']}{lost}")
    if off is not None:
        t.add_row("offline run --from, one axis", BEFORE["offline"], TARGET["offline"],
                  f"{off['rate']:,.0f} samples/s (median of {len(off['rates'])}: "
                  f"{', '.join(f'{r:,.0f}' for r in off['rates'])}; {off['samples']:,} samples)")
        t.add_row("  CPU per sample: all threads / the KRLS-T loop", "", "",
                  f"{off['cpu_us']:.1f} µs / {off['tracker_us']:.1f} µs")
    if multi is not None:
        t.add_row("offline, 2-axis trial: one process / one worker per axis", BEFORE["multi"], TARGET["multi"],
                  f"{multi['ratio']:.2f}× ({multi['one']:.2f} s / {multi['two']:.2f} s, medians of "
                  f"{len(multi['times'][1])}); files {'identical' if multi['same'] else 'DIFFERENT'}")
    Console(width=180).print(t)
    return 0


if __name__ == "__main__":
    sys.exit(main())
