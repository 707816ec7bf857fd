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

``--config FILE`` (TOML) holds the options in a ``[run]`` table with the long option names
(``model = [...]``, ``mcap``, ``rrd``, ``serve_rerun``, ``state_dir``, ``rotate_mb``,
``rotate_minutes``, ``record_truth``, ``sink_priority``, ``drain_seconds``, ``sink_start_seconds``,
``sink_stall_seconds``, ``sink_close_seconds``, ``min_free_mb``, ``listen``, ``connect``, ``mode``,
``zenoh_config``, ``multicast``, ``prefix``), the input limits in ``[run.limits]``
(:class:`feedio.limits.InputLimits`) and the input-health thresholds in ``[run.input_health]``
(:class:`monitor.input_health.InputHealthSettings`); see :mod:`feedmon.run_config`. Paths are
relative to the config file; options on the command line win.

Exit code 0 after a clean stop; 1 when the stop could not finish everything (a tracker state not
saved, a sink that did not write everything offered to it, the estimator not stopped: each said on
stderr); 2 for bad options, configuration or model files, and for outputs that cannot be written
(checked at start).
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from feedio.limits import InputLimits
from feedio.transport import add_zenoh_arguments
from monitor.sinks.child import PRIORITIES

from .run_config import RunConfig, run_config_from_args


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
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="offline: processes for a trial with several axes (default: one per core, at most one per "
                        "axis; the output is the same for every N)")
    g = p.add_argument_group("outputs (live)")
    g.add_argument("--mcap", default=None, metavar="DIR_OR_FILE",
                   help="MCAP log of inputs and estimates: a .mcap file, or a directory "
                        "(files feedmon-<date>-<time>-<pid>-000.mcap, -001, ..., rotated at "
                        "--rotate-mb/--rotate-minutes); an existing file is never overwritten")
    g.add_argument("--rotate-mb", type=float, default=None, metavar="MB",
                   help="start a new MCAP file at about this size (default 256 for a directory, none for a file)")
    g.add_argument("--rotate-minutes", type=float, default=None, metavar="MIN",
                   help="start a new MCAP file after this many minutes (default 60 for a directory, none for a file)")
    g.add_argument("--rrd", default=None, metavar="FILE", help="write a Rerun recording (.rrd)")
    g.add_argument("--serve-rerun", type=int, default=None, metavar="PORT",
                   help="serve the Rerun recording live on this port (viewer: rerun --connect ...)")
    g.add_argument("--record-truth", action="store_true",
                   help="also record ground-truth blocks (<prefix>/*/*/truth, from 'feedmon replay') in the sinks")
    g.add_argument("--sink-priority", choices=PRIORITIES, default=None,
                   help="the MCAP and Rerun processes: low (default; nice 10: a tenth of a busy core's share, so the log "
                        "keeps up on a machine kept busy by other work) or idle (SCHED_IDLE: they run only on a "
                        "core nothing else wants; estimates ~1 ms earlier at p99, but on a busy machine the log "
                        "starves, is replaced and loses messages, counted)")
    lim = p.add_argument_group("input limits (docs/limits.md; file: [run.limits])")
    lim.add_argument("--queue", type=int, default=None, metavar="N",
                     help=f"input queue capacity in messages (default {InputLimits().queue_messages}); "
                          "a full queue refuses and counts")
    lim.add_argument("--limit", action="append", default=None, metavar="NAME=VALUE",
                     help="set an input limit, repeatable; NAME one of: " + ", ".join(InputLimits.__struct_fields__))
    lim.add_argument("--drain-seconds", type=float, default=None, metavar="S",
                     help="at stop, how long the estimator may work off queued input before the rest is "
                          "discarded and counted (default 30)")
    s = p.add_argument_group("tracker state")
    s.add_argument("--state-dir", default=None, metavar="DIR",
                   help="where tracker states are saved on exit and restored on start "
                        "(default: next to each model file, <model>.state.npz)")
    s.add_argument("--fresh", action="store_true", help="do not restore a saved tracker state")
    pm = p.add_argument_group("process monitors (file: [monitors]; docs/process-monitoring.md)")
    pm.add_argument("--monitors", action="store_true",
                    help="run the process monitors on the force (collision, overload, broken tooth, runout)")
    pm.add_argument("--reference", action="append", default=None, metavar="FILE",
                    help="a reference envelope (feedmon reference learn) to compare with; implies --monitors")
    pm.add_argument("--wear-history", default=None, metavar="FILE",
                    help="wear trend across parts: this run is one part, its per-section force is appended to FILE "
                         "(JSON, made when missing) and a rising trend raises a 'wear' alarm at the end; implies "
                         "--monitors (file: [monitors.wear])")
    add_zenoh_arguments(p, role="listen")
    p.set_defaults(func=run, prefix=None)  # None: not given (the config file or the default applies)
    return p


