"""Progress of an identification: likelihood evaluations done and planned, for a bar with an ETA."""

from __future__ import annotations

import threading

from .candidates import POLISH_EVALUATIONS, REFINE_EVALUATIONS, TUNE_EVALUATIONS


class WorkPlan:
    """Counts the REML evaluations of the tuning (the identification's work; the rest is a few percent)
    and calls ``report(label, done, total)`` after each — from any tuning thread. ``total`` grows as the
    stages are planned (:meth:`plan`), and never falls below ``done``."""

    def __init__(self, report) -> None:
        self._report = report
        self._lock = threading.Lock()
        self.done = 0
        self.total = 0

    def plan(self, evaluations: int) -> None:
        with self._lock:
            self.total += int(evaluations)

    def __call__(self, label: str, *_tune_state) -> None:
        """The tuning's progress callback (:func:`kernels.likelihood.tune` passes its state, unused here)."""
        with self._lock:
            self.done += 1
            self.total = max(self.total, self.done)
            done, total = self.done, self.total
        self._report(label, done, total)

    def finish(self, label: str = "done") -> None:
        with self._lock:
            self.total = self.done = max(self.done, 1)
        self._report(label, self.done, self.total)


def planned_evaluations(periods: int, *, alternative: bool, spindle: int, tune: bool) -> int:
    """A tuning's planned REML evaluations: the squared exponential, a locally periodic and a zero-mean one
    per period, the period found in the data beside a given one, the spindle-phase candidates (each
    with its polish)."""
    if not tune:
        return 0
    full, refine = TUNE_EVALUATIONS + POLISH_EVALUATIONS, REFINE_EVALUATIONS + POLISH_EVALUATIONS
    return full + periods * (full + refine) + (full if alternative else 0) + spindle * refine
