"""Bad input through real Zenoh: the monitor stays up, rejects or re-syncs, counts, logs once per burst,
and its tracker is not corrupted.

Two levels:

* ``test_bad_input_in_process`` (one case per kind of bad input): a :class:`Monitor` in this process
  with a real listening Zenoh session; a second real session publishes a clean stream A, the bad
  input, then a clean stream B. The estimates of B and the final tracker snapshot must equal those
  of a reference :class:`AxisEstimator` that never saw the bad input (fed A and B only; where the
  monitor legitimately re-syncs, the reference sees the bad samples as a hole, which restarts the
  chain the same way — only the GAP bit of the re-sync row differs). Counters are read through the
  status queryable.
* ``test_daemon_*``: a real ``feedmon run`` subprocess gets a burst of 100 messages of every bad
  kind; its ``feedmon status --json`` counts them exactly, its stderr has one log line per burst
  (not 100), it still estimates clean samples, and a replayed milling trial with recorder glitches
  gets exactly one STALE row per glitch while moving.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh
from monitor_proc import MonitorProc
from sink_states import WORKING
from truth_models import model_from_truth, truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.limits import InputLimits
from feedio.mcapio import iter_blocks, read_trial
from feedio.transport import query_status
from monitor.axes import load_axes
from monitor.daemon import Monitor
from monitor.estimator import AxisEstimator
from monitor.model_file import load_model
from monitor.warm import warm_up
from replay.player import replay

PREFIX = "feedmon-bad"
AXIS = "linear-drive/Z"
BLOCK = 10


# ---- shared helpers (also used by test_faults.py) ---------------------------------------------
def wait_status(session, pred, prefix: str = PREFIX, timeout: float = 30.0, pid: int | None = None) -> dict:
    """Poll the status queryable until ``pred(status)``; with ``pid``, only the reply of that monitor
    counts (another monitor on the same prefix, e.g. one of an earlier test still stopping, may answer too)."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        replies = query_status(session, prefix, timeout=2.0)
        if pid is not None:
            replies = [r for r in replies if r.get("monitor", {}).get("pid") == pid]
        if replies:
            last = replies[0]
            try:
                if pred(last):
                    return last
            except (KeyError, TypeError):
                pass
        time.sleep(0.05)
    raise AssertionError(f"status condition not reached; last status: {json.dumps(last)[:3000]}")


def blocks_of(trial, start: int, stop: int, size: int = BLOCK, *, dt: float = 0.0) -> list[S.SampleBlock]:
    """Clean SampleBlocks of samples ``start … stop−1`` of a trial (times shifted by ``dt``)."""
    out = []
    for i in range(start, stop, size):
        j = min(stop, i + size)
        out.append(S.SampleBlock(machine=trial.machine, axis=trial.axis, seq=i,
                                 t=[float(x) + dt for x in trial.t[i:j]],
                                 v_ref=trial.v_ref[i:j].tolist(), v_meas=trial.v_meas[i:j].tolist()))
    return out


def rows(blocks) -> dict[str, np.ndarray]:
    """EstimateBlocks → columns (None → NaN), with ``seq``."""
    blocks = list(blocks)
    out = {"seq": np.concatenate([np.arange(b.seq, b.seq + len(b.t)) for b in blocks]) if blocks else np.zeros(0)}
    for name in ("t", "v_meas", "v_pred", "residual", "f", "f_var", "f_next", "f_next_var"):
        out[name] = np.array([np.nan if x is None else x for b in blocks for x in getattr(b, name)], dtype=float)
    for name in ("dict_size", "removed", "flags"):
        out[name] = np.array([x for b in blocks for x in getattr(b, name)], dtype=np.int64)
    return out


# ---- fixtures ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "bad_input", duration=6.0, seed=4)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


class ListSink:
    """Minimal in-memory sink (the Monitor's sink protocol): keeps every EstimateBlock."""

    name = "list"

    def __init__(self):
        self.estimates: list[S.EstimateBlock] = []

    def offer(self, item):
        if isinstance(item, S.EstimateBlock):
            self.estimates.append(item)
        return True

    def close(self, timeout=None):
        return True

    def status(self):
        return {"name": self.name, "state": "ok", "accepted": len(self.estimates), "written": 0, "dropped": 0,
                "failures": 0, "pending": 0}


