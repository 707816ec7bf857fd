"""Replay of a small trial file over real Zenoh sessions on loopback."""

from __future__ import annotations

import math
import queue
import threading
import time

import pytest

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import TrialWriter
from kernels.errors import ParameterError
from replay.player import ReplayStats, _reblock, replay, scan_trial

TS = 1.0 / 333.0
N = 666  # 2 s of samples
BLOCK = 10
WAIT = 10.0


def _meta(axis: str) -> S.TrialMeta:
    return S.TrialMeta(Ts=TS, form="velocity-loop", machine="mill", axis=axis,
                       provenance=S.Provenance(source="simulated", tool="pytest", version="0", seed=1))


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    """2 s trial, axes X (with truth) and Y, blocks of 10 samples (the last one shorter)."""
    path = tmp_path_factory.mktemp("trial") / "trial.mcap"
    with TrialWriter(path, [_meta("X"), _meta("Y")]) as w:
        for seq in range(0, N, BLOCK):
            n = min(BLOCK, N - seq)
            t = [(seq + i) * TS for i in range(n)]
            for ax in "XY":
                v = [0.02 * math.sin(2 * math.pi * 0.5 * x) for x in t]
                w.write_samples(S.SampleBlock(machine="mill", axis=ax, seq=seq, t=t, v_ref=v, v_meas=v))
            w.write_truth(S.TruthBlock(seq=seq, t=t, force=[10.0] * n, f=[-3e-4] * n), "mill", "X")
    return path


@pytest.fixture
def sessions():
    """(monitor, publisher): the monitor-side peer listens, the replay peer connects."""
    endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
    mon = T.open_session(listen=endpoint)
    pub = None
    try:
        pub = T.open_session(connect=endpoint)
        yield mon, pub, endpoint
    finally:
        if pub is not None:
            pub.close()
        mon.close()


class Collector:
    """Subscriber on every samples/truth key; decoded blocks per key, in arrival order."""

    def __init__(self, session, prefix: str = "feedmon"):
        self.q: queue.Queue = queue.Queue()
        self.by_key: dict[str, list] = {}
        self.subs = [
            session.declare_subscriber(f"{prefix}/*/*/samples", lambda s: self.q.put((str(s.key_expr), s.payload.to_bytes()))),
            session.declare_subscriber(f"{prefix}/*/*/truth", lambda s: self.q.put((str(s.key_expr), s.payload.to_bytes()))),
        ]

    def samples(self, key: str) -> int:
        return sum(len(b.t) for b in self.by_key.get(key, []))

    def wait(self, want: dict[str, int], timeout: float = WAIT) -> None:
        deadline = time.monotonic() + timeout
        while any(self.samples(k) < n for k, n in want.items()) and time.monotonic() < deadline:
            try:
                key, data = self.q.get(timeout=0.1)
            except queue.Empty:
                continue
            dec = S.decode_truth if key.endswith("/truth") else S.decode_samples
            self.by_key.setdefault(key, []).append(dec(data))

    def close(self):
        for s in self.subs:
            s.undeclare()


def _check_contiguous(blocks, n: int, start: int = 0) -> None:
    seqs = [s for b in blocks for s in range(b.seq, b.seq + len(b.t))]
    assert seqs == list(range(start, start + n))  # every sample, in order
    ts = [x for b in blocks for x in b.t]
    assert all(b > a for a, b in zip(ts, ts[1:]))


def test_scan(trial):
    scan = scan_trial(trial)
    assert scan.axes == ["mill/X", "mill/Y"]
    assert scan.samples == {"mill/X": N, "mill/Y": N}
    assert scan.Ts == pytest.approx(TS)
    assert scan.duration == pytest.approx(N * TS)
    with pytest.raises(ValueError, match="no axis"):
        scan_trial(trial, "Q")


