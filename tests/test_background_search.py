"""The disturbance search beside the per-sample path (monitor/background_search.py): the adopted
tracker, caught up on the samples learned while the search ran, is the tracker replayed over all of
them; a ring that did not simply go on gives a fresh tracker; the verdict applies ``lag`` samples on."""

from __future__ import annotations

import numpy as np

from kernels import disturbance_search as ds
from kernels import online
from monitor.background_search import caught_up, submit

TS = 1 / 333


def _ring(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = np.zeros((n, len(online.RING)))
    R[:, online.G_T] = np.arange(n) * TS
    R[:, online.G_THETA] = np.mod(np.arange(n) * 0.9, 2 * np.pi)
    R[:, online.G_RESID] = 3 * np.sin(2 * np.pi * 20.3 * R[:, online.G_T]) + rng.normal(0, 0.3, n)
    return R


def _replayed(choice: ds.TrackerChoice, R: np.ndarray):
    X = np.column_stack((R[:, online.G_T], R[:, online.G_THETA]))
    _, trk = ds.prequential(choice, X, R[:, online.G_RESID], budget=50, jitter=1e-9, Ts=TS)
    return trk


def test_caught_up_tracker_is_the_tracker_replayed_over_every_sample():
    choice = ds.TrackerChoice("periodic", sigma1=1.2, sigma2=0.5, period=1 / 20.3, gamma=100.0, forgetting=0.998)
    R = _ring(700)
    c, m = 500, 83
    at_start = _replayed(choice, R[:c + 1])           # what the search hands over: armed at entry c
    fed = caught_up(at_start, False, R[:c + 1], R[:c + 1 + m], m)
    whole = _replayed(choice, R[:c + 1 + m])          # armed at entry c + m after learning all before it
    a, b = fed.snapshot(), whole.snapshot()
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-9, atol=1e-12, err_msg=k)


def test_a_ring_that_was_restarted_gives_a_fresh_tracker():
    choice = ds.TrackerChoice("time", sigma1=0.1, gamma=10.0, forgetting=0.998)
    R = _ring(300)
    trk = _replayed(choice, R[:201])
    restarted = _ring(300, seed=1)
    restarted[:, online.G_T] += 50.0                  # other samples: the entry the search ended at is gone
    assert caught_up(trk, False, R[:201], restarted, 40) is None
    assert caught_up(trk, False, R[:201], R[:241], 400) is None   # more new entries than the ring holds
    assert caught_up(None, False, R[:201], R[:241], 40) is None
    assert caught_up(trk, False, R[:201], R[:201], 0) is trk


def test_the_verdict_is_due_lag_samples_after_the_start():
    pending = submit(lambda: 42, np.zeros((0, len(online.RING))), count=1000, lag=83)
    assert pending.due == 1083 and pending.wait() == 42
    assert submit(lambda: 1, np.zeros((0, len(online.RING))), count=5, lag=0).due == 6