class LiveMonitor:
    """An in-process Monitor on a real listening Zenoh session plus a real publishing session."""

    def __init__(self, model_path: Path, machine: str, axis: str):
        self.endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
        self.axes = load_axes([model_path])
        warm_up(self.axes)
        self.sink = ListSink()
        self.mon_session = T.open_session(listen=self.endpoint)
        self.monitor = Monitor(self.axes, self.mon_session, prefix=PREFIX, sinks=[self.sink])
        self.monitor.start()
        self.session = T.open_session(connect=self.endpoint)
        self.key = T.samples_key(PREFIX, machine, axis)
        self.pub = self.session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(self.pub, 10.0), "no subscriber matched"
        self.ax = next(iter(self.axes.values()))

    def send(self, item, key: str | None = None) -> None:
        payload = S.encode(item) if isinstance(item, msgspec.Struct) else item
        if key is None:
            self.pub.put(payload)
        else:
            self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def wait_seq(self, seq: int, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while self.ax.status.last_seq != seq:
            if time.monotonic() > deadline:
                raise AssertionError(f"last_seq {self.ax.status.last_seq}, waiting for {seq}; "
                                     f"status {self.monitor.status()}")
            time.sleep(0.01)

    def close(self) -> None:
        self.monitor.stop()
        self.session.close()
        self.mon_session.close()


# ---- the cases ---------------------------------------------------------------------------------
def _j(**kw) -> bytes:
    return json.dumps(kw).encode()


def _good(trial, seq, n=3):
    return dict(machine=trial.machine, axis=trial.axis, seq=seq, t=trial.t[seq:seq + n].tolist(),
                v_ref=trial.v_ref[seq:seq + n].tolist(), v_meas=trial.v_meas[seq:seq + n].tolist())


def _malformed(trial):
    g = _good(trial, 300)
    raw_nan = json.dumps(g).replace(repr(g["v_meas"][1]), "NaN", 1).encode()
    raw_inf = json.dumps(g).replace(repr(g["v_meas"][1]), "1e999", 1).encode()
    assert b"NaN" in raw_nan and b"1e999" in raw_inf
    return [
        b"not json at all \x00\xff",  # not JSON
        b"",  # empty payload
        b"[1, 2, 3]",  # JSON, wrong shape
        b'"a string"',
        _j(**{**g, "seq": "300"}),  # wrong types
        _j(**{**g, "v_meas": ["fast", 0.0, 0.0]}),
        _j(**{**g, "t": "yesterday"}),
        _j(**{**g, "seq": -1}),
        _j(**{k: v for k, v in g.items() if k != "v_meas"}),  # missing fields
        _j(**{k: v for k, v in g.items() if k != "t"}),
        _j(**{**g, "curent": [1.0, 1.0, 1.0]}),  # misspelt (unknown) field
        _j(**{**g, "v_meas": g["v_meas"][:2]}),  # inconsistent column lengths
        _j(**{**g, "t": [g["t"][0], None, g["t"][2]]}),  # a block without a time for one sample
        _j(**{**g, "t": [], "v_ref": [], "v_meas": []}),  # empty block
        raw_nan,  # a raw NaN token (not JSON; msgspec rejects it)
        raw_inf,  # a number out of float range
        # bounds of the schema (feedio.limits): sequence numbers, times, names
        _j(**{**g, "seq": 2**53 - 2}),  # seq + len - 1 > SEQ_MAX
        _j(**{**g, "seq": 2**64}),  # beyond int64
        _j(**{**g, "t": [g["t"][0], 2e10, g["t"][2]]}),  # not an MCAP log time (> T_MAX)
        _j(**{**g, "t": [-1.0, g["t"][1], g["t"][2]]}),  # negative controller time
        _j(**{**g, "machine": "[/]"}),  # rich markup
        _j(**{**g, "machine": "mill\r\nfeedmon run: WARNING: forged"}),  # a forged log line
        _j(**{**g, "axis": "\x1b[31mX"}),  # an ANSI escape
        _j(**{**g, "axis": "X" * 65}),  # too long
        _j(**{**g, "axis": ""}),  # empty
    ]


def _with(trial, seq, n, col, i, value):
    g = _good(trial, seq, n)
    g[col] = list(g[col])
    g[col][i] = value
    return _j(**g)


def _too_long(trial, n):
    """A block of ``n`` samples (times spaced by Ts from sample 300 on)."""
    t0, ts = float(trial.t[300]), float(trial.meta.Ts)
    return _j(machine=trial.machine, axis=trial.axis, seq=300, t=[t0 + i * ts for i in range(n)],
              v_ref=[0.0] * n, v_meas=[0.0] * n)


def _padded(trial, size):
    """A valid block padded with JSON whitespace to ``size`` bytes: refused for its size alone."""
    raw = _j(**_good(trial, 300, 5))
    return raw[:-1] + b" " * (size - len(raw)) + b"}"


# name -> (bad payloads [(key|None, bytes)], B start, reference blocks between A and B, counters, resync)
def _cases(trial):
    other = T.samples_key(PREFIX, "ghost-machine", "Q")
    ghost = S.SampleBlock(machine="ghost-machine", axis="Q", seq=300, t=trial.t[:10].tolist(),
                          v_ref=trial.v_ref[:10].tolist(), v_meas=trial.v_meas[:10].tolist())
    forged = [S.encode(b) for b in blocks_of(trial, 300, 320)]  # our axis' next samples, on another key
    skip = lambda *ks: [b for b in blocks_of(trial, 300, 305, 1) if b.seq not in ks]  # noqa: E731
    limits = InputLimits()
    return {
        "malformed": ([(None, p) for p in _malformed(trial)], 300, [], {"drops.malformed": 25}, False),
        "malformed_unknown_axis_key": ([(T.samples_key(PREFIX, "nope", "W"), b"{garbage")], 300, [],
                                       {"input.malformed": 1}, False),
        "null_v_meas": ([(None, _with(trial, 300, 5, "v_meas", 2, None))], 305, skip(302),
                        {"drops.rejected_non_finite": 1}, True),
        "null_v_ref": ([(None, _with(trial, 300, 5, "v_ref", 2, None))], 305, skip(302),
                       {"drops.rejected_non_finite": 1}, True),
        "absurd_v_meas": ([(None, _with(trial, 300, 5, "v_meas", 2, 3.0e5))], 305, skip(302),
                          {"drops.rejected_out_of_range": 1}, True),
        # a time no log can store: the whole block is refused by the schema before any sink sees it;
        # the samples it held are a hole (a gap of 5) for the monitor and the reference alike
        "absurd_time": ([(None, _with(trial, 300, 5, "t", 2, 2e10))], 305, [], {"drops.malformed": 1}, "hole"),
        "duplicate": ([(None, _j(**{**_good(trial, 299, 1), "v_meas": [0.7]}))] * 5, 300, [],
                      {"drops.duplicate": 5}, False),
        "out_of_order": ([(None, S.encode(b)) for b in blocks_of(trial, 100, 130)], 300, [],
                         {"drops.out_of_order": 30}, False),
        "no_model_axis": ([(other, S.encode(ghost))] * 7, 300, [], {"no_model.ghost-machine/Q": 70}, False),
        # routing by key: our axis' samples on another machine's key are refused, counted per key
        "key_mismatch_foreign_key": ([(T.samples_key(PREFIX, "other-machine", "Y"), p) for p in forged], 300, [],
                                     {"key_mismatch.other-machine/Y": 2}, False),
        "key_mismatch_own_key": ([(None, S.encode(ghost))] * 3, 300, [], {"drops.key_mismatch": 3}, False),
        "block_too_long": ([(None, _too_long(trial, limits.max_block_samples + 1))], 300, [],
                           {"drops.too_large": 1}, False),
        "message_too_large": ([(None, _padded(trial, limits.max_message_bytes + 1))], 300, [],
                              {"drops.too_large": 1}, False),
    }


@pytest.mark.parametrize("case", ["malformed", "malformed_unknown_axis_key", "null_v_meas", "null_v_ref",
                                  "absurd_v_meas", "absurd_time", "duplicate", "out_of_order", "no_model_axis",
                                  "key_mismatch_foreign_key", "key_mismatch_own_key", "block_too_long",
                                  "message_too_large"])
def test_bad_input_in_process(case, work, trial):
    bad, b_start, between, expected, resync = _cases(trial)[case]
    model = load_model(work / "z.model.toml")
    A, B = blocks_of(trial, 0, 300), blocks_of(trial, b_start, b_start + 300)
    live = LiveMonitor(work / "z.model.toml", trial.machine, trial.axis)
    try:
        for b in A:
            live.send(b)
        live.wait_seq(299)
        for key, payload in bad:
            live.send(payload, key)
        for b in B:
            live.send(b)
        live.wait_seq(B[-1].seq + len(B[-1].t) - 1)
        st = wait_status(live.session, lambda s: s["monitor"]["state"] == "running")  # still answers
        snap = live.ax.estimator.snapshot()
    finally:
        live.close()
    a = st["axes"][AXIS]
    # the reason is counted, exactly, in the status answered over Zenoh
    for path, n in expected.items():
        where, name = path.split(".", 1)
        if where == "drops":
            got = a["drops"].get(name, 0)
        elif where in ("no_model", "key_mismatch"):
            got = st["input"][where].get(name, 0)
        else:
            got = st["input"][name]
        assert got == n, (path, st)
    other_drops = {k: v for k, v in a["drops"].items() if f"drops.{k}" not in expected}
    assert other_drops == {}, other_drops
    assert a["gaps"] == (1 if resync == "hole" else 0)
    assert st["input"]["internal_errors"] == 0 and st["input"]["queue_full"] == 0
    # reference: an estimator that never saw the bad input (a hole where the monitor re-synced)
    ref = AxisEstimator(model)
    for b in A:
        ref.process(b)
    ref_between = [ref.process(b) for b in between]
    ref_b = [ref.process(b) for b in B]
    got = rows(live.sink.estimates)
    want = rows(ref_b)
    in_b = got["seq"] >= b_start
    for name, col in want.items():
        g = got[name][in_b]
        if name == "flags" and resync is True:
            g, col = g & ~S.GAP, col & ~S.GAP  # the reference restarted at a hole, the monitor at a rejection
        np.testing.assert_array_equal(g, col, err_msg=f"{case}: {name} after the bad input")
    ref_snap = ref.snapshot()
    assert snap.keys() == ref_snap.keys()
    for k in ref_snap:  # the tracker is exactly that of a monitor that never saw the bad input
        np.testing.assert_array_equal(snap[k], ref_snap[k], err_msg=f"{case}: tracker {k}")
    if resync == "hole":  # the refused block left a hole: rows for A and B only, B starts with GAP
        np.testing.assert_array_equal(got["seq"], np.r_[np.arange(300), np.arange(b_start, b_start + 300)])
        assert got["flags"][got["seq"] == b_start][0] & S.GAP
    elif resync:  # one REJECTED row (NaN estimates) for the bad sample, then the chain restarts
        rej = got["seq"] == 302
        assert got["flags"][rej].tolist() == [S.REJECTED]
        assert np.isnan(got["f"][rej]).all() and np.isnan(got["f_next"][rej]).all()
        assert got["flags"][got["seq"] == 303][0] & S.WARMUP and np.isnan(got["residual"][got["seq"] == 303][0])
        assert [int(x) for x in rows(ref_between)["seq"]] == [300, 301, 303, 304]
    else:  # nothing of the bad input produced a row: one row per clean sample, in order
        np.testing.assert_array_equal(got["seq"], np.arange(600))


def test_gap_and_time_backwards_resync_in_process(work, trial):
    """A sequence gap and a controller clock stepping back: counted, GAP row, chain restarted, not learned
    across; the monitor gives the same numbers as the offline pipeline on the same input."""
    model = load_model(work / "z.model.toml")
    A = blocks_of(trial, 0, 300)
    B = blocks_of(trial, 310, 500)  # samples 300..309 never arrive
    C = blocks_of(trial, 500, 700, dt=-0.5)  # the controller clock steps back by 0.5 s at seq 500
    live = LiveMonitor(work / "z.model.toml", trial.machine, trial.axis)
    try:
        for b in A + B + C:
            live.send(b)
        live.wait_seq(699)
        st = wait_status(live.session, lambda s: s["axes"][AXIS]["samples_in"] == 690)
        snap = live.ax.estimator.snapshot()
    finally:
        live.close()
    a = st["axes"][AXIS]
    assert (a["gaps"], a["missing_samples"], a["counters"]["time_backwards"]) == (1, 10, 1)
    assert a["restarts"] == 3 and a["estimates_out"] == 690 and a["dropped_total"] == 0
    got = rows(live.sink.estimates)
    for seq in (310, 500):  # re-sync rows: GAP, no residual (nothing learned across the hole / the step)
        r = got["seq"] == seq
        assert got["flags"][r][0] & S.GAP and np.isnan(got["residual"][r][0]), seq
    assert np.isfinite(got["f"][got["seq"] > 500]).all()  # estimates resume at once
    ref = AxisEstimator(model)
    want = rows([ref.process(b) for b in A + B + C])
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    for k, v in ref.snapshot().items():
        np.testing.assert_array_equal(snap[k], v, err_msg=k)


# ---- a real daemon: bursts of 100, exact counters, one log line per burst, stale glitches -------
@pytest.fixture(scope="module")
def milling(work):
    """milling-incdec with more recorder glitches than the default, and its model."""
    cfg = work / "glitchy.toml"
    cfg.write_text("[noise]\nglitch_rate = 0.01\n")
    out = work / "milling.mcap"
    r = subprocess.run([sys.executable, "-m", "feedmon.cli", "simulate", "milling-incdec", "-o", str(out),
                        "--seed", "3", "--duration", "8", "--config", str(cfg)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    tr = read_trial(out)
    rpm = tr.meta.spindle_rpm or 3000.0
    model_from_truth(out, work / "x.model.toml", period=60.0 / rpm)
    return out


@pytest.fixture(scope="module")
def daemon(work, trial, milling):
    out = work / "daemon"
    out.mkdir()
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--model", "x.model.toml", "--mcap", str(out / "log.mcap"),
                       "--fresh", "--state-dir", str(out / "state")], cwd=work)
    res: dict = {"mon": mon, "mcap": out / "log.mcap"}
    m = trial.machine, trial.axis
    key = T.samples_key(PREFIX, *m)

    def one(seq, t, v=None, vr=None):
        return S.encode(S.SampleBlock(machine=m[0], axis=m[1], seq=seq, t=[float(t)],
                                      v_ref=[float(trial.v_ref[seq % len(trial)]) if vr is None else vr],
                                      v_meas=[float(trial.v_meas[seq % len(trial)]) if v is None else v]))
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            assert T.wait_for_matching(pub, 10.0)
            res["before"] = wait_status(s, lambda x: x["monitor"]["state"] == "running")
            ts = trial.t
            send = [S.encode(b) for b in blocks_of(trial, 0, 200)]
            send += [b"\x00not json"] * 100  # malformed
            send += [S.encode(S.SampleBlock(machine=m[0], axis=m[1], seq=k, t=[float(ts[k])], v_ref=[0.0],
                                            v_meas=[None])) for k in range(200, 300)]  # NaN (JSON null)
            send += [S.encode(b) for b in blocks_of(trial, 300, 400)]
            send += [one(k, ts[k], v=1e3) for k in range(400, 500)]  # absurd magnitude
            send += [S.encode(b) for b in blocks_of(trial, 500, 600)]
            send += [one(599, ts[599])] * 100  # duplicates
            send += [one(k, ts[k]) for k in range(100)]  # out of order
            send += [one(k, ts[k]) for k in range(601, 800, 2)]  # 100 gaps of one sample
            send += [S.encode(b) for b in blocks_of(trial, 800, 1000)]
            send += [one(k, ts[999] - 0.01 * (k - 999)) for k in range(1000, 1100)]  # time going backwards
            send += [S.encode(b) for b in blocks_of(trial, 1100, 1300)]
            for p in send:
                pub.put(p)
            ghost = S.encode(S.SampleBlock(machine="ghost", axis="Q", seq=0, t=[0.0], v_ref=[0.0], v_meas=[0.0]))
            for _ in range(100):
                s.put(T.samples_key(PREFIX, "ghost", "Q"), ghost, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in range(1300, 1400):  # our axis' next samples from a peer allowed to publish elsewhere only
                s.put(T.samples_key(PREFIX, "other-machine", "Y"), one(k, ts[k % len(trial)]),
                      congestion_control=zenoh.CongestionControl.BLOCK)
            res["mid"] = wait_status(s, lambda x: x["axes"][AXIS]["last_seq"] == 1299
                                     and x["input"]["no_model"].get("ghost/Q") == 100
                                     and x["input"]["key_mismatch"].get("other-machine/Y") == 100)
            res["replay"] = replay(milling, s, rate=None, prefix=PREFIX, truth=False, wait_for_subscriber=10.0)
            n_mill = res["replay"].samples
            wait_status(s, lambda x: x["axes"]["cnc-mill/X"]["samples_in"] == n_mill)
        cli = subprocess.run([sys.executable, "-m", "feedmon.cli", "status", "--json", "--connect", mon.endpoint,
                              "--prefix", PREFIX, "--timeout", "10"], capture_output=True, text=True, timeout=60)
        assert cli.returncode == 0, cli.stderr
        res["status"] = json.loads(cli.stdout)[0]
    finally:
        res["rc"] = mon.stop()
    return res


def test_daemon_counts_every_bad_burst_exactly(daemon):
    assert daemon["rc"] == 0, daemon["mon"].stderr
    st = daemon["status"]
    a = st["axes"][AXIS]
    assert a["drops"] == {"malformed": 100, "rejected_non_finite": 100, "rejected_out_of_range": 100,
                          "duplicate": 100, "out_of_order": 100}, a["drops"]
    assert (a["gaps"], a["missing_samples"], a["counters"]["time_backwards"]) == (100, 100, 100)
    assert st["input"]["no_model"] == {"ghost/Q": 100} and st["input"]["malformed"] == 0
    assert st["input"]["key_mismatch"] == {"other-machine/Y": 100} and a["last_seq"] == 1299  # forged: not used
    assert st["input"]["internal_errors"] == 0 and st["input"]["queue_full"] == 0
    # every sample that reached the estimator has a row, except the dropped duplicates / out-of-order ones
    assert a["estimates_out"] == a["samples_in"] - 200
    assert st["monitor"]["state"] == "running" and st["sinks"][0]["state"] in WORKING  # degraded: late on a loaded host


def test_daemon_logs_once_per_burst_not_per_message(daemon):
    mon = daemon["mon"]
    for text in ("dropping malformed message", "rejected: non-finite value", "rejected: absurd magnitude",
                 "duplicate sequence number", "out-of-order sequence number", "after a sequence gap",
                 "time going backwards", "no model for axis ghost/Q", "received on key feedmon-bad/other-machine/Y"):
        n = mon.count(text)
        assert 1 <= n <= 3, f"{text!r} logged {n} times for a burst of 100:\n{mon.stderr}"


def test_daemon_still_estimates_clean_samples_after_bad_bursts(daemon, work):
    est = [b for _, b in iter_blocks(daemon["mcap"], AXIS, kinds=("disturbance",))]
    r = rows(est)
    clean = (r["seq"] >= 1100) & (r["seq"] < 1300)
    assert clean.sum() == 200
    assert np.all(r["flags"][clean] & S.REJECTED == 0)
    assert np.isfinite(r["f"][clean][1:]).all() and np.isfinite(r["f_next"][clean]).all()
    rej = r["flags"] & S.REJECTED != 0
    assert rej.sum() == 200 and np.isnan(r["f"][rej]).all()


def test_daemon_stale_rows_match_injected_glitches(daemon, milling):
    tr = read_trial(milling)
    g = np.flatnonzero(tr.truth.glitch)
    omega = load_model(milling.parent / "x.model.toml").omega
    moving = [int(k) for k in g if abs(tr.v_meas[k]) > omega or tr.v_ref[k] != tr.v_ref[k - 1]]
    assert len(moving) >= 15  # the test means something
    a = daemon["status"]["axes"]["cnc-mill/X"]
    assert a["stale"] == len(moving), (a["stale"], len(moving), len(g))
    r = rows(b for _, b in iter_blocks(daemon["mcap"], "cnc-mill/X", kinds=("disturbance",)))
    stale_seq = r["seq"][(r["flags"] & S.STALE) != 0]
    np.testing.assert_array_equal(stale_seq, tr.seq[moving])  # exactly at the glitches, nowhere else
    assert a["trained"] == a["samples_in"] - a["stale"] - a["restarts"]  # stale rows are not learned


def test_stale_detection_keeps_variance_from_spiking(milling):
    """Optional check: learning a glitch (detection off) spikes f_var right after it; skipping it does not."""
    tr = read_trial(milling)
    model = load_model(milling.parent / "x.model.toml")
    blocks = blocks_of(tr, 0, len(tr))
    on, off = AxisEstimator(model), AxisEstimator(model, stale_detection=False)
    r_on, r_off = rows([on.process(b) for b in blocks]), rows([off.process(b) for b in blocks])
    g = np.flatnonzero(tr.truth.glitch)
    g = g[(g > 200) & (g < len(tr) - 2)]
    assert off.counters["stale"] == 0 and on.counters["stale"] > 0
    nxt = g + 1  # the row after a glitch is where a learned glitch shows (its residual is the jump back)
    assert np.nanmedian(r_off["f_var"][nxt]) > np.nanmedian(r_on["f_var"][nxt])