def test_replay_rate_10_every_sample_in_order(trial, sessions):
    mon, pub, _ = sessions
    col = Collector(mon)
    try:
        stats = replay(trial, pub, rate=10.0, wait_for_subscriber=WAIT)
        col.wait({"feedmon/mill/X/samples": N, "feedmon/mill/Y/samples": N, "feedmon/mill/X/truth": N})
    finally:
        col.close()
    print(f"rate 10: {stats.samples} samples, wall {stats.wall_time:.3f} s for {stats.duration:.3f} s of trial "
          f"(ideal {stats.duration / 10:.3f} s), worst lateness {stats.max_lateness * 1e3:.1f} ms")
    assert isinstance(stats, ReplayStats) and stats.matched and not stats.interrupted
    assert stats.samples == 2 * N and stats.blocks == 2 * math.ceil(N / BLOCK)
    assert stats.truth_blocks == math.ceil(N / BLOCK) and stats.passes == 1
    for key in ("feedmon/mill/X/samples", "feedmon/mill/Y/samples", "feedmon/mill/X/truth"):
        _check_contiguous(col.by_key[key], N)
    assert col.by_key["feedmon/mill/X/samples"][0].v_ref[:3] == pytest.approx(
        [0.02 * math.sin(2 * math.pi * 0.5 * k * TS) for k in range(3)])
    # timed: at least the scaled duration (sleep-until never runs early), loosely bounded above
    assert stats.wall_time >= 0.9 * (N - BLOCK) * TS / 10
    assert stats.wall_time < 5.0


