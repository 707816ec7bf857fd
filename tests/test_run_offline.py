"""``feedmon run --from`` (offline), the monitor's robustness counters, ``feedmon status`` (tracker state files:
``test_state.py``)."""

from __future__ import annotations

import logging
import re
import time
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.limits import InputLimits
from feedio.mcapio import iter_blocks, read_trial
from feedmon import cli
from monitor.axes import load_axes
from monitor.daemon import Monitor
from monitor.status import BurstLog, LatencyRing


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "run_offline", duration=6.0, seed=3, budget=100)


def _run(*argv) -> int:
    return cli.main(["run", *map(str, argv)])


def test_offline_writes_samples_truth_estimates_and_reports_throughput(work, capsys):
    out = work / "est.mcap"
    assert _run("--from", work / "trial.mcap", "-o", out, "--model", work / "z.model.toml") == 0
    text = capsys.readouterr().out
    assert "samples/s" in text and str(out) in text
    src, res = read_trial(work / "trial.mcap"), read_trial(out)
    np.testing.assert_array_equal(res.seq, src.seq)
    np.testing.assert_array_equal(res.truth.f, src.truth.f)
    assert res.meta.truth == src.meta.truth
    assert res.meta.provenance.details["model_sha256"]
    est = [b for _, b in iter_blocks(out, kinds=("disturbance",))]
    assert sum(len(b.t) for b in est) == len(src)


def test_offline_is_deterministic(work):
    a, b = work / "a.mcap", work / "b.mcap"
    for out in (a, b):
        assert _run("--from", work / "trial.mcap", "-o", out, "--model", work / "z.model.toml") == 0
    assert a.read_bytes() == b.read_bytes()


def test_offline_errors_are_clear(work, capsys, tmp_path):
    assert _run("--from", work / "trial.mcap", "--model", work / "z.model.toml") == 2
    assert "-o/--output" in capsys.readouterr().err
    other = tmp_path / "y.model.toml"
    other.write_text((work / "z.model.toml").read_text().replace('axis = "Z"', 'axis = "Y"'))
    assert _run("--from", work / "trial.mcap", "-o", tmp_path / "o.mcap", "--model", other) == 2
    err = capsys.readouterr().err
    assert "has no axis linear-drive/Y" in err and err.rstrip().endswith("check the model files of axes "
                                                                         "(command line: --model)")
    assert _run("--from", work / "trial.mcap", "-o", tmp_path / "o.mcap", "--model", tmp_path / "none.toml") == 2
    assert "model file not found" in capsys.readouterr().err
    assert _run("--from", work / "trial.mcap", "-o", tmp_path / "o.mcap") == 2
    assert "--model" in capsys.readouterr().err


def test_offline_refuses_a_model_of_another_sampling_rate(work, capsys, tmp_path):
    # β is discrete-time: a model identified at 1 kHz on a 333 Hz trial estimates nonsense (and the
    # health check blames the drive: "inertia drift −65 %"), so the mismatch is refused up front
    text = (work / "z.model.toml").read_text()
    other = tmp_path / "fast.model.toml"
    other.write_text(re.sub(r"(?m)^Ts = .*$", "Ts = 0.001", text, count=1))
    out = tmp_path / "o.mcap"
    assert _run("--from", work / "trial.mcap", "-o", out, "--model", other) == 2
    err = capsys.readouterr().err
    assert "Ts = 0.001 s" in err and "Ts = 0.003003 s" in err and "feedmon identify" in err
    assert "Traceback" not in err and not out.exists()


