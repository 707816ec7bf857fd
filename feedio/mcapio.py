"""MCAP trial files: one writer, one reader, one schema (:mod:`feedio.schema`).

Layout of a trial file
----------------------
* Messages are JSON (``message_encoding = "json"``) encoded with ``msgspec``; every
  channel carries the ``jsonschema`` schema generated from the Struct
  (:data:`feedio.schema.JSON_SCHEMAS`).
* Channels per axis: ``/<machine>/<axis>/samples`` (:class:`SampleBlock`),
  ``/<machine>/<axis>/truth`` (:class:`TruthBlock`, simulated trials and pulse
  ground truth) and ``/<machine>/<axis>/disturbance`` (:class:`EstimateBlock`,
  written by the monitor).
* One metadata record ``feedmon.trial`` per axis (MCAP metadata is map<str,str>):
  key ``meta`` holds the :class:`TrialMeta` JSON, plus readable keys ``machine``,
  ``axis``, ``form``, ``Ts``, ``source``.
* Log time and publish time of a message = controller time of its first sample
  in ns (``round(t[0]·1e9)``; must be ≥ 0). Data time, not wall time, so a
  simulated trial is byte-identical for the same seed and replay order follows the
  controller clock. MCAP ``sequence`` = the block's ``seq`` (mod 2³²).
* Chunked, zstd-compressed. A chunk is closed whenever the written data span
  ``chunk_seconds`` (default 1 s) of controller time, or its size exceeds
  ``chunk_size``; a live writer also calls :meth:`TrialWriter.flush_if_due`
  (wall clock) so that at most about a second is lost on a crash. Wall-clock
  flushing is never automatic: it would make chunk boundaries, hence bytes,
  depend on the machine's speed.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from feedio import schema as S

__all__ = [
    "TrialFileError",
    "TrialWriter",
    "write_arrays",
    "Trial",
    "TruthArrays",
    "read_trial",
    "list_axes",
    "iter_blocks",
    "topic",
    "METADATA_NAME",
    "KINDS",
]

METADATA_NAME = "feedmon.trial"
KINDS = {"samples": S.SampleBlock, "truth": S.TruthBlock, "disturbance": S.EstimateBlock}
_MAGIC = b"\x89MCAP0\r\n"


class TrialFileError(ValueError):
    """A trial file cannot be read or written as asked; the message names file, channel, problem."""


def topic(machine: str, axis: str, kind: str) -> str:
    """``/<machine>/<axis>/<kind>`` with kind in samples, truth, disturbance."""
    if kind not in KINDS:
        raise ValueError(f"unknown channel kind {kind!r}; use one of {', '.join(KINDS)}")
    return f"/{machine}/{axis}/{kind}"


def _check_name(what: str, value: str) -> str:
    if not value or "/" in value or value.strip() != value:
        raise ValueError(f"{what} {value!r} must be a non-empty name without '/' or surrounding spaces")
    return value


def _library() -> str:
    from mcap.writer import LIBRARY_IDENTIFIER

    from . import __version__

    return f"feedmon/{__version__}; {LIBRARY_IDENTIFIER}"


# ============================================================================================
# writer
# ============================================================================================
class TrialWriter:
    """Write a trial file. Use as a context manager::

        with TrialWriter("trial.mcap", meta) as w:
            w.write_samples(block)
            w.write_truth(truth_block, machine, axis)

    ``meta`` is one :class:`TrialMeta` or a sequence of them (one per axis). Blocks of an
    axis not declared in ``meta`` are refused. ``chunk_seconds`` closes a chunk every so
    many seconds of controller time; ``chunk_size`` (bytes, uncompressed) as well.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        meta: S.TrialMeta | Sequence[S.TrialMeta],
        *,
        chunk_seconds: float = 1.0,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
    ):
        from mcap.writer import CompressionType, Writer

        metas = [meta] if isinstance(meta, S.TrialMeta) else list(meta)
        if not metas:
            raise ValueError("TrialWriter needs the TrialMeta of at least one axis")
        self.path = os.fspath(path)
        self.metas: dict[tuple[str, str], S.TrialMeta] = {}
        for m in metas:
            if not isinstance(m, S.TrialMeta):
                raise TypeError(f"meta must be TrialMeta, got {type(m).__name__}")
            key = (_check_name("machine", m.machine), _check_name("axis", m.axis))
            if key in self.metas:
                raise ValueError(f"axis {m.machine}/{m.axis} declared twice")
            self.metas[key] = m
        if not (chunk_seconds > 0):
            raise ValueError("chunk_seconds must be > 0")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}.get(compression)
        if comp is None:
            raise ValueError(f"compression {compression!r}: use zstd, lz4 or none")
        self._stream = open(self.path, "wb")  # OSError propagates with the path
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile="", library=_library())
        self._schemas: dict[type, int] = {}
        self._channels: dict[str, int] = {}
        self._chunk_seconds = float(chunk_seconds)
        self._chunk_t0: float | None = None  # controller time of the first message in the open chunk
        self._pending = 0
        self._last_wall = time.monotonic()
        self._closed = False
        for (machine, axis), m in self.metas.items():
            self._writer.add_metadata(
                METADATA_NAME,
                {
                    "meta": S.encode(m).decode(),
                    "machine": machine,
                    "axis": axis,
                    "form": m.form,
                    "Ts": repr(float(m.Ts)),
                    "source": m.provenance.source,
                    "schema": "feedmon/1",
                },
            )
            self._channel(machine, axis, "samples")

    # -- context manager ------------------------------------------------------------------
    def __enter__(self) -> TrialWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- channels ---------------------------------------------------------------------------
    def _channel(self, machine: str, axis: str, kind: str) -> int:
        name = topic(machine, axis, kind)
        cid = self._channels.get(name)
        if cid is not None:
            return cid
        if (machine, axis) not in self.metas:
            declared = ", ".join(f"{m}/{a}" for m, a in self.metas)
            raise ValueError(f"{self.path}: axis {machine}/{axis} has no TrialMeta in this file (declared: {declared})")
        type_ = KINDS[kind]
        sid = self._schemas.get(type_)
        if sid is None:
            sid = self._writer.register_schema(
                name=S.SCHEMA_NAMES[type_],
                encoding="jsonschema",
                data=json.dumps(S.json_schema(type_), sort_keys=True).encode(),
            )
            self._schemas[type_] = sid
        cid = self._writer.register_channel(
            topic=name,
            message_encoding="json",
            schema_id=sid,
            metadata={"machine": machine, "axis": axis, "kind": kind},
        )
        self._channels[name] = cid
        return cid

    # -- writing ------------------------------------------------------------------------------
    def _add(self, cid: int, block, what: str) -> None:
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        t0 = float(block.t[0])
        if not (t0 >= 0.0):
            raise ValueError(f"{self.path}: {what} starts at t = {t0!r} s; MCAP log times need controller time ≥ 0")
        log_time = int(round(t0 * 1e9))
        self._writer.add_message(
            channel_id=cid, log_time=log_time, data=S.encode(block), publish_time=log_time,
            sequence=int(block.seq) & 0xFFFFFFFF,
        )
        self._pending += 1
        t_end = float(block.t[-1])
        if self._chunk_t0 is None:
            self._chunk_t0 = t0
        if t_end - self._chunk_t0 >= self._chunk_seconds:
            self.flush()

    def write_samples(self, block: S.SampleBlock) -> None:
        """Append a :class:`SampleBlock` on ``/<machine>/<axis>/samples``."""
        if not isinstance(block, S.SampleBlock):
            raise TypeError(f"write_samples needs a SampleBlock, got {type(block).__name__}")
        block.validate()
        self._add(self._channel(block.machine, block.axis, "samples"), block, "sample block")

    def write_truth(self, block: S.TruthBlock, machine: str, axis: str) -> None:
        """Append a :class:`TruthBlock` on ``/<machine>/<axis>/truth``."""
        if not isinstance(block, S.TruthBlock):
            raise TypeError(f"write_truth needs a TruthBlock, got {type(block).__name__}")
        self._add(self._channel(machine, axis, "truth"), block, "truth block")

    def write_estimates(self, block: S.EstimateBlock) -> None:
        """Append an :class:`EstimateBlock` on ``/<machine>/<axis>/disturbance``."""
        if not isinstance(block, S.EstimateBlock):
            raise TypeError(f"write_estimates needs an EstimateBlock, got {type(block).__name__}")
        self._add(self._channel(block.machine, block.axis, "disturbance"), block, "estimate block")

    def flush(self) -> None:
        """Close the open chunk (if it has messages) and flush the file."""
        if self._closed:
            return
        if self._pending:
            self._writer.flush()
        self._pending = 0
        self._chunk_t0 = None
        self._last_wall = time.monotonic()

    def flush_if_due(self, now: float | None = None) -> bool:
        """For live writers: close the chunk when ``chunk_seconds`` of wall time passed
        since the last flush (``now`` from ``time.monotonic()``). Returns True if flushed."""
        now = time.monotonic() if now is None else now
        if self._pending and now - self._last_wall >= self._chunk_seconds:
            self.flush()
            return True
        return False

    def close(self) -> None:
        """Write the summary and close the file (idempotent)."""
        if self._closed:
            return
        try:
            self._writer.finish()
        finally:
            self._closed = True
            self._stream.close()


