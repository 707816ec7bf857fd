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
  for the repeated value in the next regressor;
* a tracker step that raises, or a state that broke down numerically
  (:meth:`kernels.krlst.KRLST.breakdown`: posterior variance above the prior, a non-finite value —
  it would never recover): the block's estimates are dropped, the tracker, online β and health
  start over from the model file (``tracker_restarts``), and :class:`TrackerBreakdown` (or the
  error) is raised for the caller to count and log (``estimator_error`` in the monitor).

Online β and health (:mod:`monitor.online_settings`): β̂ and its covariance run beside
the tracker (:class:`kernels.beta_tracker.OnlineBeta`, mode ``[adaptation] mode``), the health
statistics on every learned sample (:class:`kernels.health.HealthMonitor`); the compiled loop
writes a health report about once a second of data time, and :meth:`AxisEstimator.take_health`
hands them out as :class:`~feedio.schema.Health` messages. With the spindle-phase kernel the
tracker input is ``(t, θ)`` from the samples' ``spindle_angle`` / ``spindle_rpm``
(:mod:`kernels.online`). β̂, its covariance and the health state are part of the snapshot.
"""

from __future__ import annotations

import math
from collections import Counter
from itertools import compress
from numbers import Integral

import numpy as np

from feedio.limits import LIMITS, SAMPLE_LIMITS, SEQ_MAX  # magnitudes beyond which a sample is physically absurd (SI)
from feedio.schema import CONTEXT_COLUMNS, REASON_CHARS_MAX, REASONS_MAX, EstimateBlock, Health, SampleBlock
from kernels import KRLST, online
from kernels import disturbance_search as ds
from kernels import health as hl
from kernels.beta_tracker import PHYSICAL as PHYSICAL_PARAMS  # the order of the report rows' θ and s.e.
from kernels.beta_tracker import REBASE_EVERY, OnlineBeta, physical_of
from kernels.health import HealthMonitor, describe, physical_vector

from .background_search import PendingSearch, caught_up, submit, went_on
from .estimate_rows import EstimateRows
from .model_file import AxisModel
from .online_settings import OnlineSettings, SpindleKernel, choice_of
from .state_check import CHOICE as _CHOICE
from .state_check import StateError, check_snapshot, choice_array, choice_of_array

__all__ = ["AxisEstimator", "LIMITS", "StateError", "TrackerBreakdown"]


#: the estimator's own entries of a snapshot (the tracker's are ``tracker.<name>``): the samples learned,
#: and the disturbance model the search had chosen (:func:`monitor.state_check.choice_array`)
_TRAINED = "estimator.trained"
_C_SEQ_RANGE = online.COUNTERS.index("rejected_seq_range")


#: the float rows of :data:`kernels.online.ROWS` (the compiled loop's buffer has more below them)
_N_ROWS = len(online.ROWS)


def _as_column(values) -> np.ndarray:
    """A measured column (``None`` = missing) as float64 with NaN (one C call: NumPy turns
    ``None`` into NaN for a float64 array)."""
    return np.array(values, dtype=np.float64)


class TrackerBreakdown(ArithmeticError):
    """The tracker's state left what exact arithmetic allows; the estimator started over."""


