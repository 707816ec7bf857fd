"""The process monitors' numerics (kernels.force_monitors) against known answers."""

import math

import numpy as np
import pytest

from kernels import force_monitors as fm
from kernels.errors import ParameterError

TS = 1.0 / 333.0


def _tooth_force(theta, shares=(1.0, 1.0), peak=40.0):
    """A 2-tooth slot: tooth j cuts over half a revolution with a sine-shaped force scaled by shares[j]."""
    f = np.zeros_like(theta)
    for j, share in enumerate(shares):
        phi = (theta + math.pi * j) % (2 * math.pi)
        f += np.where(phi < math.pi, peak * share * np.sin(phi), 0.0)
    return f


def _stream(n=4000, rpm=3000.0, seed=0):
    t = np.arange(n) * TS
    theta = 2 * math.pi * rpm / 60.0 * t + 0.3
    return t, theta, np.random.default_rng(seed)


def _impulse(theta, force, sd=1.0, **kw):
    n = force.size
    kind, value, limit = np.zeros(n, np.int64), np.zeros(n), np.zeros(n)
    args = dict(ratio=2.0, ratio_angle=1.0, k_sigma=6.0, limit_abs=0.0, limit_over=math.inf, persist=3, alpha=0.5)
    args.update(kw)
    st = fm.new_impulse_state(33)
    fm.impulse_step(st, theta, force, np.full(n, sd), args["ratio"], args["ratio_angle"], args["k_sigma"],
                    args["limit_abs"], args["limit_over"], args["persist"], args["alpha"], kind, value, limit)
    return kind, value, limit


def test_impulse_detected_on_its_sample_and_nominal_cut_is_quiet():
    _, theta, rng = _stream()
    f = _tooth_force(theta) + rng.normal(0, 1.0, theta.size)
    kind, *_ = _impulse(theta, f)
    assert (kind < 0).all()  # a steady cut with its tooth ripple: nothing
    g = f.copy()
    g[2500:2503] += 120.0  # 3× the tooth peak, 3 samples
    kind, value, limit = _impulse(theta, g)
    assert np.nonzero(kind == 0)[0].tolist() == [2500]
    assert value[2500] > limit[2500] > 0


def test_impulse_without_angle_uses_the_running_peak():
    _, theta, rng = _stream()
    f = _tooth_force(theta) + rng.normal(0, 1.0, theta.size)
    nan = np.full(theta.size, np.nan)
    assert (_impulse(nan, f)[0] < 0).all()
    g = f.copy()
    g[3000] += 200.0
    kind, value, limit = _impulse(nan, g)
    assert np.nonzero(kind == 0)[0].tolist() == [3000]
    assert limit[3000] == pytest.approx(2.0 * np.abs(f[2967:3000]).max() + 6.0, rel=1e-12)


def test_overload_after_persist_samples():
    theta = np.full(50, np.nan)
    f = np.full(50, 10.0)
    f[20:30] = 600.0
    kind, value, limit = _impulse(theta, f, limit_over=500.0, ratio=1e9)
    assert np.nonzero(kind == 1)[0].tolist() == [22]  # the 3rd sample above 500 N
    assert value[22] == 600.0 and limit[22] == 500.0


def test_tooth_fit_recovers_known_coefficients():
    rng = np.random.default_rng(1)
    theta = rng.uniform(0, 20, 200)
    coef = np.array([30.0, 4.0, -3.0, 20.0, 5.0])
    f = coef[0] + coef[1] * np.cos(theta) + coef[2] * np.sin(theta) + coef[3] * np.cos(3 * theta) \
        + coef[4] * np.sin(3 * theta)
    normal, rhs = np.zeros((5, 5)), np.zeros(5)
    for th, x in zip(theta, f):
        fm._accumulate(normal, rhs, th, x, 3)
    out = np.zeros(5)
    assert fm.tooth_fit(normal, rhs, out)
    np.testing.assert_allclose(out, coef, rtol=1e-7, atol=1e-7)
    assert not fm.tooth_fit(np.zeros((5, 5)), np.zeros(5), out)  # nothing determined


