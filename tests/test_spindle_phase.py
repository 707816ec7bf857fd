"""kernels.spindle_phase: the spindle angle, its stretches of constant speed, and the spindle-phase
kernel in the batch likelihood and PL-LSSVM (block-diagonal, eq. S2) against dense references."""

import math

import numpy as np
import pytest
from scipy.linalg import block_diag

from kernels.covariance import LocallyPeriodic
from kernels.likelihood import reml_terms, tune
from kernels.pl_lssvm import pl_lssvm
from kernels.spindle_phase import (
    MAX_SEGMENTS,
    PhaseSegments,
    phase_segments,
    segment_tolerance,
    spindle_phase,
    spindle_phase_kernel,
)

try:
    from tests.test_likelihood import dense_gls_cov, dense_reml
except ImportError:
    from test_likelihood import dense_gls_cov, dense_reml

TS = 0.003


def _speed_profile(n, changes, rpm0=3000.0, ramp=40):
    """rpm per sample: rpm0, then each (sample, rpm) of ``changes`` reached by a linear ramp of ``ramp`` samples."""
    rpm = np.full(n, rpm0)
    for k, target in changes:
        start = rpm[k]
        steps = np.minimum(np.arange(n - k), ramp) / ramp
        rpm[k:] = start + (target - start) * steps
    return rpm


def test_spindle_angle_from_speed_is_the_trapezoid_integral():
    t = np.arange(2001) * TS
    rpm = _speed_profile(t.size, [(700, 2400.0), (1400, 3600.0)])
    theta = spindle_phase(t, rpm=rpm)
    ref = np.concatenate([[0.0], np.cumsum(2 * np.pi / 60 * 0.5 * (rpm[1:] + rpm[:-1]) * TS)])
    np.testing.assert_allclose(theta, ref, rtol=1e-13, atol=1e-9)
    assert spindle_phase(t) is None
    assert spindle_phase(t, rpm=np.where(t > 1, np.nan, rpm)) is None  # a hole to the end: no spindle data
    holes = rpm.copy()
    holes[500:520] = np.nan                            # 60 ms at constant speed: bridged exactly
    holes[::97] = np.nan
    holes[-1] = rpm[-1]
    np.testing.assert_allclose(spindle_phase(t, rpm=holes), ref, rtol=1e-9, atol=1e-6)
    holes[1000:1040] = np.nan                          # 120 ms: too long to bridge
    assert spindle_phase(t, rpm=holes) is None


@pytest.mark.parametrize("rpm0", [3000.0, 12000.0])  # 12000 rpm at 333 Hz turns > π per sample
def test_a_wrapped_angle_is_unwrapped_with_the_speed(rpm0):
    t = np.arange(3001) * TS
    rpm = _speed_profile(t.size, [(1000, 0.7 * rpm0)], rpm0=rpm0)
    cumulative = spindle_phase(t, rpm=rpm) + 0.3
    wrapped = np.mod(cumulative, 2 * np.pi)
    np.testing.assert_allclose(spindle_phase(t, angle=wrapped, rpm=rpm), cumulative, atol=1e-9)
    np.testing.assert_allclose(spindle_phase(t, angle=cumulative, rpm=rpm), cumulative, atol=1e-9)
    if rpm0 == 3000.0:  # below π per sample the angle alone is enough
        np.testing.assert_allclose(spindle_phase(t, angle=wrapped), cumulative, atol=1e-9)


def test_stretches_follow_the_speed_changes_and_stay_within_tolerance():
    t = np.arange(6000) * TS
    rpm = _speed_profile(t.size, [(2000, 2400.0), (4000, 3600.0)])
    theta = spindle_phase(t, rpm=rpm)
    tol = segment_tolerance(0.9)
    seg = phase_segments(t, theta, tol)
    assert seg.edges[0] == 0 and seg.edges[-1] == t.size and np.all(np.diff(seg.edges) > 0)
    long = seg.lengths > 500
    assert long.sum() == 3                             # the three constant speeds, each one stretch
    np.testing.assert_allclose(np.sort(seg.periods()[long]), [60 / 3600, 60 / 3000, 60 / 2400], rtol=1e-4)
    assert seg.count < 30                              # the two ramps take a few short stretches
    for a, b, w in zip(seg.edges[:-1], seg.edges[1:], seg.rate):  # the defining property, every stretch
        if b - a > 2:
            line = theta[a] + w * (t[a:b] - t[a])
            assert np.max(np.abs(theta[a:b] - line)) <= tol * (1 + 1e-9)
    # one speed throughout: one stretch
    assert phase_segments(t, 2 * np.pi * 50 * t, tol).count == 1


def test_a_continuously_changing_speed_is_refused_not_split_forever():
    t = np.arange(20000) * TS
    theta = 2 * np.pi * (50 * t + 20 * t * t)          # a steady spindle ramp
    with pytest.raises(ValueError, match=f"more than {MAX_SEGMENTS} stretches"):
        phase_segments(t, theta, 1e-7)
    for bad, match in ((np.full(t.size, np.nan), "non-finite"), (theta[:-1], "equal length")):
        with pytest.raises(ValueError, match=match):
            phase_segments(t, bad, 0.01)
    with pytest.raises(ValueError, match="positive angle"):
        phase_segments(t, theta, 0.0)


