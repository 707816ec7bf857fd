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
    assert len(errors) == 2  # once per burst: {3, 4, 5} and {10}


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
    topics, msgs = _read_plain(str(path))
    assert topics == {f"/mill/{a}/{k}" for a in "XY" for k in ("samples", "disturbance")} | {"/mill/X/truth"}
    assert len(msgs) == 5 * n
    x = [m for t, m in msgs if t == "/mill/X/disturbance"]
    assert [m["seq"] for m in x] == [10 * k for k in range(n)]
    trial = read_trial(path, axis="Y")  # a monitor log is a trial file
    assert len(trial) == 10 * n and trial.meta.Ts == pytest.approx(TS)


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
    total = 0
    for f in files:
        _, msgs = _read_plain(f)
        total += len(msgs)
        seqs += [m["seq"] for t, m in msgs if t == "/mill/X/samples"]
    assert total == sent and seqs == [10 * k for k in range(120)]


def test_mcap_sink_time_rotation(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    sink = McapSink(tmp_path / "t.mcap", rotate_seconds=0.15, metas=[meta("X")], flush_seconds=0.05)
    for k in range(50):
        sink.offer(samples("X", 10 * k))
        time.sleep(0.01)
    assert sink.close(timeout=10)
    assert len(sink.files) >= 2
    assert sum(len(_read_plain(f)[1]) for f in sink.files) == 50


def test_mcap_sink_bad_block_is_a_counted_failure(tmp_path):
    from monitor.sinks.mcap_sink import McapSink

    sink = McapSink(tmp_path / "neg.mcap", metas=[meta("X")])
    bad = S.SampleBlock(machine="mill", axis="X", seq=0, t=[0.0], v_ref=[0.0], v_meas=[0.0])
    bad.t = [-1.0]  # the schema refuses it on construction; edited in place it reaches the sink's own check
    sink.offer(bad)
    sink.offer("not a block")
    sink.offer(samples("X", 0))
    assert sink.close(timeout=10)
    st = sink.status()
    assert st["failures"] == 2 and st["written"] == 1
    assert len(_read_plain(str(tmp_path / "neg.mcap"))[1]) == 1


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
    sink = cls(rrd_path=rrd, psd_interval=0.1, batch_interval=0.05)
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
    assert st["psd_updates"] >= 2 and st["batches"] > 20
    cli = _rerun_cli()
    ver = subprocess.run([cli, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=60)
    assert ver.returncode == 0, ver.stdout + ver.stderr
    out = subprocess.run([cli, "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for ax in "XY":
        for ent in ("velocity/measured", "velocity/predicted", "velocity/reference", "disturbance/estimate",
                    "disturbance/upper", "disturbance/lower", "variance/f", "dictionary/size",
                    "dictionary/removed", "residual/value", "residual/psd"):
            assert f"/mill/{ax}/{ent} " in out.stdout, f"/mill/{ax}/{ent} missing"
    assert "/mill/X/disturbance/truth " in out.stdout
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