def test_monitor_counts_malformed_no_model_and_queue_full(work):
    endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
    axes = load_axes([work / "z.model.toml"])
    with T.open_session(listen=endpoint) as session:
        mon = Monitor(axes, session, prefix="feedmon-unit", limits=InputLimits(queue_messages=1))
        # the callback's view of a Zenoh sample: its key and a real Zenoh payload buffer
        fake = SimpleNamespace(key_expr="feedmon-unit/linear-drive/Z/samples", payload=zenoh.ZBytes(b"x"))
        mon._on_sample(fake)  # not started: stays queued
        mon._on_sample(fake)  # queue full: dropped and counted
        assert mon.status()["axes"]["linear-drive/Z"]["drops"] == {"input_queue_full": 1}
        mon._queue.popleft()
        mon._bytes_out += 1
        mon.start()
        try:
            t = time.perf_counter()
            assert mon.handle("feedmon-unit/linear-drive/Z/samples", b"{not json", t) is None
            assert mon.handle("feedmon-unit/other/Q/samples", b"[]", t) is None
            good = S.SampleBlock(machine="linear-drive", axis="Z", seq=0, t=[0.0, 0.003], v_ref=[0.0, 0.0],
                                 v_meas=[0.0, 0.0])
            unknown = S.SampleBlock(machine="m", axis="Q", seq=0, t=[0.0], v_ref=[0.0], v_meas=[0.0])
            assert mon.handle("feedmon-unit/m/Q/samples", S.encode(unknown), t) is None
            est = mon.handle("feedmon-unit/linear-drive/Z/samples", S.encode(good), t)
            assert est is not None and len(est.t) == 2
            st = mon.status()
        finally:
            mon.stop()
    a = st["axes"]["linear-drive/Z"]
    assert a["drops"] == {"malformed": 1, "input_queue_full": 1}
    assert a["samples_in"] == a["estimates_out"] == 2 and a["latency_us"]["count"] == 1
    assert st["input"]["malformed"] == 1  # the one on a key of no known axis
    assert st["input"]["no_model"] == {"m/Q": 1}


def test_status_without_monitor_exits_nonzero(capsys):
    port = T.free_tcp_port()
    rc = cli.main(["status", "--mode", "peer", "--connect", f"tcp/127.0.0.1:{port}", "--prefix", "feedmon-nobody",
                   "--timeout", "1"])
    assert rc == 1
    assert "no monitor answered" in capsys.readouterr().err


def test_latency_ring_and_burst_log(caplog):
    r = LatencyRing(size=100)
    assert r.summary()["p50"] is None
    for i in range(1000):
        r.record((i % 100 + 1) * 1e-6)
    s = r.summary()
    assert s["count"] == 1000 and s["window"] == 100 and 49 <= s["p50"] <= 52 and 98 <= s["p99"] <= 100
    log = logging.getLogger("test.burst")
    b = BurstLog(log, quiet=60.0)
    with caplog.at_level(logging.WARNING, logger="test.burst"):
        for _ in range(50):
            b("k", "bad thing %s", 1)
    assert caplog.text.count("bad thing") == 1


