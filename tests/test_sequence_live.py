"""Sequence numbers through the real paths: ``feedmon run --from`` on MCAP trials and a live
``feedmon run`` on Zenoh.

* Sequence numbers are integers end to end: a trial whose count ends at the schema's largest
  sequence number (2**53 − 1) gives exactly the estimates of the same trial counted from 0; one
  counted near 2**60 (beyond the schema: refused or estimated, never the abort it caused, rc 134).
* A bridge that restarts its count (with its clock running, or with its clock too) and one absurd
  far-future ``seq`` restart the chain, are counted (``seq_resets``) and logged once per burst; the
  axis keeps estimating (it got 0 estimates before).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from monitor_proc import MonitorProc
from test_bad_input import rows, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import TrialWriter, iter_blocks, read_trial, topic
from feedmon import cli
from kernels import online
from monitor.estimator import AxisEstimator
from monitor.model_file import load_model

PREFIX = "feedmon-seq"
AXIS = "linear-drive/Z"
TOP = 2**53 - 1  # feedio.schema's largest sequence number (docs/limits.md)
W = online.REORDER_WINDOW


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "sequence", duration=6.0, seed=8)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _blocks(trial, idx, seqs, size=50) -> list[S.SampleBlock]:
    """Blocks of the trial's samples ``idx`` (times as recorded) numbered ``seqs``, cut where ``seqs`` jump."""
    idx, seqs = np.asarray(idx), [int(s) for s in seqs]
    starts = [0] + [k for k in range(1, len(seqs)) if seqs[k] != seqs[k - 1] + 1 or k % size == 0]
    out = []
    for a, b in zip(starts, starts[1:] + [len(seqs)]):
        i = idx[a:b]
        block = S.SampleBlock(machine=trial.machine, axis=trial.axis, seq=0, t=trial.t[i].tolist(),
                              v_ref=trial.v_ref[i].tolist(), v_meas=trial.v_meas[i].tolist())
        block.seq = seqs[a]  # set after the schema's checks: a hostile bridge may send any number
        out.append(block)
    return out


def _write(trial, path: Path, blocks) -> Path:
    with TrialWriter(path, trial.meta) as w:
        for b in blocks:
            w.write_samples(b)
    return path


def _offline(work, src: Path, out: Path) -> int:
    return cli.main(["run", "--from", str(src), "-o", str(out), "--model", str(work / "z.model.toml")])


def test_offline_counts_up_to_the_largest_sequence_number_exactly(work, trial, tmp_path, capsys):
    n = len(trial)
    k = np.arange(n)
    plain = _write(trial, tmp_path / "plain.mcap", _blocks(trial, k, k))
    top = _write(trial, tmp_path / "top.mcap", _blocks(trial, k, TOP - (n - 1) + k))  # ends at 2**53 − 1
    assert _offline(work, plain, tmp_path / "a.mcap") == 0 and _offline(work, top, tmp_path / "b.mcap") == 0
    text = capsys.readouterr().err
    assert text.count(f"{n} samples, {n} estimates, 0 gaps") == 2, text
    a = rows(b for _, b in iter_blocks(tmp_path / "a.mcap", kinds=("disturbance",)))
    blocks_b = [b for _, b in iter_blocks(tmp_path / "b.mcap", kinds=("disturbance",))]
    assert [x for b in blocks_b for x in range(b.seq, b.seq + len(b.t))] == [TOP - (n - 1) + i for i in range(n)]
    b = rows(blocks_b)
    for name in a:  # one code path, twice in this process: the same numbers bit for bit
        if name != "seq":
            np.testing.assert_array_equal(b[name], a[name], err_msg=name)


def test_offline_bridge_restarts_keep_the_axis_estimating(work, trial, tmp_path, capsys, caplog):
    n = len(trial)
    k = np.arange(n)
    seqs = np.where(k < 600, 10**9 + k, k - 600)  # the bridge restarts its count at sample 600
    seqs = np.where(k == 1200, 2**40, seqs)  # one absurd far-future seq
    src = _write(trial, tmp_path / "restart.mcap", _blocks(trial, k, seqs))
    with caplog.at_level(logging.WARNING, logger="monitor.pipeline"):
        assert _offline(work, src, tmp_path / "o.mcap") == 0
    err = capsys.readouterr().err
    assert f"{n} samples, {n} estimates, 0 gaps" in err, err
    assert caplog.text.count("sequence numbers restarted") == 1, caplog.text  # once per burst
    r = rows(b for _, b in iter_blocks(tmp_path / "o.mcap", kinds=("disturbance",)))
    assert len(r["seq"]) == n and (r["flags"][[600, 1200, 1201]] & S.GAP).all()
    assert np.isfinite(r["f"][1202:]).all()


