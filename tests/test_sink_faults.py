"""Sink faults through the real path: a ``feedmon run`` subprocess with its real MCAP and Rerun child
processes, real files, real Zenoh on loopback; the children stopped (SIGSTOP) or killed (SIGKILL), output
directories read-only, removed, shared or full. Each test asserts the counts (every message offered to a
sink ends written, dropped or lost — and what is on disk agrees), the state the status shows, the exit code,
and that estimation went on. Tests wait on conditions (status queries), never on sleeps."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import pytest
import zenoh
from sink_states import WORKING
from test_bad_input import AXIS, PREFIX, MonitorProc, blocks_of, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_file, read_trial
from replay.recover import recover

#: seconds a sink child may be silent (or its pipe full, or its writer stuck) before it is replaced, in these
#: tests (the default is 10 s); with "low" priority a busy CI machine cannot starve the children into a stall
CONFIG = """[run]
sink_stall_seconds = {stall}
sink_priority = "low"
min_free_mb = {free}
"""


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "sink_faults", duration=6.0, seed=5)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _config(d: Path, stall: float = 5.0, free: float = 0.0) -> str:
    path = d / f"run-{stall}-{free}.toml"
    path.write_text(CONFIG.format(stall=stall, free=free))
    return str(path)


class Feeder:
    """Publishes the trial again and again (sequence numbers and times continued), 5 samples a block, about
    three times real time, on a thread, until :meth:`stop`; ``sent`` counts the samples."""

    def __init__(self, endpoint: str, trial) -> None:
        self.session = T.open_session(connect=endpoint)
        self.pub = self.session.declare_publisher(T.samples_key(PREFIX, trial.machine, trial.axis),
                                                  congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(self.pub, 15.0), "the monitor's subscriber never matched"
        self.blocks = blocks_of(trial, 0, len(trial), 5)
        self.n, self.span = len(trial), float(trial.t[-1] - trial.t[0]) + float(trial.meta.Ts)
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            for b in self.blocks:
                if self._stop.is_set():
                    return
                self.pub.put(S.encode(msgspec.structs.replace(b, seq=b.seq + k * self.n,
                                                              t=[x + k * self.span for x in b.t])))
                self.sent += len(b.t)
                time.sleep(0.005)
            k += 1

    def stop(self) -> int:
        self._stop.set()
        self._thread.join(30)
        return self.sent

    def close(self) -> None:
        self.stop()
        self.session.close()


def _sink(st: dict, name: str) -> dict:
    return next(s for s in st["sinks"] if s["name"] == name)


def _on_disk(files: list[str], tmp: Path) -> int:
    """Block messages (samples, estimates, health) in MCAP files; an incomplete one is finished by recover first."""
    n = 0
    for i, f in enumerate(files):
        fixed = tmp / f"fixed-{i}.mcap"
        rep = recover(f, fixed)
        assert rep.skipped_ranges == 0, rep.summary()  # what reached the disk is intact
        n += sum(1 for _ in iter_file(fixed, [AXIS], kinds=("samples", "disturbance", "health")))
    return n


def _stderr_sane(mon: MonitorProc, sink: str, most: int) -> None:
    """No traceback for a known condition; the sink's log lines rate-limited."""
    assert "Traceback" not in mon.stderr, mon.stderr
    assert mon.count(f"sink {sink}") <= most, mon.stderr


