"""The online search of the tracker's disturbance model (kernels.disturbance_search): its spectral
helpers against signals of known content, its prequential score against the tracker itself, and the
search adopting the model a stream needs (a period it was not told, the spindle's tooth count)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from kernels import KRLST, LocallyPeriodic
from kernels import disturbance_search as ds
from kernels.period import harmonically_related

TS = 1 / 333


def _square(t, period, duty=0.5):
    return np.where((t / period) % 1.0 < duty, 1.0, -1.0)


def test_refine_period_finds_a_period_far_below_the_periodogram_bin():
    """55.3 Hz seen for 1 s (a 1 Hz bin): the refined period is within 0.05 % (P2)."""
    t = np.arange(333) * TS
    y = np.sin(2 * np.pi * 55.3 * t) + 0.2 * np.sin(2 * np.pi * 110.6 * t + 0.4)
    y += np.random.default_rng(1).normal(0, 0.05, t.size)
    psi = ds.refine_period(y, t, 1 / 54.9)
    assert abs(psi * 55.3 - 1) < 5e-4


def test_harmonic_spectra_equal_the_dense_dft():
    """The phasor powers of ``_harmonic_powers`` against the DFT with one exponential per sample and
    harmonic (P2), on irregular sample times, for the amplitudes and for the refined period's power."""
    rng = np.random.default_rng(3)
    t = np.arange(2000) * TS + rng.normal(0, 1e-5, 2000)
    y = 3 * np.sin(2 * np.pi * 20.3 * t) + np.sin(2 * np.pi * 40.6 * t + 1) + rng.normal(0, 0.5, t.size)
    w = np.hanning(t.size)
    yw = (y - y.mean()) * w
    for period in (1 / 55, 1 / 20.3, 0.37):
        h_max = int(min(64, 0.5 * period / TS))
        dense = np.abs(np.exp(-2j * np.pi * np.outer(np.arange(1, h_max + 1), t - t[0]) / period) @ yw) * 2 / w.sum()
        np.testing.assert_allclose(ds.harmonic_amplitudes(y, t, period), dense, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ds._harmonic_powers(yw, t - t[0], 1 / period, h_max), (dense * w.sum() / 2) ** 2,
                                   rtol=1e-9, atol=1e-12)
    assert abs(ds.refine_period(y, t, 1 / 20.2) * 20.3 - 1) < 1e-3


def test_sigma2_follows_the_harmonic_content():
    """A sine carries one harmonic, a square wave many: σ2 (P3) large for the first, small for the second."""
    t = np.arange(3000) * TS
    sine = ds.sigma2_of_harmonics(ds.harmonic_amplitudes(np.sin(2 * np.pi * t / 0.5), t, 0.5))
    square = ds.sigma2_of_harmonics(ds.harmonic_amplitudes(_square(t, 0.5), t, 0.5))
    assert square < 0.2 < 0.5 <= sine


@pytest.mark.parametrize("teeth", [1, 2, 3, 4])
def test_tooth_count_from_the_spindle_orders(teeth):
    """A pattern that repeats every 2π/Z in the spindle angle, at an irregular speed: Z is found."""
    rng = np.random.default_rng(teeth)
    t = np.arange(4000) * TS
    rpm = 2400 + 600 * np.sin(2 * np.pi * 0.1 * t)
    theta = np.cumsum(rpm / 60 * 2 * np.pi * TS)
    y = np.maximum(np.sin(teeth * theta), 0.0) ** 2 + 0.02 * rng.normal(size=t.size)
    assert ds.tooth_count(ds.spindle_orders(y, theta % (2 * np.pi))) == teeth


def test_prequential_scores_are_the_trackers_own_predictions():
    """P1: the log-density of y[k] under the prediction the tracker made before learning it."""
    t = np.arange(400) * TS
    y = 1e-4 * np.sin(2 * np.pi * 55 * t) + 1e-6 * np.random.default_rng(2).normal(size=t.size)
    c = ds.TrackerChoice("periodic", sigma1=1.2, sigma2=0.5, period=1 / 55, gamma=100.0, forgetting=0.998)
    ll, trk = ds.prequential(c, np.column_stack((t, np.zeros_like(t))), y, budget=50, jitter=1e-6, Ts=TS)
    ref = KRLST(LocallyPeriodic(1.2, 0.5, 1 / 55), gamma=100.0, forgetting=0.998, budget=50, grid_step=TS, refine=True)
    want = []
    for k in range(t.size):
        mean, _, sy2, _ = ref.predict_next(t[k])
        R = sy2 * ref.s02
        want.append(-0.5 * (math.log(2 * math.pi) + math.log(R) + (y[k] - mean) ** 2 / R) if R > 0 else np.nan)
        ref.update(y[k])
    np.testing.assert_allclose(ll[1:], np.array(want)[1:], rtol=1e-9, atol=1e-9)
    assert trk.armed and 0 < trk.size <= 50


def _ring(t, y, theta=None, ref=None, rpm=None):
    n = t.size
    return ds.Ring(t=t, theta=np.zeros(n) if theta is None else theta, y=y, ref=np.full(n, np.nan) if ref is None else ref,
                   count=n, spindle=theta is not None, rpm=rpm)


