"""``feedmon demo``: the whole product in one command on a fresh install.

1. simulate an air-cut trial and a milling trial (3000 rpm, 2 flutes, slotting Al 7050);
2. identify the axis by LS on the air cut and by PL-LSSVM on the milling trial
   itself (no air cut needed: the point of the method) and write the model file;
3. start the monitor (Zenoh peer on loopback, MCAP and Rerun sinks);
4. replay the milling trial through Zenoh from a second session;
5. print where the MCAP and ``.rrd`` files are and how well the estimate followed
   the true cutting force.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table


def register(sub) -> None:
    p = sub.add_parser("demo", help="simulate, identify, monitor and replay a milling trial end to end",
                       description="Simulate an air-cut and a milling trial, identify the axis, start the monitor, "
                       "replay the milling trial through Zenoh and report how well the estimate followed the cutting force.")
    p.add_argument("--out", default="feedmon-demo", help="output directory (default ./feedmon-demo)")
    p.add_argument("--duration", type=float, default=30.0, help="length of the simulated trials in s (default 30)")
    p.add_argument("--rate", type=float, default=10.0, help="replay speed, × real time (default 10; 1 = real time)")
    p.add_argument("--seed", type=int, default=1, help="simulation seed")
    p.set_defaults(func=run)


def run(args) -> int:
    from feedio import __version__
    from feedio.mcapio import read_trial
    from monitor.identify import identify
    from monitor.model_file import save_model
    from replay.simulator import simulate_scenario, write_trial

    console = Console(stderr=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not (args.duration >= 5):
        raise ValueError(f"--duration must be at least 5 s, got {args.duration}")
    if not (args.rate > 0):
        raise ValueError(f"--rate must be > 0, got {args.rate}")

    # 1. trials
    paths = {}
    for name in ("milling-aircut", "milling-incdec"):
        paths[name] = out / f"{name}.mcap"
        write_trial(simulate_scenario(name, seed=args.seed, duration=args.duration), paths[name])
        console.print(f"[1/5] simulated {name}: {paths[name]}")

    # 2. identification
    cut_trial = read_trial(paths["milling-incdec"])
    cut = identify(cut_trial)
    air = identify(read_trial(paths["milling-aircut"]), method="ls", tune=False)  # spindle off: LS is the reference
    model_path = out / f"{cut.machine}-{cut.axis}.model.toml"
    model = cut.to_model(feedmon_version=__version__)
    offset = _offset_from_air_cut(model, air)
    save_model(model, model_path)
    _print_identification(air, cut, console)
    console.print(f"[2/5] model file (PL-LSSVM on the milling trial, force offset {offset:+.2f} N from the air cut): "
                  f"{model_path}")

    # 3.–4. monitor + replay
    mcap_path = out / "monitor.mcap"
    rrd_path = out / "monitor.rrd"
    received = _monitor_and_replay(model_path, paths["milling-incdec"], mcap_path, rrd_path, args.rate, console,
                                   teeth=cut_trial.meta.teeth)

    # 5. how well did it follow the cutting force?
    summary = _score(mcap_path, cut_trial)
    console.print(f"[5/5] monitor log (MCAP): {mcap_path}\n      Rerun recording: {rrd_path}  (open with: rerun {rrd_path})")
    table = Table(title="online disturbance estimate vs true cutting force (after 2 s warm-up)")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("samples replayed / estimates logged", f"{len(cut_trial)} / {received}")
    table.add_row("correlation, one-step-ahead prediction", f"{summary['corr_next']:.4f}")
    table.add_row("correlation, filtered estimate", f"{summary['corr_filtered']:.4f}")
    table.add_row("RMS error of the prediction, means removed (N)", f"{summary['rms_error']:.2f}")
    table.add_row("RMS of the cutting force, mean removed (N)", f"{summary['rms_force']:.2f}")
    Console().print(table)
    return 0 if summary["corr_next"] > 0.5 else 1


def _offset_from_air_cut(model, air) -> float:
    """Put the air cut's force offset (N) into ``model``'s constant column and return it.

    While cutting, a constant part of the cutting force cannot be told from a force offset: the
    milling trial's intercept holds both, and the monitor would subtract the mean cutting force
    from every estimate. Without the spindle the offset is the drive's own, so the demo takes it
    from the air cut (β_one = −b·offset with the milling model's b = K_d/K).
    """
    offset = air.model_result.candidate.physical.get("offset")
    b = model.force_gain
    if offset is None or b is None or not model.beta_names or model.beta_names[-1] != "one":
        return float("nan")
    model.beta[-1] = -b * float(offset)
    model.physical["offset"] = float(offset)
    return float(offset)


def _print_identification(air, cut, console) -> None:
    table = Table(title="β identified: LS needs an air cut; PL-LSSVM works while cutting")
    table.add_column("")
    for label in ("LS, air cut", "LS, milling", "PL-LSSVM, milling", "truth"):
        table.add_column(label, justify="right")
    truth = (cut.truth or {}).get("beta", [math.nan, math.nan])
    for i in range(2):
        table.add_row(f"β{i + 1}", f"{air.ls.beta[i]:.5f}", f"{cut.ls.beta[i]:.5f}", f"{cut.pl.beta[i]:.5f}", f"{truth[i]:.5f}")
    console.print(table)


def _monitor_and_replay(model_path, trial_path, mcap_path, rrd_path, rate, console, teeth=None) -> int:
    from feedio.transport import free_tcp_port, open_session
    from monitor.axes import live_meta, load_axes, warm_up
    from monitor.daemon import Monitor
    from monitor.sinks.mcap_sink import McapSink
    from monitor.sinks.rerun_layout import describe_model
    from monitor.sinks.rerun_process import RerunProcessSink
    from replay.player import replay

    from .replay_cmd import ProgressBar

    axes = load_axes([model_path])
    warm_up(axes)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    # the dashboard marks 1/ψ (model) and the tooth-passing frequency (spindle_rpm × the trial's teeth)
    info = {f"{a.model.machine}/{a.model.axis}": describe_model(a.model, teeth=teeth) for a in axes.values()}
    sinks = [McapSink(mcap_path, metas=[live_meta(a, source="demo") for a in axes.values()]),
             RerunProcessSink(rrd_path, axis_info=info)]
    server = open_session(listen=endpoint)
    client = None
    monitor = Monitor(axes, server, sinks=sinks, record_truth=True)
    try:
        monitor.start()
        console.print(f"[3/5] monitor listening on {endpoint}")
        client = open_session(connect=endpoint)
        with ProgressBar(trial_path) if sys.stderr.isatty() else contextlib.nullcontext() as bar:
            stats = replay(trial_path, client, rate=rate, progress=bar, wait_for_subscriber=10.0)
        console.print(f"[4/5] replayed {stats.samples} samples at {rate:g}× in {stats.wall_time:.1f} s")
        ax = next(iter(axes.values()))
        deadline = time.monotonic() + 30.0
        while ax.estimator.counters["samples_in"] < stats.samples and time.monotonic() < deadline:
            time.sleep(0.05)
        received = int(ax.estimator.counters["estimates_out"])
    finally:
        monitor.stop()
        if client is not None:
            client.close()
        server.close()
    return received


def _score(mcap_path, trial) -> dict:
    from feedio.mcapio import iter_blocks

    seq, f_next, f_filt = [], [], []
    for _kind, block in iter_blocks(mcap_path, kinds=("disturbance",)):
        seq.extend(range(block.seq, block.seq + len(block.t)))
        f_next.extend(block.force_next if block.force_next is not None else block.f_next)
        f_filt.extend(block.force if block.force is not None else block.f)
    seq = np.asarray(seq)
    f_next = np.asarray(f_next, dtype=float)
    f_filt = np.asarray(f_filt, dtype=float)
    truth = trial.truth.force
    warm = seq >= int(2.0 / trial.Ts)
    j = seq[warm]
    ok = j < truth.size
    a, b = f_next[warm][ok], truth[j[ok]]  # row j's prediction pairs with truth j
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    jf = j[ok][keep]
    c = f_filt[warm][ok][keep]
    prev = truth[np.maximum(jf - 1, 0)]  # the filtered estimate pairs with truth j−1
    bc = b - b.mean()
    return {
        "corr_next": float(np.corrcoef(a, b)[0, 1]),
        "corr_filtered": float(np.corrcoef(c, prev)[0, 1]),
        "rms_error": float(np.sqrt(np.mean(((a - a.mean()) - bc) ** 2))),
        "rms_force": float(np.sqrt(np.mean(bc ** 2))),
    }
