"""The monitor's fast paths (issue 13) with real components: estimate JSON made from the columns, the
per-stage latency rings and their status, estimation in the Zenoh callback next to the input queue
(same estimates either way), the MCAP log in its own process (the same messages as in-process), and
``run --from`` over several processes (the same file, byte for byte, as one process)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
from live_monitor import Live
from mcap.reader import make_reader
from test_bad_input import AXIS, ListSink, blocks_of, rows
from truth_models import model_from_truth, truth_workdir

from feedio import schema as S
from feedio.mcapio import TrialWriter, iter_blocks, read_trial
from monitor.axes import live_meta, load_axes
from monitor.daemon import INLINE_BYTES
from monitor.estimate_rows import EstimateRows
from monitor.offline import run_offline
from monitor.pipeline import Pipeline
from monitor.sinks.mcap_sink import McapProcessSink, McapSink
from monitor.status import STAGES, StageRing, format_status
from monitor.status_doc import AxisReport, StatusDoc
from monitor.warm import warm_up
from replay.scenarios import load_scenario
from replay.simulator import simulate, write_trial


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "fast_paths", duration=3.0, seed=11)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


# ---- the estimate JSON -----------------------------------------------------------------------------
@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("n", [1, 3, 57])
def test_estimate_json_from_the_columns_is_the_schema_encoding(force, n):
    rng = np.random.default_rng(n)
    rows_ = rng.standard_normal((6, n)) * 10.0 ** rng.integers(-300, 300, (6, n))
    rows_[rng.random(rows_.shape) < 0.2] = np.nan
    rows_[0, 0] = -0.0
    if n > 2:
        rows_[1, 1], rows_[2, 2] = np.inf, -np.inf
    irows = rng.integers(-1, 2**40, (3, n))
    fc = rng.standard_normal((3, n)) if force else None
    t = np.arange(n) * 0.003 + 1e9
    est = EstimateRows("mill-1", "X.2", 2**53 - n, t, rng.standard_normal(n), rows_, irows, fc)
    assert est.json() == S.encode(est.block())
    back = S.decode_estimates(est.json())
    assert back.seq == est.seq and len(back.t) == n and (back.force is not None) == force


def test_estimator_rows_are_the_estimate_block(trial, work):
    axes = load_axes([work / "z.model.toml"])
    ax = next(iter(axes.values()))
    for b in blocks_of(trial, 0, 400, 37):
        est = ax.estimator.process_rows(b)
        blk = est.block()
        assert est.json() == S.encode(blk)
        cols = est.scalar_columns()
        np.testing.assert_array_equal(cols["f_var"], np.array(blk.f_var, dtype=float))
        np.testing.assert_array_equal(cols["force"], np.array(blk.force, dtype=float))
        np.testing.assert_array_equal(cols["flags"], blk.flags)


# ---- the stage rings ---------------------------------------------------------------------------------
def test_stage_ring_is_fixed_size_and_summarises_each_stage():
    ring = StageRing(size=100)
    assert ring.summary()["decode"] == {"p50": None, "p99": None}
    for i in range(1000):
        ring.record(0.0, (i % 100 + 1) * 1e-6, 1e-6, 2e-6, 3e-6, 4e-6)
    assert ring.count == 1000 and ring.values().shape == (len(STAGES), 100)
    s = ring.summary()
    assert set(s) == set(STAGES) and s["queue"]["p50"] == 0.0
    assert 49 <= s["decode"]["p50"] <= 52 and 98 <= s["decode"]["p99"] <= 100 and s["sinks"]["p99"] == 4.0


# ---- the live monitor: inline and queued -----------------------------------------------------------
@pytest.mark.parametrize("inline_bytes", [1 << 20, 0], ids=["in-callback", "queued"])
def test_live_estimates_equal_the_pipeline_whether_in_the_callback_or_queued(work, trial, inline_bytes):
    """One-sample messages: estimated in the Zenoh callback when it is idle (inline_bytes large) or all
    through the queue and the estimator thread (inline_bytes 0): the same rows as the Pipeline run in
    this process on the same blocks; every message counted once; the status shows each stage."""
    axes = load_axes([work / "z.model.toml"])
    warm_up(axes)
    sink = ListSink()
    live = Live(axes, sinks=[sink], inline_bytes=inline_bytes)
    blocks = blocks_of(trial, 0, 300, 1)
    try:
        for b in blocks:
            live.pub.put(S.encode(b))
        live.wait(lambda m: m.axes[("linear-drive", "Z")].status.stages.count == 300)  # recorded last per message
        st = live.monitor.status()
    finally:
        assert live.close() == []
    ref = Pipeline(load_axes([work / "z.model.toml"]))
    want = rows(r.est.block() for r in map(ref.estimate, blocks) if r.est is not None)
    got = rows(sink.estimates)
    assert set(got) == set(want)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    # the document is the typed StatusDoc, its keys in the Structs' order (what `feedmon status --json` prints)
    typed = msgspec.convert(st, StatusDoc)
    assert list(st) == list(StatusDoc.__struct_fields__) and typed.input.received == 300
    assert list(st["axes"][AXIS]) == list(AxisReport.__struct_fields__)
    inp = st["input"]
    assert inp["received"] == inp["handled"] == 300 and inp["pending"] == 0
    if inline_bytes:
        assert inp["inline"] >= 1  # messages arriving while another is estimated still queue (counted in both)
    else:
        assert inp["inline"] == 0
    a = st["axes"][AXIS]
    assert a["latency_us"]["count"] == 300 and set(a["stages_us"]) == set(STAGES)
    assert all(v["p50"] is not None and v["p50"] >= 0 for v in a["stages_us"].values())
    assert st["stages_us"]["estimate"]["p50"] > 0


def test_status_table_shows_the_stages(work, capsys):
    from rich.console import Console

    ring = StageRing()
    ring.record(1e-5, 2e-5, 3e-5, 4e-5, 5e-5, 6e-5)
    doc = {"monitor": {"pid": 1}, "input": {}, "stages_us": ring.summary(),
           "axes": {"m/X": {"latency_us": {"p50": 150.0, "p99": 210.0}, "stages_us": ring.summary()}}}
    format_status(doc, Console(width=200, force_terminal=False))
    out = capsys.readouterr().out
    assert "latency by stage" in out and all(s in out for s in STAGES)
    assert "10" in out and "60" in out


def test_large_blocks_queue_behind_the_message_in_progress_and_are_all_estimated(work, trial):
    axes = load_axes([work / "z.model.toml"])
    warm_up(axes)
    big = [S.encode(b) for b in blocks_of(trial, 0, 998, 499)]
    assert all(len(p) > INLINE_BYTES for p in big), [len(p) for p in big]
    live = Live(axes)
    try:
        for p in big:
            live.pub.put(p)
        live.wait(lambda m: m.axes[("linear-drive", "Z")].status.last_seq == 997)
        st = live.monitor.status()
    finally:
        assert live.close() == []
    assert st["input"]["inline"] == 0 and st["input"]["handled"] == 2  # over INLINE_BYTES: the queue
    assert st["axes"][AXIS]["estimates_out"] == 998


# ---- the MCAP log in its own process ---------------------------------------------------------------
def _messages(path) -> list[tuple]:
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, m.sequence, m.data) for _, ch, m in make_reader(f).iter_messages(
            log_time_order=False)]


def test_mcap_log_in_its_own_process_holds_what_the_in_process_sink_writes(work, trial, tmp_path):
    """The same blocks, estimates and truth with the same receive times through McapSink and through
    McapProcessSink (bytes over a pipe, decoded and written in the child): the same messages, scalars
    included, and the child's counters in the status; an undecodable frame is counted, not fatal."""
    axes = load_axes([work / "z.model.toml"])
    ax = next(iter(axes.values()))
    metas = [live_meta(ax)]
    items = []
    # receive times an hour ahead: the live pairing releases a sample without its truth once it is older than
    # HOLD_NS by the wall clock, at whatever moment each sink ticks; stamps in the future keep both files
    # paired the same, whatever the load
    t0 = time.time_ns() + 3600 * 10**9
    for k, b in enumerate(blocks_of(trial, 0, 600, 25)):
        est = ax.estimator.process(b)
        tb = S.TruthBlock(seq=b.seq, t=b.t, force=[float(i) for i in range(len(b.t))], f=[0.0] * len(b.t))
        items.append((b, est, tb, t0 + k * 75_000_000))
    out = {}
    for name, cls in (("in", McapSink), ("child", McapProcessSink)):
        sink = cls(tmp_path / f"{name}.mcap", metas=metas)
        for b, est, tb, rx in items:
            assert sink.offer(b, received_ns=rx) and sink.offer(est, received_ns=rx)
            assert sink.offer_truth(ax.model.machine, ax.model.axis, tb, received_ns=rx)
        if name == "child":
            assert sink.offer_encoded(b"E", b"{not json", t0)
        assert sink.close(timeout=60)
        out[name] = sink.status()
    a, b = _messages(tmp_path / "in.mcap"), _messages(tmp_path / "child.mcap")
    assert len(a) == len(b) == 3 * len(items) + 600 and a == b
    st = out["child"]
    assert st["written"] == 3 * len(items) and st["scalars_written"] == 600 == out["in"]["scalars_written"]
    assert st["files"] == [str(tmp_path / "child.mcap")] and st["undecodable"] == 1 and st["failures"] == 1
    assert st["process_alive"] is False and st["state"] == "closed"