def write_arrays(path, meta: S.TrialMeta, samples: dict, truth: dict | None = None, *, block: int = 100) -> None:
    """Write one axis given as arrays: ``samples`` maps :class:`SampleBlock` fields (``t``,
    ``v_ref``, ``v_meas`` and optional columns; ``None`` = absent) to arrays, ``truth`` maps
    :class:`TruthBlock` fields to arrays; both are cut into blocks of ``block`` samples with
    ``seq`` from 0 (the one writer of the simulator and the importers)."""
    n = len(samples["t"])

    def cut(cols: dict, i: int, j: int) -> dict:
        return {k: None if a is None else np.asarray(a[i:j]).tolist() for k, a in cols.items()}

    with TrialWriter(os.fspath(path), meta) as w:
        for i in range(0, n, block):
            j = min(i + block, n)
            w.write_samples(S.SampleBlock(machine=meta.machine, axis=meta.axis, seq=i, **cut(samples, i, j)))
            if truth is not None:
                w.write_truth(S.TruthBlock(seq=i, **cut(truth, i, j)), meta.machine, meta.axis)


# ============================================================================================
# reader
# ============================================================================================
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
    truth: TruthArrays | None = None
    channels: list[str] = field(default_factory=list)

    @property
    def Ts(self) -> float:
        return float(self.meta.Ts)

    @property
    def form(self) -> str:
        return self.meta.form

    def __len__(self) -> int:
        return int(self.t.size)


