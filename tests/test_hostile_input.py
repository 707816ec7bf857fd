"""Hostile peers against a real ``feedmon run`` process on real Zenoh (loopback, free ports): values
no log can store, names that flood memory or forge log lines, a status flood, SIGTERM under a flood.
The monitor stays up, refuses and counts, and its outputs stay valid."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh
from monitor_proc import MonitorProc
from sink_states import WORKING
from test_bad_input import AXIS, PREFIX, blocks_of, rows, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_blocks, read_trial
from monitor.status import format_status
from replay.player import replay


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "hostile", duration=4.0, seed=11)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _raw(trial, seq, n=5, **edit) -> bytes:
    d = dict(machine=trial.machine, axis=trial.axis, seq=seq, t=trial.t[seq:seq + n].tolist(),
             v_ref=trial.v_ref[seq:seq + n].tolist(), v_meas=trial.v_meas[seq:seq + n].tolist())
    d.update(edit)
    return json.dumps(d).encode()


def _matched(session, key):
    pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    assert T.wait_for_matching(pub, 15.0), "the monitor's subscriber never matched"
    return pub


def _put(session, key, payload):
    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


# ---- values that cannot be logged never reach a sink -------------------------------------------
def test_absurd_times_and_sequence_numbers_never_reach_the_mcap_log(work, trial):
    out = work / "poison.mcap"
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--mcap", str(out), "--fresh",
                                           "--state-dir", str(work / "st-poison")], cwd=work)
    big = 2**60
    poison = [
        _raw(trial, 100, t=[float(trial.t[100]), 2e10, float(trial.t[102]), 3.0, 4.0]),  # 2e10 s: beyond a log time
        _raw(trial, 100, t=[-5.0, -4.0, -3.0, -2.0, -1.0]),  # before the log's time 0
        _raw(trial, 100, t=[1e300] * 5),
        _raw(trial, 2**64),  # beyond int64
        _raw(trial, big), _raw(trial, big + 5),  # consecutive blocks far beyond 2**53
        _raw(trial, 2**53 - 3),  # its last sample beyond SEQ_MAX
    ]
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = _matched(s, T.samples_key(PREFIX, trial.machine, trial.axis))
            for b in blocks_of(trial, 0, 100):
                pub.put(S.encode(b))
            for p in poison:
                pub.put(p)
            for b in blocks_of(trial, 100, 200):
                pub.put(S.encode(b))
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 199
                             and x["axes"][AXIS]["drops"].get("malformed") == len(poison))
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    a = st["axes"][AXIS]
    assert a["drops"] == {"malformed": len(poison)} and a["gaps"] == 0 and a["samples_in"] == 200
    sink = st["sinks"][0]
    assert sink["failures"] == 0 and sink["state"] in WORKING, sink  # degraded: late on a loaded host
    tr = read_trial(out)  # finished, readable: every block and its index
    np.testing.assert_array_equal(tr.seq, np.arange(200))
    assert tr.t.max() < 1e10 and tr.t.min() >= 0
    est = rows(b for _, b in iter_blocks(out, AXIS, kinds=("disturbance",)))
    np.testing.assert_array_equal(est["seq"], np.arange(200))


# ---- message size: counted in the callback, far too large dropped by the transport ------------------
def test_message_size_limits_in_feedmon_run(work, trial):
    # 16 KiB: the messages at the limit fit one Zenoh batch (64 KiB). A fragmented message (≥ 64 KiB) can
    # cost its peer the messages right after it in Zenoh 1.10 (seen once: 9 blocks after a 64 KiB + 1 B
    # message never reached the callback), which is Zenoh's and not what this test is about.
    limit = 16 * 1024
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--state-dir", str(work / "st-size"),
                                           "--limit", f"max_message_bytes={limit}"], cwd=work)
    pad = lambda size: _raw(trial, 100)[:-1] + b" " * (size - len(_raw(trial, 100))) + b"}"  # noqa: E731
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = _matched(s, T.samples_key(PREFIX, trial.machine, trial.axis))
            for b in blocks_of(trial, 0, 100):
                pub.put(S.encode(b))
            pub.put(pad(limit))  # exactly the limit: accepted (samples 100..104)
            pub.put(pad(limit + 1))  # over it: refused in the callback, counted
            for b in blocks_of(trial, 105, 200):
                pub.put(S.encode(b))
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 199)
            a = st["axes"][AXIS]
            assert a["drops"] == {"too_large": 1} and st["input"]["too_large"] == 1
            assert a["samples_in"] == 200 and a["gaps"] == 0 and st["limits"]["max_message_bytes"] == limit

            # 8x: over 2x + 64 KiB, the transport limit (transport/link/rx/max_message_size). Messages of
            # that peer may be lost around it (Zenoh clears its reassembly state): that costs the offending
            # peer its own data, never the monitor. Publish fresh blocks until one lands.
            pub.put(pad(8 * limit))
            landed = None
            for b in blocks_of(trial, 200, trial.t.size):
                pub.put(S.encode(b))
                st = query_last(s, mon.proc.pid)
                if st is not None and st["axes"][AXIS]["last_seq"] >= 200:
                    landed = st
                    break
            assert landed is not None, "no block landed after the oversized message"
        assert mon.proc.poll() is None, "the monitor died of an oversized message"
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    # Dropped by Zenoh (not counted) or refused by the callback (counted): never parsed, never accepted.
    # Zenoh 1.10 enforces its receive limit only on some oversized messages of a link (measured), so the
    # callback's exact limit is what the monitor relies on.
    a = landed["axes"][AXIS]
    assert set(a["drops"]) == {"too_large"} and a["drops"]["too_large"] in (1, 2)
    assert landed["input"]["too_large"] == a["drops"]["too_large"]


def query_last(session, pid):
    """This monitor's status reply, or None if it did not answer within 2 s."""
    replies = [r for r in T.query_status(session, PREFIX, timeout=2.0) if r.get("monitor", {}).get("pid") == pid]
    return replies[0] if replies else None


