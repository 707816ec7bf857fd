"""The process monitors on the Rerun dashboard: their limits and alarms on the force panel, the per-tooth panel.

The monitor process makes a :class:`~feedio.schema.ProcessView` of an axis at most every
:data:`~monitor.process_monitor.monitor.VIEW_INTERVAL_S` s of data (only when a Rerun sink runs): what the
collision test passes at that row, the overload limit, the reference envelope, and the last revolution when
one ended. Here (in the recording process) they become, below ``/<machine>/<axis>``
(:mod:`monitor.sinks.rerun_layout` has the styles and views):

* ``force/limit/collision_low|high``: the force range the collision test passes (M1), ``force/limit/
  overload_low|high`` ±the overload limit (M2), ``force/limit/band_low|high`` the reference envelope (M6),
  each at the row of its view (a step every view);
* ``force/marker/<kind>``: a point per process alarm at the alarm's row (sample, time), on the filtered force
  estimate there, named by its kind in the legend (the path sorts after ``force/estimate``: drawn over it);
* ``tooth/profile``: BarChart of the mean measured force per spindle-angle bin over the last
  :data:`~feedio.schema.TOOTH_VIEW_REVOLUTIONS` revolutions (abscissa: the bin's centre in degrees; a bin no
  sample fell in has no bar: at 333 Hz and exactly 3000 rpm the samples fall on 20 angles), ``tooth/peaks``
  their mean peak force per tooth (abscissa: tooth 1 … N), at the last revolution's last row; ``tooth/a0``,
  ``tooth/a1`` that revolution's mean force and once-per-revolution amplitude, ``tooth/a1_broken|a1_runout``
  the values of A1 the tooth monitor calls a broken tooth / runout (M4, M5).
"""

from __future__ import annotations

import math

import numpy as np

from feedio import schema as S

from . import rerun_layout as L

__all__ = ["send_views", "send_alarms", "LIMIT_FIELDS"]

#: the ProcessView fields drawn as they are, each on the entity of its name below ``force/limit``
LIMIT_FIELDS = ("collision_low", "collision_high", "band_low", "band_high")


def _col(values) -> np.ndarray:
    return np.array([math.nan if v is None else v for v in values], dtype=np.float64)


def _send(rec, path: str, seq: np.ndarray, t: np.ndarray, v: np.ndarray) -> None:
    import rerun as rr

    keep = np.isfinite(v)
    if not keep.any():
        return
    rec.send_columns(path, indexes=[rr.TimeColumn(L.SEQUENCE, sequence=seq[keep]),
                                    rr.TimeColumn(L.TIMELINE, duration=t[keep])],
                     columns=rr.Scalars.columns(scalars=v[keep]), strict=True)


def send_views(rec, root: str, views: list[S.ProcessView]) -> None:
    """The limits of ``views`` (oldest first) as series, their revolutions as the per-tooth panel."""
    import rerun as rr

    seq = np.fromiter((v.seq for v in views), dtype=np.int64, count=len(views))
    t = np.fromiter((v.t for v in views), dtype=np.float64, count=len(views))
    for name in LIMIT_FIELDS:
        _send(rec, f"{root}/force/limit/{name}", seq, t, _col(getattr(v, name) for v in views))
    over = _col(v.overload for v in views)
    _send(rec, f"{root}/force/limit/overload_high", seq, t, over)
    _send(rec, f"{root}/force/limit/overload_low", seq, t, -over)
    teeth = [v.tooth for v in views if v.tooth is not None]
    if not teeth:
        return
    rs = np.array([r.seq for r in teeth], dtype=np.int64)
    rt = np.array([r.t for r in teeth], dtype=np.float64)
    for name in ("a0", "a1", "a1_broken", "a1_runout"):
        _send(rec, f"{root}/tooth/{name}", rs, rt, _col(getattr(r, name) for r in teeth))
    for r in teeth:
        rec.set_time(L.SEQUENCE, sequence=r.seq)
        rec.set_time(L.TIMELINE, duration=r.t)
        prof, peaks = _col(r.profile), np.nan_to_num(_col(r.peaks))
        bins, seen = prof.size, np.isfinite(prof)  # a bin no sample fell in has no bar (not a bar at 0 N)
        centres = (np.arange(bins) + 0.5) * 360.0 / bins
        rec.log(f"{root}/tooth/profile", rr.BarChart(prof[seen], abscissa=centres[seen],
                                                     widths=np.full(seen.sum(), 0.8 * 360.0 / bins, dtype=np.float32),
                                                     color=L.TOOTH_COLOUR), strict=True)
        rec.log(f"{root}/tooth/peaks", rr.BarChart(peaks, abscissa=np.arange(1, peaks.size + 1, dtype=np.float64),
                                                   widths=np.full(peaks.size, 0.6, dtype=np.float32),
                                                   color=L.TOOTH_COLOUR), strict=True)


def send_alarms(rec, root: str, alarms: list[S.AlarmEvent], styled: set[str], force_at) -> None:
    """One point per alarm at its row on ``force/marker/<kind>``, at the filtered estimate ``force_at(seq)``
    (N; NaN: unknown, the point at 0 N); the style of a kind is logged with its first alarm."""
    import rerun as rr

    for kind in sorted({a.kind for a in alarms}):
        path = f"{root}/force/marker/{kind}"
        if kind not in styled:
            st = L.alarm_style(kind)
            rec.log(path, rr.SeriesPoints(names=st.label, colors=st.colour, markers="Cross",
                                          marker_sizes=L.ALARM_MARKER_SIZE), static=True, strict=True)
            styled.add(kind)
        mine = sorted((a for a in alarms if a.kind == kind), key=lambda a: a.seq)
        y = np.array([force_at(a.seq) for a in mine], dtype=np.float64)
        rec.send_columns(path, indexes=[rr.TimeColumn(L.SEQUENCE, sequence=[a.seq for a in mine]),
                                        rr.TimeColumn(L.TIMELINE, duration=[a.t for a in mine])],
                         columns=rr.Scalars.columns(scalars=np.where(np.isfinite(y), y, 0.0)), strict=True)