def _mcap_path(spec: str, cfg: RunConfig) -> tuple[Path, int | None, float | None]:
    """The MCAP log's path and rotation. A directory gets ``feedmon-<time>-<pid>.mcap`` (the sink numbers
    the files ``-000``, ``-001`` …): unique per process, and the sink creates every file exclusively, so
    two monitors logging into one directory never share a file."""
    p = Path(spec)
    rb = None if cfg.rotate_mb is None else int(cfg.rotate_mb * 1024 * 1024)
    rs = None if cfg.rotate_minutes is None else cfg.rotate_minutes * 60.0
    if p.suffix.lower() == ".mcap" and not p.is_dir():
        if not p.parent.is_dir():
            raise FileNotFoundError(f"directory of --mcap {spec!r} does not exist")
        _check_output_dir(p.parent, "--mcap", cfg)
        return p, rb, rs
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"--mcap {spec}: cannot make the directory: {exc.strerror or exc}; choose another one") from None
    _check_output_dir(p, "--mcap", cfg)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return (p / f"feedmon-{stamp}-{os.getpid()}.mcap", rb if rb is not None else 256 * 1024 * 1024,
            rs if rs is not None else 3600.0)


def _check_output_dir(d: Path, option: str, cfg: RunConfig, need_space: bool = True) -> None:
    """Refuse to start with an output directory that does not take a new file (read-only, immutable, not
    ours: tried with a real file, since root ignores permission bits) or has less than ``min_free_mb``
    free (``need_space``) — rather than a monitor that says "ok" and writes nothing."""
    probe = d / f".feedmon-write-test-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"x")
            os.fsync(fd)
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise OSError(f"{option}: cannot write a file in {d}: {exc.strerror or exc}; make the directory writable "
                      "or choose another one") from None
    free = shutil.disk_usage(d).free
    if need_space and free < cfg.min_free_mb * 2**20:
        raise OSError(f"{option}: only {free / 2**20:.1f} MiB free in {d}, less than min_free_mb = {cfg.min_free_mb:g} "
                      "MiB ([run] min_free_mb of --config); free some space or choose another directory")


def _say(msg: str) -> None:
    print(f"feedmon run: {msg}", file=sys.stderr, flush=True)


# ---- entry point -----------------------------------------------------------------------------
def _setup_logging() -> None:
    from monitor.status import EscapingFormatter

    root = logging.getLogger()
    if root.handlers:  # configured by the embedding program (or a test runner): leave it
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(EscapingFormatter("feedmon run: %(levelname)s: %(message)s"))  # one record, one line
    root.addHandler(handler)
    root.setLevel(logging.INFO)


def run(args: argparse.Namespace) -> int:
    cfg = run_config_from_args(args)
    if not cfg.model:
        raise ValueError("at least one --model FILE is needed (or 'model = [...]' in the [run] table of --config)")
    _setup_logging()
    if args.source is not None:
        return _run_offline(args, cfg)
    if args.output is not None:
        raise ValueError("-o/--output is for --from (offline); use --mcap for the live log")
    if cfg.jobs is not None:
        raise ValueError("--jobs is for --from (offline)")
    return _run_live(cfg, args)


