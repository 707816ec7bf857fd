"""Reading trial files (layout: :mod:`feedio.trialformat`): one axis into arrays (:func:`read_trial`),
or the decoded blocks of one or several axes in file order (:func:`iter_blocks`, :func:`iter_file`,
:func:`iter_axes`). Reading goes through :mod:`feedio.mcapfile` (limits, CRCs); messages are read in
file order, which for feedmon's writers is sequence order on every channel.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from feedio import schema as S
from kernels.errors import ParameterError

from .mcapfile import DEFAULT_LIMITS, Limits, McapFile, TrialFileError, json_depth
from .trialformat import (
    CHANNEL_KINDS,
    MAX_READ_AHEAD_BYTES,
    METADATA_NAME,
    SINGLE_SAMPLE_TYPES,
    TRUTH_EVENTS,
    parse_time,
    split_topic,
    topic,
)

__all__ = ["TruthArrays", "Trial", "list_axes", "iter_blocks", "iter_file", "AxisStreams", "held_bytes", "iter_axes",
           "MAX_TRIAL_SAMPLES", "TrialTooLong", "read_trial", "OpenTrial"]


@dataclass
class TruthArrays:
    """Ground truth as arrays aligned by ``seq`` with the samples (see :class:`TruthBlock`)."""

    seq: np.ndarray
    t: np.ndarray
    force: np.ndarray  # N, T_c of method §1
    f: np.ndarray  # m/s, −b·T_c
    dynamometer: np.ndarray | None = None
    v_true: np.ndarray | None = None
    glitch: np.ndarray | None = None  # bool
    inertia: np.ndarray | None = None  # kg, true J(t)
    damping: np.ndarray | None = None  # N·s/m, true B(t)
    coulomb_pos: np.ndarray | None = None  # N, true Coulomb friction for v > Ω
    coulomb_neg: np.ndarray | None = None  # N, magnitude for v < −Ω


@dataclass
class Trial:
    """One axis of a trial file as NumPy arrays (NaN where a sample was null)."""

    path: str
    machine: str
    axis: str
    meta: S.TrialMeta
    seq: np.ndarray
    t: np.ndarray
    v_ref: np.ndarray
    v_meas: np.ndarray
    u: np.ndarray | None = None
    current: np.ndarray | None = None
    position: np.ndarray | None = None
    spindle_rpm: np.ndarray | None = None
    spindle_angle: np.ndarray | None = None  # rad, unwrapped
    program_line: np.ndarray | None = None  # NC program line (float64: NaN where not known)
    tool: np.ndarray | None = None  # tool number (float64: NaN where not known)
    truth: TruthArrays | None = None
    channels: list[str] = field(default_factory=list)
    truth_events: list[S.TruthEvent] = field(default_factory=list)  # known process events (simulated trials)
    start_ns: int | None = None  # wall-clock time of controller time 0 (None: files without one)

    @property
    def Ts(self) -> float:
        return float(self.meta.Ts)

    @property
    def form(self) -> str:
        return self.meta.form

    def __len__(self) -> int:
        return int(self.t.size)

    def window(self, start: float | None = None, end: float | None = None) -> Trial:
        """The samples with ``start ≤ t − t₀ < end`` (s from the first sample; None: the record's
        start or end), and the truth of the same sequence numbers. Raises ``ValueError`` naming the
        parameter when the window is empty or ``start ≥ end`` (a :class:`~kernels.errors.ParameterError`)."""
        if start is None and end is None:
            return self
        for name, x in (("start", start), ("end", end)):
            if x is not None and not (math.isfinite(x) and x >= 0.0):
                raise ParameterError(f"window {name} must be a time ≥ 0 s from the trial's first sample, got {x!r}",
                                     name)
        if start is not None and end is not None and not start < end:
            raise ParameterError(f"window start ({start:g} s) must come before its end ({end:g} s)", "start", "end")
        rel = self.t - self.t[0] if self.t.size else self.t
        keep = (rel >= (start or 0.0)) & (rel < (math.inf if end is None else end))
        if not keep.any():
            raise ParameterError(f"{self.path}: no sample between {start or 0.0:g} s and "
                                 f"{'the end' if end is None else f'{end:g} s'} (the trial lasts "
                                 f"{float(rel[-1]):.6g} s)", "start", "end")
        idx = np.flatnonzero(keep)
        cols = {k: None if getattr(self, k) is None else getattr(self, k)[idx]
                for k in ("seq", *S.SAMPLE_COLUMNS)}
        truth = self.truth
        if truth is not None:
            lo, hi = int(self.seq[idx[0]]), int(self.seq[idx[-1]])
            sel = (truth.seq >= lo) & (truth.seq <= hi)
            truth = dataclasses.replace(truth, **{f.name: None if getattr(truth, f.name) is None
                                                  else getattr(truth, f.name)[sel]
                                                  for f in dataclasses.fields(truth)})
        lo, hi = int(self.seq[idx[0]]), int(self.seq[idx[-1]])
        events = [e for e in self.truth_events if lo <= e.seq <= hi]
        return dataclasses.replace(self, **cols, truth=truth, truth_events=events)


class OpenTrial:
    """An opened, checked trial file (:class:`~feedio.mcapfile.McapFile`) with feedmon's
    conventions: axes, their metadata, decoded messages."""

    def __init__(self, path, limits: Limits = DEFAULT_LIMITS):
        self.file = McapFile(path, limits)
        self.path = self.file.path
        self.limits = limits
        try:
            self.channels = {}
            self._ids: dict[str, list[int]] = {}
            for c in self.file.channels.values():
                self.channels.setdefault(c.topic, c)
                self._ids.setdefault(c.topic, []).append(c.id)
            self._topic_of = {c.id: c.topic for c in self.file.channels.values()}
            self._axes: list[tuple[str, str]] | None = None
            self._by_name: dict[str, list[tuple[str, str]]] = {}
            self._trial_meta: dict[tuple[str, str], dict] = {}
            self._n_trial_meta = 0
            for rec in self.file.metadata():
                if rec.name == METADATA_NAME:
                    self._n_trial_meta += 1
                    key = (rec.metadata.get("machine"), rec.metadata.get("axis"))
                    self._trial_meta.setdefault(key, rec.metadata)
        except BaseException:
            self.file.close()
            raise

    def close(self):
        self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def axes(self) -> list[tuple[str, str]]:
        if self._axes is None:
            out = []
            for name in sorted(self.channels):
                parts = name.split("/")
                if len(parts) == 4 and parts[0] == "" and parts[3] == "samples" and parts[1] and parts[2]:
                    out.append((parts[1], parts[2]))
            self._axes = out
            by_name: dict[str, list[tuple[str, str]]] = {}
            for m, a in out:
                by_name.setdefault(f"{m}/{a}", []).append((m, a))
                by_name.setdefault(a, []).append((m, a))
            self._by_name = by_name
        return list(self._axes)

    def select(self, axis: str | None) -> tuple[str, str]:
        if self._axes is None:
            self.axes()
        if axis is not None and len(self._by_name.get(axis, ())) == 1:
            return self._by_name[axis][0]
        axes = self._axes
        if not axes:
            listed = ", ".join(sorted(self.channels)[:20]) or "none"
            raise TrialFileError(
                f"{self.path} has no samples channel (/<machine>/<axis>/samples); channels present: {listed}"
            )
        names = [f"{m}/{a}" for m, a in axes]
        if axis is None:
            if len(axes) > 1:
                shown = ", ".join(names[:20]) + (", …" if len(names) > 20 else "")
                raise TrialFileError(f"{self.path} holds {len(axes)} axes ({shown}); choose one with axis=")
            return axes[0]
        hits = [(m, a) for m, a in axes if axis in (a, f"{m}/{a}")]
        if not hits:
            shown = ", ".join(names[:20]) + (", …" if len(names) > 20 else "")
            raise TrialFileError(f"{self.path} has no axis {axis!r}; axes present: {shown}")
        if len(hits) > 1:
            raise TrialFileError(
                f"{self.path}: axis {axis!r} exists on several machines ({', '.join(f'{m}/{a}' for m, a in hits)}); "
                "give it as machine/axis"
            )
        return hits[0]

    def _record(self, machine: str, axis: str) -> dict:
        rec = self._trial_meta.get((machine, axis))
        if rec is None:
            raise TrialFileError(
                f"{self.path}: missing metadata record {METADATA_NAME!r} for axis {machine}/{axis} "
                f"(sampling time and input form unknown); found {self._n_trial_meta} {METADATA_NAME} record(s)"
            )
        return rec

    def meta(self, machine: str, axis: str) -> S.TrialMeta:
        rec = self._record(machine, axis)
        if "meta" not in rec:
            raise TrialFileError(f"{self.path}: metadata record {METADATA_NAME} of {machine}/{axis} has no 'meta' key")
        raw = rec["meta"]
        depth = json_depth(raw)
        if depth > self.limits.json_depth:
            raise TrialFileError(
                f"{self.path}: metadata {METADATA_NAME} of {machine}/{axis} nests {depth} levels deep, more than "
                f"the limit of {self.limits.json_depth}")
        try:
            return S.decode_meta(raw, what=f"metadata {METADATA_NAME} of {machine}/{axis}")
        except S.SchemaError as exc:
            raise TrialFileError(f"{self.path}: {exc}") from None

    def start_ns(self, machine: str, axis: str) -> int | None:
        raw = self._record(machine, axis).get("start_time_ns")
        if raw is None:
            return None
        try:
            return parse_time(int(raw), what="start_time_ns")
        except ValueError as exc:
            raise TrialFileError(f"{self.path}: metadata {METADATA_NAME} of {machine}/{axis}: {exc}") from None

    def check_channel(self, name: str) -> None:
        ch = self.channels[name]
        if ch.message_encoding != "json":
            raise TrialFileError(f"{self.path}: channel {name} has message encoding {ch.message_encoding!r}, expected 'json'")
        sch = self.file.schemas.get(ch.schema_id)
        if sch is None or sch.encoding != "jsonschema":
            got = "no schema" if sch is None else f"schema encoding {sch.encoding!r}"
            raise TrialFileError(f"{self.path}: channel {name} has {got}, expected a 'jsonschema' schema")

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, object]]:
        """Decoded (topic, log_time, block) in file order; errors name file, channel and message index."""
        kinds = {}
        for name in topics:
            self.check_channel(name)
            split = split_topic(name)
            if split is None:
                raise ValueError(f"{name} is not a feedmon channel (/<machine>/<axis>/<kind>)")
            kinds[name] = CHANNEL_KINDS[split[2]]
        ids = [i for name in topics for i in self._ids[name]]
        counters = dict.fromkeys(topics, 0)
        for _, msg in self.file.messages(ids):
            name = self._topic_of[msg.channel_id]
            idx = counters[name]
            counters[name] = idx + 1
            type_ = kinds[name]
            try:
                block = S.decode(msg.data, type_, what=f"message {idx}")
            except S.SchemaError as exc:
                raise TrialFileError(f"{self.path}: channel {name}, {exc}") from None
            seq = block.seq
            last = seq + (len(block.t) - 1 if type_ not in SINGLE_SAMPLE_TYPES else 0)
            if last > S.SEQ_MAX:
                raise TrialFileError(
                    f"{self.path}: channel {name}, message {idx}: sequence number {seq} "
                    f"{'' if last == seq else f'(+{last - seq}) '}is beyond the largest the schema allows "
                    f"(SEQ_MAX = 2**53 − 1 = {S.SEQ_MAX}); the bridge that wrote it broke the schema")
            yield name, msg.log_time, block


def list_axes(path) -> list[str]:
    """``machine/axis`` of every samples channel in a trial file."""
    with OpenTrial(path) as f:
        return [f"{m}/{a}" for m, a in f.axes()]


def iter_blocks(path, axis: str | None = None, kinds: Sequence[str] = ("samples",)) -> Iterator[tuple[str, object]]:
    """Replay iterator: ``(kind, block)`` of one axis in file (sequence) order.

    ``kinds`` any of "samples", "truth", "disturbance", "disturbance/scalars", "health" (absent
    channels are skipped).
    """
    f = OpenTrial(path)
    try:
        machine, ax = f.select(axis)
        topics = [topic(machine, ax, k) for k in kinds]
        topics = [t for t in topics if t in f.channels]
        for name, _, block in f.messages(topics):
            yield split_topic(name)[2], block
    finally:
        f.close()


def iter_file(path, axes: Sequence[str], kinds: Sequence[str] = ("samples",)) -> Iterator[tuple[str, str, int, object]]:
    """``(axis, kind, log_time, block)`` of the given axes (``machine/axis``) and kinds in file
    order, in one pass over the file."""
    f = OpenTrial(path)
    try:
        wanted: dict[str, tuple[str, str]] = {}
        for name in axes:
            machine, ax = f.select(name)
            for k in kinds:
                tp = topic(machine, ax, k)
                if tp in f.channels:
                    wanted[tp] = (name, k)
        for tp, lt, block in f.messages(list(wanted)):
            name, kind = wanted[tp]
            yield name, kind, lt, block
    finally:
        f.close()


class AxisStreams(dict):
    """What :func:`iter_axes` returns: axis name → iterator, plus how the read-ahead went."""

    own_passes = 0  #: axes that left the shared pass and re-read the file on their own
    peak_bytes = 0  #: most bytes of blocks (:func:`held_bytes`) that waited at once


def held_bytes(block) -> int:
    """About the memory (bytes) a decoded block holds: 32 per list element (a float object and its
    pointer), 64 per field and 256 for the object. What the byte bounds of read-ahead buffers count."""
    n = 256
    for name in block.__struct_fields__:
        v = getattr(block, name)
        n += 64 + (32 * len(v) if isinstance(v, list) else 0)
    return n


def iter_axes(path, axes: Sequence[str], kinds: Sequence[str] = ("samples",), *,
              read_ahead_bytes: int = MAX_READ_AHEAD_BYTES) -> AxisStreams:
    """One iterator of ``(kind, log_time, block)`` per axis (``machine/axis``), fed by **one**
    pass over the file (:func:`iter_file`) as long as the axes are interleaved in time, so reading
    N axes costs one read, not N. Blocks of the axes not being consumed wait in memory, at most
    ``read_ahead_bytes`` of them (:func:`held_bytes`); beyond, those axes are dropped from the
    shared pass and each re-reads the file on its own from the block it had reached (its waiting
    blocks are read again), so memory stays bounded whatever the order of the file, at the cost
    of one more read per such axis (counted in the result's :attr:`AxisStreams.own_passes`).
    Meant for consuming the axes together, e.g. merged with ``heapq.merge``."""
    source = iter_file(path, axes, kinds)
    queues: dict[str, deque] = {name: deque() for name in axes}
    given = dict.fromkeys(axes, 0)  # items handed out per axis
    own: set[str] = set()  # axes that left the shared pass
    state = {"held": 0, "done": False, "open": len(axes)}
    info = AxisStreams()

    def spill(consumer: str) -> None:
        for name, q in queues.items():
            if name != consumer and q:
                state["held"] -= sum(size for *_, size in q)
                q.clear()
                own.add(name)
                info.own_passes += 1

    def own_pass(axis_name: str) -> Iterator[tuple[str, int, object]]:
        for j, (_, kind, lt, block) in enumerate(iter_file(path, [axis_name], kinds)):
            if j >= given[axis_name]:
                yield kind, lt, block

    def stream(axis_name: str) -> Iterator[tuple[str, int, object]]:
        q = queues[axis_name]
        try:
            while axis_name not in own:
                if q:
                    *item, size = q.popleft()
                    state["held"] -= size
                    given[axis_name] += 1
                    yield tuple(item)
                    continue
                if state["done"]:
                    return
                try:
                    target, kind, lt, block = next(source)
                except StopIteration:
                    state["done"] = True
                    continue
                if target == axis_name:
                    given[axis_name] += 1
                    yield kind, lt, block
                elif target not in own:
                    size = held_bytes(block)
                    queues[target].append((kind, lt, block, size))
                    state["held"] += size
                    info.peak_bytes = max(info.peak_bytes, state["held"])
                    if state["held"] > read_ahead_bytes:
                        spill(axis_name)
            yield from own_pass(axis_name)
        finally:
            state["open"] -= 1
            if state["open"] == 0:
                source.close()

    info.update((name, stream(name)) for name in axes)
    return info


def _column(blocks, name: str, n_total: int) -> np.ndarray | None:
    cols = [getattr(b, name) for b in blocks]
    if all(c is None for c in cols):
        return None
    out = []
    for b, c in zip(blocks, cols):
        out.extend(c if c is not None else [None] * len(b.t))
    arr = np.array(out, dtype=np.float64)
    assert arr.size == n_total
    return arr


def _seq(blocks) -> np.ndarray:
    if not blocks:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([np.arange(b.seq, b.seq + len(b.t), dtype=np.int64) for b in blocks])


#: most samples :func:`read_trial` keeps of one axis (the decoded blocks take ~200 bytes per sample while
#: reading: ~2 GB at this limit); ``feedmon run --from`` and ``replay`` stream a trial of any length
MAX_TRIAL_SAMPLES = 10_000_000


class TrialTooLong(TrialFileError):
    """The axis holds more than the ``max_samples`` :func:`read_trial` was given (``limit``)."""

    def __init__(self, message: str, limit: int) -> None:
        super().__init__(message)
        self.limit = limit


def read_trial(path, axis: str | None = None, *, limits: Limits = DEFAULT_LIMITS,
               max_samples: int = MAX_TRIAL_SAMPLES) -> Trial:
    """Read one axis of a trial file into arrays.

    ``axis`` "X" or "machine/X"; required when the file holds several axes. Reading stops with
    :class:`TrialTooLong` as soon as the axis has more than ``max_samples`` samples (memory stays bounded).
    Raises :class:`TrialFileError` (a ValueError) naming file, channel and problem.
    """
    with OpenTrial(path, limits) as f:
        machine, ax = f.select(axis)
        meta = f.meta(machine, ax)
        start = f.start_ns(machine, ax)
        t_s, t_t, t_e = topic(machine, ax, "samples"), topic(machine, ax, "truth"), topic(machine, ax, TRUTH_EVENTS)
        topics = [t_s] + [x for x in (t_t, t_e) if x in f.channels]
        samples, truths, events = [], [], []
        held = {t_s: 0, t_t: 0, t_e: 0}
        for name, _, block in f.messages(topics):
            if name == t_e:
                events.append(block)
                held[name] += 1
            else:
                (samples if name == t_s else truths).append(block)
                held[name] += len(block.t)
            if held[name] > max_samples:
                raise TrialTooLong(f"{f.path}: axis {machine}/{ax} holds more than {max_samples:,} samples, the most "
                                   "read into memory at once; identify a window of it or a shorter recording (the offline "
                                   "run and the replay stream a trial of any length)", max_samples)
        if not samples:
            raise TrialFileError(f"{f.path}: channel {t_s} has no messages")
        n = sum(len(b.t) for b in samples)
        trial = Trial(
            path=f.path,
            machine=machine,
            axis=ax,
            meta=meta,
            seq=_seq(samples),
            t=np.array([x for b in samples for x in b.t], dtype=np.float64),
            v_ref=_column(samples, "v_ref", n),
            v_meas=_column(samples, "v_meas", n),
            u=_column(samples, "u", n),
            current=_column(samples, "current", n),
            position=_column(samples, "position", n),
            spindle_rpm=_column(samples, "spindle_rpm", n),
            spindle_angle=_column(samples, "spindle_angle", n),
            program_line=_column(samples, "program_line", n),
            tool=_column(samples, "tool", n),
            channels=sorted(f.channels),
            start_ns=start,
            truth_events=events,
        )
        if truths:
            m = sum(len(b.t) for b in truths)
            glitch = None
            if any(b.glitch is not None for b in truths):
                glitch = np.array(
                    [g for b in truths for g in (b.glitch if b.glitch is not None else [False] * len(b.t))], dtype=bool
                )
            trial.truth = TruthArrays(
                seq=_seq(truths),
                t=np.array([x for b in truths for x in b.t], dtype=np.float64),
                force=_column(truths, "force", m),
                f=_column(truths, "f", m),
                dynamometer=_column(truths, "dynamometer", m),
                v_true=_column(truths, "v_true", m),
                glitch=glitch,
                inertia=_column(truths, "inertia", m),
                damping=_column(truths, "damping", m),
                coulomb_pos=_column(truths, "coulomb_pos", m),
                coulomb_neg=_column(truths, "coulomb_neg", m),
            )
        return trial
