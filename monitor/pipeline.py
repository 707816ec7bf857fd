"""Decode → check the key → route → estimate: the per-message work shared by the live monitor
(:mod:`monitor.daemon`) and the offline runner (:mod:`monitor.offline`), so a trial estimated
offline gives the same numbers, sample for sample, as the same trial replayed live.

Every refusal is counted (status counter in brackets) and logged once per burst:

* :meth:`Pipeline.receive` (live only): the payload is not a valid :class:`~feedio.schema.SampleBlock`
  [``malformed``]; the payload names another axis than the key it came on
  (``<prefix>/<machine>/<axis>/samples``) [``key_mismatch``]: a block is routed by its key and
  the payload must agree, so a peer allowed to publish on one axis' key cannot feed another axis.
* :meth:`Pipeline.estimate` (live and offline): no model for the axis [``no_model``, a bounded
  table of names, ``no_model_overflow`` beyond it]; more samples than ``max_block_samples``
  [``too_large``]; the estimator's own per-sample reasons (rejected, duplicate, gap, ...).

Counts land on the axis the key (or the block) names when it has a model, else in the
monitor-wide counters.

What :meth:`Pipeline.estimate` returns (:class:`Estimated`) is what the live daemon publishes
and both paths log: the axis, its estimate rows of the block (:class:`~monitor.estimate_rows.EstimateRows`,
columns; the schema object and its JSON are made once, by whoever needs them first) and
``health``: the :class:`~feedio.schema.Health` reports the block produced (about one per second
of data per axis), which the daemon publishes on
``<prefix>/<machine>/<axis>/health`` and hands to the sinks (``offer_health``), and the offline
runner writes on ``/<machine>/<axis>/health`` — produced here, next to the estimator whose state
they describe, so that live and offline give the same messages. The health of the input stream
itself (:mod:`monitor.input_health`: a frozen measurement, another rate, nothing learned) is judged
here from the estimator's per-block counts and merged into those reports (the worse state, its
reasons first); when it changes between two of the estimator's reports, or stays not ok while the
estimator makes none, the pipeline makes a report of its own.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import NamedTuple

import msgspec
import numpy as np

from feedio import schema as S
from feedio.limits import DEFAULT, NAME_RE, InputLimits
from kernels.online import COUNTERS

from .axes import AxisRuntime
from .estimate_rows import EstimateRows
from .input_health import LEVELS, REPORT_PERIOD, InputHealth, InputHealthSettings
from .status import BoundedCounter, BurstLog

__all__ = ["Pipeline", "Estimated"]

log = logging.getLogger("monitor.pipeline")

#: estimator counters that mean bad input; :meth:`Pipeline.estimate` logs them once per burst
_LOGGED_REASONS = (
    ("rejected_non_finite", "rejected: non-finite value"),
    ("rejected_out_of_range", "rejected: absurd magnitude"),
    ("duplicate", "dropped: duplicate sequence number"),
    ("out_of_order", "dropped: out-of-order sequence number"),
    ("gaps", "after a sequence gap: chain restarted"),
    ("time_backwards", "with time going backwards: chain restarted"),
    ("seq_resets", "with sequence numbers restarted (new bridge session, or seq jumped inconsistently with time): "
                   "chain restarted"),
    ("rejected_seq_range", "refused: sequence numbers beyond int64"),
    ("interval_mismatch", "at another interval than the model's Ts (more than 25 % off the previous sample): β is of "
                          "one sampling time — a stream at another rate needs a model identified at that rate"),
    ("spindle_fallback", "without usable spindle data (spindle_angle / spindle_rpm): the spindle-phase kernel runs on "
                         "the model's nominal speed, i.e. the time kernel with a fixed period"),
)


class Estimated(NamedTuple):
    """Result of :meth:`Pipeline.estimate` (see the module docstring)."""

    ax: AxisRuntime | None  #: the axis the block was routed to (None: refused, no model or too long)
    est: EstimateRows | None = None  #: its estimate rows (None: no row, every sample dropped)
    health: list[S.Health] | tuple = ()  #: the health reports the block produced (oldest first)
    #: the process alarms the block's rows raised (:mod:`monitor.process_monitor`; oldest first)
    alarms: list[S.AlarmEvent] | tuple = ()


_REFUSED = Estimated(None)
_NO_HEALTH = ()


class Pipeline:
    """Decode → check the key → route → estimate. No I/O; one thread only."""

    def __init__(self, axes: dict[tuple[str, str], AxisRuntime], *, prefix: str = "feedmon",
                 limits: InputLimits = DEFAULT, input_health: InputHealthSettings | None = None,
                 monitors=None) -> None:
        self.axes = axes
        #: the process monitors (:class:`monitor.process_monitor.ProcessMonitors`; None: none run)
        self.process = monitors
        #: the health of each axis' input stream (:mod:`monitor.input_health`), merged into its reports
        self.input_health = {key: InputHealth(float(ax.model.Ts), input_health) for key, ax in axes.items()}
        self._model_report: dict[tuple[str, str], S.Health] = {}  # each axis' last report of the loop
        self._unreported: dict[tuple[str, str], int] = {}  # samples of each axis since its last report
        self.prefix = prefix
        self.limits = limits
        self.counters: Counter[str] = Counter()  # monitor-wide: malformed / key_mismatch / too_large of no axis
        self.no_model = BoundedCounter(limits.max_unknown_axes)  # "machine/axis" -> samples dropped
        self.key_mismatch = BoundedCounter(limits.max_unknown_axes)  # key's "machine/axis" -> messages refused
        self.burst = BurstLog(log)
        self._key_prefix = f"{prefix}/"
        self._axis_by_key = {f"{prefix}/{m}/{a}/{kind}": ax for (m, a), ax in axes.items()
                             for kind in ("samples", "truth")}
        # positions of the logged reasons in the estimator's per-block counts (all of them are counted there)
        self._logged_idx = np.array([COUNTERS.index(k) for k, _ in _LOGGED_REASONS])

    def axis_of_key(self, key: str) -> AxisRuntime | None:
        """The modelled axis a ``<prefix>/<machine>/<axis>/samples|truth`` key names (None: no model)."""
        return self._axis_by_key.get(key)

    def key_name(self, key: str) -> str | None:
        """``"machine/axis"`` of a ``<prefix>/<machine>/<axis>/<kind>`` key when both are valid names."""
        if not key.startswith(self._key_prefix):
            return None
        parts = key[len(self._key_prefix):].split("/")
        if len(parts) != 3 or not (NAME_RE.fullmatch(parts[0]) and NAME_RE.fullmatch(parts[1])):
            return None
        return f"{parts[0]}/{parts[1]}"

    def count(self, reason: str, ax: AxisRuntime | None, n: int = 1) -> None:
        """Count a refusal on ``ax`` (its ``drops``) or monitor-wide when no modelled axis is concerned."""
        (ax.status.counters if ax is not None else self.counters)[reason] += n

    def receive(self, key: str, payload: bytes) -> S.SampleBlock | None:
        """Decode a message received on ``key``; None when refused (counted and logged)."""
        ax_key = self._axis_by_key.get(key)
        try:
            block = S.decode_samples(payload, what="sample block")
        except S.SchemaError as exc:
            self.count("malformed", ax_key)
            self.burst(f"malformed:{ax_key.status.name if ax_key else ''}", "dropping malformed message on %s: %s",
                       key, str(exc))
            return None
        ax = self.axes.get((block.machine, block.axis))
        if ax is not ax_key or (ax is None and key != f"{self._key_prefix}{block.machine}/{block.axis}/samples"):
            self.count("key_mismatch", ax_key)
            name = self.key_name(key) or "(invalid key)"
            listed = self.key_mismatch.add(name)
            self.burst(f"key_mismatch:{name if listed else ''}",
                       "refusing a block for %s/%s received on key %s: the payload must name the axis of its key",
                       block.machine, block.axis, key)
            return None
        return block

    def estimate(self, block: S.SampleBlock) -> Estimated:
        """Route ``block`` to its axis' estimator. ``ax`` None: refused (no model for the axis, or
        longer than ``max_block_samples``); ``est`` None: no estimate row (every sample dropped, or
        the estimator could not use the block)."""
        ax = self.axes.get((block.machine, block.axis))
        n = len(block.t)
        if ax is None:
            name = f"{block.machine}/{block.axis}"
            self.counters["no_model_blocks"] += 1
            listed = self.no_model.add(name, n)
            self.burst(f"no_model:{name if listed else ''}",
                       "no model for axis %s: dropping its samples (have models for %s)%s", name,
                       ", ".join(f"{m}/{a}" for m, a in self.axes) or "none",
                       "" if listed else f"; more than {self.no_model.limit} such axes: counted in no_model_overflow")
            return _REFUSED
        st = ax.status
        st.blocks += 1
        if n > self.limits.max_block_samples:
            st.counters["too_large"] += 1
            self.burst(f"too_large:{st.name}", "axis %s: refusing a block of %d samples (max_block_samples = %d)",
                       st.name, n, self.limits.max_block_samples)
            return _REFUSED
        ih = self.input_health[ax.key]
        try:
            est = ax.estimator.process_rows(block)
        except ValueError as exc:  # e.g. the model's form needs a column the block lacks
            self.burst(f"error:{st.name}", "axis %s: block dropped: %s", st.name, str(exc))
            return Estimated(ax, None, self._health(ax, block, ih.block(None, n)))
        except Exception as exc:  # noqa: BLE001 - never fatal; counted and logged
            st.counters["estimator_error"] += n
            self.burst(f"error:{st.name}", "axis %s: estimator failed on a block: %s: %s", st.name,
                       type(exc).__name__, str(exc), level=logging.ERROR)
            return Estimated(ax, None, self._health(ax, block, ih.block(None, n)))
        changed = ih.block(ax.estimator.block_counts, n, block.seq, block.t)
        # the estimator only counts; say it once per burst (per reason and axis)
        bc = ax.estimator.block_counts[self._logged_idx]
        if bc.any():
            for (k, what), d in zip(_LOGGED_REASONS, bc.tolist()):
                if d:
                    self.burst(f"{k}:{st.name}", "axis %s: %d sample(s) %s (status counter %r)", st.name, d, what, k)
        if est is not None:
            st.last_seq = est.seq + len(est) - 1
            st.last_t = float(est.t[-1])
        health = self._health(ax, block, changed)
        if self.process is not None and est is not None:
            alarms = self._alarms(ax, est, block)
            if alarms:
                return Estimated(ax, est, health, alarms)
        return Estimated(ax, est, health)

    def _alarms(self, ax: AxisRuntime, est: EstimateRows, block: S.SampleBlock) -> list[S.AlarmEvent]:
        """The process monitors on the block's rows (an error there is counted and logged, never fatal)."""
        try:
            alarms = self.process.update(ax.key, est, block)
        except Exception as exc:  # noqa: BLE001 - a monitor's failure must not stop the estimates
            ax.status.counters["process_monitor_error"] += 1
            self.burst(f"process:{ax.status.name}", "axis %s: process monitor failed on a block: %s: %s",
                       ax.status.name, type(exc).__name__, str(exc), level=logging.ERROR)
            return []
        for a in alarms:
            log.warning("axis %s: process alarm %s at t = %.4f s (seq %d): %.1f against limit %.1f N (%s)",
                        ax.status.name, a.kind, a.t, a.seq, a.value, a.limit, a.monitor)
        return alarms

    def finish(self, part: str, when: str) -> dict[tuple[str, str], list[S.AlarmEvent]]:
        """End of a run: the wear monitor's alarms per axis (:meth:`~monitor.process_monitor.ProcessMonitors.finish`;
        empty without one), logged like the others."""
        if self.process is None or self.process.wear is None:
            return {}
        out = self.process.finish(part, when)
        for key, alarms in out.items():
            for a in alarms:
                log.warning("axis %s/%s: process alarm %s at the end of the run: %s", key[0], key[1], a.kind, a.detail)
        return out

    def _health(self, ax: AxisRuntime, block: S.SampleBlock, input_changed: bool) -> list[S.Health] | tuple:
        """Collect the axis' health reports (returned) with the input's verdict merged in (a report of its
        own when it changed and the loop made none), update its status and log every change of the health
        state once (WARNING into warn/alarm, INFO back to ok)."""
        reports = ax.estimator.take_health()
        ih = self.input_health[ax.key]
        quiet = self._unreported[ax.key] = self._unreported.get(ax.key, 0) + len(block.t)
        if reports:
            self._model_report[ax.key] = reports[-1]
            if ih.level or ih.reasons:
                reports = [_merged(h, ih) for h in reports]
        elif input_changed or (ih.level and quiet * ih.Ts >= REPORT_PERIOD):
            own = self._own_report(ax, block, ih)  # (the loop makes none while every sample is refused)
            reports = [own] if own is not None else []
        if reports:
            self._unreported[ax.key] = 0
        if not reports:
            return _NO_HEALTH
        st = ax.status
        for h in reports:
            was = st.note_health(h)
            if was is not None:
                why = "; ".join(h.reasons) or "no reason given"
                log.log(logging.INFO if h.state == "ok" else logging.WARNING,
                        "axis %s: health %s → %s at t = %.3f s (seq %d): %s", st.name, was, h.state, h.t, h.seq, why)
        return reports

    def _own_report(self, ax: AxisRuntime, block: S.SampleBlock, ih: InputHealth) -> S.Health | None:
        """A report at the block's last sample when the input's verdict changed between two of the loop's, or
        is not ok and the loop made none for a health period: the loop's last one (or an empty one) with the
        verdict merged in."""
        n = len(block.t)
        seq, t = block.seq + n - 1, block.t[-1] if n else None
        if t is None or not (0.0 <= t <= S.T_MAX) or not 0 <= seq <= S.SEQ_MAX:
            return None
        last = self._model_report.get(ax.key)
        if last is None:
            last = S.Health(machine=ax.model.machine, axis=ax.model.axis, seq=seq, t=float(t), state="ok",
                            adaptation=getattr(ax.estimator, "mode", "track"))
        return _merged(msgspec.structs.replace(last, seq=seq, t=float(t)), ih)


def _merged(h: S.Health, ih: InputHealth) -> S.Health:
    """``h`` with the input's verdict: the worse state, the input's reasons first (the schema's bounds kept)."""
    state = LEVELS[max(LEVELS.index(h.state), ih.level)]
    reasons = [r[:S.REASON_CHARS_MAX] for r in [*ih.reasons, *h.reasons][:S.REASONS_MAX]]
    return msgspec.structs.replace(h, state=state, reasons=reasons)