def _run_offline(args, cfg: RunConfig) -> int:
    from monitor.axes import load_axes
    from monitor.offline import run_offline

    if args.output is None:
        raise ValueError("--from needs -o/--output FILE.mcap")
    for opt in ("mcap", "rrd", "serve_rerun"):
        if getattr(cfg, opt) is not None:
            raise ValueError(f"--{opt.replace('_', '-')} is for the live monitor; offline output goes to -o")
    axes = load_axes(cfg.model, cfg)
    from .run_config import monitor_settings_from_args

    res = run_offline(args.source, args.output, axes, limits=cfg.limits, jobs=cfg.jobs, input_health=cfg.input_health,
                      monitors=monitor_settings_from_args(args))
    if res.skipped_axes:
        _say(f"no model for {', '.join(res.skipped_axes)}: not estimated, not copied")
    lost = 0
    for ax in axes.values():
        c = ax.estimator.counters
        refused = f", {ax.status.counters['too_large']} blocks refused (too_large)" \
            if ax.status.counters.get("too_large") else ""
        failed = ax.status.counters.get("estimator_error", 0)
        if failed:
            lost += failed
            refused += (f"; {failed} samples LOST to estimator errors, tracker restarted {c['tracker_restarts']} "
                        "time(s) (see the log above)")
        h = ax.status.health or {}
        flagged = [r for r in h.get("reasons") or [] if r.startswith("input:")]
        health = f"; health at the end {h['state']}" + (f" ({'; '.join(flagged)})" if flagged else "") \
            if h.get("state") not in (None, "ok") else ""
        _say(f"{ax.status.name}: {c['samples_in']} samples, {c['estimates_out']} estimates, "
             f"{c['gaps']} gaps, {c['stale']} stale, dictionary {ax.estimator.tracker.size}{refused}{health}")
    for line in res.wear_report:
        _say(f"wear {line}")
    if res.wear_error:
        lost += 1
        _say(f"wear history NOT saved ({res.wear_error}): this part is not in it")
    procs = f", {res.jobs} processes" if res.jobs > 1 else ""
    print(f"estimated {res.samples} samples of {', '.join(res.axes)} in {res.seconds:.2f} s "
          f"({res.rate:,.0f} samples/s{procs}) -> {res.output} (+{res.truth_blocks} truth blocks copied)")
    return 1 if lost else 0  # the file is complete but for the lost blocks: say so in the exit code


def _zenoh_args(cfg: RunConfig) -> argparse.Namespace:
    """The Zenoh options of ``cfg`` as :func:`feedio.transport.config_from_args` reads them."""
    return argparse.Namespace(connect=cfg.connect, listen=cfg.listen, mode=cfg.mode, zenoh_config=cfg.zenoh_config,
                              multicast=cfg.multicast, prefix=cfg.prefix, _zenoh_role="listen")


