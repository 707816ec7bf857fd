"""The per-axis estimator (sample → residual → tracker → estimate), checked against the public
KRLS-T split API, against the model equations, and for its handling of bad samples and of
sequence numbers (integers up to int64, gaps, duplicates, re-sends, new bridge sessions)."""

import dataclasses
import math

import msgspec
import numpy as np
import pytest

from feedio import schema as S
from feedio.schema import SEQ_MAX
from kernels import KRLST, LocallyPeriodic, online
from kernels.feed_drive import physical_to_beta
from monitor.estimator import AxisEstimator
from monitor.model_file import AxisModel, TrackerConfig
from monitor.online_settings import LocallyPeriodicKernel

TS = 1 / 333
BETA = physical_to_beta("velocity-loop", TS, 300.0, 300.0, gain=83300.0, coulomb_pos=9.0, coulomb_neg=10.0)
OMEGA = 5e-4


def _model(form="velocity-loop", beta=BETA, **kw) -> AxisModel:
    return AxisModel(machine="m", axis="x", form=form, Ts=TS, beta=list(map(float, beta)), omega=OMEGA,
                     coulomb=True, loop_gain=83300.0 if form == "velocity-loop" else None,
                     tracker=TrackerConfig(kernel=LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=1 / 55), budget=40, forgetting=0.996), **kw)


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


def _unchecked(block: S.SampleBlock, **fields) -> S.SampleBlock:
    """A copy of ``block`` with ``fields`` set *after* the schema's checks: the decoder refuses such values
    (e.g. seq beyond SEQ_MAX), but the estimator and its compiled loop must be safe on their own."""
    out = msgspec.structs.replace(block)
    for name, value in fields.items():
        setattr(out, name, value)
    return out


def _blocks(t, v_ref, v, size, seq0=0):
    for a in range(0, t.size, size):
        yield _unchecked(S.SampleBlock(machine="m", axis="x", seq=0, t=t[a:a + size].tolist(),
                                       v_ref=v_ref[a:a + size].tolist(), v_meas=v[a:a + size].tolist()), seq=seq0 + a)


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


# ---- sequence numbers are integers: exact up to SEQ_MAX, refused beyond --------------------------------
@pytest.mark.parametrize("offset", [2**40 + 7, SEQ_MAX - 2999, SEQ_MAX - 1499])
def test_sequence_numbers_stay_exact_up_to_seq_max(offset):
    """Consecutive blocks up to the schema's SEQ_MAX = 2**53 − 1: the numbers are those of the same stream at
    seq 0 (one code path run twice: bit for bit), counters exact (a float64 seq broke from 2**53 and crashed
    at 2**60)."""
    t, v_ref, v, _ = _stream(1500)
    ref_est, est = AxisEstimator(_model()), AxisEstimator(_model())
    ref = _run(ref_est, _blocks(t, v_ref, v, 50))
    rows = [est.process(b) for b in _blocks(t, v_ref, v, 50, seq0=offset)]
    assert [r.seq for r in rows] == [offset + 50 * k for k in range(30)]  # Python ints, exact
    got = _run(AxisEstimator(_model()), _blocks(t, v_ref, v, 50, seq0=offset))
    for name, values in ref.items():
        if name != "seq":
            np.testing.assert_array_equal(got[name], values, err_msg=name)
    assert dict(est.counters) == dict(ref_est.counters)
    assert est.counters["restarts"] == 1 and est.counters["trained"] == 1499 and est.counters["estimates_out"] == 1500


def test_sequence_numbers_beyond_seq_max_are_refused_not_crashed():
    t, v_ref, v, _ = _stream(300)
    est = AxisEstimator(_model())
    first, *rest = list(_blocks(t, v_ref, v, 10))
    est.process(first)
    before = est.snapshot()
    for seq in (SEQ_MAX - 5, 2**60, online.SEQ_LIMIT - 5, 2**64, 2**70, -1):  # beyond SEQ_MAX, or not an int64
        assert est.process(_unchecked(rest[0], seq=seq)) is None
    assert est.counters["rejected_seq_range"] == 60
    assert all(np.array_equal(v, est.snapshot()[k]) for k, v in before.items())  # nothing learned
    out = est.process(rest[0])  # the stream goes on
    assert out.seq == 10 and est.counters["gaps"] == 0 and math.isfinite(out.residual[0])  # chain unbroken


