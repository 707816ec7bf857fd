"""Round-trip latency of the LinuxCNC bridge in HAL time: a sample enters the sampler → the way-back pin
``feedmon.X.sample`` shows the monitor's estimate for it (target: p99 ≤ 10 ms).

For each plant rate: the HAL plant of ``bridge/linuxcnc/hal`` with a simulated cutting force (streamer),
``feedmon run`` with the plant's true model, ``feedmon bridge linuxcnc`` (one sample per message, the
helper polling the FIFO every 0.5 ms), and ``halsampler -c 1`` logging the counter and the way-back pin
every servo cycle. The latency of sample k is the first cycle c whose logged pin shows k or later, minus
k, times Ts: the resolution is one servo period (the sampler reads the pin at the end of a cycle, so a
round trip within the same cycle counts 0). The first ``--warmup`` seconds of each run are left out.

The machine's noise: HAL runs in POSIX non-realtime threads here, on cores shared with other work; the
load average is printed with each run, and the spread between ``--repeat`` runs shows what it does.

Usage::

    python benchmarks/linuxcnc_latency.py                   # 1 kHz and 333 Hz, 3 runs of 20 s each
    python benchmarks/linuxcnc_latency.py --rates 1000 --repeat 1 --seconds 10

Needs LinuxCNC (apt-get install -y --no-install-recommends linuxcnc-uspace) and, as root, the HAL user
(useradd -m lcnc, or FEEDMON_HAL_USER).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from bridge.linuxcnc import launch as L
from feedio import transport as T
from feedmon.cli import main
from monitor.model_file import save_model, truth_model

PREFIX = "feedmon-bench-lcnc"
RATES = {1000: ("plant-1000.hal", "bridge-1000.toml", 0.001), 333: ("plant-333.hal", "bridge-333.toml", 0.003)}


def latencies(log: Path, Ts: float, warmup: float) -> np.ndarray:
    """Latency (s) of every sample after ``warmup`` s, from ``halsampler -t`` lines (tag, counter, force, pin)."""
    rows = np.array([[int(p[1]), int(p[3])] for p in (line.split() for line in log.read_text().splitlines())
                     if len(p) == 4], dtype=np.int64)
    count, pin = rows[:, 0], np.maximum.accumulate(rows[:, 1])
    answered = pin > 0
    first = count[np.argmax(answered)] + int(round(warmup / Ts))
    last = pin[-1]  # samples answered before the log ended
    k = np.arange(first, last + 1)
    idx = np.searchsorted(pin, k, side="left")
    return (count[idx] - k) * Ts


def renice(pids: list[int], nice: int) -> None:
    """Every thread of ``pids`` to niceness ``nice`` (Linux: a thread's own priority; negative needs root)."""
    for pid in pids:
        for tid in os.listdir(f"/proc/{pid}/task"):
            os.setpriority(os.PRIO_PROCESS, int(tid), nice)


def _pids(name: str) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                if Path(f"/proc/{d}/comm").read_text().strip() == name:
                    out.append(int(d))
            except OSError:
                pass
    return out


def run_once(work: Path, rate: int, mon: L.Proc, endpoint: str, args) -> dict:
    hal, cfg_name, Ts = RATES[rate]
    force = work / f"force-{rate}.txt"
    log = work / f"way-back-{rate}.txt"
    cfg = L.bridge_config(L.HAL_DIR / cfg_name, work)
    cfg.write_text(cfg.read_text().replace("block = 1 ", f"block = {args.block} "))
    plant_file = work / hal  # the plant with HAL's own measure of its thread's timing (timedelta)
    plant_file.write_text((L.HAL_DIR / hal).read_text().replace(
        "\nstart\n", "\nloadrt timedelta\naddf timedelta.0 servo-thread\nstart\n"))
    load = os.getloadavg()[0]
    with L.HalPlant(plant_file, work) as plant:
        plant.streamer(force)
        plant.sampler(log, channel=1)
        bridge = L.start_bridge(cfg, work, "--connect", endpoint, "--prefix", PREFIX)
        if args.nice is not None:
            helper = int(bridge.wait_line(r"HAL helper pid (\d+)", 10)[1])
            renice([helper, bridge.proc.pid, mon.proc.pid, *_pids("rtapi_app")], args.nice)
        time.sleep(args.seconds + args.warmup)
        jitter = {k: int(L.halcmd("getp", f"timedelta.0.{k}")) for k in ("max", "jitter")}
        bridge.stop()
    lat = latencies(log, Ts, args.warmup)
    return {"rate": rate, "samples": lat.size, "p50": np.median(lat), "p90": np.quantile(lat, 0.9),
            "p99": np.quantile(lat, 0.99), "max": lat.max(), "over": float(np.mean(lat > 0.010)),
            "load": (load + os.getloadavg()[0]) / 2, "period_max": jitter["max"] * 1e-9,
            "jitter": jitter["jitter"] * 1e-9}


def bench_rate(work: Path, rate: int, args) -> list[dict]:
    hal, _, Ts = RATES[rate]
    rate_cfg = work / f"rate-{rate}.toml"
    rate_cfg.write_text(f"rate = {1.0 / Ts!r}\n")
    trial = work / f"cut-{rate}.mcap"
    dur = str(args.seconds + args.warmup + 5)
    assert main(["simulate", "milling-inc", "-o", str(trial), "--duration", dur, "--config", str(rate_cfg)]) == 0
    assert main(["bridge", "streamer-file", str(trial), "-o", str(work / f"force-{rate}.txt"),
                 "--servo-period", str(Ts)]) == 0
    model = save_model(truth_model(L.plant_meta(Ts)), work / f"plant-{rate}.model.toml")
    endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
    mon = L.Proc(["run", "--model", str(model), "--listen", endpoint, "--prefix", PREFIX], work)
    mon.wait_line(r"ready .*listening on", 120)
    try:
        return [run_once(work, rate, mon, endpoint, args) for _ in range(args.repeat)]
    finally:
        mon.stop()
        print("  monitor:", next((line.strip() for line in mon.lines if "latency p50" in line), "?"), flush=True)


def main_(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", default="1000,333", help="plant rates (Hz): 1000 and/or 333")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured seconds per run")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds left out at the start of a run")
    ap.add_argument("--repeat", type=int, default=3, help="runs per rate")
    ap.add_argument("--block", type=int, default=1, help="samples per message (the bridge's [publish] block)")
    ap.add_argument("--nice", type=int, default=None,
                    help="run HAL, the helper, the bridge and the monitor at this niceness (negative: root)")
    args = ap.parse_args(argv)
    missing = L.linuxcnc_missing()
    if missing:
        print(f"linuxcnc_latency: {missing}", file=sys.stderr)
        return 2
    work = L.workdir("feedmon-bench-")
    results = []
    try:
        for rate in (int(r) for r in args.rates.split(",")):
            print(f"{rate} Hz plant: {args.repeat} run(s) of {args.seconds:g} s …", flush=True)
            results += bench_rate(work, rate, args)
    finally:
        if os.environ.get("KEEP_WORK"):
            print("work dir kept:", work)
        else:
            shutil.rmtree(work, ignore_errors=True)
    print(f"\nround trip in HAL time (target p99 ≤ 10 ms), {args.block} sample(s) per message"
          f"{'' if args.nice is None else f', niceness {args.nice}'}; "
          "HAL thread: longest period and worst scheduling error seen by timedelta")
    print(f"{'rate':>6} {'samples':>8} {'p50 ms':>7} {'p90 ms':>7} {'p99 ms':>7} {'max ms':>7} {'> 10 ms':>8} "
          f"{'load':>5} {'HAL max period ms':>18} {'HAL jitter ms':>14}")
    for r in results:
        print(f"{r['rate']:>6} {r['samples']:>8} {1e3 * r['p50']:>7.1f} {1e3 * r['p90']:>7.1f} {1e3 * r['p99']:>7.1f} "
              f"{1e3 * r['max']:>7.1f} {100 * r['over']:>7.2f}% {r['load']:>5.2f} {1e3 * r['period_max']:>18.1f} "
              f"{1e3 * r['jitter']:>14.1f}")
    for rate in sorted({r["rate"] for r in results}, reverse=True):
        p99 = [1e3 * r["p99"] for r in results if r["rate"] == rate]
        p50 = [1e3 * r["p50"] for r in results if r["rate"] == rate]
        print(f"{rate} Hz: median over runs p50 {np.median(p50):.1f} ms, p99 {np.median(p99):.1f} ms "
              f"(runs: p99 {min(p99):.1f} … {max(p99):.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main_())