def _run_live(cfg: RunConfig, args: argparse.Namespace | None = None) -> int:
    from feedio.transport import config_from_args, describe_config, limit_message_size, open_session
    from monitor.axes import load_axes
    from monitor.daemon import Monitor
    from monitor.state import StateStore
    from monitor.warm import warm_up

    # the estimator thread competes with the sink threads for the GIL: a shorter switch interval
    # bounds how long it waits for a sink that is busy in Python (default 5 ms) -> better p99 latency
    sys.setswitchinterval(0.0005)
    axes = load_axes(cfg.model, cfg)
    from monitor.process_monitor import build_monitors

    from .run_config import monitor_settings_from_args

    process = None if args is None else build_monitors(axes, monitor_settings_from_args(args))
    # the outputs before anything slow: a directory that cannot take the files is refused at once
    mcap = _mcap_path(cfg.mcap, cfg) if cfg.mcap is not None else None
    if cfg.rrd is not None:
        _check_output_dir(Path(cfg.rrd).resolve().parent, "--rrd", cfg)
    store = StateStore(cfg.state_dir)
    if cfg.state_dir is not None:
        _check_output_dir(Path(cfg.state_dir), "--state-dir", cfg, need_space=False)
    warm_up(axes, process)  # JIT before "ready": no real sample, search or alarm waits for a compiler
    for ax in axes.values():
        how = store.load(ax, fresh=cfg.fresh).detail  # restored (when saved, samples learned) / why not
        _say(f"axis {ax.status.name}: model {ax.status.model_path} (sha256 {ax.status.model_sha256[:12]}…), "
             f"tracker state {how}: {ax.status.state_path}")

    sinks = []
    session = None
    monitor = None
    started = False
    problems: list[str] = []
    try:
        _start_sinks(cfg, axes, sinks, mcap)
        # Zenoh itself drops what is far too large, before reassembling it (the callback counts the rest)
        zconfig = limit_message_size(config_from_args(_zenoh_args(cfg)), cfg.limits.transport_max_message_bytes)
        _estimate_queue(zconfig)
        session = open_session(zconfig)
        zdesc = describe_config(zconfig)  # what the session really does (also with --zenoh-config)
        listen, connect = zdesc["listen"], zdesc["connect"]
        endpoints = [f"listen {e}" for e in listen] + [f"connect {e}" for e in connect]
        monitor = Monitor(axes, session, prefix=cfg.prefix, sinks=sinks, limits=cfg.limits,
                          record_truth=cfg.record_truth, state=store, endpoints=endpoints,
                          drain_seconds=cfg.drain_seconds, input_health=cfg.input_health,
                          monitors=process)
        stop = threading.Event()
        received = []

        def on_signal(signum, _frame):
            received.append(signum)
            stop.set()

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            monitor.start()
            started = True
            # everything allocated so far (modules, JIT, sessions, sinks) lives for the whole run:
            # move it out of the collector's generations so full collections stay short
            gc.collect()
            gc.freeze()
            where = ", ".join(listen) if listen else "(no listen endpoint)"
            conn = f", connected to {', '.join(connect)}" if connect else ""
            _say(f"ready — Zenoh {zdesc['mode']}, listening on {where}{conn}; prefix {cfg.prefix!r}; axes "
                 f"{', '.join(a.status.name for a in axes.values())}; status: feedmon status; Ctrl-C to stop")
            while not stop.wait(0.5):
                pass
            _say(f"{signal.Signals(received[0]).name}: stopping (draining input, finishing outputs)")
            problems = monitor.stop()
        finally:
            for s, h in old.items():
                signal.signal(s, h)
    finally:
        if monitor is not None:
            problems = monitor.stop(cfg.sink_close_seconds)  # idempotent; always finishes within its bound
        else:
            for s in sinks:
                try:
                    s.close(cfg.sink_close_seconds)
                except Exception as exc:  # noqa: BLE001 - report, keep closing the others
                    _say(f"closing sink {s.name} failed: {exc}")
        if not started:
            _discard_empty_outputs(sinks)
        if session is not None:
            try:
                session.close()
            except Exception as exc:  # noqa: BLE001
                _say(f"closing the Zenoh session failed: {exc}")
    try:
        _summary(monitor)
    except Exception as exc:  # noqa: BLE001 - the summary must not turn a clean stop into a traceback
        _say(f"cannot print the summary: {type(exc).__name__}: {exc}")
    if problems:
        _say(f"stopped with {len(problems)} problem(s): " + "; ".join(problems))
        return 1
    return 0


def _start_sinks(cfg: RunConfig, axes, sinks: list, mcap: tuple | None) -> None:
    """Start the Rerun sink (the slow one to start), then the MCAP sink, each in its own process
    (decoding, pairing, compression and disk never hold the estimator's GIL), appending each to
    ``sinks`` as soon as it runs (so that a failure later closes it); say where each writes."""
    from monitor.axes import live_meta

    common = dict(priority=cfg.sink_priority, start_timeout=cfg.sink_start_seconds,
                  stall_seconds=cfg.sink_stall_seconds)
    if cfg.rrd is not None or cfg.serve_rerun is not None:
        from monitor.sinks.forward import RerunForwardSink
        from monitor.sinks.rerun_layout import describe_model

        info = {f"{a.model.machine}/{a.model.axis}": describe_model(a.model) for a in axes.values()}
        try:  # fed the bytes received and published (no second encoding)
            rs_ = RerunForwardSink(cfg.rrd, cfg.serve_rerun, axis_info=info, **common)
        except OSError as exc:
            raise OSError(_start_failed(exc, cfg, "run without --rrd/--serve-rerun")) from None
        sinks.append(rs_)
        if cfg.rrd:
            _say(f"Rerun recording: {cfg.rrd}")
        if rs_.server_uri:
            _say(f"Rerun live: rerun --connect {rs_.server_uri}")
    if mcap is not None:
        from monitor.sinks.mcap_sink import McapProcessSink

        path, rb, rs = mcap
        try:
            sink = McapProcessSink(path, rb, rs, metas=[live_meta(a) for a in axes.values()],
                                   min_free_bytes=int(cfg.min_free_mb * 2**20), **common)
        except OSError as exc:
            raise OSError(_start_failed(exc, cfg, "")) from None
        sinks.append(sink)
        rot = " (rotated" + (f" at {rb / 2**20:g} MB" if rb else "") + (f" / {rs / 60:g} min" if rs else "") \
            + "; the next files are numbered on)" if rb or rs else ""
        _say(f"MCAP log: {sink.first_file}{rot}")


