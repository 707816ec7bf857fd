"""Latency of a process alarm: a sample published on Zenoh → the alarm message received (p50/p99).

Usage::

    python benchmarks/alarm_latency.py                 # 60 s of data at 333 Hz, one sample per message
    python benchmarks/alarm_latency.py --seconds 20    # shorter

A simulated slot-milling trial (``milling-incdec``) gets a collision-like force impulse (5× the mean
cutting force for 3 samples) every ``--every`` s, put into its velocities through the drive's linear
response (``Δv(k+1) = β2·Δv(k) − b·ΔF(k)``, ``b = β1/K``). A ``feedmon run --monitors`` subprocess
listens on loopback (no sinks); this process publishes the samples one per message at 333 Hz
(congestion control BLOCK, express) and subscribes to ``<prefix>/<machine>/<axis>/alarm``. The latency
of an alarm is its arrival time minus the send time of the sample its row was made for (row ``seq``,
the same clock). Printed: alarms expected/received, p50, p99, max (ms), the machine's load.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feedio import schema as S  # noqa: E402
from feedio import transport as T  # noqa: E402

PREFIX = "feedmon-alarm-bench"


def _trial_with_impulses(work: Path, seconds: float, every: float):
    from feedio.mcapio import read_trial
    from monitor.model_file import save_model, truth_model
    from replay.scenarios import load_scenario
    from replay.simulator import simulate, write_trial

    write_trial(simulate(load_scenario("milling-incdec", duration=seconds + 2.0), seed=5), work / "trial.mcap")
    tr = read_trial(work / "trial.mcap")
    save_model(truth_model(tr.meta, period=1 / 100, budget=100), work / "m.model.toml")
    force = np.asarray(tr.truth.force)
    n, Ts = tr.t.size, tr.Ts
    starts = np.arange(int(2.0 / Ts), n - 10, int(every / Ts))  # after the cut's entry
    dF = np.zeros(n)
    for k in starts:
        dF[k:k + 3] = 5.0 * abs(force[k - 300:k]).mean()
    beta = tr.meta.truth.beta
    b = beta[0] / tr.meta.loop_gain
    dv = np.zeros(n)
    for k in range(n - 1):
        dv[k + 1] = beta[1] * dv[k] - b * dF[k]
    return tr, np.asarray(tr.v_meas) + dv, starts


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--every", type=float, default=0.5, help="s between impulses (≥ 0.4: the monitor's hold-off)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        tr, v_meas, starts = _trial_with_impulses(work, args.seconds, args.every)
        endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
        cmd = [sys.executable, "-m", "feedmon.cli", "run", "--model", str(work / "m.model.toml"), "--fresh",
               "--state-dir", str(work / "state"), "--listen", endpoint, "--prefix", PREFIX, "--monitors"]
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, cwd=ROOT)
        lines, ready = [], threading.Event()

        def read():
            for line in proc.stderr:
                lines.append(line)
                if "listening on" in line:
                    ready.set()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(120) or proc.poll() is not None:
            raise SystemExit("monitor did not start:\n" + "".join(lines))
        session = T.open_session(connect=endpoint)
        arrived: dict[int, float] = {}
        sub = session.declare_subscriber(T.alarm_key(PREFIX),
                                         lambda s: arrived.setdefault(S.decode_alarm(s.payload.to_bytes()).seq,
                                                                      time.perf_counter()))
        pub = session.declare_publisher(T.samples_key(PREFIX, tr.machine, tr.axis),
                                        congestion_control=zenoh.CongestionControl.BLOCK,
                                        encoding=zenoh.Encoding.APPLICATION_JSON, express=True)
        T.wait_for_matching(pub, 10.0)
        n = int(min(tr.t.size, (args.seconds + 2.0) / tr.Ts))
        payloads = [S.encode(S.SampleBlock(machine=tr.machine, axis=tr.axis, seq=k, t=[float(tr.t[k])],
                                           v_ref=[float(tr.v_ref[k])], v_meas=[float(v_meas[k])],
                                           spindle_angle=[float(tr.spindle_angle[k])])) for k in range(n)]
        sent = np.zeros(n)
        start = time.perf_counter() + 0.1
        for k, data in enumerate(payloads):
            wait = start + k * tr.Ts - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            sent[k] = time.perf_counter()
            pub.put(data)
        deadline = time.monotonic() + 5.0
        while len(arrived) < len(starts) and time.monotonic() < deadline:
            time.sleep(0.05)
        sub.undeclare()
        pub.undeclare()
        session.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(120)
    lat = np.array([(t - sent[seq]) * 1e3 for seq, t in arrived.items() if seq < n])
    within = sum(any(0 < s - k <= 3 for s in arrived) for k in starts)
    p50, p99 = np.percentile(lat, [50, 99]) if lat.size else (float("nan"),) * 2
    print(f"load average {os.getloadavg()[0]:.2f}; {n} samples at {1 / tr.Ts:.0f} Hz, one per message")
    print("| impulses | alarms | within 3 samples | p50 ms | p99 ms | max ms |")
    print("|---:|---:|---:|---:|---:|---:|")
    print(f"| {len(starts)} | {len(arrived)} | {within} | {p50:.2f} | {p99:.2f} | "
          f"{lat.max() if lat.size else float('nan'):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