class _Open:
    """Opened, sanity-checked MCAP file (magic at both ends, summary, channels, metadata)."""

    def __init__(self, path):
        from mcap.reader import make_reader

        self.path = os.fspath(path)
        try:
            self.stream = open(self.path, "rb")
        except OSError as exc:
            raise TrialFileError(f"cannot open trial file {self.path}: {exc.strerror or exc}") from exc
        try:
            size = os.fstat(self.stream.fileno()).st_size
            head = self.stream.read(8)
            if head != _MAGIC:
                raise TrialFileError(
                    f"{self.path} is not an MCAP file (it starts with {head[:8]!r}, "
                    f"not the MCAP magic {_MAGIC!r})"
                )
            self.stream.seek(max(size - 8, 0))
            tail = self.stream.read(8)
            if size < 16 or tail != _MAGIC:
                raise TrialFileError(
                    f"{self.path} is truncated: {size} bytes and no MCAP end magic — the recording "
                    "was not closed properly (writer killed or disk full); salvage its complete chunks with "
                    f"'feedmon recover {self.path} -o FIXED.mcap'"
                )
            self.stream.seek(0)
            self.reader = make_reader(self.stream)
            self.summary = self._guard(self.reader.get_summary, "reading the summary section")
            if self.summary is None:
                raise TrialFileError(f"{self.path} has no summary section (channels unknown); rewrite it with feedmon")
            self.channels = {c.topic: c for c in self.summary.channels.values()}
            self.metadata = self._guard(lambda: list(self.reader.iter_metadata()), "reading metadata")
        except BaseException:
            self.stream.close()
            raise

    def _guard(self, fn, doing: str):
        try:
            return fn()
        except TrialFileError:
            raise
        except Exception as exc:  # mcap raises many types (McapError, struct.error, zstd, EOF...)
            raise TrialFileError(
                f"{self.path} is corrupt or truncated ({doing}: {type(exc).__name__}: {exc})"
            ) from exc

    def close(self):
        self.stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def axes(self) -> list[tuple[str, str]]:
        out = []
        for name in sorted(self.channels):
            parts = name.split("/")
            if len(parts) == 4 and parts[0] == "" and parts[3] == "samples":
                out.append((parts[1], parts[2]))
        return out

    def select(self, axis: str | None) -> tuple[str, str]:
        axes = self.axes()
        if not axes:
            listed = ", ".join(sorted(self.channels)) or "none"
            raise TrialFileError(
                f"{self.path} has no samples channel (/<machine>/<axis>/samples); channels present: {listed}"
            )
        names = [f"{m}/{a}" for m, a in axes]
        if axis is None:
            if len(axes) > 1:
                raise TrialFileError(
                    f"{self.path} holds {len(axes)} axes ({', '.join(names)}); choose one with axis="
                )
            return axes[0]
        hits = [(m, a) for m, a in axes if axis in (a, f"{m}/{a}")]
        if not hits:
            raise TrialFileError(f"{self.path} has no axis {axis!r}; axes present: {', '.join(names)}")
        if len(hits) > 1:
            raise TrialFileError(
                f"{self.path}: axis {axis!r} exists on several machines ({', '.join(f'{m}/{a}' for m, a in hits)}); "
                "give it as machine/axis"
            )
        return hits[0]

    def meta(self, machine: str, axis: str) -> S.TrialMeta:
        found = [m for m in self.metadata if m.name == METADATA_NAME]
        for rec in found:
            if rec.metadata.get("machine") == machine and rec.metadata.get("axis") == axis:
                if "meta" not in rec.metadata:
                    raise TrialFileError(f"{self.path}: metadata record {METADATA_NAME} of {machine}/{axis} has no 'meta' key")
                try:
                    return S.decode_meta(rec.metadata["meta"], what=f"metadata {METADATA_NAME} of {machine}/{axis}")
                except S.SchemaError as exc:
                    raise TrialFileError(f"{self.path}: {exc}") from None
        raise TrialFileError(
            f"{self.path}: missing metadata record {METADATA_NAME!r} for axis {machine}/{axis} "
            f"(sampling time and input form unknown); found {len(found)} {METADATA_NAME} record(s)"
        )

    def check_channel(self, name: str) -> None:
        ch = self.channels[name]
        if ch.message_encoding != "json":
            raise TrialFileError(f"{self.path}: channel {name} has message encoding {ch.message_encoding!r}, expected 'json'")
        sch = self.summary.schemas.get(ch.schema_id)
        if sch is None or sch.encoding != "jsonschema":
            got = "no schema" if sch is None else f"schema encoding {sch.encoding!r}"
            raise TrialFileError(f"{self.path}: channel {name} has {got}, expected a 'jsonschema' schema")

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, object]]:
        """Decoded (topic, log_time, block) in log-time order; errors name channel and index."""
        for name in topics:
            self.check_channel(name)
        kinds = {name: KINDS[name.rsplit("/", 1)[1]] for name in topics}
        counters = dict.fromkeys(topics, 0)
        it = iter(self._guard(lambda: self.reader.iter_messages(topics=topics), "reading messages"))
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as exc:
                raise TrialFileError(
                    f"{self.path} is corrupt or truncated (reading messages: {type(exc).__name__}: {exc})"
                ) from exc
            _, channel, message = item
            name = channel.topic
            idx = counters[name]
            counters[name] = idx + 1
            try:
                block = S.decode(message.data, kinds[name], what=f"message {idx}")
            except S.SchemaError as exc:
                raise TrialFileError(f"{self.path}: channel {name}, {exc}") from None
            yield name, message.log_time, block


