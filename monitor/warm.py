"""Compile before "ready": every compiled function the live path can reach is compiled (or loaded from
Numba's cache) on throw-away objects, so that no real sample waits for a compiler.

The per-sample path alone was not enough. The disturbance search's replay and the rebase of online β onto
a new tracker are met only at the first search; the process monitors' cores only at the first rows they
judge. On a cold cache (a fresh install, a container whose cache was built for another CPU) the
estimator then waited ~11 s for the first search's verdict, and every alarm of those seconds with it
(docs/benchmarks.md, "Cold start").
"""

from __future__ import annotations

import copy
import math

import numpy as np

from feedio import schema as S
from kernels import disturbance_search as ds
from kernels import online

from .background_search import caught_up
from .estimator import AxisEstimator
from .model_file import AxisModel, TrackerConfig

__all__ = ["warm_up", "compile_all"]

#: the throw-away trial: samples per block, blocks, spindle speed (rpm) and feed (m/s)
_BLOCK, _BLOCKS, _RPM, _FEED = 32, 4, 6000.0, 0.01


def warm_up(axes: dict, process=None) -> None:
    """Run each axis' code paths once on throw-away copies: the estimator without and with spindle data
    (the second adopts the spindle-phase kernel: online β is rebased onto the new tracker), the process
    monitors ``process`` (a deep copy: the real ones stay untouched) on those rows, and one disturbance
    search on a time ring and one on a spindle ring."""
    for ax in axes.values():
        _warm_axis(ax.model, ax.key, None if process is None else copy.deepcopy(process))


def compile_all() -> None:
    """:func:`warm_up` on a generic axis with the process monitors on, for an image build to fill
    ``NUMBA_CACHE_DIR`` (the Dockerfile): no model file is needed."""
    from .axes import AxisRuntime
    from .process_monitor import build_monitors
    from .process_monitor.settings import MonitorSettings
    from .status import AxisStatus

    # a loop gain (N·s/m), so that the force is in newtons and the process monitors judge it
    model = AxisModel(machine="warm", axis="x", form="velocity-loop", Ts=0.003, beta=[0.8, 0.16], omega=0.0,
                      coulomb=False, loop_gain=1.0e4, tracker=TrackerConfig())
    axes = {("warm", "x"): AxisRuntime(model, AxisEstimator(model), AxisStatus("warm", "x", "<warm-up>", ""))}
    warm_up(axes, build_monitors(axes, MonitorSettings(enabled=True)))


def _warm_axis(model: AxisModel, key: tuple[str, str], process) -> None:
    est = AxisEstimator(model)
    Ts = float(model.Ts)
    for b in range(_BLOCKS):
        k = np.arange(b * _BLOCK, (b + 1) * _BLOCK)
        t = (k * Ts).tolist()
        v = (_FEED * np.minimum(1.0, k / 8.0)).tolist()
        spindle = {}
        if b >= _BLOCKS // 2:  # spindle data from the middle on: the estimator switches kernels
            spindle = {"spindle_rpm": [_RPM] * len(k), "spindle_angle": (2.0 * math.pi * _RPM / 60.0 * k * Ts).tolist()}
        block = S.SampleBlock(machine=model.machine, axis=model.axis, seq=int(k[0]), t=t, v_ref=v, v_meas=v,
                              u=v if model.form == "force-input" else None, **spindle)
        rows = est.process_rows(block)
        if rows is not None:
            S.encode(rows.block())
            if process is not None:
                process.update(key, rows, block)
        est.take_health()
    est.restore(est.snapshot())  # the state file's round trip (its templates learn one sample)
    if est.search is not None:
        _warm_search(est, Ts)


def _warm_search(est: AxisEstimator, Ts: float) -> None:
    """A search on a ring without spindle data and one with (the replayed trackers read one input
    column or two; each search fresh, with its full replay budget), then what an adoption does with
    the winner: the samples learned since the search began fed to it, its last residual learned, the
    next prediction armed. The ring: a periodic residual in noise, long enough for candidates to be weighed."""
    s = est.search
    n = max(1024, int(math.ceil(2.0 * s.s.first / Ts)))
    t = np.arange(n) * Ts
    y = 1e-4 * np.sin(2.0 * math.pi * t / (25.0 * Ts)) + 1e-5 * np.random.default_rng(0).standard_normal(n)
    theta = 2.0 * math.pi * _RPM / 60.0 * t
    R = np.zeros((n, len(online.RING)))
    R[:, online.G_T], R[:, online.G_THETA], R[:, online.G_RESID] = t, theta, y
    for spindle in (False, True):
        ring = ds.Ring(t=t, theta=theta if spindle else np.zeros(n), y=y, ref=np.full(n, _FEED), count=n,
                       rpm=np.full(n, _RPM if spindle else np.nan), spindle=spindle)
        ds.DisturbanceSearch(s.choice, Ts=s.Ts, budget=s.budget, jitter=s.jitter, noise2=s.noise2,
                             teeth=s.teeth).tick(ring, poor=True)
        choice = ds.TrackerChoice(kind="spindle", sigma1=1.0, sigma2=0.5, period=2.0 * math.pi, gamma=5.0,
                                  forgetting=0.999, teeth=1) if spindle else \
            ds.TrackerChoice(kind="time", sigma1=1.0, sigma2=0.5, period=1.0, gamma=5.0, forgetting=0.999)
        half = n // 2
        _, tracker = ds.prequential(choice, ring.X[:half], y[:half], budget=s.budget, jitter=s.jitter, Ts=Ts)
        tracker = caught_up(tracker, spindle, R[:half], R, n - half)
        tracker.update(float(y[-1]))
        tracker.predict_next(ring.X[-1] if spindle else ring.X[-1, :1])
        tracker.learn_one(ring.X[-1] if spindle else ring.X[-1, :1], float(y[-1]))