def _two_speed_record(seed=3, n=700, split=300):
    """A drive regression whose disturbance follows the spindle angle through a speed step."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    w = np.where(np.arange(n) < split, 2 * np.pi * 50.0, 2 * np.pi * 40.0)
    theta = np.concatenate([[0.0], np.cumsum(w[:-1] * TS)])
    Z = np.column_stack([rng.normal(size=n), np.sin(2 * np.pi * 0.7 * t), np.ones(n)])
    f = 0.4 * np.sin(theta) + 0.2 * np.cos(2 * theta + 0.5)
    y = Z @ np.array([0.9, 0.3, 0.05]) + f + 0.01 * rng.normal(size=n)
    return t, theta, Z, y


def test_spindle_likelihood_and_pl_lssvm_equal_the_dense_block_diagonal_reference():
    t, theta, Z, y = _two_speed_record()
    seg = phase_segments(t, theta, 1e-6)
    assert seg.count == 2 and seg.edges[1] == 301  # θ_300 still lies on the first line
    kernel, gamma = spindle_phase_kernel(0.5, 0.6), 40.0
    X = np.column_stack([t, theta])
    A = kernel(X) + np.eye(t.size) / gamma             # the kernel itself on (t, θ) …
    blocks = [A[a:b, a:b] for a, b in zip(seg.edges[:-1], seg.edges[1:])]
    A_bd = block_diag(*blocks)                         # … without the cross-stretch correlation
    terms = reml_terms(Z, y, kernel, gamma, TS, phase=seg)
    assert terms.solver == "spindle-2"
    assert terms.log_likelihood == pytest.approx(dense_reml(Z, y, A_bd, intercept=False), rel=1e-9)
    assert terms.logdet_A == pytest.approx(np.linalg.slogdet(A_bd)[1], rel=1e-9)
    np.testing.assert_allclose(terms.cov, dense_gls_cov(Z, y, A_bd, intercept=False), rtol=1e-7)
    pl = pl_lssvm(Z, y, kernel, gamma, Ts=TS, phase=seg)
    np.testing.assert_allclose(pl.beta, terms.beta, rtol=1e-8)
    alpha = np.linalg.solve(A_bd, y - Z @ pl.beta)
    np.testing.assert_allclose(pl.alpha, alpha, rtol=1e-6, atol=1e-9 * np.abs(alpha).max())
    # within one stretch the spindle-phase kernel is the time kernel at ψ = 2π/ω (eq. S2)
    one = PhaseSegments(edges=np.array([0, 300]), rate=np.array([2 * np.pi * 50.0]), tol=1e-6)
    lp = reml_terms(Z[:300], y[:300], LocallyPeriodic(0.5, 0.6, 1 / 50.0), gamma, TS)
    assert reml_terms(Z[:300], y[:300], kernel, gamma, TS, phase=one).log_likelihood == pytest.approx(
        lp.log_likelihood, rel=1e-10)


def test_the_spindle_kernel_beats_time_kernels_when_the_speed_changes_and_recovers_beta():
    t, theta, Z, y = _two_speed_record(seed=4, n=1500, split=700)
    seg = phase_segments(t, theta, segment_tolerance(0.6))
    res = tune(Z, y, TS, kind="spindle", phase=seg, init={"sigma1": 1.0, "sigma2": 0.6, "gamma": 100.0},
               max_evaluations=40)
    assert res.period == pytest.approx(2 * math.pi) and res.terms.solver == f"spindle-{seg.count}"
    for psi in (1 / 50.0, 1 / 40.0):                  # either speed's period alone explains half the record
        at_psi = tune(Z, y, TS, psi, init={"sigma1": 1.0, "sigma2": 0.6, "gamma": 100.0}, max_evaluations=40)
        assert res.log_likelihood > at_psi.log_likelihood + 50
    np.testing.assert_allclose(res.terms.beta[:2], [0.9, 0.3], rtol=0.02)
    with pytest.raises(ValueError, match="stretches"):
        tune(Z, y, TS, kind="spindle")


def test_per_tooth_is_preferred_when_the_pattern_repeats_with_every_tooth():
    """Identification weighs P = 2π (runout) against P = 2π/teeth: on a pattern periodic per tooth
    (2 teeth) the tooth kernel has the higher likelihood, on one with a revolution line the revolution's."""
    t, theta, Z, _ = _two_speed_record(seed=5, n=1200, split=500)
    rng = np.random.default_rng(6)
    base = Z @ np.array([0.9, 0.3, 0.05]) + 0.01 * rng.normal(size=t.size)
    init = {"sigma1": 1.0, "sigma2": 0.6, "gamma": 100.0}
    ll = {}
    for name, f in (("tooth", 0.4 * np.sin(2 * theta) + 0.2 * np.cos(4 * theta + 0.5)),
                    ("revolution", 0.4 * np.sin(2 * theta) + 0.2 * np.cos(theta + 0.5))):
        for per, P in (("revolution", 2 * np.pi), ("tooth", np.pi)):
            seg = phase_segments(t, theta, segment_tolerance(0.6, P))
            ll[name, per] = tune(Z, base + f, TS, P, kind="spindle", phase=seg, init=init,
                                 max_evaluations=30).log_likelihood
    assert ll["tooth", "tooth"] > ll["tooth", "revolution"]
    assert ll["revolution", "revolution"] > ll["revolution", "tooth"] + 50
