"""The disturbance search beside the per-sample path: started on a copy of the ring, applied a fixed
number of samples later.

A search (:meth:`kernels.disturbance_search.DisturbanceSearch.tick`) weighs candidate trackers by
replaying the recent residual: tens to hundreds of milliseconds. Run in line, it held every sample
that arrived meanwhile (at 333 Hz a 200 ms search delayed 67 estimates and any alarm among them).
Here it runs on a worker thread while the estimator goes on, and its verdict takes effect at the
learned sample ``lag`` samples after the one it was started at — in the live monitor and in
``feedmon run --from`` alike, so both still give the same rows whatever the machine's speed. If the
search has not finished by then, the estimator waits for it (never worse than in line).

One worker per process serves every axis (the searches are CPU work on the same cores); it is made
again in a forked child, whose copy of the parent's thread does not run.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from kernels import online
from kernels.krlst import KRLST

__all__ = ["PendingSearch", "caught_up", "submit", "went_on"]

_lock = threading.Lock()
_pool: tuple[int, ThreadPoolExecutor] | None = None


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None or _pool[0] != os.getpid():
            _pool = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="feedmon-search"))
        return _pool[1]


class PendingSearch:
    """A search under way: started at learned-sample count ``count`` on the ring entries ``ring``
    (a copy), due at ``due`` (the count at which its verdict applies)."""

    __slots__ = ("future", "ring", "count", "due")

    def __init__(self, future: Future, ring: np.ndarray, count: int, due: int) -> None:
        self.future, self.ring, self.count, self.due = future, ring, count, due

    def wait(self):
        """What the search returned (or the exception it raised), waiting for it if need be."""
        return self.future.result()


def submit(fn, ring: np.ndarray, count: int, lag: int) -> PendingSearch:
    """Start ``fn()`` on the worker; its verdict is due ``lag`` learned samples after ``count``."""
    return PendingSearch(_executor().submit(fn), ring, count, count + max(1, int(lag)))


def went_on(old: np.ndarray, R: np.ndarray, since: int) -> bool:
    """The ring ``R`` is the ring ``old`` a search saw, gone on by ``since`` learned entries (not cleared
    by a restart meanwhile): its entry ``since`` before the newest is ``old``'s newest."""
    return bool(old.shape[0]) and 0 <= since < R.shape[0] and R[-since - 1, online.G_T] == old[-1, online.G_T]


def caught_up(tracker: KRLST | None, spindle: bool, old: np.ndarray, R: np.ndarray, since: int) -> KRLST | None:
    """The search's ``tracker`` — armed at the newest entry of the ring ``old`` it saw, that entry not
    learned — fed the ``since`` entries learned after it (ring ``R`` now, :data:`kernels.online.RING`
    columns), so that it is armed at ``R``'s newest entry; None (start a fresh one) when ``R`` is not
    ``old`` gone on (a restart cleared the ring)."""
    if tracker is None or not old.shape[0] or since <= 0:
        return tracker
    if not went_on(old, R, since):
        return None
    new = R[-since:]
    X = np.column_stack((new[:, online.G_T], np.nan_to_num(new[:, online.G_THETA])))
    ys = np.concatenate(([old[-1, online.G_RESID]], new[:-1, online.G_RESID]))
    tracker.track_many(X if spindle else X[:, 0], ys, np.ones(since, dtype=bool))
    return tracker