def _revolutions(theta, force):
    acc = fm.ToothAccumulator(teeth=2, bins=36)
    rows, prof = acc.update(theta, force)
    return rows, prof


def _first_alarm(rows, det):
    for r in rows:
        for kind, value, limit in det.update(r[1], r[2]):
            return int(r[0]), kind, value, limit
    return None


def test_broken_tooth_within_five_revolutions():
    _, theta, rng = _stream(6000)
    f = _tooth_force(theta) + rng.normal(0, 1.0, theta.size)
    k0 = 4000
    f[k0:] = _tooth_force(theta[k0:], shares=(0.0, 2.0)) + rng.normal(0, 1.0, theta.size - k0)
    rows, prof = _revolutions(theta, f)
    assert prof.shape == (rows.shape[0], 36)
    det = fm.ToothDetector()
    at, kind, value, limit = _first_alarm(rows, det)
    assert kind == "broken_tooth" and value > limit
    revs = (theta[at] - theta[k0]) / (2 * math.pi)
    assert 0 < revs <= 5
    assert rows[-1, 5:].min() < 0.2 * rows[-1, 5:].max()  # one tooth's peak gone


def test_runout_growth_within_ten_revolutions_and_nominal_quiet():
    _, theta, rng = _stream(8000)
    f = _tooth_force(theta) + rng.normal(0, 1.0, theta.size)
    rows, _ = _revolutions(theta, f)
    assert _first_alarm(rows, fm.ToothDetector()) is None
    k0 = 5000  # the first tooth takes 30 % more of the tooth force, the second 30 % less: ΔA1 ≈ 0.3 × tooth force
    f[k0:] = _tooth_force(theta[k0:], shares=(1.15, 0.85)) + rng.normal(0, 1.0, theta.size - k0)
    rows, _ = _revolutions(theta, f)
    at, kind, value, limit = _first_alarm(rows, fm.ToothDetector())
    assert kind == "runout"
    assert 0 < (theta[at] - theta[k0]) / (2 * math.pi) <= 10


def _detector_run(a0, a1):
    det = fm.ToothDetector()
    rng = np.random.default_rng(4)
    return [(i, kind) for i, (x0, x1) in enumerate(zip(a0, a1 + rng.normal(0.0, 0.3, a1.size)))
            for kind, _, _ in det.update(x0, x1)]


def test_a_runout_grown_past_the_breakage_limit_is_not_a_broken_tooth():
    """A1 creeping from 3 N to 25 N over 600 revolutions, then a feed decrease that halves a0 (and with it
    the breakage limit q_b·a0): runout, once — a breakage is a step (M4), this is a growth. The same A1 as
    a step within one revolution is a broken tooth."""
    n = 900
    a0 = np.r_[np.full(700, 40.0), np.full(n - 700, 20.0)]
    creep = 3.0 + np.clip((np.arange(n) - 100) / 600.0, 0.0, 1.0) * 22.0
    alarms = _detector_run(a0, creep)
    assert [k for _, k in alarms] == ["runout"]
    step = np.where(np.arange(n) < 400, 3.0, 25.0)
    alarms = _detector_run(a0, step)
    assert [k for _, k in alarms] == ["broken_tooth"] and 400 <= alarms[0][0] <= 402