# ---- stalled and killed children ----------------------------------------------------------------------
def test_stalled_and_killed_sink_children_are_replaced_and_their_losses_counted(work, trial, tmp_path):
    """SIGSTOP of the MCAP process, SIGKILL of the Rerun process while data flows: each is detected (the status
    leaves "ok" at once), killed, counted and replaced with a new file; the state is ok again once the new
    process wrote. Then the new MCAP process is stopped too and the monitor is told to stop: the stop finishes
    within its bound anyway, exit 1 (data were lost), and every count agrees with the files."""
    logs, rrd = tmp_path / "logs", tmp_path / "rec.rrd"
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                     str(tmp_path / "st"), "--mcap", str(logs), "--rrd", str(rrd),
                                                     "--config", _config(tmp_path)])
    feeder = Feeder(mon.endpoint, trial)
    stopped = []
    try:
        with T.open_session(connect=mon.endpoint) as s:
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["samples_in"] > 500
                             and _sink(x, "mcap")["written"] > 0 and _sink(x, "rerun")["written"] > 0)
            mcap_pid, rerun_pid = _sink(st, "mcap")["pid"], _sink(st, "rerun")["pid"]
            os.kill(mcap_pid, signal.SIGSTOP)
            stopped.append(mcap_pid)
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: _sink(x, "mcap")["state"] != "ok")
            assert _sink(st, "mcap")["state"] in ("degraded", "failed")  # not "ok" while it hangs
            os.kill(rerun_pid, signal.SIGKILL)
            st = wait_status(s, pid=mon.proc.pid, timeout=60, pred=lambda x: all(
                _sink(x, k)["restarts"] >= 1 and _sink(x, k)["state"] in WORKING and _sink(x, k)["pid"] != p
                for k, p in (("mcap", mcap_pid), ("rerun", rerun_pid))))
            mc, rr = _sink(st, "mcap"), _sink(st, "rerun")
            # one restart each, or more when a loaded host starved a new child past the stall time too
            assert "stalled" in mc["last_error"] and mc["lost"] > 0 and len(mc["files"]) == 1 + mc["restarts"], mc
            assert mc["incomplete_files"] == mc["files"][:mc["restarts"]]
            assert rr["last_error"] and rr["rrd_files"][:2] == [str(rrd), str(tmp_path / "rec-001.rrd")], rr
            assert len(rr["rrd_files"]) == 1 + rr["restarts"], rr
            sent = feeder.stop()
            st = wait_status(s, pid=mon.proc.pid, timeout=60,
                             pred=lambda x: x["axes"][AXIS]["estimates_out"] == sent)
            assert st["axes"][AXIS]["dropped_total"] == 0  # estimation went on, sample for sample
            second = _sink(st, "mcap")["pid"]
        os.kill(second, signal.SIGSTOP)  # and now stop the monitor while its MCAP process hangs
        stopped.append(second)
        t0 = time.monotonic()
        rc = mon.stop(timeout=120)
        took = time.monotonic() - t0
    finally:
        feeder.close()
        for pid in stopped:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if mon.proc.poll() is None:
            mon.stop()
    assert rc == 1, mon.stderr
    assert took < 3 * 5 + 10, took  # the stall (5 s) of a send, of the finish, and a replacement started, at most
    assert "sink mcap: " in mon.stderr and "messages not written" in mon.stderr
    _stderr_sane(mon, "mcap", 8)
    _stderr_sane(mon, "rerun", 8)
    final = _summary_counts(mon.stderr, "mcap")
    assert final["written"] + final["dropped"] + final["lost"] == final["offered"], final
    files = sorted(str(p) for p in logs.glob("*.mcap"))
    assert len(files) >= 2
    on_disk = _on_disk(files, tmp_path)
    assert final["written"] <= on_disk <= final["written"] + final["lost"], (final, on_disk)


def _summary_counts(stderr: str, sink: str) -> dict[str, int]:
    """``N messages offered, W written, D dropped, L lost`` of the stop summary's line of ``sink``."""
    import re

    line = next(x for x in stderr.splitlines() if x.startswith(f"feedmon run: sink {sink}: ") and " offered" in x)
    m = re.search(r"(\d+) messages offered, (\d+) written, (\d+) dropped, (\d+) lost", line)
    assert m, line
    return dict(zip(("offered", "written", "dropped", "lost"), map(int, m.groups())))