def list_axes(path) -> list[str]:
    """``machine/axis`` of every samples channel in a trial file."""
    with _Open(path) as f:
        return [f"{m}/{a}" for m, a in f.axes()]


def iter_blocks(path, axis: str | None = None, kinds: Sequence[str] = ("samples",)) -> Iterator[tuple[str, object]]:
    """Replay iterator: ``(kind, block)`` of one axis in log-time (controller time) order.

    ``kinds`` any of "samples", "truth", "disturbance" (absent channels are skipped).
    """
    f = _Open(path)
    try:
        machine, ax = f.select(axis)
        topics = [topic(machine, ax, k) for k in kinds]
        topics = [t for t in topics if t in f.channels]
        for name, _, block in f.messages(topics):
            yield name.rsplit("/", 1)[1], block
    finally:
        f.close()


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


def read_trial(path, axis: str | None = None) -> Trial:
    """Read one axis of a trial file into arrays.

    ``axis`` "X" or "machine/X"; required when the file holds several axes.
    Raises :class:`TrialFileError` (a ValueError) naming file, channel and problem.
    """
    with _Open(path) as f:
        machine, ax = f.select(axis)
        meta = f.meta(machine, ax)
        t_s, t_t = topic(machine, ax, "samples"), topic(machine, ax, "truth")
        topics = [t_s] + ([t_t] if t_t in f.channels else [])
        samples, truths = [], []
        for name, _, block in f.messages(topics):
            (samples if name == t_s else truths).append(block)
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
            channels=sorted(f.channels),
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
