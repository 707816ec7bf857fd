"""Faults around a running monitor: signals, Zenoh peers and routers going away, sinks that cannot write,
bad model files. Real ``feedmon run`` subprocesses and real Zenoh on loopback (free ports)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh
from sink_states import WORKING
from test_bad_input import AXIS, PREFIX, MonitorProc, blocks_of, rows, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_blocks, read_trial
from monitor.axes import live_meta, load_axes
from monitor.daemon import Monitor
from monitor.sinks.mcap_sink import McapSink
from monitor.warm import warm_up
from replay.player import replay


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "faults", duration=4.0, seed=7)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _publisher(session, trial):
    pub = session.declare_publisher(T.samples_key(PREFIX, trial.machine, trial.axis),
                                    congestion_control=zenoh.CongestionControl.BLOCK)
    assert T.wait_for_matching(pub, 15.0), "the monitor's subscriber never matched"
    return pub


# ---- signals -------------------------------------------------------------------------------
def test_sigterm_then_sigint_finish_mcap_save_and_restore_state(work, trial):
    n = len(trial)
    state = work / "state-sig"
    for i, (sig, fresh) in enumerate(((signal.SIGTERM, ["--fresh"]), (signal.SIGINT, []))):
        out = work / f"sig{i}.mcap"
        mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--mcap", str(out), "--state-dir", str(state), *fresh],
                          cwd=work)
        if i == 1:
            assert "tracker state restored" in mon.stderr, mon.stderr
        with T.open_session(connect=mon.endpoint) as s:
            replay(work / "trial.mcap", s, rate=None, prefix=PREFIX, truth=False, wait_for_subscriber=10.0)
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["estimates_out"] == n)
        assert st["axes"][AXIS]["state"]["origin"] == ("fresh" if i == 0 else "restored")
        rc = mon.stop(sig)
        assert rc == 0, mon.stderr
        assert f"{sig.name}: stopping" in mon.stderr and "tracker state saved" in mon.stderr
        tr = read_trial(out)  # finished and readable (summary + footer)
        assert len(tr) == n
        assert rows(b for _, b in iter_blocks(out, AXIS, kinds=("disturbance",)))["seq"].tolist() == list(range(n))
        sf = state / "linear-drive+Z.state.npz"
        assert sf.exists()
        with np.load(sf, allow_pickle=False) as z:
            assert int(z["estimator.trained"]) == (n - 1) * (i + 1)  # the second run continued the first


# ---- Zenoh: a publisher restarts -------------------------------------------------------------
def test_publisher_restart_gap_reported(work, trial):
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--state-dir", str(work / "st-pub")], cwd=work)
    try:
        with T.open_session(connect=mon.endpoint) as s:  # first life of the controller bridge
            pub = _publisher(s, trial)
            for b in blocks_of(trial, 0, 300):
                pub.put(S.encode(b))
            wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 299)
        # it disconnected; samples 300..399 are lost; a new session (a restarted process) continues at 400
        with T.open_session(connect=mon.endpoint) as s:
            pub = _publisher(s, trial)
            probes = _probe_until_seen(s, pub, mon.proc.pid)  # the new session's route carries data
            for b in blocks_of(trial, 400, 700):
                pub.put(S.encode(b))
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 699)
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    a = st["axes"][AXIS]
    got = (a["gaps"], a["missing_samples"], a["samples_in"], a["estimates_out"])
    assert got == (1, 100, 600, 600), (a, st["input"], mon.stderr)
    assert 1 <= a["drops"]["malformed"] <= probes and set(a["drops"]) == {"malformed"}  # the probes, nothing else
    assert st["monitor"]["state"] == "running"
    assert mon.count("after a sequence gap") == 1


# ---- Zenoh: the router between publisher and monitor restarts -------------------------------------
ROUTER = """
import json, sys, time, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"router"')
c.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
print("router up", flush=True)
while True:
    time.sleep(1)
"""


def _router(endpoint: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", ROUTER, endpoint], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "router up"
    return p


PROBE = b"route probe (not a sample block)"


def _probe_until_seen(session, pub, pid: int, timeout: float = 60.0) -> int:
    """Put a probe (an undecodable payload, counted ``malformed`` on the publisher's axis and nothing
    else) through ``pub`` until the monitor's status counts one; returns the probes sent."""
    deadline = time.monotonic() + timeout
    sent = 0
    while True:
        pub.put(PROBE)
        sent += 1
        try:
            wait_status(session, pid=pid, timeout=2.0,
                        pred=lambda x: x["axes"][AXIS]["drops"].get("malformed", 0) >= 1)
            return sent
        except AssertionError:
            assert time.monotonic() < deadline, "no probe reached the monitor after the router restart"