# ---- output directories -----------------------------------------------------------------------------
@contextlib.contextmanager
def _unwritable(d: Path):
    """``d`` made unwritable for root too: a read-only bind mount, else the immutable attribute (permission
    bits are not enough: root ignores them)."""
    d.mkdir(parents=True, exist_ok=True)
    if subprocess.run(["mount", "--bind", str(d), str(d)], capture_output=True).returncode == 0:
        try:
            r = subprocess.run(["mount", "-o", "remount,ro,bind", str(d)], capture_output=True, text=True)
            assert r.returncode == 0, r.stderr
            yield "Read-only file system"
        finally:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)
        return
    r = subprocess.run(["chattr", "+i", str(d)], capture_output=True, text=True)
    assert r.returncode == 0, f"neither a read-only bind mount nor chattr +i works here: {r.stderr}"
    try:
        yield "Operation not permitted"
    finally:
        subprocess.run(["chattr", "-i", str(d)], capture_output=True)


@contextlib.contextmanager
def _tmpfs(d: Path, size: str):
    """A small tmpfs at ``d`` (we are root here and in CI)."""
    d.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(d)], capture_output=True, text=True)
    assert r.returncode == 0, f"cannot mount a tmpfs (root needed): {r.stderr}"
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def _run(work: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--model", "z.model.toml", "--prefix", PREFIX,
                           "--listen", f"tcp/127.0.0.1:{T.free_tcp_port()}", *args], cwd=work, capture_output=True,
                          text=True, timeout=120)


def test_outputs_that_cannot_be_written_are_refused_at_start(work, tmp_path):
    """A read-only directory (for root too), or one with less room than min_free_mb: refused before anything
    starts, exit 2, naming the option, the directory and the fix; no file anywhere."""
    ro = tmp_path / "ro"
    with _unwritable(ro) as why:
        for args, option in (([" --mcap", str(ro)], "--mcap"), (["--mcap", str(ro / "log.mcap")], "--mcap"),
                             (["--rrd", str(ro / "rec.rrd")], "--rrd"), (["--state-dir", str(ro)], "--state-dir")):
            args = [a.strip() for a in args]
            r = _run(work, *args)
            assert r.returncode == 2, (args, r.stderr)
            assert f"{option}: cannot write a file in {ro}: {why}" in r.stderr and "choose another" in r.stderr, r.stderr
            assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) <= 2, r.stderr
    assert list(ro.iterdir()) == []
    with _tmpfs(tmp_path / "small", "1m") as small:
        r = _run(work, "--mcap", str(small), "--config", _config(tmp_path, free=4))
        assert r.returncode == 2 and f"MiB free in {small}, less than min_free_mb = 4" in r.stderr, r.stderr
        assert list(small.iterdir()) == []


def test_mcap_directory_removed_while_running_is_made_again_and_the_loss_said(work, trial, tmp_path):
    """``rm -r`` of the log directory under a running monitor: the sink notices (the file it writes is gone),
    says so (state failed, the file listed as removed, the messages in it counted), makes the directory again
    and logs on into a new file there; the exit code says data were lost."""
    logs = tmp_path / "logs"
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                     str(tmp_path / "st"), "--mcap", str(logs),
                                                     "--config", _config(tmp_path)])
    feeder = Feeder(mon.endpoint, trial)
    try:
        with T.open_session(connect=mon.endpoint) as s:
            wait_status(s, pid=mon.proc.pid, pred=lambda x: _sink(x, "mcap")["written"] > 100)
            first = next(logs.glob("*.mcap"))
            shutil.rmtree(logs)
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: _sink(x, "mcap")["removed_files"] == [str(first)])
            mc = _sink(st, "mcap")  # (failed until the new file took a write: it may be ok again already)
            assert mc["failures"] >= 1 and "removed" in mc["last_error"] and mc["removed"] > 100, mc
            # a new file in the directory made again (and more, when a loaded host starved a logger past its stall)
            st = wait_status(s, pid=mon.proc.pid, timeout=60, pred=lambda x: _sink(x, "mcap")["state"] in WORKING
                             and len(_sink(x, "mcap")["files"]) >= 2)
            second = Path(_sink(st, "mcap")["files"][1])
            assert second.parent == logs and second.exists()
            sent = feeder.stop()
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["estimates_out"] == sent)
            assert st["axes"][AXIS]["dropped_total"] == 0  # estimation went on
    finally:
        feeder.close()
        rc = mon.stop()
    assert rc == 1, mon.stderr
    assert "written to files removed while open" in mon.stderr and str(first) in mon.stderr
    final = _summary_counts(mon.stderr, "mcap")
    assert final["written"] + final["dropped"] + final["lost"] == final["offered"], final
    removed = int(mon.stderr.split(" written to files removed while open")[0].rsplit(" ", 1)[-1])
    later = sorted(str(p) for p in logs.glob("*.mcap"))  # the new file and any after it
    assert str(second) in later
    on_disk = _on_disk(later, tmp_path)
    if len(later) == 1:
        assert on_disk == final["written"] - removed  # what is on disk, exactly
    else:  # a starved logger was replaced as well: its file ends on its last complete record
        assert final["written"] - removed <= on_disk + final["lost"], (final, on_disk)
    _stderr_sane(mon, "mcap", 6)


