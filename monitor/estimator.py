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

``z`` holds ``v_ref`` (velocity-loop) or ``u`` (force-input), ``v_m``, the Coulomb columns
when the model has them, and the constant 1 when ``beta_names`` ends with ``"one"`` (either form).

Per accepted sample the tracker runs the split KRLS-T step of method §6: the
update with the residual of the previous sample, then the forgetting and
prediction at the new sample, which the next update reuses. The whole block goes
through one ``@njit`` loop, :func:`kernels.online.track_block`; this class is the
thin Python API around it (model, counters, schema conversion, persistence).

Robustness (each reason is counted in :attr:`AxisEstimator.counters`):

* non-finite or absurd values (:data:`LIMITS`): the sample is REJECTED (row
  emitted, NaN estimates, tracker untouched); the chain restarts at the next good sample;
* sequence numbers (integers; see :mod:`kernels.online` for the rule): a duplicate or a
  late re-send (older ``seq`` and no newer time, within the reorder window ``W``) is dropped,
  no row; a gap (``seq`` and ``t`` jump together), time going backwards, or a new bridge
  session (``seq`` jumps ahead of the clock, or goes back while the clock moves on, or ``W``
  old-looking samples continue each other) restarts the chain (GAP flag; counted ``gaps`` +
  ``missing_samples``, ``time_backwards`` or ``seq_resets``); no residual is formed across it;
* a block whose sequence numbers lie beyond the schema's ``SEQ_MAX`` (2**53 − 1) is refused whole
  (``rejected_seq_range``; the decoder already refuses them, this guards direct callers);
