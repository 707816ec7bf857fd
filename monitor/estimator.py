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

Per accepted sample the tracker runs the split KRLS-T step of method §6: the
update with the residual of the previous sample, then the forgetting and
prediction at the new sample, which the next update reuses. The whole block goes
through one ``@njit`` loop, :func:`kernels.online.track_block`; this class is the
thin Python API around it (model, counters, schema conversion, persistence).

Robustness (each reason is counted in :attr:`AxisEstimator.counters`):

* non-finite or absurd values (:data:`LIMITS`): the sample is REJECTED (row
  emitted, NaN estimates, tracker untouched); the chain restarts at the next good sample;
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

import numpy as np

from kernels import KRLST, online

from .model_file import AxisModel
from .schema import EstimateBlock, SampleBlock

__all__ = ["AxisEstimator", "LIMITS"]

#: magnitudes beyond which a value is physically absurd for a machine-tool axis (SI):
#: velocities (m/s), force command (N), controller time (s)
LIMITS = {"v": 50.0, "u": 1e7, "t": 1e10}


def _as_column(values) -> np.ndarray:
    """A measured column (``None`` = missing) as float64 with NaN."""
    return np.array([math.nan if x is None else x for x in values], dtype=np.float64)


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
        kernel = cfg.build_kernel()
        self.tracker = KRLST(
            kernel,
            gamma=cfg.gamma,
            forgetting=cfg.forgetting,
            budget=cfg.budget,
            jitter=cfg.jitter,
            grid_step=model.Ts if kernel.is_stationary_1d else None,
            # one refinement step of q per update keeps ‖Q·K_D − I‖ ~1e-8 over millions of steps
            # (kafbox's rank-one update amplifies its error to ~1e-5); ~20 % more per step
            refine=True,
        )
        self.counters: Counter[str] = Counter()
        self._carry = online.new_carry()
        self._limits = np.array([LIMITS["v"], LIMITS["u"] if model.form == "force-input" else LIMITS["v"], LIMITS["t"]])
        self._counts = np.zeros(len(online.COUNTERS), dtype=np.int64)
        self._xbuf = np.zeros(1)
        self._obuf = np.zeros(16)

    def reset(self) -> None:
        """Forget the regressor chain (not the tracker): the next sample starts afresh."""
        trained = self._carry[online.K_TRAINED]
        self._carry = online.new_carry()
        self._carry[online.K_TRAINED] = trained

    @property
    def trained(self) -> int:
        """Samples the tracker has learned from."""
        return int(self._carry[online.K_TRAINED])

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
        self.counters["samples_in"] += n
        t = np.asarray(block.t, dtype=np.float64)
        e = _as_column(exo)
        v = _as_column(block.v_meas)
        rows = np.empty((n, online.N_ROW))
        size = np.empty(n, dtype=np.int64)
        removed = np.empty(n, dtype=np.int64)
        flags = np.empty(n, dtype=np.int64)
        counts = self._counts
        counts[:] = 0
        m = self.model
        first = online.track_block(
            self.tracker.core_state(self._xbuf),
            self.beta, m.coulomb, m.omega, m.form == "force-input", self._limits, self.stale_detection,
            self.warmup, self._carry, block.seq, t, e, v, rows, size, removed, flags, counts, self._xbuf, self._obuf,
        )
        for name, count in zip(online.COUNTERS, counts.tolist()):
            if count:
                self.counters[name] += count
        if first == n:
            return None
        self.counters["estimates_out"] += n - first
        return self._block(block.machine, block.axis, block.seq + first, t[first:], v[first:], rows[first:],
                           size[first:], removed[first:], flags[first:])

    def _block(self, machine, axis, seq0, t, v, rows, size, removed, flags) -> EstimateBlock:
        f, f_var, f_next = rows[:, online.R_F], rows[:, online.R_FVAR], rows[:, online.R_FNEXT]
        force = force_var = force_next = None
        b = self.force_gain
        if b is not None:
            force = (-f / b).tolist()
            force_var = (f_var / (b * b)).tolist()
            force_next = (-f_next / b).tolist()
        return EstimateBlock(
            machine=machine,
            axis=axis,
            seq=int(seq0),
            t=t.tolist(),
            v_meas=v.tolist(),
            v_pred=rows[:, online.R_VPRED].tolist(),
            residual=rows[:, online.R_RESID].tolist(),
            f=f.tolist(),
            f_var=f_var.tolist(),
            f_next=f_next.tolist(),
            f_next_var=rows[:, online.R_FNEXTVAR].tolist(),
            dict_size=size.tolist(),
            removed=removed.tolist(),
            flags=flags.tolist(),
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
        self._carry = online.new_carry()
        self._carry[online.K_TRAINED] = float(snap.get("estimator.trained", 0))
