"""Reference envelopes learned from good runs: the mean force over program progress per section, and its
spread across the runs (``feedmon reference learn|show``).

A run is an estimates log (``feedmon run --from … -o log.mcap`` or the live monitor's ``--mcap``). Each run
is cut into sections (:func:`sections_of`: contiguous rows of one ``(tool, program_line)``, the n-th run
of a key its own section); each section's force is averaged over bins of ``bin_s`` s of progress; over
the runs, bin by bin, the mean ``μ_i`` and the standard deviation ``s_i`` (ddof 1) — the envelope of
:func:`kernels.force_monitors.envelope_step` (M6). A section is kept up to the shortest run's length
(a bin every run reached).

The file is JSON (:class:`ReferenceFile`, msgspec), at most :data:`MAX_REFERENCE_BYTES`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated, Literal

import msgspec
import numpy as np

from feedio import schema as S
from feedio.limits import read_capped

__all__ = ["ReferenceFile", "SectionReference", "learn_reference", "load_reference", "save_reference",
           "section_key", "sections_of", "MAX_REFERENCE_BYTES", "MAX_BINS"]

#: a larger reference file is refused before it is parsed
MAX_REFERENCE_BYTES = 64 << 20
#: the most bins one section may have (at 0.05 s: 55 h)
MAX_BINS = 4_000_000
_Int = Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)]


def section_key(tool: int | None, program_line: int | None, occurrence: int) -> str:
    """``"T<tool>/L<line>/<occurrence>"`` (``-`` for an unknown tool or line): a section's name in the file."""
    return f"T{'-' if tool is None else tool}/L{'-' if program_line is None else program_line}/{occurrence}"


class SectionReference(msgspec.Struct, forbid_unknown_fields=True, dict=True):
    """One section: ``mean`` and ``spread`` (N) per bin of ``bin_s`` s of progress, from ``runs`` runs."""

    key: str
    tool: _Int | None
    program_line: _Int | None
    occurrence: Annotated[int, msgspec.Meta(ge=0)]
    bin_s: Annotated[float, msgspec.Meta(ge=0.001, le=60.0)]
    runs: Annotated[int, msgspec.Meta(ge=1)]
    mean: Annotated[list[float], msgspec.Meta(max_length=MAX_BINS)]
    spread: Annotated[list[float], msgspec.Meta(max_length=MAX_BINS)]

    def __post_init__(self) -> None:
        if len(self.mean) != len(self.spread):
            raise ValueError(f"section {self.key}: {len(self.mean)} means but {len(self.spread)} spreads")
        if not all(math.isfinite(x) for x in self.mean) or not all(math.isfinite(x) and x >= 0 for x in self.spread):
            raise ValueError(f"section {self.key}: means must be finite, spreads finite and ≥ 0")
        self._arrays = None

    @property
    def mean_array(self) -> np.ndarray:
        return self._cached()[0]

    @property
    def spread_array(self) -> np.ndarray:
        return self._cached()[1]

    def _cached(self):
        if getattr(self, "_arrays", None) is None:
            self._arrays = (np.array(self.mean, dtype=np.float64), np.array(self.spread, dtype=np.float64))
        return self._arrays


class ReferenceFile(msgspec.Struct, forbid_unknown_fields=True):
    """A reference of one axis (``machine``, ``axis``) learned from ``sources`` (the runs' file names)."""

    format_version: Literal[1]
    machine: S.Name
    axis: S.Name
    sources: list[str]
    sections: list[SectionReference]

    def find(self, key: str) -> SectionReference | None:
        for sec in self.sections:
            if sec.key == key:
                return sec
        return None


def sections_of(t: np.ndarray, force: np.ndarray, tool: list | None, line: list | None) -> list[tuple]:
    """``(key, tool, line, occurrence, t, force)`` per section of one run (rows in order)."""
    n = t.size
    keys = list(zip(tool if tool is not None else [None] * n, line if line is not None else [None] * n))
    out, seen, start = [], {}, 0
    for i in range(1, n + 1):
        if i == n or keys[i] != keys[start]:
            k = keys[start]
            occ = seen[k] = seen.get(k, -1) + 1
            out.append((section_key(k[0], k[1], occ), k[0], k[1], occ, t[start:i], force[start:i]))
            start = i
    return out