def test_mcap_process_sink_never_overwrites_and_says_when_it_cannot_create_its_file(tmp_path):
    """The path is taken (here by a directory): the child logs into the next free name instead; a directory
    that takes no new file at all (immutable: root ignores permission bits): the sink is not made, the error
    names the file and why (a failing writer later: tests/test_sink_faults.py)."""
    import subprocess

    target = tmp_path / "taken.mcap"
    target.mkdir()
    sink = McapProcessSink(target, metas=[_meta()], start_timeout=60)
    assert sink.first_file == str(tmp_path / "taken-001.mcap")
    for k in range(50):
        assert sink.offer(S.SampleBlock(machine="m", axis="X", seq=2 * k, t=[0.006 * k, 0.006 * k + 0.003],
                                        v_ref=[0.0, 0.0], v_meas=[0.0, 0.0]))
    assert sink.close(timeout=60)
    st = sink.status()
    assert st["written"] == st["accepted"] == 50 and st["failures"] == 0 and target.is_dir()
    locked = tmp_path / "locked"
    locked.mkdir()
    r = subprocess.run(["chattr", "+i", str(locked)], capture_output=True, text=True)
    assert r.returncode == 0, f"chattr +i is needed (root): {r.stderr}"
    try:
        with pytest.raises(OSError, match=r"MCAP logging process PermissionError: .*locked/log\.mcap"):
            McapProcessSink(locked / "log.mcap", metas=[_meta()], start_timeout=60)
    finally:
        subprocess.run(["chattr", "-i", str(locked)], capture_output=True)
    assert list(locked.iterdir()) == []


