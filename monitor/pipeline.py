"""Decode → route → estimate: the per-message work shared by the live monitor
(:mod:`monitor.daemon`) and the offline runner (:mod:`monitor.offline`), so a trial estimated
offline gives the same numbers, sample for sample, as the same trial replayed live."""

from __future__ import annotations

import logging
from collections import Counter

from feedio import schema as S

from .axes import AxisRuntime
from .status import BurstLog

__all__ = ["Pipeline"]

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
)


class Pipeline:
    """Decode → route → estimate. No I/O; one thread only."""

    def __init__(self, axes: dict[tuple[str, str], AxisRuntime], *, prefix: str = "feedmon") -> None:
        self.axes = axes
        self.prefix = prefix
        self.counters: Counter[str] = Counter()  # global: malformed (axis unknown), ...
        self.no_model: Counter[str] = Counter()  # "machine/axis" -> samples dropped
        self.burst = BurstLog(log)

    def axis_of_key(self, key: str) -> AxisRuntime | None:
        parts = key.split("/")
        if len(parts) >= 3:
            return self.axes.get((parts[-3], parts[-2]))
        return None

    def decode(self, key: str, payload: bytes) -> S.SampleBlock | None:
        try:
            return S.decode_samples(payload, what=f"sample block on {key}")
        except S.SchemaError as exc:
            ax = self.axis_of_key(key)
            (ax.status.counters if ax is not None else self.counters)["malformed"] += 1
            self.burst(f"malformed:{key}", "dropping malformed message: %s", exc)
            return None

    def estimate(self, block: S.SampleBlock) -> tuple[AxisRuntime | None, S.EstimateBlock | None]:
        """Route ``block`` to its axis' estimator; ``(None, None)`` when no model covers it."""
        ax = self.axes.get((block.machine, block.axis))
        if ax is None:
            name = f"{block.machine}/{block.axis}"
            self.no_model[name] += len(block.t)
            self.burst(f"no_model:{name}", "no model for axis %s: dropping its samples (have models for %s)",
                       name, ", ".join(f"{m}/{a}" for m, a in self.axes) or "none")
            return None, None
        st = ax.status
        st.blocks += 1
        c = ax.estimator.counters
        before = [c.get(k, 0) for k, _ in _LOGGED_REASONS]
        try:
            est = ax.estimator.process(block)
        except ValueError as exc:  # e.g. the model's form needs a column the block lacks
            self.burst(f"error:{st.name}", "axis %s: block dropped: %s", st.name, exc)
            return ax, None
        except Exception as exc:  # noqa: BLE001 - never fatal; counted and logged
            st.counters["estimator_error"] += len(block.t)
            self.burst(f"error:{st.name}", "axis %s: estimator failed on a block: %s: %s", st.name,
                       type(exc).__name__, exc, level=logging.ERROR)
            return ax, None
        for (k, what), b in zip(_LOGGED_REASONS, before):
            d = c.get(k, 0) - b
            if d:  # the estimator only counts; say it once per burst (per reason and axis)
                self.burst(f"{k}:{st.name}", "axis %s: %d sample(s) %s (status counter %r)", st.name, d, what, k)
        if est is not None:
            st.last_seq = est.seq + len(est.t) - 1
            st.last_t = est.t[-1]
        return ax, est

