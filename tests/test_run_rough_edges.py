"""What a new user meets first, through the command line: the stop summary of a monitor that estimated
nothing, a start that fails half-way (no stub log left, a message that says what to do), the MCAP file the
start message names, a Rerun recording on a machine too busy to flush in time (no traceback), tracker
states of two axes whose old file names collided."""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap

import msgspec
import pytest
import zenoh
from test_bad_input import AXIS, PREFIX, MonitorProc, blocks_of, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import read_trial


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "rough_edges", duration=4.0, seed=8)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _put(endpoint: str, key: str, blocks) -> None:
    with T.open_session(connect=endpoint) as s:
        pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(pub, 15.0)
        for b in blocks:
            pub.put(S.encode(b))


def test_the_stop_summary_of_a_monitor_that_estimated_nothing_is_plain(work, trial, tmp_path):
    """Only samples of an axis without a model arrived: no "None µs", no empty list of refusals; the MCAP file
    the start message names is the one written (with a directory: its -000 file)."""
    logs = tmp_path / "logs"
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                     str(tmp_path / "st"), "--mcap", str(logs)])
    try:
        named = mon.stderr.split("MCAP log: ")[1].split()[0]
        assert named.endswith("-000.mcap") and [str(p) for p in logs.iterdir()] == [named]
        other = [msgspec.structs.replace(b, axis="Q") for b in blocks_of(trial, 0, 100, 10)]
        _put(mon.endpoint, T.samples_key(PREFIX, trial.machine, "Q"), other)
        with T.open_session(connect=mon.endpoint) as s:
            wait_status(s, pid=mon.proc.pid, pred=lambda x: x["input"]["no_model_blocks"] == 10)
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    err = mon.stderr
    assert "None" not in err and "(messages): ;" not in err and "input refused" not in err, err
    assert f"{AXIS}: 0 blocks, 0 samples in, 0 estimates out, 0 dropped, 0 gaps; latency: no estimate published" in err
    assert "samples of axes without a model (not estimated): 100" in err
    assert f"sink mcap: 0 messages offered, 0 written, 0 dropped, 0 lost, 0 failures; {named}" in err
    from feedio.mcapio import list_axes

    assert list_axes(named) == [AXIS]  # a valid log (summary and footer written), of no sample


def test_a_start_that_fails_half_way_leaves_no_stub_and_says_why(work, tmp_path):
    """The MCAP sink started, then the Zenoh endpoint is taken: exit 2 with the reason, and the empty log the
    sink had made is removed. A recording that cannot be made is named the same way, with no log at all."""
    logs = tmp_path / "logs"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--model", "z.model.toml", "--prefix", PREFIX,
                            "--listen", f"tcp/127.0.0.1:{port}", "--mcap", str(logs), "--fresh"], cwd=work,
                           capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "MCAP log: " in r.stderr and "Traceback" not in r.stderr
    assert list(logs.iterdir()) == []  # the stub is gone
    (tmp_path / "taken.rrd").mkdir()
    r = subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--model", "z.model.toml", "--prefix", PREFIX,
                        "--listen", f"tcp/127.0.0.1:{T.free_tcp_port()}", "--mcap", str(logs), "--rrd",
                        str(tmp_path / "taken.rrd"), "--fresh"], cwd=work, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "the Rerun recording process" in r.stderr and "Is a directory" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and list(logs.iterdir()) == []


def test_a_recording_process_that_does_not_start_in_time_says_what_to_do():
    from monitor.sinks.rerun_process import RerunProcessSink

    with pytest.raises(OSError, match=r"the Rerun recording process did not start in 0.05 s \(start_timeout; a "
                                      r"machine this busy, or a slow first import\)"):
        RerunProcessSink(None, start_timeout=0.05)


