"""The live :class:`Monitor` in this process on real Zenoh sessions (loopback, free ports): input
queue bounded in messages and bytes, shutdown that always finishes (discards counted, tracker
state saved only after the estimator stopped, every failing step said), the status queryable
served from a cache and rate-limited."""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh
from live_monitor import KEY, Live
from test_bad_input import AXIS, PREFIX, ListSink, blocks_of
from truth_models import model_from_truth

from feedio import schema as S
from feedio import transport as T
from feedio.limits import InputLimits
from feedio.mcapio import read_trial
from monitor.axes import live_meta, load_axes
from monitor.daemon import Monitor
from monitor.sinks.mcap_sink import McapSink
from monitor.state import StateStore
from monitor.warm import warm_up
from replay.scenarios import load_scenario
from replay.simulator import simulate, write_trial


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("lifecycle")
    write_trial(simulate(load_scenario("shaker-constant", duration=4.0), seed=5), d / "trial.mcap")
    model_from_truth(d / "trial.mcap", d / "z.model.toml")
    return d


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _axes(work):
    axes = load_axes([work / "z.model.toml"])
    warm_up(axes)
    return axes


def _sample(payload: bytes, key: str = KEY):
    """What the Zenoh callback reads of a sample: its key and a real Zenoh payload buffer."""
    return SimpleNamespace(key_expr=key, payload=zenoh.ZBytes(payload))


def _big_blocks(trial, count: int) -> list[bytes]:
    """``count`` blocks of the whole trial each, seq and time continuing (much estimator work per message)."""
    n, span = len(trial), float(trial.t[-1] - trial.t[0]) + float(trial.meta.Ts)
    return [S.encode(S.SampleBlock(machine=trial.machine, axis=trial.axis, seq=k * n,
                                   t=(trial.t + k * span).tolist(), v_ref=trial.v_ref.tolist(),
                                   v_meas=trial.v_meas.tolist())) for k in range(count)]


# ---- the input queue ----------------------------------------------------------------------------
def test_input_queue_bounded_in_bytes_and_messages_and_size_checked_first(work):
    lim = InputLimits(max_message_bytes=16 * 1024, queue_bytes=32 * 1024, queue_messages=5)
    with T.open_session(listen=f"tcp/127.0.0.1:{T.free_tcp_port()}") as session:
        mon = Monitor(_axes(work), session, prefix=PREFIX, limits=lim)  # not started: nothing is taken off
        ten_k = b" " * 10_000
        for _ in range(4):
            mon._on_sample(_sample(ten_k))  # 3 fit in 32 KiB, the 4th does not
        mon._on_sample(_sample(b" " * (16 * 1024 + 1)))  # larger than max_message_bytes: refused before a copy
        mon._on_sample(_sample(b" " * 16, key=T.samples_key(PREFIX, "nobody", "Q")))  # fits: queued
        st = mon.status()
        assert st["input"]["received"] == 4 and st["input"]["pending"] == 4
        assert st["input"]["pending_bytes"] == 30_016 <= lim.queue_bytes
        assert st["input"]["queue_full"] == 1 and st["input"]["too_large"] == 1
        assert st["axes"][AXIS]["drops"] == {"input_queue_full": 1, "too_large": 1}
        for _ in range(3):
            mon._on_sample(_sample(b"x"))  # 5 messages: the count bound
        assert mon.status()["input"]["queue_full"] == 3
        mon.stop()  # never started: the queued messages are discarded and counted, no state is written
        mon._on_sample(_sample(b"x"))  # after stop: counted, not queued
        st = mon.status()
        assert st["input"]["shutdown_discarded"] == 6 and st["input"]["pending"] == 0 and mon.problems == []
        assert st["axes"][AXIS]["drops"]["shutdown_discarded"] == 5 and st["input"]["pending_bytes"] == 0


# ---- shutdown ----------------------------------------------------------------------------------
class _HeldSink(ListSink):
    """A sink whose ``offer`` waits until ``release`` is set (at most ``hold`` s): holds the estimator
    thread so that work is still queued when the test stops the monitor (no timing involved), or,
    held past the monitor's stop deadline, a sink that breaks its never-block promise."""

    def __init__(self, name: str, hold: float):
        super().__init__()
        self.name, self.hold = name, hold
        self.entered, self.release = threading.Event(), threading.Event()

    def offer(self, item):
        self.entered.set()
        self.release.wait(self.hold)
        return super().offer(item)


@pytest.mark.parametrize("drain", [60.0, 0.0], ids=["drained", "discarded"])
def test_stop_saves_state_only_after_the_estimator_stopped_and_counts_discards(work, trial, tmp_path, drain):
    axes = _axes(work)
    ax = axes[("linear-drive", "Z")]
    sink = _HeldSink("gate", hold=120.0)
    live = Live(axes, sinks=[sink], state=StateStore(tmp_path), drain_seconds=drain, finish_seconds=60.0)
    result: dict = {}
    try:
        blocks = _big_blocks(trial, 20)
        for b in blocks:
            live.pub.put(b)
        assert sink.entered.wait(30)  # the estimator holds the first block
        live.wait(lambda m: m.received == len(blocks))  # the other 19 are queued
        stopper = threading.Thread(target=lambda: result.update(problems=live.monitor.stop()))
        stopper.start()
        # drained: the queue is worked off after the gate opens; discarded: it is emptied first
        live.wait(lambda m: m.state == "stopping"
                  and (drain > 0 or m.status()["input"]["shutdown_discarded"] == len(blocks) - 1))
        sink.release.set()
        stopper.join(120)
        assert not stopper.is_alive()
    finally:
        sink.release.set()
        live.close()
    assert result["problems"] == [] and live.monitor.state == "stopped"
    assert not live.monitor._thread.is_alive()
    st = live.monitor.status()
    a = st["axes"][AXIS]
    discarded = a["drops"].get("shutdown_discarded", 0)
    assert a["blocks"] + discarded == len(blocks) == st["input"]["received"]
    assert st["input"]["shutdown_discarded"] == discarded and st["input"]["pending"] == 0
    assert discarded == (0 if drain > 0 else len(blocks) - 1)
    assert a["samples_in"] == a["blocks"] * len(trial)
    with np.load(tmp_path / "linear-drive+Z.state.npz", allow_pickle=False) as z:
        saved = int(z["estimator.trained"])
    assert saved == ax.estimator.trained == a["trained"] > 0  # the state of the stopped estimator, not a moment of it