# ---- names: bounded tables, no log flood, no forged lines, tables that print -------------------
def test_unknown_names_stay_bounded_and_cannot_forge_log_lines(work, trial):
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--state-dir", str(work / "st-names"),
                                           "--limit", "max_unknown_axes=8"], cwd=work)
    n_names = 300
    forged = "feedmon run: ERROR: forged line"
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = _matched(s, T.samples_key(PREFIX, trial.machine, trial.axis))
            for i in range(n_names):  # valid names, each an axis without a model
                m = f"m{i:03d}-" + "x" * 59  # 64 characters: the longest name allowed
                _put(s, T.samples_key(PREFIX, m, "Y"), _raw(trial, 0, machine=m, axis="Y"))
            long_chunk = "k" * 10_000  # keys may be long (Zenoh sends up to ~64 kB) and hold control characters
            for i in range(50):
                _put(s, f"{PREFIX}/{long_chunk}{i}/Y/samples", _raw(trial, 0, machine="n" * 100_000, axis="Y"))
                _put(s, f"{PREFIX}/mill\r\n{forged}/X{i}/samples", b"\x1b[2J\r\n" + forged.encode())
                _put(s, T.samples_key(PREFIX, trial.machine, trial.axis),
                     json.dumps({"machine": trial.machine, f"\r\n{forged}": 1}).encode())
            for b in blocks_of(trial, 0, 100):  # and the modelled axis still works
                pub.put(S.encode(b))
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 99
                             and x["input"]["malformed"] == 100 and x["axes"][AXIS]["drops"].get("malformed") == 50
                             and len(x["input"]["no_model"]) + x["input"]["no_model_overflow"] // 5 == n_names)
            doc = json.dumps(st)
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    inp = st["input"]
    assert len(inp["no_model"]) == 8 and all(v == 5 for v in inp["no_model"].values())
    assert inp["no_model_overflow"] == (n_names - 8) * 5 and inp["no_model_blocks"] == n_names
    assert len(doc) < 20_000, len(doc)  # the status does not grow with the names a peer invents
    assert mon.count("no model for axis") <= 8 + 2  # one line per listed name, one for the rest
    assert len(mon.lines) < 60, mon.stderr
    assert not any(line.startswith(forged) or "\x1b" in line for line in mon.lines), mon.stderr
    assert "\\r\\n" + forged in mon.stderr  # shown escaped instead
    assert all(len(line) < 2_000 for line in mon.lines)  # a 10 kB key is shortened in the log


def test_status_table_prints_hostile_names_as_text(tmp_path):
    """``feedmon status`` against a peer answering a status with names that are rich markup, ANSI
    escapes and line breaks, and a document of the wrong shape: plain text out, exit 0."""
    doc = {
        "monitor": {"pid": 1, "host": "h\x1b]0;pwned\x07", "prefix": "feedmon-evil", "state": "running", "uptime_s": 1},
        "input": {"received": 1, "no_model": {"[/]": 3, "[bold red]x[/]": 1, "a\r\nfeedmon run: ERROR: x": 2}},
        "axes": {"[/]": {"samples_in": 1, "drops": {"[/]": 1}, "latency_us": {"p50": "[/]"}, "state": "[/]"},
                 "m/\x1b[31mred": {}},
        "sinks": [{"name": "[/]", "state": None}, "not a dict"],
    }
    port = T.free_tcp_port()
    with T.open_session(listen=f"tcp/127.0.0.1:{port}") as s:
        key = T.status_key("feedmon-evil")
        s.declare_queryable(key, lambda q: q.reply(key, json.dumps(doc).encode()))
        r = subprocess.run([sys.executable, "-m", "feedmon.cli", "status", "--connect", f"tcp/127.0.0.1:{port}",
                            "--prefix", "feedmon-evil", "--timeout", "10"], capture_output=True, text=True,
                           timeout=60, env={**os.environ, "COLUMNS": "200"})
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    out = r.stdout
    assert "[/]" in out and "[bold red]x[/]" in out  # markup printed as text
    assert "\x1b" not in out and "\r" not in out and "\x07" not in out  # no terminal control from a peer
    assert "\\x1b[31mred" in out and "\\r\\n" in out
    # the same document through the function, into a string
    from io import StringIO

    from rich.console import Console

    buf = StringIO()
    format_status(doc, Console(file=buf, width=200, color_system=None))
    assert "[/]" in buf.getvalue()


