"""Sinks with real components: queue semantics, MCAP files read by the plain mcap reader,
an .rrd file checked by the ``rerun`` CLI."""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from feedio import schema as S
from feedio.mcapio import read_trial
from feedio.transport import free_tcp_port
from monitor.sinks import QueuedSink

TS = 1.0 / 333.0


def samples(axis: str, seq: int, n: int = 10, machine: str = "mill") -> S.SampleBlock:
    t = [(seq + i) * TS for i in range(n)]
    v = [0.01 * math.sin(2 * math.pi * x) for x in t]
    return S.SampleBlock(machine=machine, axis=axis, seq=seq, t=t, v_ref=v, v_meas=[x * 0.99 for x in v])


def estimates(axis: str, seq: int, n: int = 10, machine: str = "mill") -> S.EstimateBlock:
    t = [(seq + i) * TS for i in range(n)]
    rng = np.random.default_rng(seq)
    res = (1e-4 * rng.standard_normal(n)).tolist()
    f = [1e-3 * math.sin(2 * math.pi * 55 * x) for x in t]
    return S.EstimateBlock(
        machine=machine, axis=axis, seq=seq, t=t, v_meas=[0.01] * n, v_pred=[0.0101] * n, residual=res,
        f=f, f_var=[1e-8] * n, f_next=f, f_next_var=[1e-8] * n,
        dict_size=[min(60, seq + i + 1) for i in range(n)],
        removed=[(seq + i) % 60 if seq + i >= 60 else -1 for i in range(n)],
        flags=[S.REDUCED if (seq + i) % 97 == 0 else 0 for i in range(n)],
    )


def truth(seq: int, n: int = 10) -> S.TruthBlock:
    t = [(seq + i) * TS for i in range(n)]
    return S.TruthBlock(seq=seq, t=t, force=[30.0] * n, f=[-9e-4] * n)


def meta(axis: str, machine: str = "mill") -> S.TrialMeta:
    return S.TrialMeta(Ts=TS, form="velocity-loop", machine=machine, axis=axis,
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))


# ---- QueuedSink --------------------------------------------------------------------------------
class SlowSink(QueuedSink):
    def __init__(self, delay: float, **kw):
        self.delay = delay
        self.items: list = []
        self.finished = False
        super().__init__(**kw)

    def handle(self, item):
        time.sleep(self.delay)
        self.items.append(item)

    def finish(self):
        self.finished = True


class FlakySink(QueuedSink):
    """Fails on the items in ``bad``."""

    def __init__(self, bad: set, **kw):
        self.bad = bad
        self.items: list = []
        super().__init__(**kw)

    def handle(self, item):
        if item in self.bad:
            raise RuntimeError(f"disk on fire at item {item}")
        self.items.append(item)


def test_offer_never_blocks_on_a_slow_sink_and_counts_drops():
    sink = SlowSink(0.02, maxsize=8, name="slow")
    try:
        worst = 0.0
        for i in range(300):
            t0 = time.perf_counter()
            sink.offer(i)
            worst = max(worst, time.perf_counter() - t0)
        st = sink.status()
        print(f"worst offer() time {worst * 1e6:.0f} µs; {st}")
        assert worst < 0.02  # far below one slow write
        assert st["accepted"] + st["dropped"] == 300
        assert st["dropped"] > 200
        assert st["pending"] <= 8
    finally:
        assert sink.close(timeout=10)
    st = sink.status()
    assert sink.finished and st["state"] == "closed"
    assert st["written"] == st["accepted"] == len(sink.items)  # close drained the queue
    assert sink.items == sorted(sink.items)
    assert sink.offer(1) is False  # closed: refused and counted
    assert sink.status()["dropped"] == st["dropped"] + 1