* stale samples — the controller repeated the previous measured velocity while
  the axis moves (the thesis' recording glitch): STALE flag, the tracker is not
  trained on them (predict only) and the model's velocity prediction stands in
  for the repeated value in the next regressor.
"""

from __future__ import annotations

from collections import Counter
from numbers import Integral

import msgspec
import numpy as np

from feedio.limits import LIMITS, SEQ_MAX  # magnitudes beyond which a sample is physically absurd (SI)
from feedio.schema import EstimateBlock, SampleBlock
from kernels import KRLST, online

from .model_file import AxisModel
from .state_check import StateError, check_snapshot

__all__ = ["AxisEstimator", "EstimateRows", "LIMITS", "StateError"]


#: the estimator's own entries of a snapshot (the tracker's are ``tracker.<name>``)
_TRAINED = "estimator.trained"
_C_SEQ_RANGE = online.COUNTERS.index("rejected_seq_range")


def _as_column(values) -> np.ndarray:
    """A measured column (``None`` = missing) as float64 with NaN (one C call: NumPy turns
    ``None`` into NaN for a float64 array)."""
    return np.array(values, dtype=np.float64)


_json = msgspec.json.Encoder()
#: JSON keys of the columns of an EstimateBlock after machine, axis and seq, in field order
_COLUMN_KEYS = [f',"{name}":'.encode() for name in EstimateBlock.__struct_fields__[3:]]


class EstimateRows:
    """The estimate rows of one block as the compiled loop wrote them (columns, no per-sample
    Python objects): ``seq`` of the first row, ``t`` (s), ``v_meas`` (m/s), ``rows``
    (:data:`kernels.online.ROWS`, float64), ``irows`` (:data:`kernels.online.IROWS`, int64) and
    ``force`` (``force``, ``force_var``, ``force_next`` in N, or None when the model cannot scale).
    :meth:`block` makes the :class:`~feedio.schema.EstimateBlock` (once), :meth:`scalar_columns`
    the per-sample columns of :meth:`feedio.scalars.ScalarsPairer.add_rows`."""

    __slots__ = ("machine", "axis", "seq", "t", "v_meas", "rows", "irows", "force", "_block", "_json")

    def __init__(self, machine: str, axis: str, seq: int, t: np.ndarray, v_meas: np.ndarray, rows: np.ndarray,
                 irows: np.ndarray, force: np.ndarray | None) -> None:
        self.machine, self.axis, self.seq = machine, axis, seq
        self.t, self.v_meas, self.rows, self.irows, self.force = t, v_meas, rows, irows, force
        self._block: EstimateBlock | None = None
        self._json: bytes | None = None

    def __len__(self) -> int:
        return int(self.t.size)

    def block(self) -> EstimateBlock:
        """The :class:`~feedio.schema.EstimateBlock` (made on the first call; the columns of
        :data:`~kernels.online.ROWS` and :data:`~kernels.online.IROWS` are its fields in that order)."""
        if self._block is None:
            force = () if self.force is None else self.force.tolist()
            self._block = EstimateBlock(self.machine, self.axis, self.seq, self.t.tolist(), self.v_meas.tolist(),
                                        *self.rows.tolist(), *self.irows.tolist(), *force)
        return self._block

    def json(self) -> bytes:
        """The JSON of :meth:`block` — the bytes ``feedio.schema.encode(self.block())`` gives — made
        from the columns with one ``msgspec`` call, without the schema object (the live monitor
        publishes it before anything else). Names match ``NAME_PATTERN`` (no character to escape)."""
        if self._json is None:
            cols = [self.t.tolist(), self.v_meas.tolist(), *self.rows.tolist(), *self.irows.tolist()]
            if self.force is not None:
                cols += self.force.tolist()
            parts = _json.encode(cols)[2:-2].split(b"],[")  # "[[c0],[c1],…]" -> c0, c1, …
            body = [f'{{"machine":"{self.machine}","axis":"{self.axis}","seq":{self.seq}'.encode()]
            for key, part in zip(_COLUMN_KEYS, parts):
                body += (key, b"[", part, b"]")
            body.append(b"}")
            self._json = b"".join(body)
        return self._json

    def scalar_columns(self) -> dict[str, np.ndarray | None]:
        """The columns :meth:`feedio.scalars.ScalarsPairer.add_rows` takes (views, no copies):
        ``v_meas, f, f_var, f_next``, ``force, force_var, force_next`` (None without a force scale) and
        ``flags``."""
        r, fc = self.rows, self.force
        return {"v_meas": self.v_meas, "f": r[online.R_F], "f_var": r[online.R_FVAR], "f_next": r[online.R_FNEXT],
                "force": None if fc is None else fc[0], "force_var": None if fc is None else fc[1],
                "force_next": None if fc is None else fc[2], "flags": self.irows[online.R_FLAGS]}


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
    reorder_window : int
        W ≥ 1 (samples): how far behind the newest sequence number a sample is still taken
        as a duplicate or late re-send (dropped) — beyond, or when W of them continue each
        other, the bridge is taken to have restarted (default :data:`kernels.online.REORDER_WINDOW`).
    """

    def __init__(self, model: AxisModel, *, warmup: int | None = None, stale_detection: bool = True,
                 reorder_window: int = online.REORDER_WINDOW):
        self.model = model
        self.beta = np.asarray(model.beta, dtype=np.float64)
        self.force_gain = model.force_gain
        self.warmup = model.tracker.budget if warmup is None else int(warmup)
        self.stale_detection = stale_detection
        if isinstance(reorder_window, bool) or not isinstance(reorder_window, int) or reorder_window < 1:
            raise ValueError(f"reorder_window must be an integer >= 1 (samples), got {reorder_window!r}")
        self.reorder_window = reorder_window
        names = tuple(model.beta_names)
        intercept = names[-1:] == ("one",)
        expected = 2 + 2 * bool(model.coulomb) + intercept
        if self.beta.shape != (len(names),) or len(names) != expected:
            raise ValueError(f"axis {model.machine}/{model.axis}: beta has {self.beta.size} values for "
                             f"{len(names)} names {names}; the online residual uses e, v"
                             f"{', −σ_p, −σ_n' if model.coulomb else ''}{', one' if intercept else ''}")
        e_max = LIMITS["u"] if model.form == "force-input" else LIMITS["v"]
        self._cfg = online.new_config(
            beta=self.beta, coulomb=bool(model.coulomb), intercept=intercept, omega=float(model.omega),
            inv_ts=1.0 / float(model.Ts), v_max=LIMITS["v"], e_max=float(e_max), t_max=LIMITS["t"],
            stale_detection=bool(stale_detection), warmup=int(self.warmup), reorder_window=int(reorder_window))
        self.tracker = self._new_tracker()
        self.counters: Counter[str] = Counter()
        b = self.force_gain
        #: divisors of the rows f, f_var, f_next that give force, force_var, force_next (None: no scale)
        self._force_div = None if b is None else np.array([[-b], [b * b], [-b]])
        #: :data:`kernels.online.COUNTERS` of the last block (what :meth:`process_rows` counted)
        self.block_counts = np.zeros(len(online.COUNTERS), dtype=np.int64)
        self._state = online.new_state()
        self._xbuf, self._obuf = online.new_scratch()
        self._templates: tuple[dict[str, np.ndarray], dict[str, np.ndarray]] | None = None

    def _new_tracker(self) -> KRLST:
        cfg = self.model.tracker
        kernel = cfg.build_kernel()
        return KRLST(
            kernel,
            gamma=cfg.gamma,
            forgetting=cfg.forgetting,
            budget=cfg.budget,
            jitter=cfg.jitter,
            grid_step=self.model.Ts if kernel.is_stationary_1d else None,
            # one refinement step of q per update keeps ‖Q·K_D − I‖ ~1e-8 over millions of steps
            # (kafbox's rank-one update amplifies its error to ~1e-5); ~20 % more per step
            refine=True,
        )

    @property
    def config(self) -> online.ConfigBuffers:
        """What the compiled loop reads of the model (read only; named by :func:`kernels.online.config_of`)."""
        return self._cfg

    @property
    def trained(self) -> int:
        """Samples the tracker has learned from."""
        return int(online.state_of(*self._state).trained[0])

    # ------------------------------------------------------------------ main entry
    def process(self, block: SampleBlock) -> EstimateBlock | None:
        """Estimates for the samples of ``block`` (None when every sample was dropped or refused)."""
        rows = self.process_rows(block)
        return None if rows is None else rows.block()

    def process_rows(self, block: SampleBlock) -> EstimateRows | None:
        """:meth:`process` returning the rows as columns (:class:`EstimateRows`): the schema object
        and its JSON are made only when asked for."""
        n = len(block.t)
        exo = block.u if self.model.form == "force-input" else block.v_ref
        if exo is None:
            self.counters["rejected_missing_field"] += n
            raise ValueError(
                f"axis {block.machine}/{block.axis}: the {self.model.form} model needs "
                f"'{'u' if self.model.form == 'force-input' else 'v_ref'}' in every sample block"
            )
        c = self.counters
        c["samples_in"] += n
        seq0 = block.seq
        if type(seq0) is not int and (isinstance(seq0, bool) or not isinstance(seq0, Integral)) \
                or not 0 <= seq0 <= SEQ_MAX - (n - 1):
            c["rejected_seq_range"] += n  # not a valid sequence number: never handed to compiled code
            self.block_counts = np.zeros(len(online.COUNTERS), dtype=np.int64)
            self.block_counts[_C_SEQ_RANGE] = n
            return None
        seq0 = int(seq0)
        t = np.array(block.t, dtype=np.float64)
        e = _as_column(exo)
        v = _as_column(block.v_meas)
        rows, irows, counts = online.new_rows(n)
        first = online.track_block(*self.tracker.core_arrays(self._xbuf), *self._cfg, *self._state, seq0,
                                   t, e, v, rows, irows, counts, self._xbuf, self._obuf)
        self.block_counts = counts
        for name, k in zip(online.COUNTERS, counts.tolist()):
            if k:
                c[name] += k
        if first == n:
            return None
        c["estimates_out"] += n - first
        if first:
            t, v, rows, irows = t[first:], v[first:], rows[:, first:], irows[:, first:]
        # F = −f/b, var F = var f / b², F_next = −f_next/b (force-input form, or velocity loop with known K)
        force = None if self._force_div is None else rows[online.R_F:online.R_FNEXT + 1] / self._force_div
        return EstimateRows(block.machine, block.axis, seq0 + first, t, v, rows, irows, force)

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, np.ndarray]:
        """Tracker state plus the counters needed to resume (plain arrays, no pickle)."""
        snap = {f"tracker.{k}": v for k, v in self.tracker.snapshot().items()}
        snap[_TRAINED] = np.array(self.trained, dtype=np.int64)
        return snap

    def snapshot_templates(self) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """What a valid snapshot of this model looks like: the snapshots of a fresh tracker with the
        model's hyperparameters before any sample and after one step (keys, shapes, dtypes and the
        hyperparameter values; they follow the core's layout, whatever it is). Made once per
        estimator; treat them as read only."""
        if self._templates is None:
            tracker = self._new_tracker()
            before = {f"tracker.{k}": v for k, v in tracker.snapshot().items()}
            tracker.learn_one(0.0, 0.0)
            after = {f"tracker.{k}": v for k, v in tracker.snapshot().items()}
            before[_TRAINED] = after[_TRAINED] = np.array(0, dtype=np.int64)
            self._templates = (before, after)
        return self._templates

    def restore(self, snap: dict[str, np.ndarray]) -> None:
        """Continue from :meth:`snapshot` (the regressor chain restarts at the next sample).

        The snapshot is checked first (:func:`monitor.state_check.check_snapshot`: keys, shapes,
        dtypes, finiteness, the model's hyperparameters, the tracker's invariants); a snapshot that
        fails raises :class:`StateError` naming the reason and leaves this estimator as it was.
        """
        before, after = self.snapshot_templates()
        check_snapshot(snap, before, after, counters=(_TRAINED,))
        tracker_part = {k[len("tracker."):]: v for k, v in snap.items() if k.startswith("tracker.")}
        try:
            restored = KRLST.restore(tracker_part)
        except ValueError as exc:
            raise StateError(str(exc)) from None
        self.tracker = restored
        self._state = online.new_state(trained=int(snap[_TRAINED]))
