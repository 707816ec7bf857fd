"""`feedmon demo`: one command, real Zenoh on loopback, real MCAP and .rrd files; the dashboard in the .rrd
read back with Rerun's dataframe API."""

import re
import subprocess
import sys

import numpy as np
import pytest
from test_dashboard import events, open_rrd, rrd_rows, rrd_scalars

from feedio.mcapio import iter_blocks, read_trial

DURATION, RATE = 12, 10  # a 12 s milling trial replayed at 10× real time


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "feedmon.cli", "demo", "--out", str(out), "--duration", str(DURATION),
         "--rate", str(RATE)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr + proc.stdout
    return out, proc.stdout + proc.stderr


def test_demo_end_to_end(demo):
    out, text = demo
    assert "correlation, one-step-ahead prediction" in text
    assert (out / "monitor.rrd").stat().st_size > 10_000
    samples = sum(len(b.t) for _, b in iter_blocks(out / "monitor.mcap", kinds=("samples",)))
    estimates = sum(len(b.t) for _, b in iter_blocks(out / "monitor.mcap", kinds=("disturbance",)))
    assert samples == estimates == int(round(DURATION * 333))
    # the printed count is read after the monitor drained its queue (the last block was once missing)
    shown = re.search(r"(\d+) / (\d+)", text[text.index("estimates logged"):])
    assert shown and int(shown.group(1)) == int(shown.group(2)) == samples, text
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(out / "monitor.rrd")],
                            capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr


def test_dashboard_force_in_newtons_is_aligned_with_the_truth(demo):
    out, _ = demo
    store = open_rrd(out / "monitor.rrd")
    s_est, t_est, est = rrd_scalars(store, "/cnc-mill/X/force/estimate")
    s_act, t_act, act = rrd_scalars(store, "/cnc-mill/X/force/actual")
    common, ia, ib = np.intersect1d(s_est, s_act, return_indices=True)
    assert common.size > 0.95 * DURATION * 333
    assert np.allclose(t_est[ia], t_act[ib], atol=1e-6)  # the same sample is at the same time
    warm = common >= int(2.0 * 333)  # after the warm-up
    a, b = est[ia][warm], act[ib][warm]
    ok = np.isfinite(a) & np.isfinite(b)
    r0 = np.corrcoef(a[ok], b[ok])[0, 1]
    assert r0 >= 0.98, r0  # at zero lag: each value is placed at the sample it describes
    shifted = np.corrcoef(a[ok][1:], b[ok][:-1])[0, 1]
    assert shifted < r0 - 0.05  # one sample off is clearly worse at 100 Hz tooth passing
    assert 20.0 < np.nanstd(b) and abs(np.nanmean(a) - np.nanmean(b)) < 0.5 * np.nanstd(b)  # newtons, not m/s
    s_pred, _, pred = rrd_scalars(store, "/cnc-mill/X/force/prediction")
    common, ia, ib = np.intersect1d(s_pred, s_act, return_indices=True)
    keep = (common >= 666) & np.isfinite(pred[ia])
    assert np.corrcoef(pred[ia][keep], act[ib][keep])[0, 1] >= 0.98


def test_dashboard_spectra_are_refreshed_during_a_10x_replay(demo):
    out, _ = demo
    store = open_rrd(out / "monitor.rrd")
    for ent in ("residual_psd/residual", "disturbance_psd/estimate", "disturbance_psd/actual",
                "psd_markers/tooth_passing"):  # no 1/ψ: the job is tracked by spindle phase
        seq, _, _ = rrd_rows(store, f"/cnc-mill/X/{ent}", "BarChart:values")
        assert seq.size >= 3, ent  # every 1000 samples of data (≈ 3 s), not every few seconds of wall time
        assert np.all(np.diff(seq) > 0)
    _, _, tp = rrd_rows(store, "/cnc-mill/X/psd_markers/tooth_passing", "BarChart:abscissa")
    assert tp[-1][0]["buffer"] == [80.0, 160.0]  # the job's 2400 rpm × 2 teeth and its harmonic below Nyquist


def test_dashboard_event_log_has_warm_up_and_the_glitches_of_the_trial(demo):
    out, _ = demo
    ev = events(open_rrd(out / "monitor.rrd"), "/cnc-mill/X/events")
    texts = [t for _, _, t in ev]
    assert any(t.startswith("WARMUP ended") for t in texts)
    trial = read_trial(out / "milling-job.mcap")
    glitches = np.flatnonzero(trial.truth.glitch) + int(trial.seq[0])
    stale = sorted(s for s, _, t in ev if t.startswith("STALE"))
    assert glitches.size >= 1 and stale == glitches.tolist()  # each recording glitch, one line each
    assert any(t.startswith("REDUCED") for t in texts) and len(ev) < 20  # summarised, not one line per sample
    assert any(t.startswith("spectrum markers") and "tooth passing 80.0 Hz" in t for t in texts)