def test_failing_sink_is_reported_not_fatal(caplog):
    bad = {3, 4, 5, 10}
    with caplog.at_level(logging.ERROR, logger="monitor.sinks"):
        sink = FlakySink(bad, maxsize=100, name="flaky")
        for i in range(6):
            assert sink.offer(i)
        deadline = time.monotonic() + 10
        while sink.status()["written"] + sink.status()["failures"] < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
        st = sink.status()
        assert st["state"] == "failed" and st["failures"] == 3
        assert "disk on fire at item 5" in st["last_error"]
        assert sink.alive
        for i in range(6, 12):
            sink.offer(i)
        assert sink.close(timeout=10)
    st = sink.status()
    assert st["failures"] == 4 and st["written"] == 8
    assert sink.items == [0, 1, 2, 6, 7, 8, 9, 11]
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR and "flaky" in r.getMessage()]
    # the first failure at once (a traceback: RuntimeError is no known condition of the outside world); the
    # rest ({4, 5}, the burst {10}, the two recoveries), within the rate limit's 30 s, counted and said in one
    # line when the sink closed
    assert len(errors) == 2 and "disk on fire at item 3" in errors[0].getMessage() and errors[0].exc_info
    assert "3 more failure(s), 2 recover(ies)" in errors[1].getMessage() and "item 10" in errors[1].getMessage()


def test_exception_in_finish_and_tick_is_counted():
    class Bad(QueuedSink):
        def handle(self, item):
            pass

        def tick(self, now):
            raise OSError("tick")

        def finish(self):
            raise OSError("finish")

    sink = Bad(maxsize=4, tick_interval=0.01)
    time.sleep(0.05)
    assert sink.close(timeout=10)
    st = sink.status()
    assert st["failures"] >= 2 and "finish" in st["last_error"]


