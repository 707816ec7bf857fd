"""``feedmon demo``: the production flow in one command on a fresh install.

1. simulate an air cut (the axis moved without cutting) and a *different* job: slot milling
   Al 7050 with a 2-flute end mill at another spindle speed (2400 rpm) and another noise seed;
2. identify the axis on the air cut, as a user would (``feedmon identify`` with no options), and
   write the model file;
3. start the monitor (Zenoh peer on loopback, MCAP and Rerun sinks);
4. replay the milling job through Zenoh from a second session;
5. print where the MCAP and ``.rrd`` files are and how well the estimate followed the true
   cutting force — out of sample: the model never saw the job it monitors.
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table


def register(sub) -> None:
    p = sub.add_parser("demo", help="identify on an air cut, then monitor another milling job end to end",
                       description="Simulate an air cut and a milling job at another spindle speed, identify the axis "
                       "on the air cut (no options), start the monitor, replay the job through Zenoh and report how well "
                       "the estimate followed the cutting force it was never identified on.")
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

    # 1. trials: the identification run and the job it will monitor (another seed, another spindle speed)
    job_rpm = 2400.0
    air_path, job_path = out / "milling-aircut.mcap", out / "milling-job.mcap"
    write_trial(simulate_scenario("milling-aircut", seed=args.seed, duration=args.duration), air_path)
    write_trial(simulate_scenario("milling-inc", seed=args.seed + 1, duration=args.duration,
                                  config={"disturbance": {"spindle_rpm": job_rpm}}), job_path)
    console.print(f"[1/5] simulated an air cut ({air_path}) and a milling job at {job_rpm:g} rpm, seed {args.seed + 1} "
                  f"({job_path})")

    # 2. identification on the air cut, with no options
    air = identify(read_trial(air_path))
    model_path = out / f"{air.machine}-{air.axis}.model.toml"
    model = air.to_model(feedmon_version=__version__)
    save_model(model, model_path)
    console.print(f"[2/5] model file identified on the air cut ({air.chosen_method}): {model_path}")

    # 3.–4. monitor + replay
    job = read_trial(job_path)
    mcap_path = out / "monitor.mcap"
    rrd_path = out / "monitor.rrd"
    received = _monitor_and_replay(model_path, job_path, mcap_path, rrd_path, args.rate, console,
                                   teeth=job.meta.teeth)

    # 5. how well did it follow the cutting force of a job it was not identified on?
    summary = _score(mcap_path, job)
    console.print(f"[5/5] monitor log (MCAP): {mcap_path}\n      Rerun recording: {rrd_path}  (open with: rerun {rrd_path})")
    table = Table(title="out of sample: model from the air cut, estimate vs the job's true cutting force (from 2 s)")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("samples replayed / estimates logged", f"{len(job)} / {received}")
    table.add_row("correlation, one-step-ahead prediction", f"{summary['corr_next']:.4f}")
    table.add_row("correlation, filtered estimate", f"{summary['corr_filtered']:.4f}")
    table.add_row("RMS error of the prediction (N; its mean included)", f"{summary['rms_error']:.2f}")
    table.add_row("RMS of the cutting force (N)", f"{summary['rms_force']:.2f}")
    table.add_row("truth within ±2σ of the filtered estimate", f"{100 * summary['coverage']:.1f} %")
    table.add_row("health reports warn / alarm", f"{summary['warn']} / {summary['alarm']} of {summary['reports']}")
    Console().print(table)
    return 0 if summary["corr_next"] > 0.5 else 1


def _monitor_and_replay(model_path, trial_path, mcap_path, rrd_path, rate, console, teeth=None) -> int:
    from feedio.transport import free_tcp_port, open_session
    from monitor.axes import live_meta, load_axes
    from monitor.daemon import Monitor
    from monitor.sinks.mcap_sink import McapSink
    from monitor.sinks.rerun_layout import describe_model
    from monitor.sinks.rerun_process import RerunProcessSink
    from monitor.warm import warm_up
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
    finally:
        monitor.stop()  # drains the queue: the block being estimated is counted too
        if client is not None:
            client.close()
        server.close()
    return int(ax.estimator.counters["estimates_out"])


def _score(mcap_path, trial) -> dict:
    """The monitor's log against the trial's truth from 2 s on: correlations, the prediction's RMS error
    (its mean included: a bias counts), ±2σ coverage of the filtered estimate, the health reports."""
    from feedio.mcapio import iter_blocks

    seq, f_next, f_filt, f_sd = [], [], [], []
    reports = {"ok": 0, "warn": 0, "alarm": 0}
    for kind, block in iter_blocks(mcap_path, kinds=("disturbance", "health")):
        if kind == "health":
            reports[block.state] += 1
            continue
        seq.extend(range(block.seq, block.seq + len(block.t)))
        f_next.extend(block.force_next if block.force_next is not None else block.f_next)
        f_filt.extend(block.force if block.force is not None else block.f)
        f_sd.extend(np.sqrt(np.asarray(block.force_var if block.force_var is not None else block.f_var, dtype=float)))
    seq = np.asarray(seq)
    f_next, f_filt, f_sd = (np.asarray(x, dtype=float) for x in (f_next, f_filt, f_sd))
    truth = trial.truth.force
    keep = (seq >= int(2.0 / trial.Ts)) & (seq < truth.size)
    j = seq[keep]
    a, c, sd = f_next[keep], f_filt[keep], f_sd[keep]
    b = truth[j]                                   # row j's prediction pairs with truth j
    prev = truth[np.maximum(j - 1, 0)]             # its filtered estimate with truth j−1
    ok = np.isfinite(a) & np.isfinite(c) & np.isfinite(sd)
    a, c, sd, b, prev = a[ok], c[ok], sd[ok], b[ok], prev[ok]
    return {
        "corr_next": float(np.corrcoef(a, b)[0, 1]),
        "corr_filtered": float(np.corrcoef(c, prev)[0, 1]),
        "rms_error": float(np.sqrt(np.mean((a - b) ** 2))),
        "rms_force": float(np.sqrt(np.mean(b ** 2))),
        "coverage": float(np.mean(np.abs(c - prev) <= 2.0 * sd)),
        "reports": sum(reports.values()), "warn": reports["warn"], "alarm": reports["alarm"],
    }
