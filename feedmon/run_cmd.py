"""``feedmon run``: the live disturbance monitor (or, with ``--from``, the same pipeline offline).

Examples::

    feedmon run --model axis-x.model.toml --model axis-y.model.toml --mcap logs/ --rrd live.rrd
    feedmon run --model axis-x.model.toml --serve-rerun 9876          # live viewer: rerun --connect ...
    feedmon run --model axis-x.model.toml --connect tcp/router:7447   # client of a Zenoh router
    feedmon run --config monitor.toml
    feedmon run --from trial.mcap -o estimates.mcap --model axis-x.model.toml

Live: listens on tcp/127.0.0.1:7448 (see ``feedio.transport``), subscribes to
``<prefix>/*/*/samples``, publishes ``<prefix>/<machine>/<axis>/disturbance``,
answers ``<prefix>/monitor/status`` (``feedmon status``). SIGINT/SIGTERM stop it
cleanly (input stopped, queue drained, MCAP finished, tracker state saved), exit 0.

``--config FILE`` (TOML) holds defaults for the options, in a ``[run]`` table with
the long option names (``model = [...]``, ``mcap``, ``rrd``, ``serve_rerun``,
``state_dir``, ``rotate_mb``, ``rotate_minutes``, ``queue``, ``record_truth``,
``listen``, ``connect``, ``prefix``); paths are relative to the config file;
options on the command line win.
"""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import sys
import threading
import time
import tomllib
from pathlib import Path

from feedio.transport import add_zenoh_arguments

_CONFIG_KEYS = {
    "model": list, "mcap": str, "rrd": str, "serve_rerun": int, "state_dir": str, "fresh": bool,
    "rotate_mb": (int, float), "rotate_minutes": (int, float), "queue": int, "record_truth": bool,
    "listen": list, "connect": list, "prefix": str, "zenoh_config": str,
}
_PATH_KEYS = ("model", "mcap", "rrd", "state_dir", "zenoh_config")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run",
        help="run the live disturbance monitor (or --from a trial file, offline)",
        description="Estimate the disturbance of every axis that has a model file, live from Zenoh "
                    "or offline from a trial file (--from).",
    )
    p.add_argument("--model", action="append", default=None, metavar="FILE",
                   help="axis model file (TOML, from 'feedmon identify'); repeat for several axes")
    p.add_argument("--config", default=None, metavar="FILE", help="TOML file with defaults for these options ([run] table)")
    p.add_argument("--from", dest="source", default=None, metavar="TRIAL",
                   help="offline: estimate this trial file (.mcap) instead of listening on Zenoh")
    p.add_argument("-o", "--output", default=None, metavar="FILE",
                   help="offline: output MCAP (samples + truth + estimates); required with --from")
    g = p.add_argument_group("outputs (live)")
    g.add_argument("--mcap", default=None, metavar="DIR_OR_FILE",
                   help="MCAP log of inputs and estimates: a .mcap file, or a directory "
                        "(file feedmon-<time>.mcap, rotated at --rotate-mb/--rotate-minutes)")
    g.add_argument("--rotate-mb", type=float, default=None, metavar="MB",
                   help="start a new MCAP file at about this size (default 256 for a directory, none for a file)")
    g.add_argument("--rotate-minutes", type=float, default=None, metavar="MIN",
                   help="start a new MCAP file after this many minutes (default 60 for a directory, none for a file)")
    g.add_argument("--rrd", default=None, metavar="FILE", help="write a Rerun recording (.rrd)")
    g.add_argument("--serve-rerun", type=int, default=None, metavar="PORT",
                   help="serve the Rerun recording live on this port (viewer: rerun --connect ...)")
    g.add_argument("--record-truth", action="store_true",
                   help="also record ground-truth blocks (<prefix>/*/*/truth, from 'feedmon replay') in the sinks")
    g.add_argument("--queue", type=int, default=None, metavar="N",
                   help="input queue capacity in messages (default 8192); a full queue drops and counts")
    s = p.add_argument_group("tracker state")
    s.add_argument("--state-dir", default=None, metavar="DIR",
                   help="where tracker states are saved on exit and restored on start "
                        "(default: next to each model file, <model>.state.npz)")
    s.add_argument("--fresh", action="store_true", help="do not restore a saved tracker state")
    add_zenoh_arguments(p, role="listen")
    p.set_defaults(func=run)
    return p