_SLOW_FLUSH = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, sys.argv[2])
    from test_dashboard import est_block
    from monitor.sinks.rerun_process import RerunProcessSink

    if __name__ == "__main__":
        # every flush times out (a busy machine), but never broken_after times in a row before the end
        sink = RerunProcessSink(sys.argv[1], flush_interval=0.05, flush_timeout=1e-9, broken_after=10**6,
                                report_interval=0.05, batch_interval=0.02)
        deadline = time.monotonic() + 60
        k = 0
        # on a loaded host "the process is late" may come first: wait for the flush's own reason
        while ("a flush of the recording did not finish" not in str(sink.status().get("degraded") or "")
               and time.monotonic() < deadline):
            sink.offer(est_block(50 * k, 50))
            k += 1
            time.sleep(0.01)
        print("seen", sink.status()["state"], sink.status().get("degraded"))
        assert sink.close(timeout=60)
        st = sink.status()
        print("closed", st["state"], st["failures"], st["written"], st["lost"], st["offered"])
""")


def test_flushes_that_time_out_on_a_busy_machine_degrade_the_recording_without_a_traceback(tmp_path):
    """`feedmon demo` printed a Rerun "Flush timed out" traceback before succeeding: a flush that is only slow
    is not a failure (Rerun still holds the data); the sink says "degraded", logs nothing alarming, and the
    recording is complete."""
    from pathlib import Path

    script = tmp_path / "slow_flush.py"
    script.write_text(_SLOW_FLUSH)
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "slow.rrd"), str(Path(__file__).parent)],
                       capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    seen = next(x for x in r.stdout.splitlines() if x.startswith("seen"))
    assert seen.startswith("seen degraded a flush of the recording did not finish"), r.stdout
    closed = next(x for x in r.stdout.splitlines() if x.startswith("closed")).split()
    assert closed[1:3] == ["closed", "0"] and closed[3] == closed[5] and closed[4] == "0", r.stdout  # all written
    assert "Traceback" not in r.stderr and "timed out" not in r.stderr.lower(), r.stderr
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(tmp_path / "slow.rrd")],
                            capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr


def test_two_axes_whose_old_state_names_collided_each_keep_their_own(work, trial, tmp_path):
    """``cell_3``/``X`` and ``cell``/``3_X`` (both ``cell_3_X.state.npz`` before): through ``feedmon run``,
    both learn, both are saved, both are restored by the next start."""
    models = []
    for machine, axis in (("cell_3", "X"), ("cell", "3_X")):
        text = (work / "z.model.toml").read_text().replace('machine = "linear-drive"', f'machine = "{machine}"')
        path = tmp_path / f"{machine}-{axis}.model.toml"
        path.write_text(text.replace('axis = "Z"', f'axis = "{axis}"'))
        models += ["--model", str(path)]
    state = tmp_path / "st"
    counts = {("cell_3", "X"): 300, ("cell", "3_X"): 200}
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=[*models, "--state-dir", str(state)])
    try:
        for (machine, axis), n in counts.items():
            blocks = [msgspec.structs.replace(b, machine=machine, axis=axis) for b in blocks_of(trial, 0, n, 10)]
            _put(mon.endpoint, T.samples_key(PREFIX, machine, axis), blocks)
        with T.open_session(connect=mon.endpoint) as s:
            wait_status(s, pid=mon.proc.pid, pred=lambda x: all(x["axes"][f"{m}/{a}"]["samples_in"] == n
                                                                for (m, a), n in counts.items()))
    finally:
        assert mon.stop() == 0, mon.stderr
    assert sorted(p.name for p in state.iterdir()) == ["cell+3_X.state.npz", "cell_3+X.state.npz"]
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=[*models, "--state-dir", str(state)])
    try:
        assert mon.count("tracker state restored") == 2, mon.stderr
        assert "299 samples learned" in mon.stderr and "199 samples learned" in mon.stderr  # each its own
        with T.open_session(connect=mon.endpoint) as s:
            st = wait_status(s, pid=mon.proc.pid, pred=lambda x: True)
        for machine, axis in counts:
            assert st["axes"][f"{machine}/{axis}"]["state"]["origin"] == "restored"
    finally:
        assert mon.stop() == 0, mon.stderr
