"""Tracker state on disk: :class:`StateStore` saves each axis' :meth:`AxisEstimator.snapshot`
as an ``.npz`` (a zip of ``.npy`` arrays; never pickled) plus the model file's SHA-256, the
axis and the time of saving, and restores it at the next start.

A state file is untrusted input. Before restoring, :meth:`StateStore.load`

1. caps sizes before decompressing anything: the file size, the zip directory's member
   count, names, each member's uncompressed size and their total, against limits derived
   from the model (the snapshot of a fresh tracker with the model's budget after one step);
2. reads each member's ``.npy`` header and refuses a dtype or shape other than the template's
   before reading its data (CRC checked);
3. checks the model hash (another model file: ``ignored``), the axis, the format version;
4. has the estimator check keys, shapes, dtypes, finiteness, hyperparameters and the
   tracker's invariants (:mod:`monitor.state_check`) before anything reaches compiled code.

A refused file is reported as ``unreadable: <reason>`` and the axis starts fresh; nothing in a
state file can crash, hang or bloat the monitor. Saving writes ``<name>.tmp`` (fsync'd) and
renames it over the state; on any failure the ``.tmp`` is removed, and one left behind by a
killed process is removed at the next start.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import stat
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .axes import AxisRuntime
from .state_check import StateError

__all__ = ["StateStore", "StateLoad", "STATE_FORMAT", "read_state_file", "learned_snapshot"]

log = logging.getLogger("monitor.state")

STATE_FORMAT = 4  # 2: the β state keeps the previous sample's direction of motion (cnt has 12 entries);
#                  3: the β forgetting is per physical parameter (settings 'basis', par has 11 entries);
#                  4: the β settings hold min_speed (par has 10 entries)

#: longest ``.npy`` header accepted (numpy writes ~128 bytes for these arrays)
NPY_HEADER_MAX = 4096
#: longest name (characters) stored in ``meta.machine`` / ``meta.axis``
NAME_MAX = 1024
#: zip bookkeeping allowed per member and for the whole file (directory entries, end record, comment)
ZIP_OVERHEAD_MEMBER = 1024
ZIP_OVERHEAD_FILE = 65536 + 1024

#: the entries a state file adds to the snapshot: dtype and shape (a str dtype: up to NAME_MAX characters)
_META = {
    "meta.format": (np.dtype(np.int64), ()),
    "meta.model_sha256": (np.dtype("<U64"), ()),
    "meta.machine": (np.dtype(f"<U{NAME_MAX}"), ()),
    "meta.axis": (np.dtype(f"<U{NAME_MAX}"), ()),
    "meta.saved_unix": (np.dtype(np.float64), ()),
}


@dataclass(frozen=True)
class StateLoad:
    """What :meth:`StateStore.load` did: ``origin`` (``fresh``, ``restored``, ``ignored``,
    ``unreadable``) and a one-line ``detail`` for the log (age, samples learned, or the reason)."""

    origin: str
    detail: str


def _age(seconds: float) -> str:
    s = abs(seconds)
    if s < 120:
        text = f"{s:.0f} s"
    elif s < 7200:
        text = f"{s / 60:.0f} min"
    elif s < 2 * 86400:
        text = f"{s / 3600:.1f} h"
    else:
        text = f"{s / 86400:.1f} days"
    return f"{text} ago" if seconds >= 0 else f"{text} in the future (clock changed?)"


def read_state_file(path: str | os.PathLike, layout: dict[str, tuple[np.dtype, tuple[int, ...]]],
                    optional: frozenset[str] = frozenset()) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` at ``path``, read only if every member matches ``layout``.

    ``layout`` maps each entry to its dtype and shape (a ``U`` dtype bounds the string length);
    entries in ``optional`` may be absent. Raises :class:`StateError` naming the first problem;
    the limits are checked in this order, so no more than ``layout`` describes is ever read:
    file size; member count, names and declared sizes (zip directory); each ``.npy`` header;
    the data (and its CRC).
    """
    limits = {f"{key}.npy": (dtype, shape, NPY_HEADER_MAX + dtype.itemsize * math.prod(shape))
              for key, (dtype, shape) in layout.items()}
    total_cap = sum(cap for _, _, cap in limits.values())
    file_cap = total_cap + ZIP_OVERHEAD_MEMBER * len(limits) + ZIP_OVERHEAD_FILE
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # a FIFO must not block the start
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise StateError("it is not a regular file")
        if st.st_size > file_cap:
            raise StateError(f"the file has {st.st_size} bytes; a state of this model has at most {file_cap}")
        fh = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    with fh:
        return _read_zip(fh, limits, total_cap, optional)