# ---- McapSink -------------------------------------------------------------------------------------
def _read_plain(path: str):
    """Every message of an MCAP file with the plain mcap reader; asserts a jsonschema on every channel."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        for ch in summary.channels.values():
            assert ch.schema_id != 0, f"channel {ch.topic} has no schema"
            sch = summary.schemas[ch.schema_id]
            assert sch.encoding == "jsonschema" and json.loads(sch.data)["type"] == "object"
            assert ch.message_encoding == "json"
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in reader.iter_messages()]
        topics = {c.topic for c in summary.channels.values()}
    return topics, msgs


def test_mcap_sink_writes_samples_and_estimates_of_every_axis(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    path = tmp_path / "run.mcap"
    sink = McapSink(path, metas=[meta("X"), meta("Y")])
    n = 50
    for k in range(n):
        for ax in "XY":
            assert sink.offer(samples(ax, 10 * k))
            assert sink.offer(estimates(ax, 10 * k))
        sink.offer_truth("mill", "X", truth(10 * k))
    assert sink.close(timeout=10)
    st = sink.status()
    assert st["failures"] == 0 and st["written"] == 5 * n and st["files"] == [str(path)]
    assert st["scalars_written"] == 2 * 10 * n and st["incomplete_files"] == [] and st["messages_lost"] == 0
    topics, msgs = _read_plain(str(path))
    assert topics == ({f"/mill/{a}/{k}" for a in "XY" for k in ("samples", "disturbance", "disturbance/scalars")}
                      | {"/mill/X/truth"})
    blocks = [(t, m) for t, m in msgs if not t.endswith("/scalars")]
    assert len(blocks) == 5 * n
    x = [m for t, m in blocks if t == "/mill/X/disturbance"]
    assert [m["seq"] for m in x] == [10 * k for k in range(n)]
    trial = read_trial(path, axis="Y")  # a monitor log is a trial file
    assert len(trial) == 10 * n and trial.meta.Ts == pytest.approx(TS)


def test_mcap_sinks_given_one_file_never_share_nor_overwrite_it(tmp_path):
    """Two MCAP logs given the same file at the same time, a third given a rotated name that exists: with
    ``exclusive`` (what ``feedmon run`` uses) every file is created exclusively, so each sink writes its own (the next free name), complete, and an existing
    file is never overwritten."""
    from monitor.sinks.mcap_sink import McapSink

    path = tmp_path / "run.mcap"
    a, b = McapSink(path, metas=[meta("X")], exclusive=True), McapSink(path, metas=[meta("X")], exclusive=True)
    (tmp_path / "rot-000.mcap").write_bytes(b"not ours")
    c = McapSink(tmp_path / "rot.mcap", rotate_seconds=3600, metas=[meta("X")], exclusive=True)
    for sink, n in ((a, 3), (b, 5), (c, 7)):
        for k in range(n):
            assert sink.offer(samples("X", 10 * k))
    for sink in (a, b, c):
        assert sink.close(timeout=10)
    files = [sink.status()["files"] for sink in (a, b, c)]
    assert files == [[str(path)], [str(tmp_path / "run-001.mcap")], [str(tmp_path / "rot-001.mcap")]]
    assert [len(read_trial(f[0])) for f in files] == [30, 50, 70]
    assert (tmp_path / "rot-000.mcap").read_bytes() == b"not ours"
    assert [sink.status()["written"] for sink in (a, b, c)] == [3, 5, 7]


def test_mcap_sink_without_metas_infers_them_and_does_not_rotate_at_start(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    path = tmp_path / "live.mcap"
    sink = McapSink(path, discover_seconds=0.2)
    for k in range(20):
        sink.offer(samples("X", 10 * k))
        sink.offer(samples("Z", 10 * k))
    assert sink.close(timeout=10)
    assert sink.files == [str(path)]
    trial = read_trial(path, axis="Z")
    assert trial.meta.Ts == pytest.approx(TS) and trial.meta.provenance.details["inferred"] is True
    assert len(trial) == 200


def test_mcap_sink_rotation_produces_several_readable_files(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    path = tmp_path / "rot.mcap"
    sink = McapSink(path, rotate_bytes=6_000, metas=[meta("X")], flush_seconds=0.05)
    sent = 0
    for k in range(120):
        sink.offer(samples("X", 10 * k))
        sink.offer(estimates("X", 10 * k))
        sent += 2
        time.sleep(0.005)
    assert sink.close(timeout=10)
    files = sink.files
    print(f"{len(files)} files: {[os.path.getsize(f) for f in files]}")
    assert len(files) >= 3
    assert files[0].endswith("rot-000.mcap") and files[1].endswith("rot-001.mcap")
    seqs = []
    scalars = []
    total = 0
    for f in files:
        _, msgs = _read_plain(f)
        total += sum(not t.endswith("/scalars") for t, _ in msgs)
        seqs += [m["seq"] for t, m in msgs if t == "/mill/X/samples"]
        scalars += [m["seq"] for t, m in msgs if t.endswith("/scalars")]
    assert total == sent and seqs == [10 * k for k in range(120)]
    assert scalars == list(range(1200))  # one per sample, across the files, in order


def test_mcap_sink_time_rotation(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    sink = McapSink(tmp_path / "t.mcap", rotate_seconds=0.15, metas=[meta("X")], flush_seconds=0.05)
    for k in range(50):
        sink.offer(samples("X", 10 * k))
        time.sleep(0.01)
    assert sink.close(timeout=10)
    assert len(sink.files) >= 2
    assert sum(len(_read_plain(f)[1]) for f in sink.files) == 50  # samples only: no estimates, no scalars


def test_mcap_sink_bad_block_is_a_counted_failure(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    sink = McapSink(tmp_path / "neg.mcap", metas=[meta("X")])
    # the schema refuses these on construction; edited in place they reach the sink's own checks
    bad = S.SampleBlock(machine="mill", axis="X", seq=0, t=[0.0], v_ref=[0.0], v_meas=[0.0])
    bad.seq, bad.t = 2**60, [-1.0]
    absurd_t = S.SampleBlock(machine="mill", axis="X", seq=10, t=[0.0, 1.0], v_ref=[0.0] * 2, v_meas=[0.0] * 2)
    absurd_t.t = [2e10, -1e300]
    sink.offer(bad)  # seq beyond the schema: refused by the writer
    sink.offer("not a block")
    sink.offer(samples("X", 0))
    sink.offer(absurd_t)  # times beyond the schema: refused by the writer's validation (the pipeline refuses them first)
    sink.offer(samples("X", 12))
    assert sink.close(timeout=10)
    st = sink.status()
    assert st["failures"] == 3 and st["written"] == 2
    assert st["incomplete_files"] == [] and st["messages_lost"] == 0
    assert [m["seq"] for _, m in _read_plain(str(tmp_path / "neg.mcap"))[1]] == [0, 12]


def _scalars_plain(path) -> list[tuple[int, str, dict]]:
    """(log_time, topic, message) of every scalars message, read with the plain mcap reader."""
    with open(path, "rb") as f:
        return [(m.log_time, ch.topic, json.loads(m.data))
                for _, ch, m in make_reader(f).iter_messages(log_time_order=False) if ch.topic.endswith("/scalars")]


def _numbers_only(msg: dict) -> None:
    for k, v in msg.items():
        assert isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v), (k, v)


def test_mcap_sink_scalars_one_message_per_sample_paired_in_time(tmp_path):
    """disturbance/scalars: one message per sample with plain numbers; message k holds row k+1's filtered
    values (they describe sample k), row k's prediction and the truth of sample k; log times are wall-clock
    (after 2020), increasing per axis, the last sample of a block at its receive time."""
    import time as _time

    from monitor.sinks.mcap_sink import McapSink

    path = tmp_path / "sc.mcap"
    sink = McapSink(path, metas=[meta("X"), meta("Y")])
    n, t_start = 40, _time.time_ns()
    rx = {}
    for k in range(n):
        rx[k] = t_start + k * 30_000_000  # blocks received 30 ms apart (10 samples at 3 ms)
        for ax in "XY":
            sink.offer(samples(ax, 10 * k), received_ns=rx[k])
            est = estimates(ax, 10 * k)
            if k == 7:
                est.force = [float(i) for i in range(10)]
                est.force_var = [4.0] * 10
                est.force_next = [0.5] * 10
                est.f = [math.nan if i == 3 else x for i, x in enumerate(est.f)]  # missing: left out, never null
            sink.offer(est, received_ns=rx[k])
        sink.offer_truth("mill", "X", truth(10 * k), received_ns=rx[k])
    assert sink.close(timeout=10)
    got = _scalars_plain(path)
    rows = {(b.axis, b.seq + i): (b, i) for ax in "XY" for k in range(n)
            for b in [estimates(ax, 10 * k)] for i in range(10)}
    for ax in "XY":
        mine = [(lt, m) for lt, tp, m in got if tp == f"/mill/{ax}/disturbance/scalars"]
        assert [m["seq"] for _, m in mine] == list(range(10 * n))  # one per sample, in order
        times = [lt for lt, _ in mine]
        assert times[0] > 1577836800 * 10**9 and all(b > a for a, b in zip(times, times[1:]))
        for lt, m in mine:
            _numbers_only(m)
            seq = m["seq"]
            k, i = divmod(seq, 10)
            assert lt == rx[k] - round((9 - i) * TS * 1e9)  # receive time minus the controller-time offset
            b, j = rows[(ax, seq)]
            assert m["t"] == b.t[j] and m["f_next"] == b.f_next[j] and m["flags"] == b.flags[j]
            if (ax, seq + 1) in rows and not (k == 7 and i == 2):
                nb, nj = rows[(ax, seq + 1)]
                assert m["f"] == nb.f[nj] and m["f_sd"] == pytest.approx(1e-4)  # the next row's filtered value
            if seq == 10 * n - 1:
                assert "f" not in m and "f_sd" not in m  # not known yet for the last sample: left out
            if k == 7 and i == 2:
                assert "f" not in m and m["f_sd"] == pytest.approx(1e-4)  # NaN: left out, never null
            if ax == "X":
                assert m["truth_force"] == 30.0 and m["truth_f"] == -9e-4
            else:
                assert "truth_force" not in m
    x7 = {m["seq"]: m for _, tp, m in got if tp == "/mill/X/disturbance/scalars" and 69 <= m["seq"] <= 79}
    assert x7[71]["force"] == 2.0 and x7[71]["force_sd"] == 2.0 and x7[71]["force_next"] == 0.5
    assert "force" in x7[69] and x7[69]["force"] == 0.0 and "force_next" not in x7[69]  # row 70 filtered, row 69 none
    assert "force" not in x7[79] and x7[79]["force_next"] == 0.5


_FULL_DISK_SINK = """
import json, os, resource, signal, sys, time
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
sys.path.insert(0, sys.argv[2])
from test_sinks import meta, samples
from monitor.sinks.mcap_sink import McapSink
resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, resource.RLIM_INFINITY))  # every file stops at 30 kB
sink = McapSink(sys.argv[1], metas=[meta("X")], flush_seconds=0.02, max_pending_bytes=20_000, scalars=False)
for k in range(600):
    assert sink.offer(samples("X", 10 * k))
    if k % 50 == 0:
        time.sleep(0.05)
    if k == 450:  # space comes back: the file open now finishes properly
        resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