def test_replay_max_is_faster_and_reblocks_and_loops(trial, sessions):
    mon, pub, _ = sessions
    col = Collector(mon)
    try:
        t_rate = replay(trial, pub, rate=10.0, axis="X", truth=False, wait_for_subscriber=WAIT)
        col.wait({"feedmon/mill/X/samples": N})
        col.by_key.clear()
        stats = replay(trial, pub, rate=None, block=7, loop=2, axis="mill/X", wait_for_subscriber=WAIT)
        col.wait({"feedmon/mill/X/samples": 2 * N, "feedmon/mill/X/truth": 2 * N})
    finally:
        col.close()
    print(f"--max: wall {stats.wall_time:.3f} s for 2 passes; rate 10: wall {t_rate.wall_time:.3f} s for 1 pass")
    assert stats.rate is None and stats.passes == 2 and stats.samples == 2 * N
    assert stats.wall_time < t_rate.wall_time
    blocks = col.by_key["feedmon/mill/X/samples"]
    per_pass = [7] * (N // 7) + ([N % 7] if N % 7 else [])  # re-cut per pass
    assert [len(b.t) for b in blocks] == per_pass * 2
    _check_contiguous(blocks, 2 * N)  # pass 2 continues seq and time
    assert blocks[-1].t[-1] == pytest.approx((2 * N - 1) * TS)
    _check_contiguous(col.by_key["feedmon/mill/X/truth"], 2 * N)
    assert "feedmon/mill/Y/samples" not in col.by_key


def test_replay_progress_callback_counts_up_to_the_total(trial, sessions):
    """``progress(sent, total)``: (0, total) when sending starts, then after every sample block a growing
    count, ending at the total (two axes, two passes, re-cut into blocks of 7)."""
    mon, pub, _ = sessions
    col = Collector(mon)
    calls: list[tuple[int, int | None]] = []
    try:
        stats = replay(trial, pub, rate=None, block=7, loop=2, truth=False, wait_for_subscriber=WAIT,
                       progress=lambda sent, total: calls.append((sent, total)))
        col.wait({"feedmon/mill/X/samples": 2 * N, "feedmon/mill/Y/samples": 2 * N})
    finally:
        col.close()
    total = 2 * 2 * N
    assert stats.samples == total and stats.blocks == 2 * 2 * math.ceil(N / 7)
    assert calls[0] == (0, total) and calls[-1] == (total, total)
    assert len(calls) == stats.blocks + 1 and {t for _, t in calls} == {total}
    steps = [b[0] - a[0] for a, b in zip(calls, calls[1:])]
    assert all(0 < d <= 7 for d in steps) and sum(steps) == total


def test_cli_progress_bar_is_fed_by_the_callback(trial, sessions, capsys):
    """``feedmon replay``'s rich bar (:class:`feedmon.replay_cmd.ProgressBar`) as the library's callback: it
    ends at every sample of the replay."""
    from feedmon.replay_cmd import ProgressBar

    mon, pub, _ = sessions
    col = Collector(mon)
    try:
        with ProgressBar(trial) as bar:
            stats = replay(trial, pub, rate=None, axis="X", truth=False, wait_for_subscriber=WAIT, progress=bar)
        col.wait({"feedmon/mill/X/samples": N})
    finally:
        col.close()
    out = capsys.readouterr().out
    assert stats.samples == N and "replay trial.mcap" in out and f"{N}/{N} samples" in out


def test_replay_bad_arguments_name_the_parameter(trial, sessions):
    _, pub, _ = sessions
    for kwargs, name in (({"rate": 0.0}, "rate"), ({"block": 0}, "block"), ({"loop": 0}, "loop"),
                         ({"progress": True}, "progress")):
        with pytest.raises(ParameterError, match=f"^{name} must be") as err:
            replay(trial, pub, **kwargs)
        assert err.value.parameters == (name,) and "--" not in str(err.value)


def test_replay_stop_event_and_no_subscriber(trial, sessions):
    _, pub, _ = sessions
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    t0 = time.monotonic()
    calls: list[tuple[int, int | None]] = []
    stats = replay(trial, pub, rate=1.0, loop=True, prefix="nobody", wait_for_subscriber=0.05, stop=stop,
                   progress=lambda sent, total: calls.append((sent, total)))
    assert time.monotonic() - t0 < WAIT
    assert stats.interrupted and not stats.matched and stats.passes == 0
    assert 0 < stats.samples < 2 * N
    assert calls[0] == (0, None) and calls[-1] == (stats.samples, None)  # looping forever: no total


def test_reblock_never_glues_across_a_gap():
    def blk(seq, n):
        return S.SampleBlock(machine="m", axis="a", seq=seq, t=[(seq + i) * TS for i in range(n)],
                             v_ref=[0.0] * n, v_meas=[0.0] * n, u=[1.0] * n if seq else None)

    out = [b for _, b in _reblock(iter([("samples", blk(0, 3)), ("samples", blk(3, 4)), ("samples", blk(10, 5))]), 4)]
    assert [(b.seq, len(b.t)) for b in out] == [(0, 4), (4, 3), (10, 4), (14, 1)]
    assert out[0].u == [None, None, None, 1.0]


def test_cli_replay_as_client_of_the_monitor_peer(trial, sessions, capsys):
    from feedmon.cli import main

    mon, _, endpoint = sessions
    col = Collector(mon, prefix="cli")
    try:
        rc = main(["replay", str(trial), "--max", "--axis", "Y", "--connect", endpoint, "--prefix", "cli",
                   "--wait", str(WAIT), "--block", "50"])
        col.wait({"cli/mill/Y/samples": N})
    finally:
        col.close()
    out = capsys.readouterr()
    print(out.out)
    assert rc == 0, out.err
    assert f"replayed {N} samples" in out.out and "mill/Y" in out.out
    _check_contiguous(col.by_key["cli/mill/Y/samples"], N)


def test_cli_errors_are_clear(tmp_path, capsys):
    from feedmon.cli import main

    rc = main(["replay", str(tmp_path / "missing.mcap"), "--connect", f"tcp/127.0.0.1:{T.free_tcp_port()}"])
    err = capsys.readouterr().err
    assert rc == 2 and "feedmon replay: error:" in err
    # nothing listens there: the library names its parameter, the CLI adds the flag
    assert "check the connect endpoints) (command line: --connect)" in err
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    port = T.free_tcp_port()
    listener = T.open_session(listen=f"tcp/127.0.0.1:{port}")
    try:
        rc = main(["replay", str(bad), "--connect", f"tcp/127.0.0.1:{port}", "--wait", "0"])
    finally:
        listener.close()
    err = capsys.readouterr().err
    assert rc == 2 and "not an MCAP file" in err


def test_replay_of_a_simulated_trial(tmp_path, sessions):
    """The simulator's trial (samples + ground truth) arrives complete and equal to the file."""
    from feedio.mcapio import read_trial
    from replay.simulator import simulate_scenario, write_trial

    path = tmp_path / "sim.mcap"
    write_trial(simulate_scenario("shaker-control", seed=3, duration=1.0), path)
    tr = read_trial(path)
    mon, pub, _ = sessions
    col = Collector(mon)
    try:
        stats = replay(path, pub, rate=None, wait_for_subscriber=WAIT)
        key = f"feedmon/{tr.machine}/{tr.axis}"
        col.wait({f"{key}/samples": len(tr), f"{key}/truth": len(tr)})
    finally:
        col.close()
    assert stats.samples == len(tr) and stats.truth_samples == len(tr)
    got = col.by_key[f"{key}/samples"]
    _check_contiguous(got, len(tr))
    assert [x for b in got for x in b.v_meas] == pytest.approx(tr.v_meas.tolist(), nan_ok=True)
    truth = col.by_key[f"{key}/truth"]
    assert [x for b in truth for x in b.f] == pytest.approx(tr.truth.f.tolist(), nan_ok=True)


def test_replay_of_many_axes_reads_the_file_once(tmp_path, sessions, monkeypatch):
    """1500 axes (the old player opened and decoded the whole file once per axis: quadratic, > 100 s for
    3000 axes). Now the scan and each pass read the file once for all axes; every block arrives."""
    import feedio.mcapio as mcapio

    n_axes = 1500
    path = tmp_path / "many.mcap"
    metas = [_meta(f"A{i}") for i in range(n_axes)]
    with TrialWriter(path, metas, start="2024-05-01T08:00:00Z") as w:
        for seq in (0, 5):
            t = [(seq + i) * TS for i in range(5)]
            for i in range(n_axes):
                w.write_samples(S.SampleBlock(machine="mill", axis=f"A{i}", seq=seq, t=t, v_ref=[0.0] * 5,
                                              v_meas=[0.001 * i] * 5))
    opens = []
    real_init = mcapio.OpenTrial.__init__

    def counting_init(self, *a, **k):
        opens.append(a[0] if a else k.get("path"))
        real_init(self, *a, **k)

    monkeypatch.setattr(mcapio.OpenTrial, "__init__", counting_init)
    mon, pub, _ = sessions
    got: list[str] = []
    sub = mon.declare_subscriber("feedmon/mill/*/samples", lambda s: got.append(str(s.key_expr)))
    try:
        stats = replay(path, pub, rate=None, wait_for_subscriber=WAIT)
        deadline = time.monotonic() + WAIT
        while len(got) < 2 * n_axes and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        sub.undeclare()
    assert stats.blocks == 2 * n_axes and stats.samples == 10 * n_axes
    assert len(got) == 2 * n_axes and len(set(got)) == n_axes
    assert len(opens) <= 3, opens  # list_axes, scan, one pass — whatever the number of axes


def test_axes_not_interleaved_in_time_are_read_in_bounded_memory(tmp_path):
    """All of X, then all of Y: beyond the read-ahead bound (bytes) X leaves the shared pass and re-reads
    the file from where it was; every block of both axes comes out once, in order, and no more than the
    bound (plus one block) ever waits in memory."""
    import tracemalloc

    from feedio.mcapio import held_bytes, iter_axes

    path = tmp_path / "blocks.mcap"
    with TrialWriter(path, [_meta("X"), _meta("Y")], start="2024-05-01T08:00:00Z") as w:
        for ax in "XY":  # all of X, then all of Y
            for seq in range(0, 60_000, BLOCK):
                t = [(seq + i) * TS for i in range(BLOCK)]
                w.write_samples(S.SampleBlock(machine="mill", axis=ax, seq=seq, t=t, v_ref=[0.0] * BLOCK,
                                              v_meas=[0.0] * BLOCK))

    def consume(bound: int):
        streams = iter_axes(path, ["mill/X", "mill/Y"], read_ahead_bytes=bound)
        tracemalloc.start()
        try:
            x0 = next(streams["mill/X"])[2]  # X's first block, then Y's stream reads past all of X
            ys = [b.seq for _, _, b in streams["mill/Y"]]
            xs = [x0.seq] + [b.seq for _, _, b in streams["mill/X"]]
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        return streams, xs, ys, peak, held_bytes(x0)

    bound = 200 * 1024
    streams, xs, ys, peak, one = consume(bound)
    assert xs == ys == list(range(0, 60_000, BLOCK))
    assert streams.own_passes == 1 and bound < streams.peak_bytes <= bound + one
    unbounded, xs2, _, peak2, _ = consume(1 << 40)  # everything of X waits while Y is read
    assert xs2 == xs and unbounded.own_passes == 0 and unbounded.peak_bytes > 10 * bound
    # in real memory too: what the bounded read saves is what the unbounded one held (the rest of either
    # peak is the reader's decompressed chunks, bounded by the chunk limits)
    assert peak2 - peak > 0.5 * (unbounded.peak_bytes - bound), (peak, peak2, unbounded.peak_bytes)