def _read_zip(fh, limits: dict, total_cap: int, optional: frozenset[str]) -> dict[str, np.ndarray]:
    try:
        zf = zipfile.ZipFile(fh)
    except Exception as exc:  # noqa: BLE001 - whatever a crafted zip directory makes zipfile raise
        raise StateError(f"not an npz (zip) file: {exc}") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > len(limits):
            raise StateError(f"it has {len(infos)} entries; a state of this model has at most {len(limits)}")
        names = [i.filename for i in infos]
        if len(set(names)) != len(names):
            raise StateError("an entry appears twice")
        unknown = sorted(n for n in names if n not in limits)
        if unknown:
            raise StateError(f"unexpected entries {', '.join(map(repr, unknown[:5]))}")
        missing = sorted(n[:-4] for n in set(limits) - set(names) if n[:-4] not in optional)
        if missing:
            raise StateError(f"missing entries {', '.join(missing)}")
        for info in infos:
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise StateError(f"{info.filename!r} uses an unsupported compression ({info.compress_type})")
            if info.file_size > limits[info.filename][2]:
                raise StateError(f"{info.filename!r} would inflate to {info.file_size} bytes; "
                                 f"at most {limits[info.filename][2]} expected")
            if info.flag_bits & 0x1:
                raise StateError(f"{info.filename!r} is encrypted")
        if sum(i.file_size for i in infos) > total_cap:
            raise StateError(f"the entries would inflate to more than {total_cap} bytes")
        return {info.filename[:-4]: _read_member(zf, info, *limits[info.filename][:2]) for info in infos}


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """One ``.npy`` member: header checked against ``dtype``/``shape`` before its data is read."""
    from numpy.lib import format as npy

    key = info.filename[:-4]
    try:
        with zf.open(info) as fh:
            version = npy.read_magic(fh)
            if version == (1, 0):
                got_shape, fortran, got_dtype = npy.read_array_header_1_0(fh, max_header_size=NPY_HEADER_MAX)
            elif version == (2, 0):
                got_shape, fortran, got_dtype = npy.read_array_header_2_0(fh, max_header_size=NPY_HEADER_MAX)
            else:
                raise StateError(f"{key!r} has .npy format {version}, not 1.0 or 2.0")
            if got_shape != shape:
                raise StateError(f"{key!r} has shape {got_shape}, expected {shape}")
            if dtype.kind == "U":
                ok = got_dtype.kind == "U" and got_dtype.byteorder in ("<", "=") and got_dtype.itemsize <= dtype.itemsize
            else:
                ok = got_dtype == dtype
            if not ok:
                raise StateError(f"{key!r} is {got_dtype}, expected {dtype}")
            nbytes = got_dtype.itemsize * math.prod(shape)
            data = fh.read(nbytes + 1)  # one more: reaches the end, so the CRC is checked
    except StateError:
        raise
    except Exception as exc:  # noqa: BLE001 - bad header, CRC, truncation, decompression: all "unreadable"
        raise StateError(f"{key!r} cannot be read: {type(exc).__name__}: {exc}") from None
    if len(data) != nbytes:
        raise StateError(f"{key!r} has {len(data)} bytes of data, expected {nbytes}")
    arr = np.frombuffer(data, dtype=got_dtype).reshape(shape, order="F" if fortran else "C")
    return np.array(arr, order="C")  # own, writable, C-contiguous copy


def learned_snapshot(estimator) -> dict[str, np.ndarray] | None:
    """The estimator's snapshot when it holds something learned and can be restored as it is; None for
    an estimator that never stepped its tracker (a snapshot with the online β and health parts but no
    tracker state matches neither template of :func:`monitor.state_check.check_snapshot`, and there is
    nothing in it worth keeping)."""
    snap = estimator.snapshot()
    _, after = estimator.snapshot_templates()
    return snap if set(snap) == set(after) else None