def test_router_restart_monitor_reconnects_and_reports_gap(work, trial):
    endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
    router = _router(endpoint)
    mon = None
    try:
        mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--state-dir", str(work / "st-router"),
                           "--connect", endpoint], cwd=work, listen=False)
        assert "connected to " + endpoint in mon.stderr
        with T.open_session(mode="client", connect=endpoint) as s:
            pub = _publisher(s, trial)
            for b in blocks_of(trial, 0, 300):
                pub.put(S.encode(b))
            wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 299)
            router.kill()
            router.wait(10)
            for b in blocks_of(trial, 300, 400):  # published while the router is down: lost
                pub.put(S.encode(b))
            router = _router(endpoint)  # same port; both clients reconnect by themselves
            # The publisher's matching status survives the router's death (nobody told it the subscriber
            # went away), so it proves nothing. Proof that the route publisher -> router -> monitor exists
            # again: a probe sent through the same publisher shows up in the monitor's status.
            probes = _probe_until_seen(s, pub, mon.proc.pid)
            for b in blocks_of(trial, 400, 700):
                pub.put(S.encode(b))
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 699)
        assert mon.proc.poll() is None  # survived the router restart
    finally:
        rc = mon.stop() if mon is not None else None
        router.kill()
        router.wait(10)
    assert rc == 0, mon.stderr
    a = st["axes"][AXIS]
    assert (a["gaps"], a["missing_samples"], a["samples_in"], a["estimates_out"]) == (1, 100, 600, 600)
    assert 1 <= a["drops"]["malformed"] <= probes and set(a["drops"]) == {"malformed"}  # the probes, nothing else


# ---- sinks ---------------------------------------------------------------------------------
def test_no_rerun_viewer_nothing_blocks(work, trial):
    n = len(trial)
    port = T.free_tcp_port()
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--serve-rerun", str(port), "--mcap", str(work / "norr.mcap"),
                       "--fresh", "--state-dir", str(work / "st-rr")], cwd=work)
    try:
        assert "rerun --connect" in mon.stderr
        with T.open_session(connect=mon.endpoint) as s:
            replay(work / "trial.mcap", s, rate=None, prefix=PREFIX, truth=False, wait_for_subscriber=10.0, block=5)
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["estimates_out"] == n, timeout=20)
    finally:
        rc = mon.stop(timeout=90)
    assert rc == 0, mon.stderr
    assert "did not finish" not in mon.stderr  # every sink closed by itself, none waited for a viewer
    sinks = {x["name"]: x for x in st["sinks"]}
    assert sinks["rerun"]["state"] in WORKING and sinks["rerun"]["failures"] == 0  # degraded: late on a loaded host
    assert st["axes"][AXIS]["dropped_total"] == 0
    assert len(read_trial(work / "norr.mcap")) == n


# (a full disk under the MCAP log: tests/test_sink_faults.py)


class _SlowFile:
    """A file handle on a disk that writes ``rate`` bytes/s (sleeps in write) until ``fast`` is set."""

    def __init__(self, fh, rate: float, fast: threading.Event):
        self._fh, self._rate, self._fast = fh, rate, fast

    def write(self, data) -> int:
        if not self._fast.is_set():
            time.sleep(len(data) / self._rate)
        return self._fh.write(data)

    def __getattr__(self, name):
        return getattr(self._fh, name)