_JITTER_HINT = " (a jitter ε_j < 1e-7 makes K_D nearly singular: use 1e-6)"


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
        self.settings = getattr(model, "online", None) or OnlineSettings()
        kernel = model.tracker.kernel
        self.spindle = kernel if isinstance(kernel, SpindleKernel) else None
        #: samples from a command to its force (``[model] delay``): the first regressor holds the command
        #: that many samples back (:meth:`_delayed_command`)
        self.delay = int(getattr(model, "delay", 0) or 0)
        self._delay_hist = np.full((2, self.delay), np.nan)
        #: the disturbance model is chosen online (kernels.disturbance_search) unless the model file says not to
        self.searching = bool(getattr(model.tracker, "search", True))
        #: the disturbance model that publishes (``choice``) and the one online β learns with (``beta_choice``,
        #: :func:`kernels.disturbance_search.for_beta`: the structure the process demands at the model file's
        #: hyperparameters); when they differ, ``pub`` is the publishing tracker
        self.choice = self.beta_choice = choice_of(model.tracker) if self.searching else None
        self._file_choice = self.choice
        self.pub: KRLST | None = None
        self._no_pub = (np.zeros(0), np.zeros(0, dtype=np.int64))
        noise = getattr(model, "noise", None)
        self.noise2 = float(noise) ** 2 if noise else 0.0
        self.search = ds.DisturbanceSearch(self.choice, Ts=float(model.Ts), budget=model.tracker.budget,
                                           jitter=model.tracker.jitter, noise2=self.noise2,
                                           teeth=self.spindle.teeth if self.spindle else None) if self.searching else None
        self._search_bufs = online.new_search(float(model.Ts), noise2=self.noise2, enabled=self.searching)
        #: the search under way beside the per-sample path (:mod:`monitor.background_search`)
        self._pending: PendingSearch | None = None
        self._lag = max(1, int(round(ds.SearchSettings().lag / float(model.Ts))))
        self._sync_search()
        self.search_error: str | None = None
        #: one-off reasons for the next health report (e.g. a restart of online β)
        self._pending_reasons: list[str] = []
        #: why values of the health reports are not given (static per axis)
        self.notes: list[str] = []
        self.mode = self.settings.adaptation.mode
        self._start_fresh()                                # may switch the mode off (notes say why)
        self.notes += self._notes()
        e_max = LIMITS["u"] if model.form == "force-input" else LIMITS["v"]
        sp = self.spindle
        self._cfg = online.new_config(
            beta=self.beta, coulomb=bool(model.coulomb), intercept=intercept, omega=float(model.omega),
            inv_ts=1.0 / float(model.Ts), v_max=LIMITS["v"], e_max=float(e_max), t_max=LIMITS["t"],
            stale_detection=bool(stale_detection), warmup=int(self.warmup), reorder_window=int(reorder_window),
            mode=self.mode, spindle=sp is not None, theta_period=sp.period if sp else 2.0 * math.pi,
            rpm_nominal=sp.spindle_rpm if sp else 0.0, rpm_max=SAMPLE_LIMITS.spindle_rpm_max,
            tick_period=self.settings.health.period)
        self._spindle_seen = False
        if self.searching:
            online.set_tracker_input(self._cfg, self.choice.spindle, 2.0 * math.pi / self.choice.teeth)
        self.counters: Counter[str] = Counter()
        b = self.force_gain
        #: force, force_var, force_next = the rows f, f_var, f_next divided by sign·b^power (F = −f/b,
        #: var F = var f/b², F_next = −f_next/b); b fixed (None: no scale) or, in apply mode, β̂1 per row
        #: times ``_beta1_to_b`` (1 in force-input form, 1/K in velocity-loop form)
        self._force_sign = np.array([[-1.0], [1.0], [-1.0]])
        self._force_power = np.array([[1.0], [2.0], [1.0]])
        self._force_div = None if b is None else self._force_sign * b ** self._force_power
        self._beta1_to_b = 1.0 if model.form == "force-input" else 1.0 / (model.loop_gain or math.nan)
        #: :data:`kernels.online.COUNTERS` of the last block (what :meth:`process_rows` counted)
        self.block_counts = np.zeros(len(online.COUNTERS), dtype=np.int64)
        self._xdim = 2 if (self.choice.spindle if self.searching else sp is not None) else 1
        self._xbuf = np.zeros(self._xdim)  # an example input (its size) for the tracker's buffers
        self._scratch = online.new_scratch(len(names))
        self._no_spindle = np.zeros((2, 0))
        self._no_ref = np.zeros(0)
        self._health_out: list[Health] = []
        hp = self.health.state.par  # fewest samples between two changes of the validity level
        self._change_min = int(max(1.0, min(hp[hl.Q_NPERS], hp[hl.Q_NHOLD])))
        self._tick_min = int(online.config_of(*self._cfg).tick_min)  # fewest samples between two periodic reports
        self._ticks_n, self._ticks = -1, None  # the health-report buffer of the last block size (_ticks_for)
        # what the model's form decides per block, looked up once
        self._force_input, self._velocity_loop = model.form == "force-input", model.form == "velocity-loop"
        self._templates: tuple[dict[str, np.ndarray], dict[str, np.ndarray]] | None = None

    def _new_tracker(self, choice: ds.TrackerChoice | None = None) -> KRLST:
        """A fresh tracker of ``choice`` (default: online β's; without the search, the model file's)."""
        cfg = self.model.tracker
        choice = choice or self.beta_choice
        kernel = cfg.build_kernel() if choice is None else choice.kernel()
        return KRLST(
            kernel,
            gamma=cfg.gamma if choice is None else choice.gamma,
            forgetting=cfg.forgetting if choice is None else choice.forgetting,
            budget=cfg.budget,
            jitter=cfg.jitter,
            grid_step=self.model.Ts if kernel.is_stationary_1d else None,
            # one refinement step of q per update keeps ‖Q·K_D − I‖ ~1e-8 over millions of steps
            # (kafbox's rank-one update amplifies its error to ~1e-5); ~20 % more per step
            refine=True,
        )

    def _new_online(self, tracker: KRLST) -> OnlineBeta:
        """The online β of the model (β₀, its covariance when the model file has one, the settings);
        a β that is not a physical drive cannot be adapted: the mode falls back to ``off``."""
        m, a = self.model, self.settings.adaptation
        names = tuple(m.beta_names)
        kw = dict(omega=float(m.omega), gain=m.loop_gain if m.form == "velocity-loop" else None,
                  allowance=a.allowance, memory=a.memory, inertia_memory=a.inertia_memory, huber=a.huber,
                  reject=a.reject, hold=a.hold, min_speed=a.min_speed, instrument=a.instrument,
                  enabled=self.mode != "off",
                  rebase_every=REBASE_EVERY if self.mode == "apply" else 0)
        try:
            return OnlineBeta(tracker, self.beta, names, float(m.Ts), beta_cov=_beta_cov(m), **kw)
        except ValueError as exc:
            if self.mode != "off":
                self.notes.append(f"adaptation off: {exc}")
                self.mode = "off"
            # β is still needed by the loop's layout: a stand-in physical drive, never adapted nor reported
            stand_in = self.beta.copy()
            stand_in[0], stand_in[1] = 1.0, 0.5 - (1.0 if m.form == "velocity-loop" else 0.0)
            return OnlineBeta(tracker, stand_in, names, float(m.Ts), **{**kw, "enabled": False, "rebase_every": 0})

    def _notes(self) -> list[str]:
        """Which values of the health reports are not given, and why (static per axis)."""
        m = self.model
        if self.mode == "off":
            return [] if self.notes else ["not given: physical parameters (adaptation off)"]
        notes = []
        missing = [name for name, col in (("coulomb", "-sigma_p"), ("offset", "one")) if col not in m.beta_names]
        if missing:
            notes.append(f"not given: {', '.join(missing)} (the model has no such column)")
        if self._friction_untested():
            notes.append(f"not tested for drift: Coulomb friction (below min_speed = "
                         f"{self.settings.adaptation.min_speed:.3g} m/s the friction departs from the law; the model "
                         f"file's was fitted down to standstill, the monitor learns above min_speed)")
        if m.form == "velocity-loop" and m.loop_gain is None:
            notes.append("not given: absolute inertia, damping, Coulomb, offset (a velocity-loop model without the "
                         "loop gain K determines them over K only; their drift is still tested)")
        return notes

    def _friction_untested(self) -> bool:
        """Whether the Coulomb friction has no reference to test drift against: the friction departs from the
        law below ``min_speed``, where the online β does not learn, while the model file's friction comes from a
        fit down to standstill (the real EMPS drive: LS 20.3 N, the monitor above 3.5 cm/s 25 N on the very
        identification trial). Compared, the two estimators' difference would read as a drift."""
        return self.settings.adaptation.min_speed > 0.0

    def _new_health(self) -> HealthMonitor:
        """Health statistics with the model file's physical parameters (and standard errors when the model
        file has them) as the drift reference."""
        m = self.model
        names = tuple(m.beta_names)
        gain = m.loop_gain if m.form == "velocity-loop" else None
        cov = _beta_cov(m)
        P = np.zeros((len(names), len(names))) if cov is None else (np.diag(cov * cov) if cov.ndim == 1 else cov)
        try:
            th0, se0 = physical_of(self.beta, names, float(m.Ts), P, gain=gain)
        except ValueError:
            th0 = se0 = np.full(6, np.nan)
        if self._friction_untested():
            th0 = th0.copy()
            th0[[PHYSICAL_PARAMS.index(k) for k in ("coulomb_pos", "coulomb_neg", "coulomb")]] = np.nan
        return HealthMonitor(float(m.Ts), physical_vector(th0), physical_vector(se0),
                             physical_vector(self.online.prior_se), config=self.settings.health.config())

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
        """Estimates for the samples of ``block`` (None when every sample was dropped or refused);
        the health reports it produced wait in :meth:`take_health`."""
        rows = self.process_rows(block)
        return None if rows is None else rows.block()

    def process_rows(self, block: SampleBlock) -> EstimateRows | None:
        """:meth:`process` returning the rows as columns (:class:`EstimateRows`): the schema object
        and its JSON are made only when asked for; the health reports wait in :meth:`take_health`."""
        n = len(block.t)
        exo = block.u if self._force_input else block.v_ref
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
        sp = self._no_spindle
        has_spindle = block.spindle_angle is not None or block.spindle_rpm is not None
        if has_spindle and (self.spindle is not None or self.searching):
            sp = np.full((2, n), np.nan)
            if block.spindle_angle is not None:
                sp[0] = _as_column(block.spindle_angle)
            if block.spindle_rpm is not None:
                sp[1] = _as_column(block.spindle_rpm)
            if self.searching and not self._spindle_seen:
                self._spindle_seen = True
                self._spindle_appeared(sp[1])
        rows, irows, counts = online.new_rows(n)
        ticks = self._ticks_for(n)
        vref = e if self._velocity_loop else (
            _as_column(block.v_ref) if block.v_ref is not None else self._no_ref)
        if self.delay:
            e = self._delayed_command(seq0, e, v)
        start = first = 0
        sint = self._search_bufs[1]
        try:
            while True:
                done = int(counts[online.C_TICKS])
                got = online.track_block(*self.tracker.core_buffers(self._xbuf), *self.online.buffers,
                                         *self.health.buffers, *self._cfg, *self._state, seq0, t, e, v, sp, rows,
                                         irows, counts, ticks[done:], self._scratch, start, *self._search_bufs,
                                         vref, *self._pub_buffers())
                if start == 0:
                    first = got
                if sint[online.S_PAUSE] == online.PAUSE_NONE:
                    break
                start = int(sint[online.S_STOP])
                if self._pending is None:
                    self._start_search(poor=sint[online.S_PAUSE] == online.PAUSE_POOR)
                else:
                    self._finish_search()
        except Exception:  # a state half-way through a step is not trusted: start over, then say why
            self._start_over()
            raise
        why = self.tracker.breakdown()
        if why is not None:
            self._start_over()
            raise TrackerBreakdown(
                f"axis {block.machine}/{block.axis}: the tracker's numerics broke down ({why}); {n} samples "
                f"dropped, tracker restarted{_JITTER_HINT if self.model.tracker.jitter < 1e-7 else ''}")
        if self.mode != "off":
            why_beta = self.online.breakdown()
            if why_beta is not None:
                self._restart_beta(why_beta)
        self.block_counts = counts
        counted = counts.tolist()
        for name, k in compress(zip(online.COUNTERS, counted), counted):  # the counts not zero, in order
            c[name] += k
        nt = counted[online.C_TICKS]
        if nt:
            self._health_out.extend(self._health(block.machine, block.axis, ticks[i]) for i in range(nt))
        if first == n:
            return None
        c["estimates_out"] += n - first
        if first:
            t, v, rows, irows = t[first:], v[first:], rows[:, first:], irows[:, first:]
        # the context of row i is that of sample first + i (the dropped samples are a prefix)
        context = {}
        for k in CONTEXT_COLUMNS:
            col = getattr(block, k)
            if col is not None:
                context[k] = col[first:]
        return EstimateRows(block.machine, block.axis, seq0 + first, t, v, rows[:_N_ROWS], irows,
                            self._force(rows), context)

    def _ticks_for(self, n: int) -> np.ndarray:
        """The buffer the compiled loop writes a block's health reports to (:func:`kernels.online.new_ticks`),
        kept while the blocks keep their size: it never leaves the estimator (:meth:`_health` reads the rows
        a block wrote before the next block), and the live monitor sends one sample per block."""
        if n != self._ticks_n:
            self._ticks_n, self._ticks = n, online.new_ticks(n, self._tick_min, self._change_min)
        return self._ticks

    def _delayed_command(self, seq0: int, e: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The first regressor of a model whose force acts ``d`` samples late (``[model] delay``, as
        :func:`kernels.feed_drive.regressors` builds it for the batch fit): ``u(k−d)`` in the force-input form,
        ``v_r(k−d) − v_m(k−d) + v_m(k)`` in the velocity-loop form. The last ``d`` samples are carried from
        block to block; a sample whose predecessors did not arrive in sequence (the start, a gap, a
        reordered block) or were not finite keeps its own command, as the batch's first ``d`` rows do."""
        d = self.delay
        if self._delay_next != seq0:
            self._delay_hist = np.full((2, d), np.nan)
        he = np.concatenate((self._delay_hist[0], e))
        hv = np.concatenate((self._delay_hist[1], v))
        n = e.shape[0]
        z = he[:n] if self.model.form == "force-input" else he[:n] - hv[:n] + v
        z = np.where(np.isfinite(z), z, e)
        self._delay_hist = np.stack((he[-d:], hv[-d:]))
        self._delay_next = seq0 + n
        return z

    def _start_fresh(self) -> None:
        """Tracker, online β, health statistics and regressor chain as the model file starts them."""
        self._delay_next = -1                              # the delayed command has no past yet
        self.tracker = self._new_tracker()
        self.online = self._new_online(self.tracker)
        self.health = self._new_health()
        self._state = online.new_state()

    def _start_over(self) -> None:
        """:meth:`_start_fresh` after a step that failed or a state that broke down
        (:meth:`kernels.krlst.KRLST.breakdown`), which would otherwise never recover (counted
        ``tracker_restarts``)."""
        notes, mode = self.notes, self.mode
        if self.searching:
            self._drop_search()
            self.choice = self.search.choice = self.beta_choice
            self._set_dual(None)
        self._start_fresh()
        self.notes, self.mode = notes, mode  # as decided at the start (the model is the same)
        sint = self._search_bufs[1]
        sint[online.S_FILL] = sint[online.S_HEAD] = 0  # the ring's scores were the old tracker's
        self.counters["tracker_restarts"] += 1

    def _pub_buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """The buffers of the publishing tracker when it is not online β's (else empty)."""
        if self.pub is None:
            return self._no_pub
        return self.pub.core_buffers(np.zeros(2 if self.choice.spindle else 1))

    def _set_dual(self, pub: KRLST | None) -> None:
        sint = self._search_bufs[1]
        self.pub = pub
        sint[online.S_DUAL] = int(pub is not None)
        sint[online.S_PUB_SPINDLE] = int(pub is not None and self.choice.spindle)

    def _restart_beta(self, why: str) -> None:
        """Online β from the model file's prior again after a numerical breakdown of its recursion; the
        tracker is rebuilt from the ring (with fresh shadow means) and the estimates go on. Counted
        ``beta_restarts``; the next health report says why."""
        fresh = self._new_online(self._new_tracker(self.beta_choice))
        R = self._ring()
        self.tracker = self._new_tracker(self.beta_choice)
        self.online = fresh.reseated(self.tracker, np.nan_to_num(R[:, [online.G_T, online.G_THETA]] if self._xdim == 2
                                                                 else R[:, [online.G_T]]),
                                     R[:, online.G_EXO], R[:, online.G_V], R[:, online.G_TARGET],
                                     self._x_now(self._xdim == 2))
        self.counters["beta_restarts"] += 1
        self._pending_reasons.append(f"online β restarted from the model file: its recursion broke down numerically "
                                     f"({why}); the disturbance estimates went on")

    # ------------------------------------------------------------------ the disturbance model
    def _sync_search(self) -> None:
        """Hand the search's schedule to the compiled loop (when to pause, until when to freeze)."""
        if self.search is None:
            return
        sint = self._search_bufs[1]
        sint[online.S_NEXT_TICK] = self.search.next_tick
        sint[online.S_NEXT_RETRY] = self.search.next_retry
        sint[online.S_FREEZE] = self.search.freeze_until

    def _ring(self) -> np.ndarray:
        """The ring's entries, oldest first (a copy; :data:`kernels.online.RING` columns)."""
        ring, sint, _ = self._search_bufs
        fill, head = int(sint[online.S_FILL]), int(sint[online.S_HEAD])
        return ring[(head - fill + np.arange(fill)) % ring.shape[0]]

    def _start_search(self, poor: bool) -> None:
        """Start a search of the disturbance model on a copy of the ring
        (:meth:`kernels.disturbance_search.DisturbanceSearch.tick`, :mod:`monitor.background_search`); the
        compiled loop pauses again at the learned sample its verdict is due at. While a search that
        began on poor predictions runs, the validity test waits for it (as it waits for a search in line)."""
        R = self._ring()
        theta = R[:, online.G_THETA]
        sint = self._search_bufs[1]
        count = int(sint[online.S_COUNT])
        ring = ds.Ring(t=R[:, online.G_T], theta=np.nan_to_num(theta), y=R[:, online.G_RESID],
                       ref=R[:, online.G_REF], count=count, rpm=R[:, online.G_RPM],
                       spindle=bool(R.shape[0]) and bool(np.isfinite(theta).all()))
        self.counters["tracker_searches"] += 1
        if not self.noise2:  # without the model file's noise level, the tracker's own: s0²/γ
            self.search.noise2 = self.tracker.s02 * self.tracker.sn2
        search, beta_now, online_now = self.search, self.beta_choice, self.online

        def work():
            verdict = search.tick(ring, poor)
            return verdict, self._rebuild_ahead(verdict, R, beta_now, online_now)

        self._pending = submit(work, R, count, self._lag)
        sint[online.S_NEXT_TICK] = sint[online.S_NEXT_RETRY] = self._pending.due
        if poor:
            sint[online.S_FREEZE] = max(int(sint[online.S_FREEZE]), self._pending.due)

    def _finish_search(self) -> None:
        """Apply the verdict of the search under way (waiting for it if need be): a better model publishes
        the disturbance (:meth:`_adopt`), its tracker first fed the samples learned since the search
        began. A search that failed is counted and the trackers kept."""
        pending, self._pending = self._pending, None
        try:
            verdict, ahead = pending.wait()
            if verdict.adopt is not None:
                R = self._ring()
                since = int(self._search_bufs[1][online.S_COUNT]) - pending.count
                tracker = caught_up(verdict.tracker, verdict.adopt.spindle, pending.ring, R, since)
                if ahead is not None and not (went_on(pending.ring, R, since) and verdict.window + since <= R.shape[0]):
                    ahead = None                  # the ring did not go on from the one the search saw
                self._adopt(verdict.adopt, tracker, R[-(verdict.window + since):] if verdict.window else R,
                            ahead, since)
                self.counters["tracker_adoptions"] += 1
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            self.counters["tracker_search_errors"] += 1
            self.search_error = str(exc)
        self._sync_search()

    def _drop_search(self) -> None:
        """Forget the search under way (after it ends: it reads the search's state) — the trackers it
        weighed against are being replaced."""
        if self._pending is not None:
            try:
                self._pending.wait()
            except (ValueError, ArithmeticError, np.linalg.LinAlgError):
                pass
            self._pending = None
            self._sync_search()

    def _x_now(self, spindle: bool) -> np.ndarray | None:
        """The input x of the last accepted sample (the one the tracker is armed at), None before any."""
        t = float(online.state_of(*self._state).last_t[0])
        if not math.isfinite(t):
            return None
        if not spindle:
            return np.array([t])
        theta = float(self._search_bufs[2][online.Q_THETA])
        return np.array([t, theta if math.isfinite(theta) else float(self._scratch[1] if self._xdim == 2 else 0.0)])

    def _adopt(self, choice: ds.TrackerChoice, tracker: KRLST | None, R: np.ndarray, ahead=None,
               since: int = 0) -> None:
        """Publish the disturbance with ``choice``; online β learns with
        :func:`kernels.disturbance_search.for_beta` of it (the same tracker when they agree). ``tracker``:
        ``choice``'s tracker replayed over ``R`` (armed at its newest entry), or None (a fresh one).
        ``ahead``: online β's replay begun on the search's worker (:meth:`_rebuild_ahead`) over ``R`` but
        its newest ``since`` entries."""
        beta_choice = self._beta_choice_for(choice)
        if beta_choice != self.beta_choice:
            self._reseat_beta(beta_choice, R, ahead, since)
        self.choice = choice
        if choice == self.beta_choice:
            self._set_dual(None)
            return
        x = self._x_now(choice.spindle)
        if tracker is None:
            tracker = self._new_tracker(choice)
        elif R.shape[0]:
            tracker.update(float(R[-1, online.G_RESID]))   # the newest entry: it was armed there
        if x is not None:
            tracker.predict_next(x)
        self._set_dual(tracker)

    def _beta_choice_for(self, choice: ds.TrackerChoice) -> ds.TrackerChoice:
        """The tracker online β learns with while ``choice`` publishes the disturbance."""
        return ds.for_beta(choice, self._file_choice) if self.mode != "off" else choice

    def _rebuild_ahead(self, verdict: ds.Verdict, R: np.ndarray, beta_now: ds.TrackerChoice | None,
                       online_now: OnlineBeta):
        """On the search's worker, after its verdict: when adopting it will give online β another
        tracker, that tracker and its shadow means replayed over the search's window of the ring
        (:meth:`kernels.beta_tracker.OnlineBeta.rebuilt`) — tens of milliseconds that the per-sample path
        would otherwise wait for. ``(choice, online β it was begun from, the replay)`` or None."""
        if verdict.adopt is None or not verdict.window:
            return None
        choice = self._beta_choice_for(verdict.adopt)
        if choice == beta_now:
            return None
        old = R[-verdict.window:]
        X = old[:, [online.G_T, online.G_THETA]] if choice.spindle else old[:, [online.G_T]]
        return choice, online_now, online_now.rebuilt(self._new_tracker(choice), np.nan_to_num(X),
                                                      old[:, online.G_EXO], old[:, online.G_V], old[:, online.G_TARGET])

    def _reseat_beta(self, choice: ds.TrackerChoice, R: np.ndarray, ahead=None, since: int = 0) -> None:
        """Online β's tracker becomes ``choice``: a fresh one rebuilt from the ring entries ``R`` (with its
        shadow means; β keeps what it learned) and armed at the current sample. With ``ahead``
        (:meth:`_rebuild_ahead`) still valid, only ``R``'s newest ``since`` entries are replayed here."""
        begun = None
        if ahead is not None:
            a_choice, a_online, rebuilt = ahead
            if a_choice == choice and a_online is self.online and rebuilt.fits(self.online):
                begun, R = rebuilt, R[R.shape[0] - since:]
        tracker = begun.new.tracker if begun is not None else self._new_tracker(choice)
        X = R[:, [online.G_T, online.G_THETA]] if choice.spindle else R[:, [online.G_T]]
        self.online = self.online.reseated(tracker, np.nan_to_num(X), R[:, online.G_EXO], R[:, online.G_V],
                                           R[:, online.G_TARGET], self._x_now(choice.spindle), begun=begun)
        self.tracker = tracker
        self.beta_choice = choice
        online.set_tracker_input(self._cfg, choice.spindle, 2.0 * math.pi / choice.teeth)
        self._xdim = 2 if choice.spindle else 1
        self._xbuf = np.zeros(self._xdim)

    def _spindle_appeared(self, rpm: np.ndarray) -> None:
        """The first samples with spindle data: the spindle-phase kernel from now on (whatever the
        model file's tracker was), with the speed seen as the nominal one where the model has none."""
        finite = rpm[np.isfinite(rpm) & (np.abs(rpm) > 0) & (np.abs(rpm) <= SAMPLE_LIMITS.spindle_rpm_max)]
        if finite.size and not online.config_of(*self._cfg).rpm_nominal > 0.0:
            online.set_tracker_input(self._cfg, online.config_of(*self._cfg).spindle,
                                     online.config_of(*self._cfg).theta_period, rpm_nominal=float(np.median(np.abs(finite))))
        c = self.choice
        if c.spindle:
            return
        self._drop_search()
        periodic = c.kind == "periodic"
        choice = ds.TrackerChoice("spindle", sigma1=c.sigma1 if periodic else ds.SPINDLE_START["sigma1"],
                                  sigma2=c.sigma2 if periodic else ds.SPINDLE_START["sigma2"], gamma=c.gamma,
                                  forgetting=c.forgetting, teeth=1)
        self._adopt(choice, None, self._ring()[:0])
        self.search.choice = choice
        self.counters["tracker_adoptions"] += 1

    def _force(self, rows: np.ndarray) -> np.ndarray | None:
        """``force``, ``force_var``, ``force_next`` (N) of the rows: F = −f/b, var F = var f / b²,
        F_next = −f_next/b with b = β1 (force-input) or β1/K (velocity loop with known K), the β1 the
        row's disturbance goes with (β̂ per row in apply mode); None when the model cannot scale."""
        if self._force_div is None:
            return None
        div = self._force_div if self.mode != "apply" else \
            self._force_sign * (rows[online.R_BETA1] * self._beta1_to_b) ** self._force_power
        return rows[online.R_F:online.R_FNEXT + 1] / div

    def take_health(self) -> list[Health]:
        """The health reports produced since the last call (oldest first), and forget them."""
        out, self._health_out = self._health_out, []
        return out

    def _health(self, machine: str, axis: str, row: np.ndarray) -> Health:
        """A :class:`Health` message from one report row of the compiled loop (:data:`kernels.online.TICK`)."""
        k = online
        level = row[k.K_LEVEL:k.K_LEVEL + hl.N_REASON].astype(np.int64)
        n_par = len(hl.PARAMS)
        reasons = describe(level, row[k.K_Z:k.K_Z + n_par], row[k.K_REL:k.K_REL + n_par], float(row[k.K_NU2]),
                           float(row[k.K_EWMAX]))
        if self.mode != "off":  # estimated, but the data do not determine it: flagged, not tested for drift
            weak = [f"{name} (s.e. {row[k.K_SE + i]:.3g})" for d, (i, name) in enumerate(zip(hl.PHYS_INDEX, hl.PARAMS))
                    if d != hl.STEP and math.isfinite(row[k.K_THETA + i]) and row[k.K_DET + d] == 0.0]
            if weak:
                reasons.append("not determined by the data, not tested for drift: " + ", ".join(weak))
        reasons += self.notes
        if self._pending_reasons:
            reasons = self._pending_reasons + reasons
            self._pending_reasons = []
        vals: dict[str, float | None] = {}
        absolute = self.mode != "off" and (self.model.form == "force-input" or self.model.loop_gain is not None)
        for i, name in enumerate(PHYSICAL_PARAMS):
            x, se = float(row[k.K_THETA + i]), float(row[k.K_SE + i])
            ok = absolute and math.isfinite(x) and math.isfinite(se)
            vals[name] = x if ok else None
            vals[f"{name}_se"] = se if ok else None
        nu2 = float(row[k.K_NU2])
        reasons = [r[:REASON_CHARS_MAX] for r in reasons[:REASONS_MAX]]  # the schema's bounds
        return Health(machine=machine, axis=axis, seq=int(row[k.K_SEQ]), t=float(row[k.K_T]),
                      state=("ok", "warn", "alarm")[int(row[k.K_STATE])], reasons=reasons,
                      nu2=nu2 if math.isfinite(nu2) else None, adaptation=self.mode, **vals)

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, np.ndarray]:
        """Tracker state, online β (β̂, its covariance, the shadow means), the health state, the
        disturbance model the search chose and the counters needed to resume (plain arrays, no pickle)."""
        snap = {f"tracker.{k}": v for k, v in self.tracker.snapshot().items()}
        snap.update(self.online.snapshot())
        snap.update(self.health.snapshot())
        snap[_TRAINED] = np.array(self.trained, dtype=np.int64)
        if self.searching:
            snap[_CHOICE] = choice_array(self.beta_choice)
        return snap

    def snapshot_templates(self, choice: ds.TrackerChoice | None = None) -> tuple[dict, dict]:
        """What a valid snapshot of this model looks like with the disturbance model ``choice`` (default:
        the current one): the snapshots of a fresh tracker before any sample and after one step, the
        latter with the online β and health entries (keys, shapes, dtypes and the hyperparameter values;
        they follow the core's layout, whatever it is). Made once per choice; treat them as read only."""
        choice = choice or self.beta_choice
        if self._templates is None or self._templates[0] != choice:
            tracker = self._new_tracker(choice)
            xdim = 2 if (choice.spindle if choice else self.spindle is not None) else 1
            before = {f"tracker.{k}": v for k, v in tracker.snapshot().items()}
            fresh = self._new_online(self._new_tracker(choice))
            tracker.learn_one(np.zeros(xdim), 0.0)
            after = {f"tracker.{k}": v for k, v in tracker.snapshot().items()}
            after.update(fresh.snapshot())
            after.update(self._new_health().snapshot())
            before[_TRAINED] = after[_TRAINED] = np.array(0, dtype=np.int64)
            if self.searching:
                before[_CHOICE] = after[_CHOICE] = choice_array(choice)
            self._templates = (choice, (before, after))
        return self._templates[1]

    def restore(self, snap: dict[str, np.ndarray]) -> None:
        """Continue from :meth:`snapshot` (the regressor chain restarts at the next sample).

        The snapshot is checked first (:func:`monitor.state_check.check_snapshot`: keys, shapes,
        dtypes, finiteness, the hyperparameters — the model file's, or the disturbance model the
        search had chosen, within the ranges a model file allows —, the tracker's invariants; then the
        online β and health parts, :func:`kernels.beta_tracker.validate_beta_state`,
        :func:`kernels.health.validate_health_state`); a snapshot that fails raises
        :class:`StateError` naming the reason and leaves this estimator as it was.
        """
        choice = self.beta_choice
        if self.searching:
            if _CHOICE not in snap:
                raise StateError(f"its entries do not match this model's tracker; missing {_CHOICE}")
            choice = choice_of_array(snap[_CHOICE])
        before, after = self.snapshot_templates(choice)
        check_snapshot(snap, before, after, counters=(_TRAINED,))
        tracker_part = {k[len("tracker."):]: v for k, v in snap.items() if k.startswith("tracker.")}
        try:
            restored = KRLST.restore(tracker_part)
        except ValueError as exc:
            raise StateError(str(exc)) from None
        online_part = {k: v for k, v in snap.items() if k.startswith("beta.")}
        health_part = {k: v for k, v in snap.items() if k.startswith("health.")}
        ob, hm = self._new_online(self._new_tracker(choice)), self._new_health()
        if online_part or health_part:  # a snapshot made after a step holds both
            try:
                ob.restore(online_part, restored)
                hm.restore(health_part)
            except ValueError as exc:
                raise StateError(str(exc)) from None
        else:
            ob = self._new_online(restored)
        self.tracker = restored
        self.online = ob
        self.health = hm
        self._state = online.new_state(trained=int(snap[_TRAINED]))
        if self.searching:
            self._drop_search()
            self.choice = self.beta_choice = self.search.choice = choice
            self._set_dual(None)
            online.set_tracker_input(self._cfg, choice.spindle, 2.0 * math.pi / choice.teeth)
            self._xdim = 2 if choice.spindle else 1
            self._xbuf = np.zeros(self._xdim)


def _beta_cov(model: AxisModel) -> np.ndarray | None:
    """The model file's covariance (p×p) or standard errors (p,) of β when it has them (identification
    writes them; older files do not), else None."""
    for name in ("beta_cov", "beta_se", "beta_stderr"):
        value = getattr(model, name, None)
        if value is not None:
            arr = np.asarray(value, dtype=np.float64)
            p = len(model.beta)
            if arr.shape in ((p,), (p, p)) and np.all(np.isfinite(arr)):
                return arr
    return None