@pytest.mark.parametrize("seq0", [-1, -(2**63), online.SEQ_LIMIT - 8, online.SEQ_LIMIT])
def test_compiled_loop_refuses_any_int64_that_does_not_fit(seq0):
    """Defence in depth: the ``@njit`` loop itself, handed an int64 the Python layer would refuse."""
    t, v_ref, v, _ = _stream(10)
    est = AxisEstimator(_model())
    rows, irows, counts = online.new_rows(10)
    first = online.track_block(*est.tracker.core_buffers(np.zeros(1)), *est.online.buffers, *est.health.buffers,
                               *est.config, *online.new_state(), np.int64(seq0), t, v_ref, v, np.zeros((2, 0)), rows,
                               irows, counts, online.new_ticks(10, 1), online.new_scratch(len(est.beta)), 0,
                               *online.new_search(1 / 333), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    assert first == 10 and counts[online.COUNTERS.index("rejected_seq_range")] == 10


# ---- sequence numbers and time together: gaps, re-sends, new bridge sessions --------------------------------
def _seq_blocks(t, v_ref, v, seqs, size):
    """Blocks of ``size`` (cut where the sequence numbers are not consecutive) with the given seq per sample."""
    starts = [0] + [k for k in range(1, len(seqs)) if seqs[k] != seqs[k - 1] + 1 or k % size == 0]
    out = []
    for a, b in zip(starts, starts[1:] + [len(seqs)]):
        out.append(_unchecked(S.SampleBlock(machine="m", axis="x", seq=0, t=t[a:b].tolist(),
                                            v_ref=v_ref[a:b].tolist(), v_meas=v[a:b].tolist()), seq=int(seqs[a])))
    return out


def _rows_and_counters(t, v_ref, v, seqs, size):
    est = AxisEstimator(_model())
    return _run(est, _seq_blocks(t, v_ref, v, list(seqs), size)), est.counters


@pytest.fixture(scope="module")
def stream():
    return _stream(1500)


def _same_rows(a, b, skip=("seq",)):
    for name in a:
        if name not in skip:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


@pytest.mark.parametrize("size", [1, 64])
def test_bridge_restarting_its_count_with_the_clock_running_restarts_the_chain_at_once(stream, size):
    t, v_ref, v, _ = stream
    k = np.arange(t.size)
    seqs = np.where(k < 100, k, k - 100)  # the bridge restarted at sample 100: seq 0, 1, … again, time goes on
    got, c = _rows_and_counters(t, v_ref, v, seqs, size)
    assert (c["seq_resets"], c["gaps"], c["missing_samples"], c["estimates_out"]) == (1, 0, 0, 1500)
    assert got["flags"][100] & S.GAP and got["flags"][100] & S.WARMUP and np.isnan(got["residual"][100])
    assert np.isfinite(got["f"][101:]).all()  # estimates go on
    # the same numbers as a stream with a gap there (the chain restarts the same way)
    ref, _ = _rows_and_counters(t, v_ref, v, np.where(k < 100, k, k + 1), size)
    _same_rows(got, ref)


@pytest.mark.parametrize("size", [1, 64])
def test_one_far_future_seq_costs_two_restarts_not_the_axis(stream, size):
    t, v_ref, v, _ = stream
    k = np.arange(t.size)
    seqs = np.where(k == 800, 2**50, k)  # one far-future (but valid) seq, then the count goes on
    got, c = _rows_and_counters(t, v_ref, v, seqs, size)
    assert (c["seq_resets"], c["gaps"], c["missing_samples"], c["out_of_order"]) == (2, 0, 0, 0)
    assert c["estimates_out"] == 1500 and got["flags"][800] & S.GAP and got["flags"][801] & S.GAP
    ref, _ = _rows_and_counters(t, v_ref, v, np.where(k < 800, k, np.where(k == 800, k + 1, k + 2)), size)
    _same_rows(got, ref)


@pytest.mark.parametrize("size", [1, 64])
def test_bridge_restarting_count_and_clock_loses_at_most_the_reorder_window(stream, size):
    """Both seq and t start again from 0 (a power cycle; or the same trial replayed twice): the first W − 1
    samples look like a late re-send and are dropped; the W-th in a row starts a new session."""
    t, v_ref, v, _ = stream
    W = online.REORDER_WINDOW
    idx = np.r_[np.arange(800), np.arange(700)]  # samples 0…799, then 0…699 again (seq and t)
    got, c = _rows_and_counters(t[idx], v_ref[idx], v[idx], idx, size)
    assert (c["out_of_order"], c["duplicate"], c["seq_resets"], c["gaps"]) == (W - 1, 0, 1, 0)
    assert c["estimates_out"] == 1500 - (W - 1)
    second = got["seq"][800:]
    assert second[0] == W - 1 and (np.diff(second) == 1).all() and got["flags"][800] & S.GAP
    keep = np.r_[np.arange(800), 800 + np.arange(W - 1, 700)]
    ref, _ = _rows_and_counters(t[idx][keep], v_ref[idx][keep], v[idx][keep], np.r_[np.arange(800), 10**6 + np.arange(701 - W)],
                                size)
    _same_rows(got, ref)


def test_genuine_gap_stays_a_gap_seq_jump_without_time_is_a_new_session(stream):
    t, v_ref, v, _ = stream
    k = np.arange(t.size)
    lost = 5000  # an outage: seq and time jump together
    _, c = _rows_and_counters(t + (k >= 800) * lost * TS, v_ref, v, np.where(k < 800, k, k + lost), 64)
    assert (c["gaps"], c["missing_samples"], c["seq_resets"]) == (1, lost, 0)
    _, c = _rows_and_counters(t, v_ref, v, np.where(k < 800, k, k + lost), 64)  # seq ahead of the clock
    assert (c["gaps"], c["missing_samples"], c["seq_resets"]) == (0, 0, 1)
    _, c = _rows_and_counters(t, v_ref, v, np.where(k < 800, k, k + 100), 64)  # within the window: a gap
    assert (c["gaps"], c["missing_samples"], c["seq_resets"]) == (1, 100, 0)


def test_late_resends_and_duplicates_are_dropped_even_far_back(stream):
    t, v_ref, v, _ = stream
    est = AxisEstimator(_model())
    _run(est, _blocks(t[:800], v_ref[:800], v[:800], 100))
    for k in (799, 799, 700, 100, 3):  # duplicates and old samples, as they were sent (old times)
        assert est.process(next(_blocks(t[k:k + 1], v_ref[k:k + 1], v[k:k + 1], 1, seq0=k))) is None
    assert (est.counters["duplicate"], est.counters["out_of_order"], est.counters["seq_resets"]) == (2, 3, 0)
    out = est.process(next(_blocks(t[800:900], v_ref[800:900], v[800:900], 100, seq0=800)))
    assert out.seq == 800 and out.flags[0] & S.GAP == 0 and math.isfinite(out.residual[0])  # chain unbroken


# ---- the intercept ("one") enters the residual in both input forms ---------------------------------------
def _with_intercept(model: AxisModel, offset: float) -> AxisModel:
    """``model`` with the constant column "one" appended to β (value ``offset``)."""
    names = (*model.beta_names, "one")
    beta = [*model.beta, offset]
    if "beta_names" in {f.name for f in dataclasses.fields(AxisModel)}:
        return dataclasses.replace(model, beta=beta, beta_names=list(names))

    class WithIntercept(AxisModel):
        beta_names = property(lambda self: names)

    return WithIntercept(**{**{f.name: getattr(model, f.name) for f in dataclasses.fields(AxisModel)}, "beta": beta})


def test_velocity_loop_intercept_enters_the_residual():
    rng = np.random.default_rng(5)
    n, c = 1200, 3e-4  # a constant velocity offset (m/s per step) the model knows as β_one
    t = np.arange(n) * TS
    v_ref = 0.05 * np.sin(2 * np.pi * 0.7 * t)
    v = np.zeros(n)
    for k in range(n - 1):
        v[k + 1] = (BETA[0] * v_ref[k] + BETA[1] * v[k] - BETA[2] * (v[k] > OMEGA) - BETA[3] * (v[k] < -OMEGA) + c
                    + 2e-6 * rng.standard_normal())
    model = _with_intercept(_model(), c)
    assert model.form == "velocity-loop" and model.beta_names[-1] == "one"
    out = _run(AxisEstimator(model), _blocks(t, v_ref, v, 50))
    z = np.column_stack([v_ref[:-1], v[:-1], -1.0 * (v[:-1] > OMEGA), -1.0 * (v[:-1] < -OMEGA), np.ones(n - 1)])
    np.testing.assert_allclose(out["residual"][1:], v[1:] - z @ np.array(model.beta), rtol=0, atol=1e-15)
    assert abs(np.mean(out["residual"][1:])) < 1e-6 < c  # without the 1 the residual would carry c
    without = _run(AxisEstimator(_model()), _blocks(t, v_ref, v, 50))
    assert abs(np.mean(without["residual"][1:]) - c) < 1e-6


def test_a_tracker_that_broke_down_starts_over_and_its_block_is_dropped():
    """A state that left what exact arithmetic allows (here: μ poisoned with NaN, as a Q lost to roundoff
    leaves it) never recovers by itself: the block is dropped with :class:`TrackerBreakdown` naming the
    axis and the reason, the tracker, online β and health start over from the model file
    (``tracker_restarts``), and the next blocks are estimated again, every value finite."""
    from monitor.estimator import TrackerBreakdown

    t, v_ref, v, _ = _stream(900)
    est = AxisEstimator(_model())

    def block(a, b):
        return S.SampleBlock(machine="m", axis="x", seq=a, t=t[a:b].tolist(), v_ref=v_ref[a:b].tolist(),
                             v_meas=v[a:b].tolist())

    assert est.process(block(0, 300)) is not None and est.tracker.size > 0
    est.tracker.core_state(np.zeros(1)).mu[:] = np.nan
    with pytest.raises(TrackerBreakdown, match=r"axis m/x: the tracker's numerics broke down \(non-finite state"):
        est.process(block(300, 350))
    assert est.counters["tracker_restarts"] == 1 and est.tracker.size == 0 and est.tracker.breakdown() is None
    out = est.process(block(350, 900))
    f_next = np.array(out.f_next, dtype=float)
    assert len(f_next) == 550 and np.all(np.isfinite(f_next[1:])) and est.tracker.size > 0
    assert est.counters["tracker_restarts"] == 1


def test_samples_at_another_interval_than_the_models_ts_are_counted():
    """β is of one sampling time: a stream at 1 kHz into a 333 Hz model (each sample the next ``seq``)
    is counted ``interval_mismatch`` sample by sample (the offline path refuses such a trial outright, the
    live stream has no metadata to refuse); ±10 % jitter of the controller's clock is not."""
    t, v_ref, v, _ = _stream(400)
    rng = np.random.default_rng(1)
    for times, expected in ((np.arange(400) * 1e-3, 399), (t + rng.uniform(-0.1, 0.1, 400) * TS, 0)):
        est = AxisEstimator(_model())
        for a in range(0, 400, 50):
            est.process(S.SampleBlock(machine="m", axis="x", seq=a, t=times[a:a + 50].tolist(),
                                      v_ref=v_ref[a:a + 50].tolist(), v_meas=v[a:a + 50].tolist()))
        assert est.counters["interval_mismatch"] == expected