def _start_failed(exc: OSError, cfg: RunConfig, other: str) -> str:
    """The error of a sink process that did not start, with what to do when it was only slow."""
    if "did not start in" not in str(exc):
        return str(exc)
    ways = ["try again", f"allow it more time with [run] sink_start_seconds in --config (now {cfg.sink_start_seconds:g} "
            "s)", *([other] if other else [])]
    return f"{exc}: " + ", or ".join(ways)


def _discard_empty_outputs(sinks) -> None:
    """After a failed start: remove the files the sinks made that hold nothing (no stub log is left behind)."""
    for s in sinks:
        try:
            st = s.status()
        except Exception:  # noqa: BLE001
            continue
        if st.get("written") or st.get("accepted"):
            continue
        for f in (st.get("files") or []) + (st.get("rrd_files") or []):
            try:
                os.unlink(f)
            except OSError:
                pass


#: Zenoh transmission queue (batches) of the estimates' priority (DATA_HIGH, Zenoh's default 2). Estimates
#: are published express, one batch each, with congestion control DROP (a slow subscriber never holds the
#: monitor): after a burst (a backlog worked off) two slots drop estimates a subscriber would have taken
#: 1 ms later; 16 (Zenoh's maximum) absorbs such bursts
ESTIMATE_TX_QUEUE = 16


def _estimate_queue(zconfig) -> None:
    """Raise the DATA_HIGH transmission queue to :data:`ESTIMATE_TX_QUEUE` unless the configuration
    (``--zenoh-config``) already set it larger."""
    key = "transport/link/tx/queue/size/data_high"
    try:
        now = int(json.loads(zconfig.get_json(key)))
    except (ValueError, TypeError):
        now = 0
    if now < ESTIMATE_TX_QUEUE:
        zconfig.insert_json5(key, str(ESTIMATE_TX_QUEUE))


def _summary(monitor) -> None:
    st = monitor.status()
    inp = st["input"]
    _say(f"input: {inp['received']} messages received, {inp['handled']} handled")
    for name, a in st["axes"].items():
        lat = a["latency_us"]
        when = f"latency p50 {lat['p50']} µs, p99 {lat['p99']} µs" if lat.get("p50") is not None \
            else "latency: no estimate published"
        _say(f"{name}: {a['blocks']} blocks, {a['samples_in']} samples in, {a['estimates_out']} estimates out, "
             f"{a['dropped_total']} dropped{' ' + str(a['drops']) if a['drops'] else ''}, {a['gaps']} gaps; {when}")
    refused = [f"{k}={inp[k]}" for k in ("too_large", "queue_full", "malformed", "key_mismatch_total",
                                         "shutdown_discarded") if inp.get(k)]
    nm = sum(inp["no_model"].values()) + inp["no_model_overflow"]
    if refused:
        _say("input refused (messages): " + ", ".join(refused))
    if nm:
        _say(f"samples of axes without a model (not estimated): {nm}")
    if st["status"]["refused"]:
        _say(f"status queries: {st['status']['served']} answered, {st['status']['refused']} refused (rate limit)")
    for s in st["sinks"]:
        files = s.get("files") or s.get("rrd_files") or ([s["rrd_path"]] if s.get("rrd_path") else [])
        extra = "".join(f", {s[k]} {k}" for k in ("restarts", "removed") if s.get(k))
        _say(f"sink {s['name']}: {s.get('offered', s['accepted'] + s['dropped'])} messages offered, {s['written']} "
             f"written, {s['dropped']} dropped, {s.get('lost', 0)} lost, {s['failures']} failures{extra}; "
             + (", ".join(map(str, files)) or "no file"))
        if s.get("incomplete_files"):
            _say(f"sink {s['name']}: incomplete files ({s.get('incomplete_note') or 'they end where writing stopped'}): "
                 f"{', '.join(map(str, s['incomplete_files']))}")
    process = monitor.pipeline.process
    for line in process.wear.report if process is not None and process.wear is not None else ():
        _say(f"wear {line}")
    for p in monitor.saved_states:
        _say(f"tracker state saved: {p}")
    for name in monitor.unsaved_states:
        _say(f"tracker state of {name} NOT saved: learned from input the monitor flagged (see the log above)")