# ---- configuration -----------------------------------------------------------------------------
def _apply_config(args: argparse.Namespace) -> None:
    path = Path(args.config)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"config file {str(path)!r} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config file {path}: not valid TOML ({exc})") from None
    table = doc.get("run", doc)
    if not isinstance(table, dict):
        raise ValueError(f"config file {path}: [run] must be a table")
    base = path.resolve().parent
    for key, value in table.items():
        if key not in _CONFIG_KEYS:
            raise ValueError(f"config file {path}: unknown key {key!r}; known: {', '.join(sorted(_CONFIG_KEYS))}")
        kind = _CONFIG_KEYS[key]
        if kind is list and isinstance(value, str):
            value = [value]
        if isinstance(value, bool) and kind is not bool or not isinstance(value, kind):
            raise ValueError(f"config file {path}: key {key!r} has the wrong type ({type(value).__name__})")
        if key in _PATH_KEYS:
            value = [str(base / v) for v in value] if isinstance(value, list) else str(base / value)
        if key == "fresh" or key == "record_truth":
            setattr(args, key, bool(getattr(args, key)) or value)
        elif getattr(args, key, None) is None:
            setattr(args, key, value)
    if args.prefix is None:
        args.prefix = "feedmon"


def _mcap_path(spec: str, args) -> tuple[Path, int | None, float | None]:
    p = Path(spec)
    rb = None if args.rotate_mb is None else int(args.rotate_mb * 1024 * 1024)
    rs = None if args.rotate_minutes is None else args.rotate_minutes * 60.0
    if p.suffix.lower() == ".mcap" and not p.is_dir():
        if not p.parent.is_dir():
            raise FileNotFoundError(f"directory of --mcap {spec!r} does not exist")
        return p, rb, rs
    p.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return (p / f"feedmon-{stamp}.mcap", rb if rb is not None else 256 * 1024 * 1024,
            rs if rs is not None else 3600.0)


def _say(msg: str) -> None:
    print(f"feedmon run: {msg}", file=sys.stderr, flush=True)


# ---- entry point -----------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    raw_prefix = args.prefix
    if args.config:
        # the parser's --prefix default must not hide the config file's value
        if raw_prefix == "feedmon":
            args.prefix = None
        _apply_config(args)
    if not args.model:
        raise ValueError("at least one --model FILE is needed (or 'model = [...]' in --config)")
    if args.rotate_mb is not None and not args.rotate_mb > 0:
        raise ValueError(f"--rotate-mb must be > 0, got {args.rotate_mb}")
    if args.rotate_minutes is not None and not args.rotate_minutes > 0:
        raise ValueError(f"--rotate-minutes must be > 0, got {args.rotate_minutes}")
    if args.queue is not None and args.queue < 1:
        raise ValueError(f"--queue must be ≥ 1, got {args.queue}")
    logging.basicConfig(level=logging.INFO, format="feedmon run: %(levelname)s: %(message)s", stream=sys.stderr)
    if args.source is not None:
        return _run_offline(args)
    if args.output is not None:
        raise ValueError("-o/--output is for --from (offline); use --mcap for the live log")
    return _run_live(args)


def _run_offline(args) -> int:
    from monitor.axes import load_axes
    from monitor.offline import run_offline

    if args.output is None:
        raise ValueError("--from needs -o/--output FILE.mcap")
    for opt in ("mcap", "rrd", "serve_rerun"):
        if getattr(args, opt) is not None:
            raise ValueError(f"--{opt.replace('_', '-')} is for the live monitor; offline output goes to -o")
    axes = load_axes(args.model)
    res = run_offline(args.source, args.output, axes)
    if res.skipped_axes:
        _say(f"no model for {', '.join(res.skipped_axes)}: not estimated, not copied")
    for ax in axes.values():
        c = ax.estimator.counters
        _say(f"{ax.status.name}: {c['samples_in']} samples, {c['estimates_out']} estimates, "
             f"{c['gaps']} gaps, {c['stale']} stale, dictionary {ax.estimator.tracker.size}")
    print(f"estimated {res.samples} samples of {', '.join(res.axes)} in {res.seconds:.2f} s "
          f"({res.rate:,.0f} samples/s) -> {res.output} (+{res.truth_blocks} truth blocks copied)")
    return 0


