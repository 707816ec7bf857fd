"""kernels.period: the period of a disturbance from the harmonic-sum periodogram of a residual."""

import numpy as np
import pytest

from kernels.period import Z_MIN, detect_periods, harmonic_score, harmonically_related, motion_period, sampled_harmonic

TS = 1e-3


def _square(t, period, duty=0.5):
    return ((t / period) % 1.0 < duty).astype(float)


@pytest.mark.parametrize("period", [0.0731, 0.41, 1.3])
def test_square_pulses_found_at_their_fundamental(period):
    """Odd harmonics only (50 % duty): not at 2/ψ, not at a sub-harmonic."""
    rng = np.random.default_rng(1)
    n = 20000
    t = np.arange(n) * TS
    r = 0.2 * _square(t, period) + 0.05 * rng.normal(size=n) + 0.1 * np.cumsum(rng.normal(size=n)) / np.sqrt(n)
    found, motion = detect_periods(r, TS)
    assert motion is None
    assert found and found[0].period == pytest.approx(period, rel=2e-3)
    assert found[0].score > Z_MIN


def test_nothing_in_white_noise():
    r = np.random.default_rng(2).normal(size=12000)
    found, _ = detect_periods(r, TS)
    assert found == []


def test_sine_with_weak_fundamental_and_a_period_locked_to_the_motion():
    rng = np.random.default_rng(3)
    n = 30000
    t = np.arange(n) * TS
    motion = np.sign(np.sin(2 * np.pi * t / 3.0))  # the commanded motion repeats every 3 s
    disturbance = np.sin(2 * np.pi * 55 * t) + 0.3 * np.sin(2 * np.pi * 110 * t + 0.5)
    mismatch = 0.5 * _square(t, 1.5)  # a "disturbance" every 1.5 s: half the motion period
    r = disturbance + mismatch + 0.2 * rng.normal(size=n)
    assert motion_period(motion, TS) == pytest.approx(3.0, rel=1e-3)
    found, psi_m = detect_periods(r, TS, reference=motion)
    assert psi_m == pytest.approx(3.0, rel=1e-3)
    periods = [c.period for c in found]
    assert periods[0] == pytest.approx(1 / 55, rel=1e-3)
    assert not any(abs(p - 1.5) < 0.05 for p in periods)  # locked to the motion: left out


def test_harmonic_relations_and_errors():
    assert harmonically_related(1.0, 3.0) and harmonically_related(3.0, 1.0) and harmonically_related(1.0, 1.01)
    assert not harmonically_related(1.0, 2.5)
    assert not harmonically_related(1.0, 6.0, max_ratio=4)
    with pytest.raises(ValueError, match="16 finite samples"):
        harmonic_score(np.ones(5), TS)
    f0, z, nh = harmonic_score(np.random.default_rng(0).normal(size=64), 1.0, f_min=0.6)
    assert f0.size == 0  # nothing between f_min and Nyquist


def test_a_line_folded_from_a_spindle_harmonic_is_recognised():
    """4-tooth cutter at 3000 rpm (spindle period 20 ms) sampled at 333.3 Hz: the 200 Hz tooth line
    appears at 133.3 Hz; a 55 Hz shaker line is no harmonic of 50, 40 or 60 Hz, folded or not."""
    Ts = 1 / 333.33
    assert sampled_harmonic(1 / 133.33, 0.02, Ts) and sampled_harmonic(1 / 100.0, 0.02, Ts)
    assert not sampled_harmonic(1 / 133.33, 0.02, Ts, max_harmonic=3)    # h = 4 is needed
    for base in (0.02, 0.025, 1 / 60):
        assert not sampled_harmonic(1 / 55.0, base, Ts)
