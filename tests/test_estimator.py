"""The per-axis estimator (sample → residual → tracker → estimate), checked against the public
KRLS-T split API, against the model equations, and for its handling of bad samples."""

import math

import numpy as np
import pytest

from feedio import schema as S
from kernels import KRLST, LocallyPeriodic
from kernels.feed_drive import physical_to_beta
from monitor.estimator import AxisEstimator
from monitor.model_file import AxisModel, TrackerConfig

TS = 1 / 333
BETA = physical_to_beta("velocity-loop", TS, 300.0, 300.0, gain=83300.0, coulomb_pos=9.0, coulomb_neg=10.0)
OMEGA = 5e-4


def _model(form="velocity-loop", beta=BETA, **kw) -> AxisModel:
    return AxisModel(machine="m", axis="x", form=form, Ts=TS, beta=list(map(float, beta)), omega=OMEGA,
                     coulomb=True, loop_gain=83300.0 if form == "velocity-loop" else None,
                     tracker=TrackerConfig(kernel=LocallyPeriodic(1.2, 0.495, 1 / 55).to_dict(), budget=40), **kw)


def _stream(n=1500, seed=0):
    """A closed-loop velocity stream from the exact discrete model with a 55 Hz disturbance (m/s)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    v_ref = 0.05 * np.sin(2 * np.pi * 0.7 * t)
    f = 2e-4 * np.sin(2 * np.pi * 55 * t) * (t > 1.0)
    v = np.zeros(n)
    for k in range(n - 1):
        sp, sn = v[k] > OMEGA, v[k] < -OMEGA
        v[k + 1] = BETA[0] * v_ref[k] + BETA[1] * v[k] - BETA[2] * sp - BETA[3] * sn + f[k] + 2e-6 * rng.standard_normal()
    return t, v_ref, v, f


def _blocks(t, v_ref, v, size, seq0=0):
    for a in range(0, t.size, size):
        yield S.SampleBlock(machine="m", axis="x", seq=seq0 + a, t=t[a:a + size].tolist(),
                            v_ref=v_ref[a:a + size].tolist(), v_meas=v[a:a + size].tolist())


def _run(est, blocks):
    rows = [est.process(b) for b in blocks]
    out = {}
    for name in ("v_pred", "residual", "f", "f_var", "f_next", "f_next_var", "dict_size", "removed", "flags", "force_next"):
        dtype = int if name in ("dict_size", "removed", "flags") else float
        out[name] = np.array([x for r in rows if r is not None for x in getattr(r, name)], dtype=dtype)
    out["seq"] = np.array([r.seq + i for r in rows if r is not None for i in range(len(r.t))])
    return out


def test_matches_the_public_krlst_split_api_and_the_model_equations():
    t, v_ref, v, _ = _stream()
    est = _run(AxisEstimator(_model()), _blocks(t, v_ref, v, 50))
    # reference: the same timing written with KRLST.predict_next / KRLST.update (method §6)
    tr = KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), gamma=5.85, forgetting=0.996, budget=40, jitter=1e-6, grid_step=TS,
               refine=True)
    f_next = np.full(t.size, np.nan)
    f_filt = np.full(t.size, np.nan)
    resid = np.full(t.size, np.nan)
    for j in range(t.size):
        if j > 0:
            z = np.array([v_ref[j - 1], v[j - 1], -float(v[j - 1] > OMEGA), -float(v[j - 1] < -OMEGA)])
            resid[j] = v[j] - z @ BETA  # eq. 2.13
            f_filt[j] = tr.update(resid[j]).filtered
        f_next[j] = tr.predict_next(t[j])[0]
    np.testing.assert_array_equal(est["seq"], np.arange(t.size))
    np.testing.assert_allclose(est["residual"][1:], resid[1:], rtol=0, atol=1e-15)
    # The residual comes from two compiled paths (njit in the estimator, BLAS here) that may round
    # differently on other CPUs (FMA, vector width); the tracker then carries that last-bit
    # difference along. A wrong equation or timing would be off by O(1) relative, not 1e-7.
    scale = np.max(np.abs(f_next))
    np.testing.assert_allclose(est["f_next"], f_next, rtol=1e-7, atol=1e-9 * scale)
    np.testing.assert_allclose(est["f"][1:], f_filt[1:], rtol=1e-7, atol=1e-9 * scale)
    assert np.isnan(est["residual"][0]) and est["flags"][0] & S.WARMUP
    # v_pred(j) = βᵀz(j−1) + f_next(j−1)
    np.testing.assert_allclose(est["v_pred"][1:], v[1:] - resid[1:] + f_next[:-1], atol=1e-15)
    # in newtons: F = −f/b with b = K_d/K
    np.testing.assert_allclose(est["force_next"], -f_next / (BETA[0] / 83300.0))


def test_block_size_does_not_change_the_estimates():
    t, v_ref, v, _ = _stream(900)
    ref = _run(AxisEstimator(_model()), _blocks(t, v_ref, v, 1))
    for size in (7, 100, 900):
        got = _run(AxisEstimator(_model()), _blocks(t, v_ref, v, size))
        for name, values in ref.items():
            np.testing.assert_array_equal(got[name], values, err_msg=f"{name}, block {size}")


def test_tracks_the_disturbance():
    t, v_ref, v, f = _stream(3000)
    out = _run(AxisEstimator(_model()), _blocks(t, v_ref, v, 100))
    late = slice(1000, None)
    assert np.corrcoef(out["f_next"][late], f[late])[0, 1] > 0.95  # row j predicts f(j)
    assert np.corrcoef(out["f"][1:][late], f[:-1][late])[0, 1] > 0.95  # row j filters f(j−1)
    assert np.all(out["f_next_var"][late] > 0)


def test_bad_samples_rejected_duplicates_dropped_gaps_restart():
    t, v_ref, v, _ = _stream(600)
    est = AxisEstimator(_model())
    blocks = list(_blocks(t, v_ref, v, 100))
    est.process(blocks[0])
    before = est.tracker.snapshot()
    # a block with a null and an absurd value: rows emitted, REJECTED, tracker untouched by them
    bad = S.SampleBlock(machine="m", axis="x", seq=100, t=[t[100], t[101]], v_ref=[v_ref[100], 1e6],
                        v_meas=[None, v[101]])
    out = est.process(bad)
    assert out.flags == [S.REJECTED, S.REJECTED] and all(math.isnan(x) for x in out.f_next)
    after = est.tracker.snapshot()
    assert all(np.array_equal(before[k], after[k]) for k in before)
    assert est.counters["rejected_non_finite"] == 1 and est.counters["rejected_out_of_range"] == 1
    # a duplicate and an old block: dropped, no rows
    assert est.process(blocks[0]) is None  # seq 0–99 after 101: out of order
    dup = S.SampleBlock(machine="m", axis="x", seq=101, t=[t[101]], v_ref=[v_ref[101]], v_meas=[v[101]])
    assert est.process(dup) is None  # the last one seen again
    assert est.counters["duplicate"] == 1 and est.counters["out_of_order"] == 100
    # the next good sample restarts the chain (no residual across the rejected ones)
    out = est.process(S.SampleBlock(machine="m", axis="x", seq=102, t=[t[102]], v_ref=[v_ref[102]], v_meas=[v[102]]))
    assert math.isnan(out.residual[0]) and out.flags[0] & S.WARMUP
    # a gap of 10 samples: counted, flagged, restarts
    out = est.process(S.SampleBlock(machine="m", axis="x", seq=113, t=[t[113]], v_ref=[v_ref[113]], v_meas=[v[113]]))
    assert out.flags[0] & S.GAP and math.isnan(out.residual[0])
    assert est.counters["gaps"] == 1 and est.counters["missing_samples"] == 10
    # time going backwards
    out = est.process(S.SampleBlock(machine="m", axis="x", seq=114, t=[t[50]], v_ref=[v_ref[114]], v_meas=[v[114]]))
    assert out.flags[0] & S.GAP and est.counters["time_backwards"] == 1


def test_stale_samples_predict_only():
    t, v_ref, v, _ = _stream(800)
    glitched = v.copy()
    glitch = [300, 301, 550]  # two in a row, then one
    for k in glitch:
        glitched[k] = glitched[k - 1]
    est = AxisEstimator(_model())
    out = _run(est, _blocks(t, v_ref, glitched, 64))
    stale = (out["flags"] & S.STALE) != 0
    assert np.flatnonzero(stale).tolist() == glitch
    assert est.counters["stale"] == 3 and est.counters["trained"] == 800 - 1 - 3
    assert np.all(np.isnan(out["residual"][stale])) and np.all(np.isfinite(out["f"][stale]))
    # the model's prediction stands in for the repeated value: the residual after the glitch stays small
    assert abs(out["residual"][302]) < 10 * np.nanstd(out["residual"][100:290])


def test_snapshot_restore_continues():
    t, v_ref, v, _ = _stream(600)
    blocks = list(_blocks(t, v_ref, v, 100))
    a = AxisEstimator(_model())
    for b in blocks[:3]:
        a.process(b)
    b_est = AxisEstimator(_model())
    b_est.restore(a.snapshot())
    assert b_est.trained == a.trained and b_est.tracker.size == a.tracker.size
    out = b_est.process(blocks[3])
    assert out.flags[0] & S.WARMUP  # the chain restarts after a restore
    assert np.all(np.isfinite(np.array(out.f_next)))


def test_force_input_form_scales_with_b():
    beta = physical_to_beta("force-input", TS, 95.0, 200.0, coulomb_pos=20.0, coulomb_neg=20.0, offset=-3.0)
    est = AxisEstimator(_model(form="force-input", beta=beta))
    n = 200
    t = np.arange(n) * TS
    u = 50 * np.sin(2 * np.pi * t)
    blk = S.SampleBlock(machine="m", axis="x", seq=0, t=t.tolist(), v_ref=[0.0] * n, v_meas=(1e-3 * u).tolist(),
                        u=u.tolist())
    out = est.process(blk)
    np.testing.assert_allclose(out.force_next, -np.array(out.f_next) / beta[0])
    with pytest.raises(ValueError, match="'u'"):
        est.process(S.SampleBlock(machine="m", axis="x", seq=n, t=[1.0], v_ref=[0.0], v_meas=[0.0]))


def test_ordering_checked_after_a_rejected_sample():
    t, v_ref, v, _ = _stream(300)
    est = AxisEstimator(_model())
    est.process(next(_blocks(t, v_ref, v, 100)))
    est.process(S.SampleBlock(machine="m", axis="x", seq=100, t=[t[100]], v_ref=[v_ref[100]], v_meas=[None]))
    # a duplicate of the rejected sample is dropped, not taken as a restart
    assert est.process(S.SampleBlock(machine="m", axis="x", seq=100, t=[t[100]], v_ref=[v_ref[100]],
                                     v_meas=[v[100]])) is None
    assert est.counters["duplicate"] == 1
    # a gap right after the rejected sample is counted
    out = est.process(S.SampleBlock(machine="m", axis="x", seq=105, t=[t[105]], v_ref=[v_ref[105]], v_meas=[v[105]]))
    assert out.flags[0] & S.GAP and est.counters["gaps"] == 1 and est.counters["missing_samples"] == 4
    # time going backwards across a rejected sample is counted
    est.process(S.SampleBlock(machine="m", axis="x", seq=106, t=[t[106]], v_ref=[v_ref[106]], v_meas=[math.inf]))
    out = est.process(S.SampleBlock(machine="m", axis="x", seq=107, t=[t[10]], v_ref=[v_ref[107]], v_meas=[v[107]]))
    assert out.flags[0] & S.GAP and est.counters["time_backwards"] == 1