# ---- a status flood does not stop the estimates --------------------------------------------------
def test_status_flood_is_rate_limited_and_estimation_goes_on(work, trial):
    n = len(trial)
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--state-dir", str(work / "st-flood"),
                                           "--limit", "status_rate=20", "--limit", "status_burst=20"], cwd=work)
    stop = threading.Event()
    sent = [0]

    def flood(session):
        key = T.status_key(PREFIX)
        while not stop.is_set():
            session.get(key, timeout=0.5)  # replies (if any) are not even read
            sent[0] += 1

    try:
        with T.open_session(connect=mon.endpoint) as s, T.open_session(connect=mon.endpoint) as fs:
            wait_status(s, pid=mon.proc.pid, pred=lambda x: x["monitor"]["state"] == "running")
            th = threading.Thread(target=flood, args=(fs,), daemon=True)
            th.start()
            while sent[0] < 2000:  # the flood is under way before the data comes
                time.sleep(0.01)
            replay(work / "trial.mcap", s, rate=None, prefix=PREFIX, truth=False, wait_for_subscriber=10.0, block=1)
            while sent[0] < 4000:
                time.sleep(0.01)
            stop.set()
            th.join(30)
            st = wait_status(s, pid=mon.proc.pid, timeout=60, pred=lambda x: x["axes"][AXIS]["estimates_out"] == n)
    finally:
        stop.set()
        rc = mon.stop()
    assert rc == 0, mon.stderr
    a = st["axes"][AXIS]
    assert a["dropped_total"] == 0 and a["estimates_out"] == n and st["input"]["queue_full"] == 0
    served, refused = st["status"]["served"], st["status"]["refused"]
    assert refused > 1000, st["status"]
    # a token bucket of 20 replies with 20 more per second: never more over the monitor's whole life
    assert served <= 20 + 20 * st["monitor"]["uptime_s"] + 1, (served, st["monitor"]["uptime_s"])


# ---- SIGTERM under a flood: what is discarded is counted -------------------------------------------
def test_sigterm_under_flood_counts_what_it_discards(work, trial):
    """A model with a large KRLS-T budget makes each block cost ~1 s of estimation on any CPU, so work is
    certainly queued when SIGTERM comes; with --drain-seconds 0 it is discarded at once, and counted."""
    slow = work / "slow.model.toml"
    text = (work / "z.model.toml").read_text()
    assert "budget = 50" in text
    slow.write_text(text.replace("budget = 50", "budget = 1000"))
    n, span = len(trial), float(trial.t[-1] - trial.t[0]) + float(trial.meta.Ts)
    count = 20
    blocks = [S.encode(S.SampleBlock(machine=trial.machine, axis=trial.axis, seq=k * n, t=(trial.t + k * span).tolist(),
                                     v_ref=trial.v_ref.tolist(), v_meas=trial.v_meas.tolist())) for k in range(count)]
    state = work / "st-sigterm"
    mon = MonitorProc(prefix=PREFIX, args=["--model", str(slow), "--fresh", "--state-dir", str(state),
                                           "--drain-seconds", "0"], cwd=work)
    with T.open_session(connect=mon.endpoint) as s:
        pub = _matched(s, T.samples_key(PREFIX, trial.machine, trial.axis))
        for b in blocks:
            pub.put(b)
        wait_status(s, pid=mon.proc.pid, pred=lambda x: x["input"]["received"] == count and x["input"]["pending"] >= 5)
        rc = mon.stop()
    assert rc == 0, mon.stderr
    m = re.search(r"linear-drive/Z: (\d+) blocks, (\d+) samples in.*'shutdown_discarded': (\d+)", mon.stderr)
    assert m, mon.stderr
    handled, samples_in, discarded = map(int, m.groups())
    assert discarded >= 5 and handled + discarded == count and samples_in == handled * n
    assert f"shutdown_discarded={discarded}" in mon.stderr  # the input summary says it too
    assert f"input: {count} messages received, {handled} handled" in mon.stderr
    with np.load(state / "linear-drive+Z.state.npz", allow_pickle=False) as z:
        assert 0 < int(z["estimator.trained"]) <= samples_in