def _run_live(args) -> int:
    from feedio.transport import config_from_args, describe_config, open_session
    from monitor.axes import live_meta, load_axes, warm_up
    from monitor.daemon import Monitor
    from monitor.state import StateStore

    # the estimator thread competes with the sink threads for the GIL: a shorter switch interval
    # bounds how long it waits for a sink that is busy in Python (default 5 ms) -> better p99 latency
    sys.setswitchinterval(0.0005)
    axes = load_axes(args.model)
    warm_up(axes)  # JIT before "ready": the first real sample must not wait for a compiler
    store = StateStore(args.state_dir)
    for ax in axes.values():
        how = store.load(ax, fresh=args.fresh).detail  # restored (when saved, samples learned) / why not
        _say(f"axis {ax.status.name}: model {ax.status.model_path} (sha256 {ax.status.model_sha256[:12]}…), "
             f"tracker state {how}: {ax.status.state_path}")

    sinks = []
    session = None
    monitor = None
    try:
        if args.mcap is not None:
            from monitor.sinks.mcap_sink import McapSink

            path, rb, rs = _mcap_path(args.mcap, args)
            sinks.append(McapSink(path, rb, rs, metas=[live_meta(a) for a in axes.values()]))
            rot = " (rotated" + (f" at {rb / 2**20:g} MB" if rb else "") + (f" / {rs / 60:g} min" if rs else "") + ")" \
                if rb or rs else ""
            _say(f"MCAP log: {path}{rot}")
        if args.rrd is not None or args.serve_rerun is not None:
            from monitor.sinks.rerun_layout import describe_model
            from monitor.sinks.rerun_process import RerunProcessSink

            info = {f"{a.model.machine}/{a.model.axis}": describe_model(a.model) for a in axes.values()}
            rs_ = RerunProcessSink(args.rrd, args.serve_rerun, axis_info=info)  # own process: never holds our GIL
            sinks.append(rs_)
            if args.rrd:
                _say(f"Rerun recording: {args.rrd}")
            if rs_.server_uri:
                _say(f"Rerun live: rerun --connect {rs_.server_uri}")
        zconfig = config_from_args(args)
        session = open_session(zconfig)
        zdesc = describe_config(zconfig)  # what the session really does (also with --zenoh-config)
        listen, connect = zdesc["listen"], zdesc["connect"]
        endpoints = [f"listen {e}" for e in listen] + [f"connect {e}" for e in connect]
        monitor = Monitor(axes, session, prefix=args.prefix, sinks=sinks, queue_size=args.queue or 8192,
                          record_truth=args.record_truth, state=store, endpoints=endpoints)
        stop = threading.Event()
        received = []

        def on_signal(signum, _frame):
            received.append(signum)
            stop.set()

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            monitor.start()
            # everything allocated so far (modules, JIT, sessions, sinks) lives for the whole run:
            # move it out of the collector's generations so full collections stay short
            gc.collect()
            gc.freeze()
            where = ", ".join(listen) if listen else "(no listen endpoint)"
            conn = f", connected to {', '.join(connect)}" if connect else ""
            _say(f"ready — Zenoh {zdesc['mode']}, listening on {where}{conn}; prefix {args.prefix!r}; axes "
                 f"{', '.join(a.status.name for a in axes.values())}; status: feedmon status; Ctrl-C to stop")
            while not stop.wait(0.5):
                pass
            _say(f"{signal.Signals(received[0]).name}: stopping (draining input, finishing outputs)")
            monitor.stop()
        finally:
            for s, h in old.items():
                signal.signal(s, h)
    finally:
        if monitor is not None:
            monitor.stop()
        else:
            for s in sinks:
                s.close()
        if session is not None:
            session.close()
    st = monitor.status()
    for name, a in st["axes"].items():
        lat = a["latency_us"]
        _say(f"{name}: {a['samples_in']} samples in, {a['estimates_out']} estimates out, "
             f"{a['dropped_total']} dropped{' ' + str(a['drops']) if a['drops'] else ''}, {a['gaps']} gaps; "
             f"latency p50 {lat['p50']} µs, p99 {lat['p99']} µs")
    for s in st["sinks"]:
        files = s.get("files") or ([s["rrd_path"]] if s.get("rrd_path") else [])
        _say(f"sink {s['name']}: {s['written']} written, {s['dropped']} dropped, {s['failures']} failures; "
             + ", ".join(files))
    for p in monitor.saved_states:
        _say(f"tracker state saved: {p}")
    return 0