def test_envelope_missing_cut_and_over_band():
    mean = np.r_[np.zeros(10), np.full(40, 50.0)]  # 0.5 s air, 2 s of cut, bins of 0.05 s
    spread = np.full(50, 2.0)
    p = np.arange(0, 2.5, TS)
    f = mean[np.minimum((p / 0.05).astype(int), 49)].copy()
    f[(p > 1.0) & (p < 1.5)] = 0.5  # the cut is missing for 0.5 s
    kind, value, limit = np.zeros(p.size, np.int64), np.zeros(p.size), np.zeros(p.size)
    st = fm.new_envelope_state()
    n = fm.envelope_step(st, p, f, np.full(p.size, 1.0), mean, spread, 0.05, 5.0, 5.0, 5.0, 10, kind, value, limit)
    assert n == 1
    i = int(np.nonzero(kind == 0)[0][0])
    first_missing = int(np.nonzero(p > 1.0)[0][0])
    assert i - first_missing == 9 and (p[i] - p[first_missing]) < 0.5
    assert limit[i] == pytest.approx(50.0 - 5.0 * math.sqrt(4.0 + 1.0))
    g = mean[np.minimum((p / 0.05).astype(int), 49)] * 1.5
    st = fm.new_envelope_state()
    fm.envelope_step(st, p, g, np.full(p.size, 1.0), mean, spread, 0.05, 5.0, 5.0, 5.0, 10, kind, value, limit)
    assert (kind == 1).sum() == 1 and (kind == 0).sum() == 0


def test_wear_trend_known_slope():
    y = 100.0 * (1 + 0.01 * np.arange(20)) + np.random.default_rng(3).normal(0, 1.0, 20)
    tstat, rise, sd = fm.wear_trend(y)
    assert rise == pytest.approx(0.19, abs=0.02) and tstat > 10 and 0.5 < sd < 2.0
    assert math.isnan(fm.wear_trend(np.array([1.0, 2.0]))[0])


def test_parameter_ranges_refused():
    with pytest.raises(ParameterError, match="window"):
        fm.new_impulse_state(1)
    with pytest.raises(ParameterError, match="teeth"):
        fm.ToothAccumulator(teeth=0)
    with pytest.raises(ParameterError, match="learn"):
        fm.ToothDetector(learn=1)


def test_the_dashboards_bands_are_the_limits_the_steps_judge_by():
    """impulse_band: a force above its high edge is a collision at any angle, one on the profile is not;
    envelope_band: the step's band (M6) at that bin."""
    t, theta, rng = _stream(2000)
    force = _tooth_force(theta) + rng.normal(0, 1.0, theta.size)
    n = force.size
    st = fm.new_impulse_state(33)
    args = (2.0, 1.0, 6.0, 10.0)  # ratio, ratio_angle, k, floor
    out = np.zeros(n, np.int64), np.zeros(n), np.zeros(n)
    assert fm.impulse_step(st, theta, force, np.ones(n), *args, math.inf, 3, 0.5, *out) == 0
    lo, hi = fm.impulse_band(st, *args)
    assert lo < force.min() and hi > force.max() and hi - lo > 2 * 10.0
    for angle in np.linspace(0.0, 2 * math.pi, 12, endpoint=False):
        for f, alarms in ((hi + 1.0, 1), (lo - 1.0, 1), (float(_tooth_force(np.array([angle]))[0]), 0)):
            trial = st.copy()
            one = np.zeros(1, np.int64), np.zeros(1), np.zeros(1)
            assert fm.impulse_step(trial, np.array([angle]), np.array([f]), np.ones(1), *args, math.inf, 3, 0.5,
                                   *one) == alarms, (angle, f)
    assert all(math.isnan(x) for x in fm.impulse_band(fm.new_impulse_state(33), *args))  # not filled yet
    mean, spread = np.array([0.0, 50.0]), np.array([1.0, 2.0])
    assert fm.envelope_band(0.07, 3.0, mean, spread, 0.05, 5.0, 5.0) == pytest.approx((50 - 5 * math.sqrt(13),
                                                                                      50 + 5 * math.sqrt(13)))
    assert fm.envelope_band(0.01, math.nan, mean, spread, 0.05, 5.0, 5.0) == (-5.0, 5.0)  # band_min; σ NaN: 0
    assert all(math.isnan(x) for x in fm.envelope_band(0.2, 1.0, mean, spread, 0.05, 5.0, 5.0))  # past the end