def test_offline_truncated_input_fails_clearly_without_hanging(work, capsys, tmp_path):
    """Reading runs on a prefetch thread: its error must still reach the command, promptly."""
    data = (work / "trial.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    t0 = time.monotonic()
    assert _run("--from", cut, "-o", tmp_path / "o.mcap", "--model", work / "z.model.toml") == 2
    err = capsys.readouterr().err
    assert str(cut) in err and "truncated" in err and "feedmon recover" in err, err
    assert time.monotonic() - t0 < 60


def test_offline_applies_the_block_limit_like_live(work, capsys, tmp_path):
    """``max_block_samples`` refuses the same blocks offline as live (same Pipeline): counted, not copied."""
    out = tmp_path / "limited.mcap"
    src = read_trial(work / "trial.mcap")
    sizes = [len(b.t) for _, b in iter_blocks(work / "trial.mcap")]
    limit = max(sizes) - 1  # every full-size block is refused, a shorter last one is not
    assert _run("--from", work / "trial.mcap", "-o", out, "--model", work / "z.model.toml",
                "--limit", f"max_block_samples={limit}") == 0
    refused = sum(n > limit for n in sizes)
    assert f"{refused} blocks refused (too_large)" in capsys.readouterr().err
    kept = sum(n for n in sizes if n <= limit)
    assert len(read_trial(out)) == kept < len(src)
    est = [b for _, b in iter_blocks(out, kinds=("disturbance",))]
    assert sum(len(b.t) for b in est) == kept


def _break_down_once(monkeypatch, at_call: int, why: str) -> None:
    """Fault injection: :meth:`KRLST.breakdown` (the estimator calls it once per block) reports ``why`` on
    its ``at_call``-th call, and checks the real state otherwise."""
    from kernels.krlst import KRLST

    calls = {"n": 0}
    real = KRLST.breakdown

    def breaks_once(self):
        calls["n"] += 1
        return why if calls["n"] == at_call else real(self)

    monkeypatch.setattr(KRLST, "breakdown", breaks_once)


def test_offline_says_which_blocks_the_estimator_lost_and_exits_1(work, capsys, caplog, monkeypatch):
    """A tracker whose numerics break down (fault injected: :meth:`KRLST.breakdown` reports it once, on
    the 5th block) loses that block, starts over and estimates the rest; the run says how many samples
    were lost, the file holds every other estimate, and the exit code is 1 (it was 0, with NaN)."""
    _break_down_once(monkeypatch, at_call=5, why="posterior variance above the prior (injected)")
    out = work / "lost.mcap"
    assert _run("--from", work / "trial.mcap", "-o", out, "--model", work / "z.model.toml", "--jobs", 1) == 1
    err = capsys.readouterr().err
    blocks = [b for _, b in iter_blocks(work / "trial.mcap", kinds=("samples",))]
    lost = len(blocks[4].t)
    assert f"{lost} samples LOST to estimator errors, tracker restarted 1 time(s)" in err
    assert f"the tracker's numerics broke down (posterior variance above the prior (injected)); {lost} samples " \
           "dropped, tracker restarted" in caplog.text
    est = [b for _, b in iter_blocks(out, kinds=("disturbance",))]
    assert sum(len(b.t) for b in est) == sum(len(b.t) for b in blocks) - lost
    assert blocks[4].seq not in {b.seq for b in est}


def test_self_check_reports_a_tracker_breakdown_as_an_alarm(work, monkeypatch):
    """identify's self-check runs the same estimator: a breakdown there (injected once) is not a crash
    of identify but the strongest finding, an alarm naming it."""
    from monitor.model_file import load_model
    from monitor.self_check import self_check

    model = load_model(work / "z.model.toml")
    assert self_check(str(work / "trial.mcap"), model).state == "ok"
    _break_down_once(monkeypatch, at_call=3, why="non-finite state (injected)")
    check = self_check(str(work / "trial.mcap"), model)
    assert check.state == "alarm" and check.reports > 0
    assert "the tracker broke down 1 time(s): axis linear-drive/Z: the tracker's numerics broke down " \
           "(non-finite state (injected))" in check.summary()


def test_jobs_n_gives_the_file_and_exit_code_of_jobs_1_whatever_was_refused(work, tmp_path):
    """Two axes, every block of Y refused (longer than max_block_samples): ``--jobs 2`` once exited 2
    ("missing tracker.D …") where ``--jobs 1`` exited 0; now the same exit code, the same bytes, the same
    per-axis summary."""
    import subprocess
    import sys

    import msgspec

    from feedio.mcapio import TrialWriter

    src = read_trial(work / "trial.mcap")
    mx, my = (msgspec.structs.replace(src.meta, axis=a) for a in ("X", "Y"))
    blocks = [b for _, b in iter_blocks(work / "trial.mcap")]
    path = tmp_path / "two.mcap"
    with TrialWriter(path, [mx, my], start="2024-05-01T08:00:00Z") as w:
        for i, b in enumerate(blocks):
            w.write_samples(msgspec.structs.replace(b, axis="X"))
            if i % 20 == 19:  # 200 samples of Y ending here
                j = sum(len(x.t) for x in blocks[:i + 1])
                w.write_samples(S.SampleBlock(machine=src.machine, axis="Y", seq=j - 200,
                                              t=src.t[j - 200:j].tolist(), v_ref=src.v_ref[j - 200:j].tolist(),
                                              v_meas=src.v_meas[j - 200:j].tolist()))
    models = []
    for a in ("X", "Y"):
        (tmp_path / f"{a}.model.toml").write_text((work / "z.model.toml").read_text().replace('axis = "Z"',
                                                                                               f'axis = "{a}"'))
        models += ["--model", str(tmp_path / f"{a}.model.toml")]
    runs = {}
    for jobs in (1, 2):
        out = tmp_path / f"out-{jobs}.mcap"
        r = subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--from", str(path), "-o", str(out), *models,
                            "--limit", "max_block_samples=150", "--jobs", str(jobs)], capture_output=True, text=True,
                           timeout=300)
        lines = [x for x in r.stderr.splitlines() if x.startswith("feedmon run: linear-drive/")]
        runs[jobs] = (r.returncode, out.read_bytes() if out.exists() else None, lines)
        assert ("2 processes" in r.stdout) == (jobs == 2), r.stdout + r.stderr
    assert runs[1][0] == runs[2][0] == 0, runs
    assert runs[1][1] == runs[2][1] and runs[1][2] == runs[2][2], runs[2][2]
    assert any("linear-drive/Y: 0 samples" in x and "blocks refused (too_large)" in x for x in runs[2][2])
