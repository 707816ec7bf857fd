"""Wear trend across parts (M7): a bounded history file of per-section statistics and the ``wear`` alarm.

A worn tool needs more force for the same chip, so a section's mean force (or its cut energy) creeps up
from part to part, far slower than anything inside one run shows. At the end of each run
(:meth:`WearMonitor.add_run`) every cutting section's statistic is appended to its history; over the last
``window`` parts :func:`kernels.force_monitors.wear_trend` fits a line, and the section raises ``wear``
when the slope's t statistic exceeds ``sensitivity`` *and* the fitted rise exceeds ``min_rise`` of the
fitted first value: the t test bounds the false alarms whatever the part-to-part spread
(``docs/process-monitoring.md``, "Wear"), the rise keeps a significant but harmless drift quiet.

The file (:class:`WearHistory`, JSON, ``format_version = 1``) is at most :data:`MAX_HISTORY_BYTES`, holds
at most :data:`MAX_HISTORY_SECTIONS` sections and ``keep`` (≤ :data:`~.settings.MAX_KEEP`) parts per
section, and is replaced atomically (temporary file, fsync, rename). A file that cannot be used is refused
naming the file and the fix, and left as it was.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated, Literal, NamedTuple

import msgspec
import numpy as np

from feedio import schema as S
from feedio.limits import read_capped
from kernels.force_monitors import wear_trend

from .reference import section_key
from .settings import MAX_KEEP, WearSettings

__all__ = ["WearHistory", "WearSection", "WearPart", "WearVerdict", "WearMonitor", "judge", "load_history",
           "save_history", "MAX_HISTORY_BYTES", "MAX_HISTORY_SECTIONS"]

#: a larger history file is refused before it is parsed (and never written)
MAX_HISTORY_BYTES = 64 << 20
#: the most sections one history file holds, over all its axes; a run's new sections beyond are not recorded
MAX_HISTORY_SECTIONS = 1000
#: a part's label is cut to its last this many characters
PART_CHARS_MAX = 64
_Int = Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)]
_FIX = "move it away (or name another file) to start a new history; the file is left as it was"


class WearPart(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One part's statistics of one section: ``part`` (the run's label), ``time`` (UTC, when recorded)."""

    part: Annotated[str, msgspec.Meta(max_length=PART_CHARS_MAX)]
    time: Annotated[str, msgspec.Meta(max_length=40)]
    mean_force_N: Annotated[float, msgspec.Meta(ge=-1e7, le=1e7)]
    energy_J: Annotated[float, msgspec.Meta(ge=-1e12, le=1e12)]
    rows: Annotated[int, msgspec.Meta(ge=1, le=2**53)]


class WearSection(msgspec.Struct, forbid_unknown_fields=True):
    """A section (:func:`~.reference.section_key`) and its last parts, oldest first."""

    key: Annotated[str, msgspec.Meta(max_length=64)]
    tool: _Int | None
    program_line: _Int | None
    occurrence: Annotated[int, msgspec.Meta(ge=0, le=2**31)]
    parts: Annotated[list[WearPart], msgspec.Meta(max_length=MAX_KEEP)] = []


class WearAxis(msgspec.Struct, forbid_unknown_fields=True):
    machine: S.Name
    axis: S.Name
    sections: Annotated[list[WearSection], msgspec.Meta(max_length=MAX_HISTORY_SECTIONS)] = []


class WearHistory(msgspec.Struct, forbid_unknown_fields=True):
    format_version: Literal[1] = 1
    axes: Annotated[list[WearAxis], msgspec.Meta(max_length=MAX_HISTORY_SECTIONS)] = []

    def __post_init__(self) -> None:
        n = sum(len(a.sections) for a in self.axes)
        if n > MAX_HISTORY_SECTIONS:
            raise ValueError(f"{n} sections, more than {MAX_HISTORY_SECTIONS}")

    def axis(self, machine: str, axis: str) -> WearAxis:
        for a in self.axes:
            if (a.machine, a.axis) == (machine, axis):
                return a
        a = WearAxis(machine=machine, axis=axis)
        self.axes.append(a)
        return a


def load_history(path: str | os.PathLike) -> WearHistory:
    """The history in ``path`` (empty when the file does not exist yet); ``ValueError`` naming the file, what
    is wrong and the fix for a file that is too large, not JSON, of another version or out of its bounds."""
    path = Path(path)
    if not path.exists():
        if not path.parent.is_dir():
            raise ValueError(f"wear history {path}: its directory does not exist; create it or name another file")
        return WearHistory()
    try:
        raw = read_capped(path, MAX_HISTORY_BYTES, "wear history")
        return msgspec.json.decode(raw, type=WearHistory)
    except (msgspec.ValidationError, msgspec.DecodeError, ValueError) as exc:
        raise ValueError(f"wear history {path}: {exc}; it is not a wear history of this feedmon "
                         f"(JSON, format_version 1, at most {MAX_HISTORY_BYTES} bytes): {_FIX}") from None