def test_stuck_estimator_stop_finishes_without_saving_state(work, trial, tmp_path):
    """Large blocks go through the input queue to the estimator thread, which a sink breaking its
    never-block promise holds: the monitor keeps receiving and counting; stop gives up on the block
    in progress, discards the queue and saves no state."""
    sink = _HeldSink("stuck", hold=60.0)
    live = Live(_axes(work), sinks=[sink], state=StateStore(tmp_path), drain_seconds=0.2, finish_seconds=0.2)
    try:
        for b in _big_blocks(trial, 3):
            live.pub.put(b)
        assert sink.entered.wait(30)
        live.wait(lambda m: m.status()["input"]["pending"] >= 1)
        problems = live.monitor.stop()
        assert live.monitor.state == "stopped"
        assert any("did not stop" in p and "NOT saved" in p for p in problems), problems
        assert not (tmp_path / "linear-drive+Z.state.npz").exists()
        assert live.monitor.status()["input"]["shutdown_discarded"] >= 1
    finally:
        sink.release.set()
        live.close()


class _FailingStore(StateStore):
    """A real StateStore whose save fails with an error other than OSError (as a NUL in a path does)."""

    def save(self, ax):
        raise ValueError("embedded null byte")


class _BadClose(ListSink):
    name = "bad-close"

    def close(self, timeout=None):
        raise RuntimeError("sink exploded while closing")


def test_every_failing_shutdown_step_is_said_and_stop_still_finishes(work, trial, tmp_path):
    axes = _axes(work)
    out = tmp_path / "log.mcap"
    mcap = McapSink(out, metas=[live_meta(a) for a in axes.values()])
    live = Live(axes, sinks=[_BadClose(), mcap], state=_FailingStore(tmp_path))
    try:
        for b in blocks_of(trial, 0, 100):
            live.pub.put(S.encode(b))
        live.wait(lambda m: m.axes[("linear-drive", "Z")].status.last_seq == 99)
        problems = live.monitor.stop()
    finally:
        live.close()
    assert live.monitor.state == "stopped"
    assert len(problems) == 2, problems
    assert "closing sink bad-close failed: RuntimeError" in problems[0]
    assert "cannot save the tracker state of linear-drive/Z: ValueError: embedded null byte" in problems[1]
    assert len(read_trial(out)) == 100  # the sink after the failing one was still closed: a complete file
    assert live.monitor.stop() == problems  # idempotent


def test_model_with_a_name_messages_cannot_carry_is_refused_at_start(work, tmp_path, capsys):
    from feedmon.cli import main

    bad = tmp_path / "nul.model.toml"
    bad.write_text((work / "z.model.toml").read_text().replace('machine = "linear-drive"', 'machine = "mill\\u0000"'))
    assert main(["run", "--model", str(bad), "--listen", f"tcp/127.0.0.1:{T.free_tcp_port()}"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "not a valid name" in err and "\\x00" in err and "\x00" not in err


# ---- the status queryable ----------------------------------------------------------------------
def _ask(session) -> list[dict]:
    return [json.loads(r.ok.payload.to_bytes()) for r in session.get(T.status_key(PREFIX), timeout=5.0)
            if r.ok is not None]


def test_status_is_cached_and_rate_limited(work):
    live = Live(_axes(work), limits=InputLimits(status_refresh_s=60.0, status_rate=0.1, status_burst=3))
    try:
        deadline = time.monotonic() + 10
        first = _ask(live.s)
        while not first:  # the queryable's declaration takes a moment to arrive
            assert time.monotonic() < deadline
            first = _ask(live.s)
        answers = [first[0]] + [a for _ in range(5) for a in _ask(live.s)]
        st = live.monitor.status()
    finally:
        live.close()
    assert len(answers) == 3  # the burst; then no reply until tokens come back (one per 10 s)
    assert all(a == answers[0] for a in answers)  # one cached document (uptime, served and all)
    assert answers[0]["status"]["served"] == 1
    assert st["status"]["served"] == 3 and st["status"]["refused"] >= 3


def test_status_refresh_zero_rebuilds_every_reply(work):
    live = Live(_axes(work), limits=InputLimits(status_refresh_s=0.0))
    try:
        got = []
        deadline = time.monotonic() + 10
        while len(got) < 2:
            assert time.monotonic() < deadline
            got += _ask(live.s)
    finally:
        live.close()
    assert got[1]["status"]["served"] == got[0]["status"]["served"] + 1  # each reply built afresh