#: joins machine and axis in a state file's name: a character no machine or axis name may hold
#: (:data:`feedio.limits.NAME_PATTERN`), so two axes never share a file (``cell_3``/``X`` and ``cell``/``3_X``
#: did with ``_``)
NAME_JOIN = "+"


class StateStore:
    """Where tracker snapshots live: ``<dir>/<machine>+<axis>.state.npz`` with ``state_dir``,
    else next to the model file (``axis-x.model.toml`` → ``axis-x.model.state.npz``).

    A state saved by an older feedmon as ``<dir>/<machine>_<axis>.state.npz`` (a name two axes could
    share) is read when the new name does not exist yet — used only when it holds this axis' state
    (its recorded machine and axis), and removed once this axis' state is saved under the new name."""

    def __init__(self, state_dir: str | os.PathLike | None = None) -> None:
        self.dir = None if state_dir is None else Path(state_dir)
        if self.dir is not None and not self.dir.is_dir():
            self.dir.mkdir(parents=True, exist_ok=True)  # OSError: reported by the CLI
        self._legacy_read: set[Path] = set()  # legacy files this store restored an axis from

    def path_for(self, ax: AxisRuntime) -> Path:
        if self.dir is not None:
            return self.dir / f"{ax.model.machine}{NAME_JOIN}{ax.model.axis}.state.npz"
        mp = Path(ax.status.model_path)
        stem = mp.name[:-5] if mp.name.endswith(".toml") else mp.name
        return mp.with_name(stem + ".state.npz")

    def _legacy_path(self, ax: AxisRuntime) -> Path | None:
        return None if self.dir is None else self.dir / f"{ax.model.machine}_{ax.model.axis}.state.npz"

    @staticmethod
    def _tmp(path: Path) -> Path:
        return path.with_name(path.name + ".tmp")

    def save(self, ax: AxisRuntime) -> Path | None:
        """Atomically write the axis' snapshot (+ model hash, axis, time); on any failure no
        ``.tmp`` file is left behind and an existing state is untouched. None (nothing written) when
        the tracker never learned a sample (:func:`learned_snapshot`: nothing worth keeping, and a
        state saved earlier stays as it is)."""
        path = self.path_for(ax)
        snap = learned_snapshot(ax.estimator)
        if snap is None:
            return None
        snap = dict(snap)
        snap["meta.format"] = np.array(STATE_FORMAT, dtype=np.int64)
        snap["meta.model_sha256"] = np.array(ax.status.model_sha256)
        snap["meta.machine"] = np.array(ax.model.machine)
        snap["meta.axis"] = np.array(ax.model.axis)
        snap["meta.saved_unix"] = np.array(time.time())
        tmp = self._tmp(path)
        try:
            with open(tmp, "wb") as fh:
                np.savez(fh, **snap)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError, ValueError):
                tmp.unlink()
            raise
        with contextlib.suppress(OSError):  # make the rename itself durable (best effort)
            fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        legacy = self._legacy_path(ax)
        if legacy in self._legacy_read:  # this axis' state, now under its own name
            with contextlib.suppress(OSError):
                legacy.unlink()
            self._legacy_read.discard(legacy)
        ax.status.state_path = str(path)
        return path

    def load(self, ax: AxisRuntime, *, fresh: bool = False) -> StateLoad:
        """Restore the axis' tracker if a valid state for its model exists (see the module doc);
        with ``fresh`` only clean up (``--fresh``: the state is still saved there at exit).

        Returns a :class:`StateLoad`; ``ax.status.state`` is set to its origin. Never raises for
        the file's content: a bad file is ``unreadable`` (the axis keeps a fresh estimator)."""
        path = self.path_for(ax)
        ax.status.state_path = str(path)
        tmp = self._tmp(path)
        if tmp.exists():
            try:
                tmp.unlink()
                log.warning("removed %s, a partial tracker state left by an interrupted save", tmp)
            except OSError as exc:
                log.warning("cannot remove the partial tracker state %s: %s", tmp, exc)
        if fresh:
            return self._result(ax, "fresh", "fresh (--fresh)")
        legacy = self._legacy_path(ax)
        if not path.exists() and legacy is not None and legacy.exists():
            if self._legacy_axis(ax, legacy) != ax.key:  # another axis' (the old names were ambiguous)
                return self._result(ax, "fresh", f"fresh (no saved state; {legacy.name} is another axis' state)")
            path = legacy
        if not path.exists():
            return self._result(ax, "fresh", "fresh (no saved state)")
        try:
            snap = self._read(ax, path)
        except _Ignored as why:
            log.warning("tracker state %s %s; ignoring it and starting fresh", path, why)
            return self._result(ax, "ignored", f"ignored ({why})")
        except Exception as exc:  # noqa: BLE001 - StateError, OSError, or anything else: never fatal
            reason = str(exc) if isinstance(exc, (StateError, OSError)) else f"{type(exc).__name__}: {exc}"
            log.warning("tracker state %s of %s is unreadable: %s; starting fresh", path, ax.status.name, reason)
            return self._result(ax, "unreadable", f"unreadable: {reason}")
        if path == legacy:
            self._legacy_read.add(legacy)
            log.info("tracker state of %s read from %s (the name of an older feedmon); it is saved as %s from now on",
                     ax.status.name, legacy, self.path_for(ax))
        age = time.time() - float(snap["meta.saved_unix"])
        when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(float(snap["meta.saved_unix"])))
        est = ax.estimator
        return self._result(ax, "restored", f"restored (saved {when}, {_age(age)}; {est.trained:,} samples "
                                            f"learned, dictionary {est.tracker.size} of {est.tracker.budget})")

    @staticmethod
    def _legacy_axis(ax: AxisRuntime, path: Path) -> tuple[str, str] | None:
        """``(machine, axis)`` a legacy state file records (None: unreadable — then it is read as this
        axis' and refused with the reason)."""
        try:
            arrays = read_state_file(path, *_layout(ax))
        except Exception:  # noqa: BLE001 - StateError, OSError: judged again (and reported) when read
            return ax.key
        return str(arrays["meta.machine"][()]), str(arrays["meta.axis"][()])

    @staticmethod
    def _result(ax: AxisRuntime, origin: str, detail: str) -> StateLoad:
        ax.status.state = origin
        return StateLoad(origin, detail)

    def _read(self, ax: AxisRuntime, path: Path) -> dict[str, np.ndarray]:
        """Read, check and restore; raises :class:`StateError` (unusable) or :class:`_Ignored` (other model)."""
        snap = read_state_file(path, *_layout(ax))
        saved = str(snap["meta.model_sha256"][()])
        if saved != ax.status.model_sha256:
            raise _Ignored(f"was saved with another model file (sha256 {saved[:12]}…, now "
                           f"{ax.status.model_sha256[:12]}…)")
        fmt = int(snap["meta.format"])
        if fmt != STATE_FORMAT:
            raise StateError(f"state format {fmt}; this feedmon reads format {STATE_FORMAT}")
        names = (str(snap["meta.machine"][()]), str(snap["meta.axis"][()]))
        if names != ax.key:
            raise StateError(f"it is the state of axis {names[0]}/{names[1]}")
        saved_unix = float(snap["meta.saved_unix"])
        if not (math.isfinite(saved_unix) and 0.0 <= saved_unix <= 1e11):
            raise StateError(f"its time of saving {saved_unix!r} is not a plausible Unix time")
        ax.estimator.restore({k: v for k, v in snap.items() if not k.startswith("meta.")})
        return snap


def _layout(ax: AxisRuntime) -> tuple[dict[str, tuple[np.dtype, tuple[int, ...]]], frozenset[str]]:
    """The entries of a state file of this axis' model (:func:`read_state_file`'s ``layout``, ``optional``)."""
    before, after = ax.estimator.snapshot_templates()
    layout = {k: (v.dtype, v.shape) for k, v in after.items()}
    layout.update(_META)
    return layout, frozenset(set(after) - set(before))


class _Ignored(Exception):
    """A well-formed state of another model file."""