def _read_run(path: str | os.PathLike, axis: str | None) -> tuple[str, str, np.ndarray, np.ndarray, list, list]:
    from feedio import mcapio

    machine = ax = None
    t, f, tool, line = [], [], [], []
    has_tool = has_line = True
    for _, b in mcapio.iter_blocks(path, axis, ("disturbance",)):
        machine, ax = b.machine, b.axis
        if b.force is None:
            raise ValueError(f"{path}: the estimates of {b.machine}/{b.axis} have no force in N (the model cannot "
                             "scale): a reference needs the force")
        t += b.t
        f += b.force
        has_tool &= b.tool is not None
        has_line &= b.program_line is not None
        tool += b.tool if b.tool is not None else [None] * len(b.t)
        line += b.program_line if b.program_line is not None else [None] * len(b.t)
    if machine is None:
        raise ValueError(f"{path}: no estimates (channel /<machine>/<axis>/disturbance): give the log of a "
                         "feedmon run, not a trial")
    return machine, ax, np.array(t), np.array(f, dtype=np.float64), tool if has_tool else None, \
        line if has_line else None


def _binned(t: np.ndarray, f: np.ndarray, bin_s: float) -> np.ndarray:
    idx = ((t - t[0]) / bin_s).astype(np.int64)
    ok = np.isfinite(f)
    nb = int(idx[-1]) + 1
    s = np.bincount(idx[ok], weights=f[ok], minlength=nb)
    c = np.bincount(idx[ok], minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / c


def learn_reference(paths: list[str | os.PathLike], *, axis: str | None = None, bin_s: float = 0.05) -> ReferenceFile:
    """Learn a reference from ``paths`` (≥ 2 estimates logs of the same program and tool, one axis)."""
    if len(paths) < 2:
        raise ValueError(f"a reference needs at least 2 good runs, got {len(paths)}")
    if not 0.001 <= bin_s <= 60.0:
        raise ValueError(f"bin_s {bin_s!r} s out of range: 0.001 … 60")
    runs, name = [], None
    for p in paths:
        machine, ax, t, f, tool, line = _read_run(p, axis)
        if name is not None and (machine, ax) != name:
            raise ValueError(f"{p}: axis {machine}/{ax}, but the other runs are of {name[0]}/{name[1]}")
        name = (machine, ax)
        runs.append({s[0]: s for s in sections_of(t, f, tool, line)})
    sections = []
    for key, (_, tool, line, occ, *_rest) in runs[0].items():
        if not all(key in r for r in runs):
            continue  # a section not every run has is not a reference
        binned = [_binned(r[key][4], r[key][5], bin_s) for r in runs]
        nb = min(b.size for b in binned)
        if nb == 0 or nb > MAX_BINS:
            continue
        x = np.vstack([b[:nb] for b in binned])
        mean = np.nanmean(x, axis=0)
        spread = np.nanstd(x, axis=0, ddof=1)
        mean = np.where(np.isfinite(mean), mean, 0.0)
        spread = np.where(np.isfinite(spread), spread, 0.0)
        sections.append(SectionReference(key=key, tool=tool, program_line=line, occurrence=occ, bin_s=bin_s,
                                         runs=len(runs), mean=mean.tolist(), spread=spread.tolist()))
    return ReferenceFile(format_version=1, machine=name[0], axis=name[1], sources=[Path(p).name for p in paths],
                         sections=sections)


def save_reference(ref: ReferenceFile, path: str | os.PathLike) -> None:
    tmp = Path(str(path) + ".tmp")
    tmp.write_bytes(msgspec.json.encode(ref))
    os.replace(tmp, path)


def load_reference(path: str | os.PathLike) -> ReferenceFile:
    """Read a reference file; ``ValueError`` naming the file and what is wrong."""
    path = Path(path)
    raw = read_capped(path, MAX_REFERENCE_BYTES, "reference file")
    try:
        return msgspec.json.decode(raw, type=ReferenceFile)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise ValueError(f"reference file {path}: {exc}") from None