def test_mcap_process_sink_queue_is_bounded_in_bytes(tmp_path):
    sink = McapProcessSink(tmp_path / "b.mcap", metas=[_meta()], max_bytes=4096, start_timeout=60)
    try:
        assert not sink.offer_encoded(b"S", b" " * 5000, time.time_ns())  # more than the whole bound: refused
        assert sink.status()["dropped"] == 1 and sink.status()["accepted"] == 0
    finally:
        assert sink.close(timeout=60)
    assert sink.status()["queued_bytes"] == 0


def test_rerun_forward_sink_records_encoded_blocks(tmp_path):
    """The Rerun recording fed with encoded blocks (as the live monitor feeds it): the recording process
    decodes every one (no undecodable frame, no failure) and the file verifies with Rerun's CLI."""
    from test_sinks import _rerun_cli, estimates, samples, truth

    from monitor.sinks.forward import RerunForwardSink

    rrd = tmp_path / "fwd.rrd"
    sink = RerunForwardSink(rrd_path=rrd, psd_every=200, batch_interval=0.05)
    for k in range(40):
        rx = time.time_ns()
        assert sink.offer_encoded(b"S", S.encode(samples("X", 10 * k)), rx)
        assert sink.offer_encoded(b"E", S.encode(estimates("X", 10 * k)), rx)
        assert sink.offer_encoded(b"T", S.encode(truth(10 * k)), rx, b"mill\0X")
    assert sink.close(timeout=30)
    st = sink.status()
    assert st["failures"] == 0 and st["written"] == 120, st
    child = st["child"]
    assert child["written"] == 120 and child["undecodable"] == 0 and child["failures"] == 0
    ver = subprocess.run([_rerun_cli(), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=60)
    assert ver.returncode == 0, ver.stdout + ver.stderr
    out = subprocess.run([_rerun_cli(), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=60)
    assert "/mill/X/disturbance/estimate " in out.stdout and "/mill/X/disturbance/actual " in out.stdout


def _meta():
    return S.TrialMeta(Ts=0.003, form="velocity-loop", machine="m", axis="X",
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))


# ---- run --from over several processes ----------------------------------------------------------------
@pytest.fixture(scope="module")
def two_axes(tmp_path_factory):
    """A 2-axis trial (X shaker, Y milling with truth) with gaps, a repeated block and a NaN, and models."""
    import msgspec

    from replay.simulator import simulate_scenario

    d = tmp_path_factory.mktemp("two_axes")
    a = simulate(load_scenario("shaker-constant", duration=4.0), seed=1)
    b = simulate_scenario("milling-incdec", seed=2, duration=4.0, created="2024-05-01T08:00:00Z")
    write_trial(a, d / "a.mcap")
    write_trial(b, d / "b.mcap")
    ta, tb = read_trial(d / "a.mcap"), read_trial(d / "b.mcap")
    ma = msgspec.structs.replace(ta.meta, axis="X")
    mb = msgspec.structs.replace(tb.meta, axis="Y", machine=ma.machine)
    items = []
    for name, path in (("X", d / "a.mcap"), ("Y", d / "b.mcap")):
        for kind, blk in iter_blocks(path, kinds=("samples", "truth")):
            items.append((float(blk.t[-1]), name, kind, blk))
    items.sort(key=lambda x: (x[0], x[1]))
    y = 0  # Y's samples blocks so far
    with TrialWriter(d / "two.mcap", [ma, mb], start="2024-05-01T08:00:00Z") as w:
        for _, name, kind, blk in items:
            if kind == "truth":
                w.write_truth(blk, ma.machine, name)
                continue
            blk = msgspec.structs.replace(blk, machine=ma.machine, axis=name)
            if name == "Y":
                y += 1
                if y == 3:
                    continue  # a gap
                if y == 5:
                    vm = list(blk.v_meas)
                    vm[1] = None
                    blk = msgspec.structs.replace(blk, v_meas=vm)
            w.write_samples(blk)
            if name == "Y" and y == 7:
                w.write_samples(blk)  # re-sent
    for name, src in (("X", d / "a.mcap"), ("Y", d / "b.mcap")):
        model_from_truth(src, d / f"{name}.model.toml")
        tr = read_trial(src)
        text = (d / f"{name}.model.toml").read_text()
        text = text.replace(f'axis = "{tr.axis}"', f'axis = "{name}"').replace(
            f'machine = "{tr.machine}"', f'machine = "{ma.machine}"')
        (d / f"{name}.model.toml").write_text(text)
    return d


def _summary(axes) -> dict:
    return {f"{m}/{a}": (dict(ax.estimator.counters), dict(ax.status.counters), ax.estimator.tracker.size,
                         ax.estimator.trained, ax.status.blocks, ax.status.last_seq)
            for (m, a), ax in axes.items()}


def test_offline_over_processes_writes_the_one_process_file_byte_for_byte(two_axes):
    """jobs=2 with a thread running in this process: children spawned, building their estimators from the
    model files; the file is the one of jobs=1, byte for byte, and the axes end in the same state."""
    d = two_axes
    models = [d / "X.model.toml", d / "Y.model.toml"]
    one = load_axes(models)
    r1 = run_offline(d / "two.mcap", d / "one.mcap", one, jobs=1)
    stop = threading.Event()
    th = threading.Thread(target=stop.wait, daemon=True)  # a thread alive: spawn, not fork
    th.start()
    try:
        two = load_axes(models)
        r2 = run_offline(d / "two.mcap", d / "two-procs.mcap", two, jobs=2)
    finally:
        stop.set()
    assert r1.jobs == 1 and r2.jobs == 2
    assert (d / "one.mcap").read_bytes() == (d / "two-procs.mcap").read_bytes()
    assert (r1.samples, r1.estimates, r1.truth_blocks) == (r2.samples, r2.estimates, r2.truth_blocks)
    assert r1.health_reports == r2.health_reports > 0
    health = {a: [b for _, b in iter_blocks(d / "one.mcap", axis=a, kinds=("health",))] for a in "XY"}
    assert sum(map(len, health.values())) == r1.health_reports and all(health.values())
    assert _summary(one) == _summary(two)
    for key, ax in one.items():  # the health the workers' status ended with came back
        assert ax.status.health is not None
        assert {k: v for k, v in ax.status.health.items() if k != "since_unix"} == \
            {k: v for k, v in two[key].status.health.items() if k != "since_unix"}
    s = _summary(one)["linear-drive/Y"][0]
    assert s["gaps"] > 0 and s["duplicate"] > 0 and s["rejected_non_finite"] > 0  # the hard cases were there


def test_offline_with_config_overrides_is_not_spread_over_spawned_workers(two_axes, tmp_path):
    """Axes loaded with --config tracker overrides differ from their model files: a spawned worker would
    build them from the files, so the run stays in this process (jobs 1) and uses the overrides."""
    from types import SimpleNamespace

    from monitor.online_settings import TrackerOverride

    d = two_axes
    models = [d / "X.model.toml", d / "Y.model.toml"]
    cfg = SimpleNamespace(tracker=TrackerOverride(forgetting=0.99), adaptation=None, health=None)
    stop = threading.Event()
    th = threading.Thread(target=stop.wait, daemon=True)  # a thread alive: spawn, not fork
    th.start()
    try:
        r = run_offline(d / "two.mcap", tmp_path / "over.mcap", load_axes(models, cfg), jobs=2)
    finally:
        stop.set()
    plain = tmp_path / "plain.mcap"
    run_offline(d / "two.mcap", plain, load_axes(models), jobs=1)
    again = tmp_path / "again.mcap"
    run_offline(d / "two.mcap", again, load_axes(models, cfg), jobs=1)
    assert r.jobs == 1
    assert (tmp_path / "over.mcap").read_bytes() == again.read_bytes() != plain.read_bytes()


def test_offline_cli_forks_workers_and_writes_the_same_file(two_axes):
    """The command line (no other thread: workers forked) with --jobs 2 and --jobs 1: the same bytes."""
    d = two_axes
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    outs = []
    for jobs in (2, 1):
        out = d / f"cli-{jobs}.mcap"
        r = subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--from", str(d / "two.mcap"), "-o", str(out),
                            "--model", str(d / "X.model.toml"), "--model", str(d / "Y.model.toml"), "--jobs",
                            str(jobs)], capture_output=True, text=True, timeout=300, env=env)
        assert r.returncode == 0, r.stderr
        assert ("2 processes" in r.stdout) == (jobs == 2), r.stdout
        assert "linear-drive/Y:" in r.stderr and "gaps" in r.stderr  # the per-axis summary, counters from the workers
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