def test_trial_writer_refuses_seq_beyond_the_schema(trial, tmp_path):
    """seq near 2**60 can no longer reach a trial file: the writer refuses it, naming SEQ_MAX (was rc 134 in
    ``run --from``). Crafted files holding such numbers are refused by the reader: tests/test_mcap_fuzz.py."""
    k = np.arange(10)
    with pytest.raises(ValueError, match="SEQ_MAX"):
        _write(trial, tmp_path / "huge.mcap", _blocks(trial, k, 2**60 + k))


# ---- live -------------------------------------------------------------------------------------------------
def test_live_monitor_survives_far_sequence_numbers_and_bridge_restarts(work, trial):
    """One monitor, four bridge behaviours in a row, each through real Zenoh:

    A. counting at the top of the schema's range (2**53 − 600 … 2**53 − 1);
    B. the bridge restarts its count at 0, its clock running: the chain restarts at once;
    C. one message with seq 2**60, then the count goes on (refused by the schema: a one-sample hole);
    D. the bridge restarts count and clock (the trial replayed again): W − 1 samples dropped, then estimates.
    """
    k = np.arange(len(trial))
    A = _blocks(trial, k[:600], TOP - 599 + k[:600])
    B = _blocks(trial, k[600:1200], k[:600])
    C = _blocks(trial, k[1200:1201], [2**60]) + _blocks(trial, k[1201:1500], 601 + k[:299])
    D = _blocks(trial, k[:800], k[:800])
    sent = 600 + 600 + 300 + 800
    log = work / "live.mcap"
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--mcap", str(log),
                                           "--state-dir", str(work / "st")], cwd=work)
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = s.declare_publisher(T.samples_key(PREFIX, trial.machine, trial.axis),
                                      congestion_control=zenoh.CongestionControl.BLOCK)
            assert T.wait_for_matching(pub, 15.0)
            for phase, last in ((A, TOP), (B, 599), (C, 899), (D, 799)):
                for b in phase:
                    pub.put(S.encode(b))
                st = wait_status(s, prefix=PREFIX, pid=mon.proc.pid, pred=lambda x, last=last: x["axes"][AXIS]["last_seq"] == last)
            st = wait_status(s, prefix=PREFIX, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["samples_in"]
                             + x["axes"][AXIS]["drops"].get("malformed", 0) == sent)
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    a = st["axes"][AXIS]
    c = a["counters"]
    refused = a["drops"].get("malformed", 0)  # the 2**60 message: beyond the schema's SEQ_MAX
    assert refused == 1 and st["input"]["internal_errors"] == 0
    assert c.get("out_of_order", 0) == W - 1 and c.get("duplicate", 0) == 0
    # B, D restart; C's count went on after a one-sample hole
    assert (c["seq_resets"], a["gaps"], a["missing_samples"]) == (2, 1, 1)
    assert a["estimates_out"] == sent - refused - (W - 1)
    assert 1 <= mon.count("sequence numbers restarted") <= 4, mon.stderr
    # the log in the order it was written (not by controller time: D repeats the times of A):
    # every phase estimated, the exact sequence numbers, GAP where the chain restarted
    with open(log, "rb") as fh:
        est = [S.decode_estimates(m.data) for _, _, m in
               make_reader(fh).iter_messages(topics=[topic(trial.machine, trial.axis, "disturbance")],
                                                    log_time_order=False)]
    seq = [x for b in est for x in range(b.seq, b.seq + len(b.t))]
    assert seq[:600] == list(range(TOP - 599, TOP + 1)) and seq[600:1200] == list(range(600))
    assert seq[-(800 - (W - 1)):] == list(range(W - 1, 800))
    r = rows(est)
    for i in (600, len(seq) - (800 - (W - 1))):  # the first rows of B and of D's new session
        assert r["flags"][i] & S.GAP and np.isnan(r["residual"][i]), i
    assert np.isfinite(r["f_next"]).all()
    # the same numbers as the estimator in this process fed the same blocks (another process: a tolerance)
    ref = AxisEstimator(load_model(work / "z.model.toml"))
    blocks = A + B + C[1:] + D
    want = rows(o for o in (ref.process(b) for b in blocks) if o is not None)
    np.testing.assert_array_equal(r["seq"], want["seq"])
    np.testing.assert_array_equal(r["flags"], want["flags"])
    np.testing.assert_allclose(r["f_next"], want["f_next"], rtol=1e-9, atol=1e-12)
