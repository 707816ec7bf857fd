"""The soak test of benchmarks/soak.py, CI size: 3 minutes of one 333 Hz axis (~60 000 samples)
through the monitor's decode → estimate → encode path, with every defect the full soak injects
(glitches, NaN readings, sequence gaps, re-sent blocks) at rates high enough to occur here.

The full run (24 h of stream, 28.8 M samples): ``python benchmarks/soak.py``.
"""

from __future__ import annotations

import importlib.util
import io
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _soak_module():
    spec = importlib.util.spec_from_file_location("feedmon_soak", ROOT / "benchmarks" / "soak.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


soak = _soak_module()

#: 0.05 h = 59 940 samples; defects more frequent than in the 24 h run so that each one happens
SHORT = ["--hours", "0.05", "--nan-rate", "2e-4", "--gap-rate", "0.01", "--dup-rate", "0.01",
         "--glitch-rate", "1e-3", "--checkpoint", "18"]


@pytest.fixture(scope="module")
def short_run():
    out = io.StringIO()
    # no --rate-check: a rate is a benchmark's figure (benchmarks/soak.py), not a test's on a loaded machine
    opts = soak.build_parser().parse_args([*SHORT, "--max-rss-growth", "25"])
    res = soak.run_soak(opts, out=out)
    return res, out.getvalue()


def test_the_short_run_passes_and_prints_the_table(short_run):
    """What ``soak.main`` prints and judges (its exit code is ``res.ok``; the failing path is the test below)."""
    res, text = short_run
    assert res.ok and soak.HEADER in text and "soak: PASS" in text
    assert "samples/s" in text and "24 h of one axis would take" in text


def test_every_criterion_holds_on_a_short_run(short_run):
    res, text = short_run
    assert res.ok, text
    assert set(res.checks) == {"nan", "accounting", "memory", "inverse", "quality", "health"}
    assert res.health["ok"] > 150 and res.health["warn"] == res.health["alarm"] == 0
    assert res.samples > 55_000
    assert len(res.rows) == 10
    c = res.counters
    # the defects were really there and went where the estimator puts them
    assert c["rejected_non_finite"] > 0 and c["gaps"] > 0 and c["stale"] > 0
    assert c.get("duplicate", 0) + c.get("out_of_order", 0) > 0
    assert c.get("status.estimator_error", 0) == 0


def test_no_nan_and_quality_equal_in_first_and_last_window(short_run):
    res, _ = short_run
    assert res.nan == 0
    assert res.first.corr > 0.95 and res.last.corr > 0.95
    assert abs(res.first.corr - res.last.corr) < 0.01
    assert abs(res.first.nrmse - res.last.nrmse) < 0.03


def test_memory_has_no_growth_trend(short_run):
    """A short run cannot prove a 10 MB bound for 24 h; it can show there is no trend: RSS over
    the second half of the checkpoints grows by at most a few MB, and the number of GC-tracked
    objects stays put (a leak of one object per block would add ~600)."""
    res, text = short_run
    rss = np.array([r.rss_mb for r in res.rows])
    half = rss[len(rss) // 2:]
    assert half.max() - half[0] <= 5.0, text
    assert res.objects[-1] - res.objects[1] < 200, res.objects


def test_inverse_error_bounded(short_run):
    res, _ = short_run
    assert 0.0 < res.inv_err_max <= 1e-6  # the estimator runs KRLS-T with refine=True (~1e-8)
    assert all(r.inv_err <= 1e-6 for r in res.rows)


def test_a_failed_criterion_gives_exit_code_1():
    out = io.StringIO()
    assert soak.main(["--hours", "0.01", "--min-corr", "1.01", "--checkpoint", "18"], out=out) == 1
    assert "[FAIL] quality" in out.getvalue()


def test_stream_is_the_exact_model():
    """Without noise and defects, the generated samples satisfy the PL-ARX model with the model
    file's β exactly: v(k+1) − βᵀz(k) = −b·T_c(k) (what the estimator's truth pairing relies on)."""
    from kernels.feed_drive import coulomb_indicators

    s = soak.DriveStream(60.0, seed=3, noise_std=0.0, glitch_rate=0.0, nan_rate=0.0)
    a, b = s.next_chunk(5000), s.next_chunk(5000)  # across a chunk boundary
    v = np.concatenate([a.v_meas, b.v_meas])
    vr = np.concatenate([a.v_ref, b.v_ref])
    tc = np.concatenate([a.force, b.force])
    d = soak.DRIVE
    beta = soak.physical_to_beta("velocity-loop", 1 / soak.RATE, d["inertia"], d["damping"], gain=d["loop_gain"],
                                 coulomb_pos=d["coulomb_pos"], coulomb_neg=d["coulomb_neg"])
    sp, sn = coulomb_indicators(v[:-1], d["omega"])
    pred = beta[0] * vr[:-1] + beta[1] * v[:-1] - beta[2] * sp - beta[3] * sn
    gain = beta[0] / d["loop_gain"]
    np.testing.assert_allclose(v[1:] - pred, -gain * tc[:-1], atol=1e-12)
    assert np.abs(tc).max() > 50 and (tc == 0).any()  # the disturbance switches on and off