def test_jobs_option_is_checked(two_axes, tmp_path, capsys):
    from feedmon.cli import main

    base = ["run", "--from", str(two_axes / "two.mcap"), "-o", str(tmp_path / "o.mcap"), "--model",
            str(two_axes / "X.model.toml")]
    assert main([*base, "--jobs", "0"]) == 2
    assert "--jobs" in capsys.readouterr().err
    assert main(["run", "--model", str(two_axes / "X.model.toml"), "--jobs", "2"]) == 2
    assert "--jobs is for --from" in capsys.readouterr().err


def test_offline_worker_error_is_raised_clearly(two_axes, tmp_path):
    """A trial damaged after its first chunk: the worker's error reaches the caller (named file and
    offset), no hang, no partial success."""
    data = bytearray((two_axes / "two.mcap").read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    axes = load_axes([two_axes / "X.model.toml", two_axes / "Y.model.toml"])
    stop = threading.Event()
    th = threading.Thread(target=stop.wait, daemon=True)
    th.start()
    try:
        with pytest.raises(ValueError, match="bad.mcap"):
            run_offline(bad, tmp_path / "out.mcap", axes, jobs=2)
    finally:
        stop.set()


def test_scalars_channel_of_the_offline_file_is_per_sample_and_finite(two_axes):
    path = two_axes / "one.mcap"
    if not path.exists():
        run_offline(two_axes / "two.mcap", path, load_axes([two_axes / "X.model.toml", two_axes / "Y.model.toml"]),
                    jobs=1)
    with open(path, "rb") as f:
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]
    for axis in "XY":
        sc = [m for t, m in msgs if t == f"/linear-drive/{axis}/disturbance/scalars"]
        est = [m for t, m in msgs if t == f"/linear-drive/{axis}/disturbance"]
        assert len(sc) == sum(len(m["t"]) for m in est) > 0
        assert all(isinstance(v, (int, float)) and math.isfinite(v) for m in sc for v in m.values())


