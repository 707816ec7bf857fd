"""The monitor's MCAP log through the real path: a ``feedmon run`` subprocess on real Zenoh, read back
with the plain ``mcap`` reader (issue 9 #2, issue 12 #2)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from test_bad_input import MonitorProc, blocks_of, wait_status
from truth_models import model_from_truth

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import read_trial
from feedmon import cli
from replay.player import replay
from replay.scenarios import load_scenario
from replay.simulator import simulate, write_trial

REPO = Path(__file__).resolve().parents[1]
PREFIX = "feedmon-mcaplive"
AXIS = "linear-drive/Z"
CREATED = "2024-05-01T08:00:00Z"
Y2020 = 1577836800 * 10**9


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("mcaplive")
    write_trial(simulate(load_scenario("shaker-constant", duration=4.0), seed=11, created=CREATED), d / "trial.mcap")
    model_from_truth(d / "trial.mcap", d / "z.model.toml")
    return d


def _plain(path, topic: str) -> list[tuple[int, dict]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        ch = [c for c in summary.channels.values() if c.topic == topic]
        assert len(ch) == 1, sorted(c.topic for c in summary.channels.values())
        schema = json.loads(summary.schemas[ch[0].schema_id].data)
        assert schema["title"] == "DisturbanceScalars" or "DisturbanceScalars" in schema.get("$id", "")
        assert "row of sample k+1" in schema["description"]  # the timing is stated on the channel
        return [(m.log_time, json.loads(m.data)) for _, _, m in reader.iter_messages(topics=[topic],
                                                                                    log_time_order=False)]


def _check_scalars(msgs: list[tuple[int, dict]], n: int) -> None:
    """The issue-12 check: one message per sample, numbers only (missing values left out, never null),
    log times after 2020 and increasing."""
    assert [m["seq"] for _, m in msgs] == list(range(n))
    times = [lt for lt, _ in msgs]
    assert times[0] > Y2020 and all(b > a for a, b in zip(times, times[1:]))
    for _, m in msgs:
        for k, v in m.items():
            assert isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v), (k, v)


def _corr(a, b) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def test_live_log_has_per_sample_scalars_that_other_tools_read(work):
    """Monitor with --mcap and --record-truth, the trial replayed with its truth. The scalars of sample k
    pair the filtered force (row k+1) with the truth of sample k: they correlate far better than the
    one-row-late pairing. run --from on the same trial writes the same values, stamped with the
    input's times (start + t)."""
    tr = read_trial(work / "trial.mcap")
    n = len(tr)
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--mcap", "live.mcap",
                                                     "--record-truth", "--fresh", "--state-dir", "st-live"])
    try:
        with T.open_session(connect=mon.endpoint) as s:
            t0 = time.time_ns()
            replay(work / "trial.mcap", s, rate=None, prefix=PREFIX, truth=True, wait_for_subscriber=10.0, block=5)
            wait_status(s, prefix=PREFIX, pid=mon.proc.pid, pred=lambda x: x["axes"][AXIS]["estimates_out"] == n, timeout=60)
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    live = _plain(work / "live.mcap", f"/{AXIS}/disturbance/scalars")
    _check_scalars(live, n)
    assert t0 - 60 * 10**9 < live[0][0] < live[-1][0] < time.time_ns()  # wall-clock receive times
    force = np.array([m.get("force", np.nan) for _, m in live])
    truth = np.array([m.get("truth_force", np.nan) for _, m in live])
    assert np.isfinite(truth).sum() > 0.9 * n  # the truth of (nearly) every sample came with it
    paired = _corr(force[200:], truth[200:])
    late = _corr(force[201:], truth[200:-1])  # what plotting row k's filtered value at sample k would give
    print(f"\ncorrelation force/truth: paired {paired:.3f}, one row late {late:.3f}")
    assert paired > 0.9 and paired - late > 0.1

    out = work / "offline.mcap"
    assert cli.main(["run", "--from", str(work / "trial.mcap"), "-o", str(out), "--model",
                     str(work / "z.model.toml")]) == 0
    off = _plain(out, f"/{AXIS}/disturbance/scalars")
    _check_scalars(off, n)
    start = read_trial(work / "trial.mcap").start_ns
    stamps = np.array([lt for lt, _ in off]) - (start + np.round(tr.t * 1e9).astype(np.int64))
    assert np.abs(stamps).max() <= 2  # the input's times: start + t of each sample (ns rounding)
    for key in ("f", "f_sd", "force", "force_sd", "force_next", "truth_force"):
        a = np.array([m.get(key, np.nan) for _, m in live], dtype=float)
        b = np.array([m.get(key, np.nan) for _, m in off], dtype=float)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12, equal_nan=True, err_msg=key)
    # Rerun: `rerun mcap convert` reads the log (JSON channels arrive as raw bytes in Rerun 0.41), and the
    # converter in deploy/ turns the scalars into time series that Rerun plots
    rerun = str(Path(sys.executable).with_name("rerun"))
    r = subprocess.run([rerun, "mcap", "convert", str(work / "live.mcap"), "-o", str(work / "convert.rrd")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([sys.executable, str(REPO / "deploy" / "mcap_scalars_to_rerun.py"), str(work / "live.mcap"),
                        "-o", str(work / "scalars.rrd")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and f"/{AXIS}/disturbance/scalars: {n} samples" in r.stdout, r.stdout + r.stderr
    assert subprocess.run([rerun, "rrd", "verify", str(work / "scalars.rrd")], capture_output=True,
                          timeout=120).returncode == 0
    printed = subprocess.run([rerun, "rrd", "print", str(work / "scalars.rrd")], capture_output=True, text=True,
                             timeout=120).stdout
    for field in ("force", "force_sd", "truth_force", "f"):
        assert f"/{AXIS}/{field} - data columns: [Scalars:scalars]" in printed, printed[:2000]
    # the offline block channels keep the input's log times too
    with open(work / "trial.mcap", "rb") as f:
        src = [m.log_time for _, ch, m in make_reader(f).iter_messages(log_time_order=False)
               if ch.topic.endswith("/samples")]
    with open(out, "rb") as f:
        dst = [m.log_time for _, ch, m in make_reader(f).iter_messages(log_time_order=False)
               if ch.topic.endswith("/samples")]
    assert dst == src


def test_absurd_controller_time_does_not_poison_the_live_log(work):
    """A finite t = 2e10 s (which used to overflow the log time, fail every later write and leave the
    file without a footer) is refused by the schema before any sink sees it (counted ``malformed``);
    every block before and after is logged, the file closes complete, and the sink counts no failure."""
    tr = read_trial(work / "trial.mcap")
    good1, good2 = blocks_of(tr, 0, 300), blocks_of(tr, 310, 600)
    absurd = S.SampleBlock(machine=tr.machine, axis=tr.axis, seq=300, t=tr.t[300:310].tolist(),
                           v_ref=tr.v_ref[300:310].tolist(), v_meas=tr.v_meas[300:310].tolist())
    absurd.t = [2e10 + 0.003 * i for i in range(10)]  # set after the schema's checks, as a peer may send it
    blocks = good1 + [absurd] + good2
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--mcap", "poison.mcap",
                                                     "--fresh", "--state-dir", "st-poison"])
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = s.declare_publisher(T.samples_key(PREFIX, tr.machine, tr.axis),
                                      congestion_control=zenoh.CongestionControl.BLOCK)
            assert T.wait_for_matching(pub, 15.0)
            for b in blocks:
                pub.put(S.encode(b))
            st = wait_status(s, prefix=PREFIX, pid=mon.proc.pid, timeout=30,
                             pred=lambda x: x["axes"][AXIS]["samples_in"] == 590
                             and x["axes"][AXIS]["drops"].get("malformed", 0) == 1)
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    sink = st["sinks"][0]
    assert sink["failures"] == 0 and sink["messages_lost"] == 0 and sink["incomplete_files"] == [], sink
    log = read_trial(work / "poison.mcap")  # footer and summary: a complete file
    assert log.seq.tolist() == list(range(300)) + list(range(310, 600))
    assert np.all(log.t < 1e3)
    scalars = _plain(work / "poison.mcap", f"/{AXIS}/disturbance/scalars")
    times = [lt for lt, _ in scalars]
    assert times[0] > Y2020 and all(b > a for a, b in zip(times, times[1:])) and times[-1] < time.time_ns()


def test_foxglove_layout_plots_fields_of_the_scalars_channel():
    """deploy/foxglove/feedmon-disturbance.layout.json: valid JSON, every panel of the layout tree is
    configured, and every plotted path is a field of the scalars schema on a scalars channel."""
    doc = json.loads((REPO / "deploy" / "foxglove" / "feedmon-disturbance.layout.json").read_text())
    panels = set(doc["configById"])

    def leaves(node):
        if isinstance(node, str):
            yield node
        else:
            yield from leaves(node["first"])
            yield from leaves(node["second"])

    assert set(leaves(doc["layout"])) == panels
    fields = set(S.DisturbanceScalars.__struct_fields__)
    paths = [p["value"] for c in doc["configById"].values() for p in c.get("paths", [])]
    assert len(paths) >= 8
    for p in paths:
        topic, field = p.rsplit(".", 1)
        assert topic.endswith("/disturbance/scalars") and field in fields, p