def test_two_monitors_logging_into_one_directory_never_share_a_file(work, trial, tmp_path):
    """Two monitors started together on one --mcap directory (in the same second, as likely as not): each
    logs into a file of its own (named by its process, created exclusively), which holds all of its blocks.
    (A file given twice: ``test_sinks.py``.)"""
    from concurrent.futures import ThreadPoolExecutor

    d = tmp_path / "shared"
    d.mkdir()

    def start(i: int) -> MonitorProc:
        return MonitorProc(prefix=f"{PREFIX}-{i}", cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                                  str(tmp_path / f"st{i}"), "--mcap", str(d)])

    with ThreadPoolExecutor(2) as pool:
        mons = list(pool.map(start, range(2)))
    counts = (300, 200)
    try:
        for i, (mon, n) in enumerate(zip(mons, counts)):
            with T.open_session(connect=mon.endpoint) as s:
                pub = s.declare_publisher(T.samples_key(f"{PREFIX}-{i}", trial.machine, trial.axis),
                                          congestion_control=zenoh.CongestionControl.BLOCK)
                assert T.wait_for_matching(pub, 15.0)
                for b in blocks_of(trial, 0, n, 10):
                    pub.put(S.encode(b))
                wait_status(s, prefix=f"{PREFIX}-{i}", pid=mon.proc.pid,
                            pred=lambda x, n=n: x["axes"][AXIS]["estimates_out"] == n)
    finally:
        rcs = [m.stop() for m in mons]
    assert rcs == [0, 0], [m.stderr for m in mons]
    files = [m.stderr.split("MCAP log: ")[1].split()[0] for m in mons]
    assert files[0] != files[1] and sorted(str(p) for p in d.iterdir()) == sorted(files), files
    for f, n in zip(files, counts):
        assert len(read_trial(f)) == n  # every block of its own monitor, none of the other's


def test_full_disk_says_what_was_written_and_what_was_lost(work, trial, tmp_path):
    """The log's disk fills up under a running monitor: estimation goes on; the sink fails visibly; at stop
    the summary's "written" is what the file holds (recover finishes it), the rest is counted lost, and the
    exit code says so."""
    with _tmpfs(tmp_path / "disk", "4m") as disk:
        mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                         str(tmp_path / "st"), "--mcap", str(disk / "log.mcap"),
                                                         "--config", _config(tmp_path, free=1)])
        feeder = Feeder(mon.endpoint, trial)
        try:
            with T.open_session(connect=mon.endpoint) as s:
                wait_status(s, pid=mon.proc.pid, pred=lambda x: _sink(x, "mcap")["written"] > 100)
                with open(disk / "filler", "wb") as fh:  # the rest of the disk, but for a few kB
                    with contextlib.suppress(OSError):
                        fh.write(b"\0" * (4 * 2**20 - (disk / "log.mcap").stat().st_size - 24 * 1024))
                st = wait_status(s, pid=mon.proc.pid, pred=lambda x: _sink(x, "mcap")["flush_failures"] > 0)
                assert _sink(st, "mcap")["state"] == "failed" and "No space left" in _sink(st, "mcap")["last_error"]
                sent = feeder.stop()
                st = wait_status(s, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["estimates_out"] == sent)
                assert st["axes"][AXIS]["dropped_total"] == 0  # estimation unaffected
        finally:
            feeder.close()
            rc = mon.stop()
        assert rc == 1, mon.stderr
        final = _summary_counts(mon.stderr, "mcap")
        assert final["lost"] > 0 and final["written"] + final["dropped"] + final["lost"] == final["offered"], final
        assert _on_disk([str(disk / "log.mcap")], tmp_path) == final["written"], final  # "written" is on disk
        assert (tmp_path / "st" / "linear-drive+Z.state.npz").exists()  # the state went elsewhere: saved
        _stderr_sane(mon, "mcap", 6)