@pytest.mark.parametrize("priority", ["idle", "low"])
def test_sink_processes_run_below_the_monitor(tmp_path, priority):
    """The MCAP and Rerun processes yield the CPU to the monitor: 'idle' is Linux's SCHED_IDLE
    (they run only on a core nothing else wants), 'low' (default) nice 10 only; both are niced. A priority that is
    neither is refused before any process starts. Finishing moves them out of the idle class
    (:func:`monitor.sinks.child.leave_idle`), nice kept."""
    from monitor.sinks.child import leave_idle
    from monitor.sinks.rerun_process import RerunProcessSink

    base = os.getpriority(os.PRIO_PROCESS, 0)
    sinks = [McapProcessSink(tmp_path / "p.mcap", metas=[_meta()], start_timeout=60, priority=priority),
             RerunProcessSink(tmp_path / "p.rrd", start_timeout=60, priority=priority)]
    try:
        for sink in sinks:
            pid = sink._proc.pid
            policy = os.sched_getscheduler(pid)
            # (a child late at its start on a loaded host is moved out of the idle class: counted first)
            want = os.SCHED_IDLE if priority == "idle" and sink.idle_left == 0 else os.SCHED_OTHER
            assert policy == want, (sink.name, policy, sink.idle_left)
            assert os.getpriority(os.PRIO_PROCESS, pid) >= min(19, base + 10)
        for sink in sinks:  # what finishing does first: out of the idle class, so a busy machine cannot starve it
            pid = sink._proc.pid
            assert leave_idle(pid) >= (1 if priority == "idle" else 0)
            threads = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
            assert len(threads) > 1 and all(os.sched_getscheduler(t) == os.SCHED_OTHER for t in threads)
            assert os.getpriority(os.PRIO_PROCESS, pid) >= min(19, base + 10)
    finally:
        for sink in sinks:
            assert sink.close(timeout=60)
    with pytest.raises(ValueError, match="sink priority must be one of idle, low"):
        McapProcessSink(tmp_path / "q.mcap", metas=[_meta()], priority="realtime")