sink.close(timeout=30)
print(json.dumps(sink.status()))
"""


def test_mcap_sink_gives_up_a_refused_file_and_goes_on_in_a_fresh_one(tmp_path):
    """Every file is limited to 30 kB (RLIMIT_FSIZE, in a subprocess): when more than max_pending_bytes
    wait for the disk, the sink gives the file up (it ends on its last complete record, listed in
    incomplete_files) and the next block opens a fresh file; once the limit is lifted the file then open
    is finished properly. Counters never go back; every block
    accepted is either in a file (recover finishes the given-up ones without a damaged byte) or counted
    in messages_lost."""
    from replay.recover import recover

    r = subprocess.run([sys.executable, "-c", _FULL_DISK_SINK, str(tmp_path / "log.mcap"), str(Path(__file__).parent)],
                       capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))
    assert r.returncode == 0, r.stderr
    st = json.loads(r.stdout)
    assert st["accepted"] == 600 and st["dropped"] == 0
    assert st["failures"] > 0 and "File too large" in st["last_error"] and st["flush_failures"] > 0
    assert len(st["incomplete_files"]) >= 2 and len(st["files"]) > len(st["incomplete_files"])
    found = []
    for f in st["files"]:
        if f in st["incomplete_files"]:
            rep = recover(f, f + ".fixed")
            assert rep.skipped_ranges == 0 and rep.bytes_dropped == 0, rep.summary()
            f += ".fixed"
        found += [m["seq"] for _, m in _read_plain(f)[1]]
    assert found == sorted(found) and len(set(found)) == len(found)
    assert len(found) + st["messages_lost"] == 600


# ---- RerunSink ---------------------------------------------------------------------------------------
def _rerun_cli() -> str:
    exe = Path(sys.executable).with_name("rerun")
    if exe.exists():
        return str(exe)
    found = shutil.which("rerun")
    if not found:
        pytest.fail("the rerun CLI (installed with rerun-sdk) is missing: pip install -e '.[dev]'")
    return found


@pytest.mark.parametrize("where", ["in-process", "child-process"])
def test_rerun_sink_rrd_verifies_and_has_the_entities(tmp_path, where):
    from monitor.sinks.rerun_process import RerunProcessSink
    from monitor.sinks.rerun_sink import RerunSink

    rrd = tmp_path / "mon.rrd"
    cls = RerunSink if where == "in-process" else RerunProcessSink
    sink = cls(rrd_path=rrd, psd_every=200, batch_interval=0.05)
    for k in range(60):
        for ax in "XY":
            sink.offer(samples(ax, 10 * k))
            sink.offer(estimates(ax, 10 * k))
        sink.offer_truth("mill", "X", truth(10 * k))
        time.sleep(0.004)
    assert sink.close(timeout=20)
    st = sink.status()
    assert st["failures"] == 0, st["last_error"]
    assert st["written"] == 300
    if where == "child-process":  # the child's own RerunSink reports at the end
        assert not st["process_alive"]
        st = st["child"]
        assert st["written"] == 300 and st["undecodable"] == 0 and st["failures"] == 0
    assert st["psd_updates"] >= 2 and st["batches"] >= 5  # samples + estimates of 2 axes, truth of 1
    cli = _rerun_cli()
    ver = subprocess.run([cli, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=60)
    assert ver.returncode == 0, ver.stdout + ver.stderr
    out = subprocess.run([cli, "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for ax in "XY":  # these blocks carry no force (no loop gain): the disturbance in µm/s
        for ent in ("velocity/measured", "velocity/predicted", "velocity/reference", "disturbance/estimate",
                    "disturbance/upper", "disturbance/lower", "disturbance/prediction", "sigma/estimate",
                    "sigma/prediction", "dictionary/size", "dictionary/pruned", "dictionary/reduced",
                    "residual_psd/residual", "disturbance_psd/estimate", "events"):
            assert f"/mill/{ax}/{ent} " in out.stdout, f"/mill/{ax}/{ent} missing"
    assert "/mill/X/disturbance/actual " in out.stdout  # the truth (constant here: no spectrum of it)
    assert "Blueprint" in out.stdout  # the layout travels with the file


def test_rerun_sink_grpc_server_without_viewer(tmp_path):
    from monitor.sinks.rerun_sink import RerunSink

    port = free_tcp_port()
    sink = RerunSink(serve_port=port, memory_limit="64MB")
    try:
        assert str(port) in sink.server_uri
        for k in range(20):
            sink.offer(estimates("X", 10 * k))
    finally:
        assert sink.close(timeout=20)
    assert sink.status()["failures"] == 0