# ---- a host kept busy by other work ---------------------------------------------------------------------
@contextlib.contextmanager
def _cpu_hogs(n: int):
    """``n`` processes spinning at normal priority: every core busy with other work, as on a shared host."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield hogs
    finally:
        for h in hogs:
            h.kill()
            h.wait()


def test_the_log_keeps_up_on_a_host_kept_busy_by_other_work(work, trial, tmp_path):
    """With the default sink priority, two spinning processes on every core (more than this machine has)
    do not starve the MCAP child: it is never taken for stalled, nothing is lost, every block reaches the
    file, the stop exits 0. (An idle-class child gets no CPU at all on such a host.)"""
    logs = tmp_path / "logs"
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                     str(tmp_path / "st"), "--mcap", str(logs)])
    n = 600
    with _cpu_hogs(2 * (os.cpu_count() or 2)):  # (started once the monitor is up: the claim is the log's)
        try:
            with T.open_session(connect=mon.endpoint) as s:
                pub = s.declare_publisher(T.samples_key(PREFIX, trial.machine, trial.axis),
                                          congestion_control=zenoh.CongestionControl.BLOCK)
                assert T.wait_for_matching(pub, 15.0)
                for b in blocks_of(trial, 0, n, 10):
                    pub.put(S.encode(b))
                st = wait_status(s, prefix=PREFIX, pid=mon.proc.pid, timeout=300.0,
                                 pred=lambda x: x["axes"][AXIS]["estimates_out"] == n)
                assert _sink(st, "mcap")["state"] in WORKING and _sink(st, "mcap")["lost"] == 0, st
        finally:
            rc = mon.stop()
    assert rc == 0, mon.stderr
    assert "stalled" not in mon.stderr, mon.stderr
    assert len(read_trial(mon.stderr.split("MCAP log: ")[1].split()[0])) == n


def test_a_starved_child_is_told_from_a_stopped_or_sleeping_one():
    """What decides between waiting for a late child (starved: runnable) and replacing it (stalled): a
    spinning process is runnable and uses CPU; stopped (SIGSTOP) or sleeping, it is not runnable."""
    from monitor.sinks.child import cpu_state

    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    sleep = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        deadline = time.monotonic() + 60
        while not (cpu_state(spin.pid)[0] > 0.05 and cpu_state(spin.pid)[1]) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert cpu_state(spin.pid)[1] and cpu_state(spin.pid)[0] > 0.05
        os.kill(spin.pid, signal.SIGSTOP)
        while cpu_state(spin.pid)[1] and time.monotonic() < deadline:
            time.sleep(0.05)
        used = cpu_state(spin.pid)[0]
        assert not cpu_state(spin.pid)[1] and cpu_state(spin.pid)[0] == used
        while cpu_state(sleep.pid)[1] and time.monotonic() < deadline:  # (its start-up may still run)
            time.sleep(0.05)
        assert cpu_state(sleep.pid)[1] is False
    finally:
        for p in (spin, sleep):
            p.kill()
            p.wait()
    assert cpu_state(spin.pid) is None  # gone: nothing to read
