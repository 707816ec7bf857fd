"""The Rerun dashboard: values placed at the sample they describe, spectra refreshed by data, the event
log, and every failure inside the recording process counted. Real .rrd files, read back with Rerun's
dataframe API (``rerun.chunk.RrdReader`` → ``ChunkStore.reader``)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from sink_states import WORKING

from feedio import schema as S
from monitor.sinks.rerun_events import FlagDigest
from monitor.sinks.rerun_spectra import marker_frequencies, psd_above_floor

TS = 1.0 / 333.0
REPO = Path(__file__).resolve().parents[1]


# ---- reading a recording back ----------------------------------------------------------------------
def open_rrd(path):
    """The recording of an .rrd file as a Rerun ChunkStore (dataframe queries with ``.reader``)."""
    from rerun.chunk import RrdReader

    return RrdReader(str(path)).stream().collect()


def rrd_rows(store, entity: str, component: str = "Scalars:scalars") -> tuple[np.ndarray, np.ndarray, list]:
    """(sample numbers, times in s, values) of the rows where ``entity`` has ``component``."""
    tab = store.reader(index="sample", contents=entity).to_arrow_table()
    name = f"{entity}:{component}"
    if name not in tab.column_names:
        return np.zeros(0, dtype=np.int64), np.zeros(0), []
    vals = tab.column(name).to_pylist()
    keep = [i for i, v in enumerate(vals) if v is not None]
    seq = tab.column("sample").to_numpy()[keep]
    t = tab.column("time").cast("int64").to_numpy()[keep] * 1e-9
    return seq, t, [vals[i] for i in keep]


def tensor(value) -> list[float]:
    """The numbers of one row of a tensor component (a BarChart's values or abscissa)."""
    return list(value[0]["buffer"])


def rrd_scalars(store, entity: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    seq, t, vals = rrd_rows(store, entity)
    return seq, t, np.array([v[0] for v in vals], dtype=float)


# ---- synthetic blocks with a known disturbance g(k) -----------------------------------------------
def g(k):
    """The 'true' force of sample k (N): a 100 Hz tooth-passing wave on a slow ramp."""
    k = np.asarray(k, dtype=float)
    return 40.0 * np.sin(2 * np.pi * 100.0 * k * TS) + 0.01 * k


B = 2e-6  # m/s per N (f = −b·F)


def est_block(seq: int, n: int, axis: str = "X", machine: str = "mill", flags=None) -> S.EstimateBlock:
    """Rows as the estimator emits them: filtered values of row j describe sample j−1, the prediction sample j."""
    j = np.arange(seq, seq + n)
    filt, nxt = g(j - 1), g(j)
    return S.EstimateBlock(
        machine=machine, axis=axis, seq=seq, t=(j * TS).tolist(), v_meas=[0.01] * n, v_pred=[0.0101] * n,
        residual=(-B * filt).tolist(), f=(-B * filt).tolist(), f_var=[(B * 2.0) ** 2] * n,
        f_next=(-B * nxt).tolist(), f_next_var=[(B * 3.0) ** 2] * n,
        dict_size=[min(50, int(x) + 1) for x in j], removed=[int(x) % 50 if x >= 50 else -1 for x in j],
        flags=[0] * n if flags is None else list(flags),
        force=filt.tolist(), force_var=[4.0] * n, force_next=nxt.tolist(),
    )


def truth_block(seq: int, n: int) -> S.TruthBlock:
    j = np.arange(seq, seq + n)
    return S.TruthBlock(seq=seq, t=(j * TS).tolist(), force=g(j).tolist(), f=(-B * g(j)).tolist(),
                        dynamometer=(-g(j)).tolist())


def sample_block(seq: int, n: int, axis: str = "X", rpm: float = 3000.0) -> S.SampleBlock:
    j = np.arange(seq, seq + n)
    return S.SampleBlock(machine="mill", axis=axis, seq=seq, t=(j * TS).tolist(), v_ref=[0.01] * n,
                         v_meas=[0.0099] * n, spindle_rpm=[rpm] * n)


# ---- events from flags ---------------------------------------------------------------------------------
def _feed(flags: np.ndarray, block: int, seq0: int = 0, **kw) -> list:
    d = FlagDigest(**kw)
    seq = np.arange(seq0, seq0 + flags.size)
    out = []
    for a in range(0, flags.size, block):
        out += d.feed(seq[a:a + block], seq[a:a + block] * TS, flags[a:a + block])
    return out + d.close()


def test_flag_events_are_one_line_per_run_and_the_same_for_any_block_size():
    flags = np.zeros(5000, dtype=np.int64)
    flags[:100] |= S.WARMUP
    flags[970] |= S.STALE
    flags[2000:2004] |= S.STALE  # one glitch burst of 4 samples
    flags[3000:3002] |= S.REJECTED
    flags[np.arange(1200, 5000, 3)] |= S.REDUCED
    runs = [[(e.seq, e.level, e.text) for e in _feed(flags, b)] for b in (1, 7, 100, 5000)]
    assert runs[0] == runs[1] == runs[2] == runs[3]  # a replay at any speed gives the same log
    ev = runs[0]
    texts = [t for _, _, t in ev]
    assert sum(t.startswith("STALE") for t in texts) == 2
    assert (2000, "INFO") in [(s, lv) for s, lv, t in ev if t.startswith("STALE: 4 samples 2000–2003")]
    assert [(s, lv) for s, lv, t in ev if t.startswith("REJECTED")] == [(3000, "WARN")]
    warm = [(s, t) for s, _, t in ev if t.startswith("WARMUP")]
    assert [s for s, _ in warm] == [0, 100] and "ended" in warm[1][1]
    reduced = [t for _, lv, t in ev if t.startswith("REDUCED")]
    n_red = int(((flags & S.REDUCED) != 0).sum())
    assert len(reduced) == math.ceil(5000 * TS / 10.0)  # one summary per 10 s of data
    assert sum(int(t.split()[1]) for t in reduced) == n_red  # every REDUCED sample counted once


def test_gaps_are_reported_with_the_missing_count_and_floods_are_summarised():
    d = FlagDigest(max_lines=3)
    ev = d.feed(np.array([0, 1, 2]), np.array([0, 1, 2]) * TS, np.zeros(3, dtype=np.int64))
    ev += d.feed(np.array([10, 11]), np.array([10, 11]) * TS, np.array([S.GAP, 0]))
    gap = [e for e in ev if e.text.startswith("GAP")]
    assert len(gap) == 1 and gap[0].seq == 10 and "7 samples missing" in gap[0].text and gap[0].level == "WARN"
    # 1000 isolated glitches in 10 s of data: 3 listed, the rest in one line when the window closes
    flags = np.zeros(4000, dtype=np.int64)
    flags[np.arange(0, 3000, 3)] = S.STALE
    ev = _feed(flags, 50, max_lines=3)
    stale = [e.text for e in ev if e.text.startswith("STALE")]
    assert len(stale) <= 3 + 2 and any("more" in t and "not listed" in t for t in stale)
    listed = sum(1 for t in stale if "not listed" not in t)
    held = sum(int(t.split()[1]) for t in stale if "not listed" in t)
    assert listed + held == 1000


# ---- spectra -----------------------------------------------------------------------------------------
def test_psd_peaks_stand_above_the_floor_at_the_tooth_passing_frequency():
    rng = np.random.default_rng(3)
    k = np.arange(4096)
    x = np.sin(2 * np.pi * 100.0 * k * TS) + 0.1 * rng.standard_normal(k.size)
    freq, db = psd_above_floor(x, 1 / TS, 512)
    assert freq[0] > 0 and freq[-1] <= 0.5 / TS + 1e-9  # DC left out, Hz up to Nyquist
    assert abs(freq[np.argmax(db)] - 100.0) < 1.0 and db.max() > 20.0
    assert np.median(db) < 1.0 and db.min() == 0.0
    assert psd_above_floor(np.full(100, 3.0), 333.0) is None  # no floor, no spectrum
    assert psd_above_floor(x[:10], 333.0) is None


def test_markers_from_the_model_period_the_spindle_speed_and_the_teeth():
    m = marker_frequencies(333.0, period=0.02, spindle_rpm=3000.0, teeth=2)
    assert m["1_over_psi"].tolist() == [50.0] and m["tooth_passing"].tolist() == [100.0]
    m = marker_frequencies(1000.0, period=0.02, spindle_rpm=3000.0, teeth=2)
    assert m["tooth_passing"].tolist() == [100.0, 200.0, 300.0, 400.0]  # harmonics strictly below Nyquist
    m = marker_frequencies(333.0, spindle_rpm=2400.0)
    assert m == {"spindle": pytest.approx(np.array([40.0]))}
    assert marker_frequencies(333.0, period=float("nan"), spindle_rpm=-5.0, teeth=2) == {}


# ---- the recording --------------------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["in-process", "child-process"])
def test_values_are_placed_at_the_sample_they_describe(tmp_path, where):
    from monitor.sinks.rerun_process import RerunProcessSink
    from monitor.sinks.rerun_sink import RerunSink

    rrd = tmp_path / "stamp.rrd"
    cls = RerunSink if where == "in-process" else RerunProcessSink
    sink = cls(rrd, batch_interval=0.05, psd_every=500,
               axis_info={"mill/X": {"period": 0.02, "teeth": 2, "Ts": TS, "force": True}})
    for seq in range(0, 1500, 20):
        if seq == 800:
            continue  # a lost message: samples 800–819 never arrive
        sink.offer(sample_block(seq, 20))
        sink.offer_truth("mill", "X", truth_block(seq, 20))
        sink.offer(est_block(seq, 20))
    assert sink.close(timeout=60)
    assert sink.status()["failures"] == 0, sink.status()["last_error"]
    store = open_rrd(rrd)
    s_est, t_est, est = rrd_scalars(store, "/mill/X/force/estimate")
    s_act, t_act, act = rrd_scalars(store, "/mill/X/force/actual")
    # the filtered value of row j is placed at sample j−1, with that sample's time: it equals the truth there
    assert s_est[0] == 0 and s_est[-1] == 1498
    assert np.allclose(est, g(s_est), atol=1e-9) and np.allclose(t_est, s_est * TS, atol=2e-9)
    common, ia, ib = np.intersect1d(s_est, s_act, return_indices=True)
    assert common.size > 1400 and np.allclose(est[ia], act[ib], atol=1e-9)
    assert 819 in s_est  # row 820 (first after the gap) describes sample 819, at t = 819·Ts
    assert abs(t_est[s_est == 819][0] - 819 * TS) < 2e-9
    s_pred, _, pred = rrd_scalars(store, "/mill/X/force/prediction")
    assert np.allclose(pred, g(s_pred), atol=1e-9)  # the one-step prediction describes sample j
    s_up, _, up = rrd_scalars(store, "/mill/X/force/upper")
    assert np.allclose(up - g(s_up), 4.0, atol=1e-9)  # ±2σ with σ = √force_var = 2 N
    _, _, sig = rrd_scalars(store, "/mill/X/sigma/prediction")
    assert np.allclose(sig, 3.0, atol=1e-9)  # σ of the prediction in N: √(f_next_var·force_var/f_var)
    _, _, dyn = rrd_scalars(store, "/mill/X/force/dynamometer")
    assert np.allclose(dyn, act, atol=1e-9)  # the reading along the axis, sign turned to the disturbance's
    _, _, vel = rrd_scalars(store, "/mill/X/velocity/measured")
    assert np.allclose(vel, 9.9)  # mm/s
    _, _, pruned = rrd_scalars(store, "/mill/X/dictionary/pruned")
    assert pruned[-1] == pytest.approx(333.0, rel=0.01)  # one element pruned per sample once full


def test_spectra_refresh_every_n_samples_of_data_whatever_the_batching(tmp_path):
    from monitor.sinks.rerun_sink import RerunSink

    counts = []
    for k, interval in enumerate((0.01, 5.0)):  # many small batches, or one batch at the end
        rrd = tmp_path / f"psd{k}.rrd"
        sink = RerunSink(rrd, batch_interval=interval, psd_every=1000, flush_interval=60.0,
                         axis_info={"mill/X": {"period": 0.02, "teeth": 2, "Ts": TS}})
        for seq in range(0, 4200, 100):
            sink.offer(sample_block(seq, 100))
            sink.offer_truth("mill", "X", truth_block(seq, 100))
            sink.offer(est_block(seq, 100))
        assert sink.close(timeout=60)
        store = open_rrd(rrd)
        s_res, _, res = rrd_rows(store, "/mill/X/residual_psd/residual", "BarChart:values")
        s_dist, _, _ = rrd_rows(store, "/mill/X/disturbance_psd/estimate", "BarChart:values")
        s_act, _, _ = rrd_rows(store, "/mill/X/disturbance_psd/actual", "BarChart:values")
        s_tp, _, tp = rrd_rows(store, "/mill/X/psd_markers/tooth_passing", "BarChart:abscissa")
        counts.append((s_res.tolist(), s_dist.tolist(), s_act.tolist()))
        assert s_res.tolist() == [1000, 2000, 3000, 4000, 4199]  # every 1000 samples, and once at the end
        assert s_tp.size == 5
    assert counts[0] == counts[1]
    _, _, marks = rrd_rows(store, "/mill/X/psd_markers/1_over_psi", "BarChart:abscissa")
    assert len(marks) == 5
    assert [tensor(m) for m in marks] == [[50.0]] * 5 and tensor(tp[-1]) == [100.0]
    # the spectrum of the estimate peaks at the tooth-passing frequency (100 Hz), in Hz, dB above its floor
    _, _, absc = rrd_rows(store, "/mill/X/disturbance_psd/estimate", "BarChart:abscissa")
    _, _, vals = rrd_rows(store, "/mill/X/disturbance_psd/estimate", "BarChart:values")
    freq, db = np.array(tensor(absc[-1])), np.array(tensor(vals[-1]))
    assert abs(freq[np.argmax(db)] - 100.0) < 1.0 and db.min() == 0.0 and db.max() > 20.0


def events(store, entity: str = "/mill/X/events") -> list[tuple[int, str, str]]:
    """(sample, level, text) of every event-log line, in order. Read chunk by chunk: a dataframe
    query keeps one row per index value, and two events may concern the same sample."""
    out = []
    for chunk in store.stream():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        d = chunk.to_record_batch().to_pydict()
        out += [(int(s), lv[0], t[0]) for s, lv, t in zip(d["sample"], d["TextLog:level"], d["TextLog:text"])]
    return sorted(out, key=lambda e: e[0])


def test_event_log_has_flags_gaps_glitches_and_health_changes(tmp_path):
    from monitor.sinks.rerun_sink import RerunSink

    rrd = tmp_path / "events.rrd"
    sink = RerunSink(rrd, batch_interval=0.05, axis_info={"mill/X": {"period": 0.02, "Ts": TS}})
    for seq in range(0, 2000, 50):
        if seq == 1000:
            continue
        fl = np.zeros(50, dtype=np.int64)
        if seq < 100:
            fl[:] = S.WARMUP
        if seq == 1050:
            fl[0] = S.GAP
        if seq == 1500:
            fl[10] = S.STALE
        sink.offer(est_block(seq, 50, flags=fl.tolist()))
    sink.offer_health("mill", "X", {"seq": 600, "t": 600 * TS, "state": "ok", "reasons": []})
    sink.offer_health("mill", "X", {"seq": 1200, "t": 1200 * TS, "state": "warn", "reasons": ["inertia +4.1 se"]})
    sink.offer_health("mill", "X", {"seq": 1300, "t": 1300 * TS, "state": "warn", "reasons": ["inertia +4.3 se"]})
    sink.offer_health("mill", "X", {"seq": 1400, "t": 1400 * TS, "state": "alarm", "reasons": ["χ² window 31"]})
    sink.offer_event("mill", "X", 1900, 1900 * TS, "ERROR", "spindle stopped")
    assert sink.close(timeout=60)
    st = sink.status()
    assert st["failures"] == 0, st["last_error"]
    ev = events(open_rrd(rrd))
    by_kind = {t.split(":")[0].split()[0]: (s, lv, t) for s, lv, t in ev if not t.startswith("HEALTH")}
    assert [(s, t.split(" at ")[0]) for s, _, t in ev if t.startswith("WARMUP")] == \
        [(0, "WARMUP from sample 0 (t = 0.000 s): estimates not trusted yet"), (100, "WARMUP ended")]
    s, lv, t = by_kind["GAP"]
    assert (s, lv) == (1050, "WARN") and "50 samples missing" in t
    s, lv, t = by_kind["STALE"]
    assert (s, lv) == (1510, "INFO") and t.startswith("STALE: sample 1510")
    health = [(s, lv, t) for s, lv, t in ev if t.startswith("HEALTH")]
    assert [(s, lv) for s, lv, _ in health] == [(1200, "WARN"), (1400, "ERROR")]  # changes of state only
    assert "inertia +4.1 se" in health[0][2] and "warn → alarm" in health[1][2]
    assert (1900, "ERROR", "spindle stopped") in ev
    assert any(t.startswith("spectrum markers") and "50.0 Hz" in t for _, _, t in ev)


def test_refused_items_are_counted_and_the_rest_is_recorded(tmp_path):
    from monitor.sinks.rerun_sink import RerunSink

    rrd = tmp_path / "refused.rrd"
    sink = RerunSink(rrd, batch_interval=0.05, max_axes=2)
    sink.offer(est_block(0, 50, axis="X"))
    sink.offer(est_block(0, 50, axis="Y"))
    sink.offer(est_block(0, 50, axis="Z"))  # a third axis: refused
    sink.offer_event("mill", "X", 10, 1e12, "INFO", "a time no timeline can hold")  # refused
    sink.offer_event("mill", "X", 10, 0.03, "LOUD", "not a level")  # refused
    sink.offer_health("mill", "X", {"seq": 1, "t": 0.0, "state": "broken", "reasons": []})  # refused
    sink.offer(est_block(50, 50, axis="X"))
    assert sink.close(timeout=60)
    st = sink.status()
    assert st["failures"] == 4 and st["written"] == 3 and st["axes"] == ["mill/X", "mill/Y"]
    seq, _, _ = rrd_scalars(open_rrd(rrd), "/mill/X/force/estimate")
    assert seq.max() == 98
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(rrd)], capture_output=True,
                            text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr


def _wait(cond, timeout: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_a_dead_recording_process_is_replaced_and_what_it_lost_is_counted(tmp_path):
    """SIGKILL of the recording process: the sink notices, counts what it had not written, starts a new one
    writing a new file (the old one left as it was), and is ``failed`` until the new one recorded a block;
    every block offered ends written, lost or dropped."""
    from monitor.sinks.rerun_process import RerunProcessSink

    sink = RerunProcessSink(tmp_path / "dead.rrd", stall_seconds=5.0, batch_interval=0.05)
    sink.offer(est_block(0, 50))
    assert _wait(lambda: sink.status()["written"] == 1)
    os.kill(sink.status()["pid"], signal.SIGKILL)
    for k in range(1, 6):
        assert sink.offer(est_block(50 * k, 50))  # offer never blocks nor raises
    assert _wait(lambda: sink.status()["restarts"] == 1 and sink.status()["process_alive"])
    st = sink.status()
    assert st["failures"] >= 1 and ("died" in st["last_error"] or "broke" in st["last_error"]), st
    sink.offer(est_block(300, 50))
    assert _wait(lambda: sink.status()["state"] in WORKING and sink.status()["written"] > 1)  # the new one records
    assert sink.close(timeout=30)
    st = sink.status()
    assert st["rrd_files"] == [str(tmp_path / "dead.rrd"), str(tmp_path / "dead-001.rrd")]
    assert st["incomplete_files"] == [str(tmp_path / "dead.rrd")]
    assert st["written"] + st["lost"] + st["dropped"] == st["offered"] == 7, st
    assert st["written"] >= 2 and st["state"] == "closed"
    assert os.path.getsize(tmp_path / "dead-001.rrd") > 0


_FULL_DISK = textwrap.dedent("""
    import json, resource, signal, sys, time
    import numpy as np
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))  # inherited by the recording process
    sys.path.insert(0, sys.argv[2])
    from test_dashboard import est_block
    from monitor.sinks.rerun_process import RerunProcessSink

    def main():
        sink = RerunProcessSink(sys.argv[1], flush_interval=0.2, flush_timeout=0.5, broken_after=2,
                                report_interval=0.1, batch_interval=0.05)
        deadline = time.monotonic() + 120
        seq = 0
        # until the child has declared its output broken (broken_after failed flushes): the blocks
        # offered after that are the ones it must count as lost, however loaded the machine is
        while not sink.status().get("child", {}).get("broken") and time.monotonic() < deadline:
            sink.offer(est_block(seq, 100))
            seq += 100
            time.sleep(0.005)
        during = sink.status()
        for _ in range(20):
            sink.offer(est_block(seq, 100))
            seq += 100
        closed = sink.close(timeout=90)
        print(json.dumps({"during": during, "after": sink.status(), "closed": closed, "offered": seq // 100}))

    if __name__ == "__main__":
        main()
""")


def test_a_full_disk_in_the_recording_process_is_counted_in_the_monitors_sink_status(tmp_path):
    script = tmp_path / "full_disk.py"
    script.write_text(_FULL_DISK)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, str(script), str(tmp_path / "full.rrd"), str(Path(__file__).parent)],
                          capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    during, after = res["during"], res["after"]
    assert during["failures"] >= 1 and during["state"] == "failed"  # seen while the monitor runs
    assert "recording process" in during["last_error"] and during["child"]["state"] == "failed"
    assert res["closed"] and not after["process_alive"]  # the child did not hang on its stuck writer
    child = after["child"]
    assert child["final"] and child["broken"]
    assert after["failures"] == child["failures"] + child["undecodable"] >= 20  # blocks lost after it broke
    assert os.path.getsize(tmp_path / "full.rrd") <= 65536


def test_axis_info_is_checked_when_the_sink_is_made(tmp_path):
    from monitor.sinks.rerun_sink import RerunSink

    for bad, word in (({"period": -0.02}, "period"), ({"teeth": 2.5}, "teeth"), ({"Ts": float("inf")}, "Ts"),
                      ({"force": "yes"}, "force"), ({"spindle": 3000}, "unknown keys")):
        with pytest.raises(ValueError, match=word):
            RerunSink(tmp_path / "bad.rrd", axis_info={"mill/X": bad})
    with pytest.raises(ValueError, match="psd_window"):
        RerunSink(tmp_path / "bad.rrd", psd_window=4)


def test_the_axis_info_of_a_model_follows_its_tracker_kernel():
    """ψ of the marker: the time kernel's period, the spindle-phase kernel's period in time at the nominal
    speed (per tooth: divided by the teeth, which the layout takes too), none for a smooth kernel."""
    from monitor.model_file import AxisModel, TrackerConfig
    from monitor.online_settings import LocallyPeriodicKernel, SpindleKernel, SquaredExponentialKernel
    from monitor.sinks.rerun_layout import describe_model

    def model(kernel):
        return AxisModel(machine="m", axis="x", form="velocity-loop", Ts=0.003, beta=[0.37, 0.63], omega=1e-5,
                         coulomb=False, loop_gain=184900.0, tracker=TrackerConfig(kernel=kernel))

    assert describe_model(model(LocallyPeriodicKernel(sigma1=1.0, sigma2=0.5, period=0.02))) == {
        "period": 0.02, "Ts": 0.003, "force": True, "teeth": None}
    tooth = describe_model(model(SpindleKernel(sigma1=1.0, sigma2=0.5, per="tooth", teeth=4, spindle_rpm=3000.0)))
    assert tooth["period"] == pytest.approx(60.0 / 3000.0 / 4) and tooth["teeth"] == 4
    rev = describe_model(model(SpindleKernel(sigma1=1.0, sigma2=0.5, teeth=2, spindle_rpm=2400.0)), teeth=3)
    assert rev["period"] == pytest.approx(60.0 / 2400.0) and rev["teeth"] == 3
    assert describe_model(model(SquaredExponentialKernel(lengthscale=1.0)))["period"] is None


def _view_windows(rrd) -> list[float]:
    """Rolling windows (s before the time cursor) of the views in the recording's layout."""
    from rerun.chunk import RrdReader

    r = RrdReader(str(rrd))
    out = []
    for chunk in r.stream(store=r.blueprints()[-1]).to_chunks():
        if chunk.entity_path.endswith("/VisibleTimeRanges"):
            for row in chunk.to_record_batch().to_pydict()["VisibleTimeRanges:ranges"]:
                out += [-r["range"]["start"] * 1e-9 for r in row if r["timeline"] == "time"]
    return sorted(out)


def test_live_views_roll_a_window_and_a_file_shows_the_whole_run(tmp_path):
    from feedio.transport import free_tcp_port
    from monitor.sinks.rerun_sink import RerunSink

    axes = ("X", "Y")
    for tag, kw in (("file", {}), ("live", {"serve_port": free_tcp_port(), "memory_limit": "64MB"})):
        sink = RerunSink(tmp_path / f"{tag}.rrd", **kw)
        for ax in axes:
            sink.offer(est_block(0, 50, axis=ax))
        assert sink.close(timeout=60)
        windows = _view_windows(tmp_path / f"{tag}.rrd")
        detail = [pytest.approx(0.25)] * len(axes)  # the waveform panel of each axis rolls in any case
        if tag == "file":
            assert windows == detail
        else:  # force, velocity, σ, dictionary of each axis and the overview's force panels: last 10 s
            assert windows == detail + [pytest.approx(10.0)] * (4 * len(axes) + len(axes))