def save_history(history: WearHistory, path: str | os.PathLike) -> None:
    """Replace ``path`` atomically: a temporary file next to it, flushed to disk, renamed over it."""
    path = Path(path)
    data = msgspec.json.encode(history)
    if len(data) > MAX_HISTORY_BYTES:
        raise ValueError(f"wear history {path}: {len(data)} bytes, more than {MAX_HISTORY_BYTES}: keep fewer parts "
                         "([monitors.wear] keep) or start a new history; the file is left as it was")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class WearVerdict(NamedTuple):
    """One section judged over ``parts`` parts: the slope's ``t``, the fitted ``rise`` (relative), the rise it
    had to exceed (``limit``: the larger of ``min_rise`` and the rise at which t = sensitivity), ``sd`` the
    residual standard deviation relative to the mean; ``alarm`` ⇔ rise > limit."""

    parts: int
    t: float
    rise: float
    limit: float
    sd: float
    alarm: bool


def judge(values, s: WearSettings) -> WearVerdict | None:
    """(M7) over the last ``window`` of ``values`` (oldest first); None with fewer than ``min_parts``."""
    y = np.abs(np.asarray(values, dtype=np.float64))[-s.window:]
    y = y[np.isfinite(y)]
    if y.size < s.min_parts:
        return None
    t, rise, sd = wear_trend(y)
    if not (math.isfinite(t) and math.isfinite(rise)):
        return WearVerdict(int(y.size), t, rise, math.nan, math.nan, False)
    # t ∝ rise at a given spread: the rise at which t would equal the sensitivity
    at_k = s.sensitivity * rise / t if t > 0 else math.inf
    limit = max(s.min_rise, at_k)
    return WearVerdict(int(y.size), float(t), float(rise), float(limit), float(sd / y.mean()),
                       bool(t > s.sensitivity and rise > s.min_rise))


class WearMonitor:
    """The wear history of a monitor's axes (loaded at start, so a bad file is refused before any work)."""

    def __init__(self, settings: WearSettings) -> None:
        self.s = settings
        self.path = Path(settings.history)
        self.history = load_history(self.path)
        self.refused_sections = 0  # new sections not recorded: the file holds MAX_HISTORY_SECTIONS already
        #: one line per section judged at the last run (the exit report)
        self.report: list[str] = []
        self.error: str | None = None  # why the history could not be saved at the end of the run

    def add_run(self, machine: str, axis: str, sections: list[dict], part: str, when: str,
                last: tuple[int, float] | None) -> list[S.AlarmEvent]:
        """Append one run's per-section statistics (:meth:`~.monitor.AxisProcessMonitor.finish`) and judge each
        section; the alarms carry ``last`` (seq, t: the run's last row, where the decision is made)."""
        s, hist = self.s, self.history.axis(machine, axis)
        by_key = {sec.key: sec for sec in hist.sections}
        out, refused = [], self.refused_sections
        for st in sections:
            if not abs(st["mean_force_N"]) >= s.cut_min_N:
                continue  # no cut (approach, retract): nothing wears there
            key = section_key(st["tool"], st["program_line"], st["occurrence"])
            sec = by_key.get(key)
            if sec is None:
                if sum(len(a.sections) for a in self.history.axes) >= MAX_HISTORY_SECTIONS:
                    self.refused_sections += 1
                    continue
                sec = by_key[key] = WearSection(key=key, tool=st["tool"], program_line=st["program_line"],
                                                occurrence=st["occurrence"])
                hist.sections.append(sec)
            sec.parts.append(WearPart(part=part[-PART_CHARS_MAX:], time=when, mean_force_N=float(st["mean_force_N"]),
                                      energy_J=float(st["energy_J"]), rows=int(st["rows"])))
            del sec.parts[:-s.keep]
            field = "mean_force_N" if s.statistic == "mean_force" else "energy_J"
            v = judge([getattr(p, field) for p in sec.parts], s)
            name = f"{machine}/{axis} {key}"
            if v is None:
                self.report.append(f"{name}: {len(sec.parts)} part(s), judged from {s.min_parts}")
                continue
            self.report.append(f"{name}: {s.statistic} {v.rise:+.1%} over {v.parts} parts, t = {v.t:.1f}"
                               + (f" — WEAR (above {v.limit:.1%})" if v.alarm else ""))
            if v.alarm and last is not None:
                out.append(S.AlarmEvent(
                    machine=machine, axis=axis, seq=last[0], t=last[1], kind="wear", monitor="wear", value=v.rise,
                    limit=v.limit, sigma=v.sd if math.isfinite(v.sd) else None, program_line=st["program_line"], tool=st["tool"],
                    detail=f"section {key}: |{s.statistic}| rose {v.rise:.1%} (relative, fitted) over the last "
                           f"{v.parts} parts, t = {v.t:.1f} > {s.sensitivity:g} and rise > {s.min_rise:.0%}; "
                           f"value, limit and sigma are relative (1 = 100 %)"))
        if self.refused_sections > refused:
            self.report.append(f"{machine}/{axis}: {self.refused_sections - refused} new section(s) NOT recorded: the "
                               f"history holds {MAX_HISTORY_SECTIONS} sections already (start a new one)")
        return out

    def save(self) -> None:
        save_history(self.history, self.path)
