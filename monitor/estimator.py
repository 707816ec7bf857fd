"""Per-axis estimator: sample → residual → tracker → estimate (method §6, "Timing in the monitor").

No I/O: the live daemon and the offline ``--from`` path both feed
:class:`SampleBlock` s into :meth:`AxisEstimator.process` and get one
:class:`EstimateBlock` row per accepted sample, so both paths give the same
numbers sample for sample.

Row ``j`` (emitted when sample ``j`` arrives) holds, with ``z(j−1)`` the
regressor of the previous sample and ``β`` from the model file:

* ``residual``  ``v(j−1) = v_m(j) − βᵀ z(j−1)`` (method eq. 2.13), m/s
* ``v_pred``    ``βᵀ z(j−1) + f̂(j−1)``: the velocity the model predicted for this sample
* ``f, f_var``  the filtered disturbance of the step that ended at ``j``
  (KRLS-T posterior after training on ``(x(j−1), v(j−1))``), m/s and (m/s)²;
  it pairs with the ground truth of sample ``j−1``
* ``f_next, f_next_var``  the one-step-ahead prediction of ``f(j)`` from ``x(j)``
  before ``v_m(j+1)`` is seen — what a feedforward compensator uses; pairs with
  the truth of sample ``j``
* ``force, force_var, force_next``  the same in newtons (``F = −f/b``) when the
  model can scale (force-input form, or known loop gain K)

Robustness (each reason is counted in :attr:`AxisEstimator.counters`):

* non-finite or absurd values: the sample is REJECTED (row emitted, NaN
  estimates); the regressor chain restarts at the next good sample;
* duplicate or out-of-order sequence numbers: dropped, no row;
* a sequence gap or time going backwards: the chain restarts (GAP flag); no
  residual is formed across the gap;
* stale samples — the controller repeated the previous measured velocity while
  the axis moves (the thesis' recording glitch): STALE flag, the tracker is not
  trained on them (predict only) and the model's velocity prediction stands in
  for the repeated value in the next regressor.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from kernels import KRLST
from kernels.feed_drive import coulomb_indicators

from .model_file import AxisModel
from .schema import GAP, REDUCED, REJECTED, STALE, WARMUP, EstimateBlock, SampleBlock

__all__ = ["AxisEstimator", "LIMITS"]

#: magnitudes beyond which a value is physically absurd for a machine-tool axis (SI)
LIMITS = {"v": 50.0, "u": 1e7, "t": 1e10}


@dataclass
class _Prev:
    """What the next sample needs from the previous accepted one."""

    seq: int
    t: float
    e: float  # exogenous input: v_ref (m/s) or u (N)
    v_raw: float  # v_meas as received (m/s), for stale detection
    v_used: float  # v_meas used in z (the prediction when stale)
    x: np.ndarray  # tracker input x(k)


class AxisEstimator:
    """Disturbance estimator for one axis.

    Parameters
    ----------
    model : AxisModel
        β, input form, Ω, Ts and tracker hyperparameters (from the model file).
    warmup : int, optional
        Number of trained samples flagged WARMUP (default: the dictionary budget M).
    stale_detection : bool
        Detect repeated measured velocities (default True).
    """

    def __init__(self, model: AxisModel, *, warmup: int | None = None, stale_detection: bool = True):
        self.model = model
        self.beta = np.asarray(model.beta, dtype=np.float64)
        self.force_gain = model.force_gain
        self.warmup = model.tracker.budget if warmup is None else int(warmup)
        self.stale_detection = stale_detection
        cfg = model.tracker
        self.tracker = KRLST(
            cfg.build_kernel(),
            gamma=cfg.gamma,
            forgetting=cfg.forgetting,
            budget=cfg.budget,
            jitter=cfg.jitter,
            grid_step=model.Ts if cfg.build_kernel().is_stationary_1d else None,
        )
        self.counters: Counter[str] = Counter()
        self.trained = 0
        self._prev: _Prev | None = None
        self._pending = (math.nan, math.nan)  # (f_next, f_next_var) predicted at _prev
        self._x = np.zeros(1)

    # ------------------------------------------------------------------ helpers
    def _regressor(self, e: float, v: float) -> float:
        """``βᵀ z(k)`` for one sample (method §2)."""
        b = self.beta
        acc = b[0] * e + b[1] * v
        if self.model.coulomb:
            sp, sn = coulomb_indicators(v, self.model.omega)
            acc -= b[2] * float(sp) + b[3] * float(sn)
        if self.model.form == "force-input":
            acc += b[-1]
        return float(acc)  # a Python float: msgspec cannot encode numpy.float64

    def _predict_next(self, x: np.ndarray) -> tuple[float, float]:
        if self.tracker.size == 0:
            return 0.0, math.nan
        mean, var = self.tracker.predict_one(x, noise=False, forget=True)
        return mean, var

    def reset(self) -> None:
        """Forget the regressor chain (not the tracker): the next sample starts afresh."""
        self._prev = None
        self._pending = (math.nan, math.nan)

    # ------------------------------------------------------------------ main entry
    def process(self, block: SampleBlock) -> EstimateBlock | None:
        """Estimates for the samples of ``block`` (None when every sample was dropped)."""
        n = len(block.t)
        exo = block.u if self.model.form == "force-input" else block.v_ref
        if exo is None:
            self.counters["rejected_missing_field"] += n
            raise ValueError(
                f"axis {block.machine}/{block.axis}: the {self.model.form} model needs "
                f"'{'u' if self.model.form == 'force-input' else 'v_ref'}' in every sample block"
            )
        rows: dict[str, list] = {k: [] for k in _ROW_FIELDS}
        for i in range(n):
            self._one(block.seq + i, block.t[i], exo[i], block.v_meas[i], rows)
        if not rows["seq"]:
            return None
        return self._block(block.machine, block.axis, rows)

    def _one(self, seq: int, t, e, v, rows: dict) -> None:
        c = self.counters
        prev = self._prev
        c["samples_in"] += 1
        if prev is not None and seq <= prev.seq:
            c["duplicate" if seq == prev.seq else "out_of_order"] += 1
            return
        flags = 0
        if not _finite(t, e, v):
            c["rejected_non_finite"] += 1
            self._reject(seq, t, v, rows)
            return
        if abs(v) > LIMITS["v"] or abs(e) > (LIMITS["u"] if self.model.form == "force-input" else LIMITS["v"]) or abs(t) > LIMITS["t"]:
            c["rejected_out_of_range"] += 1
            self._reject(seq, t, v, rows)
            return
        if prev is not None and seq > prev.seq + 1:
            c["gaps"] += 1
            c["missing_samples"] += seq - prev.seq - 1
            flags |= GAP
            prev = None
        elif prev is not None and t <= prev.t:
            c["time_backwards"] += 1
            flags |= GAP
            prev = None
        x = np.array([float(t)])
        if prev is None:  # chain (re)starts: no residual yet
            f_next, f_next_var = self._predict_next(x)
            self._prev = _Prev(seq, float(t), float(e), float(v), float(v), x)
            self._pending = (f_next, f_next_var)
            c["restarts"] += 1
            self._row(rows, seq, t, v, math.nan, math.nan, math.nan, math.nan, f_next, f_next_var, -1, flags | WARMUP)
            return

        base = self._regressor(prev.e, prev.v_used)
        f_pred, f_pred_var = self._pending
        v_pred = base + (f_pred if math.isfinite(f_pred) else 0.0)
        moving = abs(v) > self.model.omega or abs(e - prev.e) > 0.0
        if self.stale_detection and v == prev.v_raw and moving:
            c["stale"] += 1
            f_next, f_next_var = self._predict_next(x)
            self._prev = _Prev(seq, float(t), float(e), float(v), v_pred, x)
            self._pending = (f_next, f_next_var)
            self._row(rows, seq, t, v, v_pred, math.nan, f_pred, f_pred_var, f_next, f_next_var, -1, flags | STALE)
            return

        residual = float(v) - base  # v(k) = v_m(k+1) − βᵀz(k), eq. 2.13
        step = self.tracker.learn_one(prev.x, residual)
        self.trained += 1
        c["trained"] += 1
        s02 = step.s02
        f, f_var = step.filtered, step.filtered_var * s02
        if step.reduced:
            flags |= REDUCED
        if self.trained <= self.warmup:
            flags |= WARMUP
        f_next, f_next_var = self._predict_next(x)
        self._prev = _Prev(seq, float(t), float(e), float(v), float(v), x)
        self._pending = (f_next, f_next_var)
        self._row(rows, seq, t, v, v_pred, residual, f, f_var, f_next, f_next_var, step.removed, flags)

    def _reject(self, seq, t, v, rows) -> None:
        self.reset()
        self._prev = None
        tt = float(t) if _finite(t) else math.nan
        self._row(rows, seq, tt, v, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, -1, REJECTED)

    def _row(self, rows, seq, t, v, v_pred, residual, f, f_var, f_next, f_next_var, removed, flags) -> None:
        rows["seq"].append(seq)
        rows["t"].append(float(t))
        rows["v_meas"].append(float(v) if _finite(v) else math.nan)
        rows["v_pred"].append(v_pred)
        rows["residual"].append(residual)
        rows["f"].append(f)
        rows["f_var"].append(f_var)
        rows["f_next"].append(f_next)
        rows["f_next_var"].append(f_next_var)
        rows["dict_size"].append(self.tracker.size)
        rows["removed"].append(int(removed))
        rows["flags"].append(int(flags))
        self.counters["estimates_out"] += 1

    def _block(self, machine: str, axis: str, rows: dict) -> EstimateBlock:
        """Rows → :class:`EstimateBlock`; contiguous only when seq is contiguous (the caller splits)."""
        force = force_var = force_next = None
        b = self.force_gain
        if b is not None:
            force = [-x / b for x in rows["f"]]
            force_var = [x / (b * b) for x in rows["f_var"]]
            force_next = [-x / b for x in rows["f_next"]]
        return EstimateBlock(
            machine=machine,
            axis=axis,
            seq=rows["seq"][0],
            t=rows["t"],
            v_meas=rows["v_meas"],
            v_pred=rows["v_pred"],
            residual=rows["residual"],
            f=rows["f"],
            f_var=rows["f_var"],
            f_next=rows["f_next"],
            f_next_var=rows["f_next_var"],
            dict_size=rows["dict_size"],
            removed=rows["removed"],
            flags=rows["flags"],
            force=force,
            force_var=force_var,
            force_next=force_next,
        )

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, np.ndarray]:
        """Tracker state plus the counters needed to resume (plain arrays, no pickle)."""
        snap = {f"tracker.{k}": v for k, v in self.tracker.snapshot().items()}
        snap["estimator.trained"] = np.array(self.trained, dtype=np.int64)
        return snap

    def restore(self, snap: dict[str, np.ndarray]) -> None:
        """Continue from :meth:`snapshot` (the regressor chain restarts at the next sample)."""
        tracker_part = {k[len("tracker."):]: v for k, v in snap.items() if k.startswith("tracker.")}
        restored = KRLST.restore(tracker_part)
        if restored.kernel != self.tracker.kernel or restored.gamma != self.tracker.gamma:
            raise ValueError("saved tracker state was made with other hyperparameters than the model file; "
                             "start without the state (--fresh) or use the matching model file")
        self.tracker = restored
        self.trained = int(snap.get("estimator.trained", 0))
        self.reset()


_ROW_FIELDS = ("seq", "t", "v_meas", "v_pred", "residual", "f", "f_var", "f_next", "f_next_var", "dict_size", "removed", "flags")


def _finite(*values) -> bool:
    for value in values:
        if value is None or not math.isfinite(value):
            return False
    return True