def test_search_adopts_a_period_it_was_not_told():
    """A 73 Hz disturbance in the residual of a tracker that only knows time: the first search adopts a
    locally periodic kernel at 73 Hz (within 0.1 %)."""
    rng = np.random.default_rng(3)
    t = np.arange(1500) * TS
    y = 2e-4 * np.sin(2 * np.pi * 73 * t) + 5e-5 * np.sin(2 * np.pi * 146 * t) + 2e-6 * rng.normal(size=t.size)
    s = ds.DisturbanceSearch(ds.TrackerChoice("time", sigma1=1.2, gamma=5.85, forgetting=0.998), Ts=TS, budget=60,
                             jitter=1e-6, noise2=4e-12)
    v = s.tick(_ring(t, y), poor=True)
    assert v.adopt is not None and v.adopt.kind == "periodic", v.weighed
    assert abs(v.adopt.period * 73 - 1) < 1e-3
    assert s.choice == v.adopt and v.gain > s.s.margin


def test_search_keeps_a_primary_that_explains_the_data():
    """The right model already: no structural candidate beats the control by the margin."""
    rng = np.random.default_rng(4)
    t = np.arange(1500) * TS
    y = 2e-4 * np.sin(2 * np.pi * 55 * t) + 2e-6 * rng.normal(size=t.size)
    c = ds.TrackerChoice("periodic", sigma1=1.2, sigma2=1.0, period=1 / 55, gamma=1e4, forgetting=0.998)
    s = ds.DisturbanceSearch(c, Ts=TS, budget=60, jitter=1e-6, noise2=4e-12)
    v = s.tick(_ring(t, y), poor=True)
    assert v.adopt is None or v.adopt.kind == "periodic" and abs(v.adopt.period * 55 - 1) < 1e-3


def test_with_spindle_data_the_spindle_phase_kernel_is_weighed_and_time_kernels_at_its_period_are_not():
    """Spindle data in the samples: a primary of another kind faces the spindle-phase kernel at every
    search, and a time period that is the spindle's own is left to it."""
    rng = np.random.default_rng(5)
    t = np.arange(2000) * TS
    rpm = np.full(t.size, 3000.0)
    theta = (rpm / 60 * 2 * np.pi * t) % (2 * np.pi)
    y = 1e-4 * np.maximum(np.sin(2 * theta), 0) ** 2 + 2e-6 * rng.normal(size=t.size)
    s = ds.DisturbanceSearch(ds.TrackerChoice("time", sigma1=1.2, gamma=5.85, forgetting=0.998), Ts=TS, budget=60,
                             jitter=1e-6, noise2=4e-12)
    v = s.tick(_ring(t, y, theta=theta, rpm=rpm), poor=True)
    kinds = [c.kind for c, _ in v.weighed]
    assert "spindle" in kinds
    assert not any(c.kind == "periodic" and harmonically_related(c.period, 0.02, max_ratio=8) for c, _ in v.weighed)
    assert v.adopt is not None and v.adopt.kind == "spindle" and v.adopt.teeth in (1, 2)


def test_the_replay_budget_bounds_the_work():
    """Replayed samples never exceed the budget's burst plus its rate × the learned samples."""
    rng = np.random.default_rng(6)
    t = np.arange(4000) * TS
    y = 2e-4 * np.sin(2 * np.pi * 61 * t) + 2e-6 * rng.normal(size=t.size)
    settings = ds.SearchSettings(replay_rate=0.25, replay_burst=2.0)
    s = ds.DisturbanceSearch(ds.TrackerChoice("time", sigma1=1.2, gamma=5.85, forgetting=0.998), Ts=TS, budget=40,
                             jitter=1e-6, noise2=4e-12, settings=settings)
    calls = []
    orig = ds.prequential

    def counting(choice, X, y_, **kw):
        calls.append(y_.size)
        return orig(choice, X, y_, **kw)

    ds.prequential = counting
    try:
        for end in range(600, 4001, 200):
            s.tick(_ring(t[:end], y[:end]), poor=bool(end % 400))
    finally:
        ds.prequential = orig
    assert sum(calls) <= round(2.0 / TS) + 0.25 * 4000 + 1
    assert calls, "nothing was weighed"


def test_online_beta_learns_with_the_files_tracker_unless_the_process_brings_what_it_cannot_follow():
    """β keeps the file's tracker for a weak searched model or the file's own structure; a spindle brings its
    phase kernel (at the file's σ1, γ, λ); a strong disturbance of another structure (γ ≥ STRONG_GAMMA × the
    file's), which the file's tracker would leave in β's noise, brings the searched model itself."""
    base = ds.TrackerChoice("time", sigma1=1.2, gamma=5.85, forgetting=0.998)
    short = ds.TrackerChoice("time", sigma1=0.05, gamma=1e3, forgetting=0.999)
    periodic = ds.TrackerChoice("periodic", sigma1=2.0, sigma2=0.5, period=1.0, gamma=50.0, forgetting=0.998)
    spindle = ds.TrackerChoice("spindle", sigma1=0.3, sigma2=0.25, gamma=900.0, forgetting=0.999, teeth=2)
    weak = replace(short, gamma=ds.STRONG_GAMMA * base.gamma * 0.99)
    assert ds.for_beta(weak, base) == base and ds.for_beta(replace(periodic, gamma=10.0), base) == base
    strong = replace(periodic, gamma=100.0)
    assert ds.for_beta(short, base) == short and ds.for_beta(strong, base) == strong
    b = ds.for_beta(spindle, base)
    assert (b.kind, b.teeth, b.sigma2) == ("spindle", 2, 0.25) and (b.sigma1, b.gamma, b.forgetting) == (1.2, 5.85, 0.998)
    # the file's own period, re-tuned by the search: the file's hyperparameters
    assert ds.for_beta(replace(periodic, gamma=5e3, sigma1=9.0), periodic) == periodic
    # another period, strong: the file's periodic tracker cannot follow it
    assert ds.for_beta(replace(periodic, gamma=5e3, sigma1=9.0, period=0.8), periodic).period == 0.8