def test_slow_disk_mcap_sink_never_stalls_estimation(work, trial, monkeypatch):
    """In process (the slowness must be injected into the sink's file handle): a real McapSink whose file
    writes at 20 kB/s behind a real Monitor on real Zenoh. Estimation keeps pace; the sink queue fills and
    its drops are counted in the status; once the disk is fast again the file closes complete and readable."""
    import builtins

    import feedio.trialwriter as trialwriter

    fast = threading.Event()
    real_open = builtins.open
    monkeypatch.setattr(trialwriter, "open", lambda *a, **k: _SlowFile(real_open(*a, **k), 20_000.0, fast),
                        raising=False)
    n = len(trial)
    axes = load_axes([work / "z.model.toml"])
    warm_up(axes)
    out = work / "slow.mcap"
    sink = McapSink(out, metas=[live_meta(a) for a in axes.values()], maxsize=200, flush_seconds=0.1)
    ep = f"tcp/127.0.0.1:{T.free_tcp_port()}"
    with T.open_session(listen=ep) as ms:
        mon = Monitor(axes, ms, prefix=PREFIX, sinks=[sink])
        mon.start()
        try:
            with T.open_session(connect=ep) as s:
                replay(work / "trial.mcap", s, rate=None, prefix=PREFIX, truth=False, wait_for_subscriber=10.0,
                       block=1)
                st = wait_status(s, pid=os.getpid(), pred=lambda x: x["axes"][AXIS]["estimates_out"] == n, timeout=60)
        finally:
            fast.set()
            mon.stop()
    sk = st["sinks"][0]
    assert sk["dropped"] > 0 and sk["written"] < sk["accepted"], sk  # the sink fell behind, visibly
    a = st["axes"][AXIS]
    # every estimate was out while the sink was still behind: estimation never waited for the disk
    assert a["dropped_total"] == 0 and a["estimates_out"] == n and st["input"]["queue_full"] == 0
    tr = read_trial(out)  # complete file with what was written
    assert 0 < len(tr) < n


# ---- bad model files ------------------------------------------------------------------------


@pytest.mark.parametrize("name,edit,needle", [
    ("garbage", lambda s: "this is [not toml", "not a valid TOML model file"),
    ("noversion", lambda s: s.replace("format_version = 2", ""), "format_version"),
    ("version99", lambda s: s.replace("format_version = 2", "format_version = 99"), "format_version"),
    ("nanbeta", lambda s: _set_beta(s, "[nan, 0.1]"), "model.beta"),
    ("shortbeta", lambda s: _set_beta(s, "[0.5]"), "model.beta"),
    ("badform", lambda s: s.replace('form = "velocity-loop"', 'form = "hydraulic"'), "model.form"),
    ("missing", None, "not found"),
])
def test_bad_model_file_clear_error_nonzero_exit(work, name, edit, needle):
    src = (work / "z.model.toml").read_text()
    path = work / f"bad-{name}.model.toml"
    if edit is not None:
        changed = edit(src)
        assert changed != src
        path.write_text(changed)
    r = subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--model", str(path), "--listen",
                        f"tcp/127.0.0.1:{T.free_tcp_port()}", "--prefix", PREFIX], capture_output=True, text=True,
                       timeout=60, cwd=work)
    assert r.returncode != 0
    assert str(path) in r.stderr and needle in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) <= 2, r.stderr


def _set_beta(src: str, value: str) -> str:
    import re

    return re.sub(r"(?m)^beta = .*$", f"beta = {value}", src, count=1)


def test_mismatched_or_corrupt_state_file_starts_fresh_with_warning(work, trial):
    """A tracker state of another model, or a corrupt one, is not used: warning naming it, fresh start; what
    the axis then learns replaces it at exit."""
    state = work / "st-bad"
    state.mkdir()
    sf = state / "linear-drive+Z.state.npz"
    sf.write_bytes(b"PK\x03\x04 definitely not a zip")
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--state-dir", str(state)], cwd=work)
    try:
        assert "unreadable" in mon.stderr and str(sf) in mon.stderr
        with T.open_session(connect=mon.endpoint) as s:
            pub = _publisher(s, trial)
            for b in blocks_of(trial, 0, 300):
                pub.put(S.encode(b))
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["last_seq"] == 299)
        assert st["axes"][AXIS]["state"]["origin"] == "unreadable"
    finally:
        assert mon.stop() == 0, mon.stderr
    with np.load(sf, allow_pickle=False) as z:  # replaced by a good state at exit
        state_sha = str(z["meta.model_sha256"][()])
    other = work / "other.model.toml"  # same axis, other hyperparameters -> other hash
    other.write_text((work / "z.model.toml").read_text().replace("forgetting = 0.996", "forgetting = 0.99"))
    mon = MonitorProc(prefix=PREFIX, args=["--model", str(other), "--state-dir", str(state)], cwd=work)
    try:
        assert "saved with another model file" in mon.stderr and state_sha[:8] in mon.stderr, mon.stderr
    finally:
        assert mon.stop() == 0
