"""Tracker state files (``monitor.state``): round trip, what a restart says, and hostile files.

Everything goes through the real :class:`StateStore` (real ``.npz`` files on disk, the estimator's
real restore) and, for the daemon, a real ``feedmon run`` process: a crafted state with the right
model hash, a decompression bomb, fuzzed files — each is refused with a reason and the axis starts
fresh; nothing crashes, hangs or grows without bound. Saving leaves no ``.tmp`` behind, not even
on a full disk, and one left by a killed process is removed at the next start.
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import signal
import subprocess
import time
import zipfile
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh
from monitor_proc import MonitorProc
from test_bad_input import blocks_of, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_blocks, read_trial
from kernels import _krlst_core as core
from monitor.axes import load_axes
from monitor.state import StateStore, read_state_file
from monitor.state_check import COUNT_MAX

PREFIX = "feedmon-state"
AXIS = ("linear-drive", "Z")


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "state", duration=6.0, seed=3, budget=100)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _axis(work):
    return load_axes([work / "z.model.toml"])[AXIS]


@pytest.fixture(scope="module")
def saved(work, tmp_path_factory):
    """A valid state file of the trained axis (the trial learned once), and that axis."""
    ax = _axis(work)
    for _, b in iter_blocks(work / "trial.mcap"):
        ax.estimator.process(b)
    assert ax.estimator.tracker.size == 100 and ax.estimator.trained > 1000
    path = StateStore(tmp_path_factory.mktemp("saved")).save(ax)
    return path, ax


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _write(path: Path, arrays: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def _load_fresh(work, state_dir: Path):
    """A fresh axis and what loading ``state_dir``'s state did to it."""
    ax = _axis(work)
    return ax, StateStore(state_dir).load(ax)


def _still_estimates(ax, trial) -> None:
    out = [ax.estimator.process(b) for b in blocks_of(trial, 0, 300, 50)]
    assert sum(len(o.t) for o in out) == 300
    assert np.isfinite(np.array([x for o in out for x in o.f_next], dtype=float)).all()


# ---- round trip and what a restart says ----------------------------------------------------------------
def test_state_roundtrip_and_mismatch_is_ignored(work, saved, tmp_path, caplog):
    path, ax = saved
    assert str(_arrays(path)["meta.model_sha256"]) == ax.status.model_sha256  # plain arrays only
    _write(tmp_path / "s" / path.name, _arrays(path))
    again, res = _load_fresh(work, tmp_path / "s")
    assert res.origin == "restored" == again.status.state
    assert again.estimator.tracker.size == ax.estimator.tracker.size and again.estimator.trained == ax.estimator.trained
    np.testing.assert_array_equal(again.estimator.tracker.mu, ax.estimator.tracker.mu)
    np.testing.assert_array_equal(again.estimator.tracker.Q, ax.estimator.tracker.Q)
    model = tmp_path / "z.model.toml"  # another model file: its state is meaningless
    model.write_text((work / "z.model.toml").read_text() + "\n# edited\n")
    edited = load_axes([model])[AXIS]
    with caplog.at_level(logging.WARNING, logger="monitor.state"):
        res = StateStore(tmp_path / "s").load(edited)
    assert res.origin == "ignored" and "another model file" in caplog.text and "another model file" in res.detail
    assert edited.estimator.tracker.size == 0
    (tmp_path / "s" / path.name).write_bytes(b"garbage")
    assert _load_fresh(work, tmp_path / "s")[1].origin == "unreadable"
    default = StateStore(None).path_for(edited)
    assert default.name == "z.model.state.npz" and default.parent == tmp_path


def test_restored_state_says_when_it_was_saved_and_what_it_had_learned(work, saved, tmp_path):
    path, ax = saved
    arrays = _arrays(path)
    arrays["meta.saved_unix"] = np.array(time.time() - 3 * 3600.0)  # as if saved 3 h ago (then SIGKILL)
    _write(tmp_path / path.name, arrays)
    _, res = _load_fresh(work, tmp_path)
    when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(float(arrays["meta.saved_unix"])))
    assert res.origin == "restored"
    assert f"saved {when}" in res.detail and "3.0 h ago" in res.detail, res.detail
    assert f"{ax.estimator.trained:,} samples learned" in res.detail and "dictionary 100 of 100" in res.detail


# ---- crafted states with the right model hash ----------------------------------------------------------------
def _ist(a, slot, value):
    a["tracker.ist"] = a["tracker.ist"].copy()
    a["tracker.ist"][slot] = value


def _set(key, fn):
    def edit(a):
        a[key] = fn(a[key].copy())
    return edit


def _below_diagonal(Q):
    Q[1, 0] += 1e-3  # the core keeps the strict upper triangle: the rest must stay zero
    return Q


def _free_slot(a):
    order, n = a["tracker.order"], int(a["tracker.ist"][core.I_N])
    free = int(order[n])  # dictionary 100 of 101 slots: one is free
    K = a["tracker.K"].copy()
    K[: free, free] = 0.5  # its column of the upper triangle, where a free slot must be empty
    a["tracker.K"] = K


def _scaled(key, factor):
    return _set(key, lambda x: x * factor)


CRAFTED = {  # name -> (edit of the valid arrays, words of the reason)
    "order 10**9": (_set("tracker.order", lambda o: np.where(o == o.max(), 10**9, o)), "not a permutation"),
    "I_N 10**6": (lambda a: _ist(a, core.I_N, 10**6), "dictionary size 1000000"),
    "high-water mark beyond the slots": (lambda a: _ist(a, core.I_HW, 10**6), "high-water mark"),
    "pending mode 7": (lambda a: _ist(a, core.I_QPEND, 7), "pending Q update is 7"),
    "negative step count": (lambda a: _ist(a, core.I_STEPS, -5), "step count"),
    "Q all NaN": (_set("tracker.Q", lambda q: np.full_like(q, np.nan)), "'tracker.Q' holds non-finite"),
    "Sigma with inf": (_set("tracker.D", lambda s: np.where(s == s.max(), np.inf, s)), "non-finite"),
    "Q below its triangle": (_set("tracker.Q", _below_diagonal), "on or below the diagonal"),
    "K entries in a free slot": (_free_slot, "'K' has entries in free slots"),
    "Q not the inverse of K": (_scaled("tracker.Q", 1.5), "Q is not the inverse of K_D"),
    "K not the kernel of the dictionary": (_scaled("tracker.Kd", 1.1), "not the kernel of its dictionary"),
    "Sigma beyond the prior": (_scaled("tracker.Dd", -1e3), "between 0 and the prior"),
    "mu 1e300": (_set("tracker.mu", lambda m: np.where(m != 0, 1e300, m)), "implausibly large"),
    "trained 1e300": (lambda a: a.update({"estimator.trained": np.array(1e300)}), "'estimator.trained' is float64"),
    "trained 2**62": (lambda a: a.update({"estimator.trained": np.array(2**62)}), f"outside 0…{COUNT_MAX}"),
    "trained negative": (lambda a: a.update({"estimator.trained": np.array(-1)}), "outside"),
    "other gamma": (lambda a: a.update({"tracker.gamma": np.array(50.0)}), "'tracker.gamma' is 50.0"),
    "other budget": (lambda a: a.update({"tracker.budget": np.array(10**6)}), "'tracker.budget'"),
    "forgetting inside the core": (_set("tracker.fst", lambda f: np.where(np.arange(f.size) == core.F_LAM, 0.5, f)),
                                   "forgetting"),
    "Q of another shape": (lambda a: a.update({"tracker.Q": np.zeros((5, 5))}), "'tracker.Q' has shape (5, 5), expected ("),
    "order as floats": (_set("tracker.order", lambda o: o.astype(np.float64)), "'tracker.order' is float64"),
    "a tracker array missing": (lambda a: a.pop("tracker.D"), "missing tracker.D"),
    "an unexpected entry": (lambda a: a.update({"evil": a.pop("tracker.mu")}), "unexpected entries 'evil.npy'"),
    "one entry too many": (lambda a: a.update({"evil": np.zeros(3)}), "entries; a state of this model has at most"),
    "another axis": (lambda a: a.update({"meta.axis": np.array("Y")}), "state of axis linear-drive/Y"),
    "another format": (lambda a: a.update({"meta.format": np.array(7)}), "state format 7"),
    "saved in year 5000": (lambda a: a.update({"meta.saved_unix": np.array(1e12)}), "not a plausible Unix time"),
    "a pickled object": (lambda a: a.update({"estimator.trained": np.array({"x": 1}, dtype=object)}),
                         "'estimator.trained' is object"),
}


@pytest.mark.parametrize("name", list(CRAFTED))
def test_crafted_state_with_the_right_hash_is_refused_and_the_axis_starts_fresh(name, work, saved, trial, tmp_path,
                                                                                caplog):
    edit, reason = CRAFTED[name]
    path, _ = saved
    arrays = _arrays(path)
    edit(arrays)
    _write(tmp_path / path.name, arrays)
    with caplog.at_level(logging.WARNING, logger="monitor.state"):
        ax, res = _load_fresh(work, tmp_path)
    assert res.origin == "unreadable" == ax.status.state, res
    assert res.detail.startswith("unreadable: ") and reason in res.detail, res.detail
    assert reason in caplog.text and str(tmp_path / path.name) in caplog.text
    assert ax.estimator.tracker.size == 0 and ax.estimator.trained == 0  # fresh, untouched
    _still_estimates(ax, trial)


# ---- sizes are capped before anything is decompressed ------------------------------------------------------
def _zip_with(path: Path, members: dict[str, bytes | tuple[int, int]], method=zipfile.ZIP_DEFLATED) -> Path:
    """A zip of ``members``: bytes, or ``(n, chunk)``: n zero bytes streamed in chunks (a bomb)."""
    with zipfile.ZipFile(path, "w", compression=method) as zf:
        for name, data in members.items():
            if isinstance(data, tuple):
                n, chunk = data
                with zf.open(name, "w", force_zip64=True) as fh:
                    block = bytes(chunk)
                    for _ in range(n // chunk):
                        fh.write(block)
            else:
                zf.writestr(name, data)
    return path


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


@pytest.mark.parametrize("inflated, refusal", [
    (2**30, "a state of this model has at most"),  # a ~1 MB file: more than any state of this model
    (2**28, "'tracker.Q.npy' would inflate to 268435456 bytes"),  # small enough: its zip directory says it
])
def test_decompression_bomb_is_refused_before_inflating(inflated, refusal, work, saved, tmp_path):
    import tracemalloc

    path, _ = saved
    members = {f"{k}.npy": _npy(v) for k, v in _arrays(path).items()}
    members["tracker.Q.npy"] = (inflated, 2**20)
    bomb = _zip_with(tmp_path / path.name, members)
    assert bomb.stat().st_size < 2_000_000
    tracemalloc.start()
    try:
        ax, res = _load_fresh(work, tmp_path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert res.origin == "unreadable" and refusal in res.detail, res.detail
    assert peak < 50 * 2**20, f"peak {peak / 2**20:.0f} MiB while refusing"


def test_npy_header_lying_about_its_shape_is_refused_before_its_data(work, saved, tmp_path):
    from numpy.lib import format as npy

    path, _ = saved
    members = {f"{k}.npy": _npy(v) for k, v in _arrays(path).items()}
    hdr = io.BytesIO()  # a header claiming 10**12 float64 (8 TB), and no data
    npy.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)})
    members["tracker.mu.npy"] = hdr.getvalue()
    _zip_with(tmp_path / path.name, members, method=zipfile.ZIP_STORED)
    ax, res = _load_fresh(work, tmp_path)
    assert res.origin == "unreadable" and "shape (1000000000000,)" in res.detail, res.detail


def test_too_many_entries_or_a_huge_file_are_refused_unread(work, saved, tmp_path):
    path, _ = saved
    members = {f"{k}.npy": _npy(v) for k, v in _arrays(path).items()}
    n = len(members)
    members.update({f"x{i}.npy": b"" for i in range(100)})
    (tmp_path / "a").mkdir()
    _zip_with(tmp_path / "a" / path.name, members)
    assert f"{n + 100} entries; a state of this model has at most {n}" in _load_fresh(work, tmp_path / "a")[1].detail
    (tmp_path / "b").mkdir()
    with open(tmp_path / "b" / path.name, "wb") as fh:  # 64 MB: beyond any state of this model
        fh.truncate(64 * 2**20)
    res = _load_fresh(work, tmp_path / "b")[1]
    assert res.origin == "unreadable" and "a state of this model has at most" in res.detail, res.detail


@pytest.mark.parametrize("kind", ["fifo", "directory", "device"])
def test_a_state_path_that_is_not_a_regular_file_is_refused_without_blocking(kind, work, tmp_path):
    import os

    target = _axis_state_path(tmp_path)
    if kind == "fifo":
        os.mkfifo(target)  # opening it for reading would wait for a writer forever
    elif kind == "directory":
        target.mkdir()
    else:
        target.symlink_to("/dev/zero")  # endless zeros
    ax, res = _load_fresh(work, tmp_path)
    assert res.origin == "unreadable" and "not a regular file" in res.detail, res.detail


def test_read_state_file_needs_every_entry_of_the_layout(saved):
    path, _ = saved
    arrays = _arrays(path)
    layout = {k: (v.dtype, v.shape) for k, v in arrays.items() if not k.startswith("meta.")}
    layout["estimator.extra"] = (np.dtype(np.int64), ())
    with pytest.raises(ValueError, match="missing entries estimator.extra"):
        read_state_file(path, {**layout, **{k: (v.dtype, v.shape) for k, v in arrays.items() if k.startswith("meta.")}})


# ---- fuzzing: mutated, truncated and crafted files, a fixed number of cases -----------------------------------
def _mutations(valid: bytes, arrays: dict[str, np.ndarray], rng: np.random.Generator):
    n = len(valid)
    yield "empty", b""
    yield "junk", rng.bytes(4096)
    for _ in range(40):
        cut = int(rng.integers(0, n))
        yield f"truncated at {cut}", valid[:cut]
    for _ in range(120):
        data = bytearray(valid)
        for pos in rng.integers(0, n, size=int(rng.integers(1, 9))):
            data[pos] = int(rng.integers(0, 256))
        yield "bytes flipped", bytes(data)
    keys = sorted(arrays)
    for _ in range(100):
        a = dict(arrays)
        key = keys[int(rng.integers(len(keys)))]
        kind = int(rng.integers(6))
        old = a[key]
        if kind == 0:  # random values of the right dtype and shape
            if old.dtype.kind == "f":
                a[key] = rng.standard_normal(old.shape) * 10.0 ** rng.integers(-300, 300)
            elif old.dtype.kind in "iu":
                a[key] = rng.integers(-(2**62), 2**62, size=old.shape, dtype=np.int64)
            else:
                a[key] = np.array("x" * int(rng.integers(0, 100)))
        elif kind == 1:  # another shape
            a[key] = np.zeros(tuple(int(x) for x in rng.integers(0, 4, size=int(rng.integers(0, 3)))),
                              dtype=old.dtype if old.dtype.kind != "U" else np.float64)
        elif kind == 2:  # another dtype
            a[key] = old.astype(np.float32 if old.dtype.kind != "f" else np.int64) if old.dtype.kind != "U" else \
                np.array(3.0)
        elif kind == 3:  # one element replaced by an extreme value
            flat = old.reshape(-1).copy()
            if flat.size and old.dtype.kind in "fiu":
                extremes = [np.nan, np.inf, -1e300, 1e300] if old.dtype.kind == "f" else [-1, 10**6, 2**62, -(2**63)]
                flat[int(rng.integers(flat.size))] = extremes[int(rng.integers(len(extremes)))]
                a[key] = flat.reshape(old.shape)
        elif kind == 4:  # random bits of its data flipped (the file itself stays a valid npz)
            raw = bytearray(old.tobytes())
            for pos in rng.integers(0, max(len(raw), 1), size=int(rng.integers(1, 9))):
                if raw:
                    raw[pos] ^= 1 << int(rng.integers(8))
            a[key] = np.frombuffer(bytes(raw), dtype=old.dtype).reshape(old.shape)
        else:
            a.pop(key)
        buf = io.BytesIO()
        np.savez(buf, **a)
        yield f"{key} changed ({kind})", buf.getvalue()


def test_fuzzed_state_files_never_crash(work, saved, trial, tmp_path):
    """262 damaged files, every load ends as restored/unreadable/ignored — never an exception, hang or crash
    (a crash would take pytest down); a state that is restored must then estimate."""
    path, _ = saved
    valid, arrays = path.read_bytes(), _arrays(path)
    rng = np.random.default_rng(20240611)
    target = tmp_path / path.name
    ax = _axis(work)
    store = StateStore(tmp_path)
    seen: dict[str, int] = {}
    for what, data in _mutations(valid, arrays, rng):
        target.write_bytes(data)
        res = store.load(ax)
        seen[res.origin] = seen.get(res.origin, 0) + 1
        assert res.origin in ("restored", "unreadable", "ignored"), (what, res)
        if res.origin == "restored":
            out = ax.estimator.process(blocks_of(trial, 0, 20, 20)[0])
            assert out is not None and len(out.t) == 20, what
            ax = _axis(work)  # a fresh one for the next case
        else:
            assert ax.estimator.tracker.size == 0 and ax.estimator.trained == 0, what  # untouched
    assert seen.get("unreadable", 0) > 150 and sum(seen.values()) == 262, seen


# ---- saving: atomic, no .tmp left, stale .tmp removed ------------------------------------------------------
@contextlib.contextmanager
def _full_directory(base: Path):
    """A directory where a state file cannot be written: a 64 KiB tmpfs (we are root in this sandbox),
    else this process' file-size limit lowered to 16 KiB (writes fail with EFBIG)."""
    d = base / "full"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode == 0:
        try:
            yield d, "No space left"
        finally:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)
        return
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (16 * 1024, hard))
    try:
        yield d, "File too large"
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)


def test_failed_save_leaves_no_tmp_and_keeps_the_old_state(saved, tmp_path):
    _, ax = saved
    with _full_directory(tmp_path) as (d, why):
        small = _axis_state_path(d)
        small.write_bytes(b"previous state")  # fits; the new one (260 kB) does not
        with pytest.raises(OSError, match=why):
            StateStore(d).save(ax)
        assert sorted(p.name for p in d.iterdir()) == [small.name]  # no .tmp left behind
        assert small.read_bytes() == b"previous state"


def _axis_state_path(d: Path) -> Path:
    return d / f"{AXIS[0]}+{AXIS[1]}.state.npz"


def test_stale_tmp_of_a_killed_save_is_removed_at_start(work, saved, tmp_path, caplog):
    path, _ = saved
    tmp = tmp_path / (path.name + ".tmp")
    tmp.write_bytes(path.read_bytes()[:1000])  # what a SIGKILL during a save leaves
    with caplog.at_level(logging.WARNING, logger="monitor.state"):
        ax, res = _load_fresh(work, tmp_path)
    assert not tmp.exists() and "interrupted save" in caplog.text and res.origin == "fresh"
    tmp.write_bytes(b"x")
    assert StateStore(tmp_path).load(_axis(work), fresh=True).origin == "fresh" and not tmp.exists()


# ---- the daemon ----------------------------------------------------------------------------------------------
def _replay_and_wait(mon, trial, n_expected):
    with T.open_session(connect=mon.endpoint) as s:
        pub = s.declare_publisher(T.samples_key(PREFIX, *AXIS), congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(pub, 15.0)
        for b in blocks_of(trial, 0, len(trial), 50):
            pub.put(S.encode(b))
        return wait_status(s, prefix=PREFIX, pid=mon.proc.pid,
                           pred=lambda x: x["axes"]["linear-drive/Z"]["estimates_out"] == n_expected)


def test_daemon_refuses_a_crafted_state_runs_and_saves_a_good_one(work, saved, trial, tmp_path):
    path, _ = saved
    arrays = _arrays(path)
    CRAFTED["order 10**9"][0](arrays)
    _write(_axis_state_path(tmp_path), arrays)
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--state-dir", str(tmp_path)], cwd=work)
    try:
        assert "tracker state unreadable: tracker state 'order' is not a permutation" in mon.stderr, mon.stderr
        st = _replay_and_wait(mon, trial, len(trial))
        assert st["axes"]["linear-drive/Z"]["state"]["origin"] == "unreadable"
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    assert "Traceback" not in mon.stderr
    ax, res = _load_fresh(work, tmp_path)  # replaced at exit by the state of this run
    assert res.origin == "restored" and ax.estimator.trained == len(trial) - 1


def test_restart_after_sigkill_says_how_old_the_state_is(work, trial, tmp_path):
    """Run 1 saves at SIGTERM; run 2 restores it and is killed (its learning is lost); run 3 says it restored
    the state of run 1, when that was saved and how much it had learned. A stale .tmp is removed at start."""
    n = len(trial)
    sf = _axis_state_path(tmp_path)
    tmp = sf.with_name(sf.name + ".tmp")
    tmp.write_bytes(b"PK\x03\x04 half a state")
    args = ["--model", "z.model.toml", "--state-dir", str(tmp_path)]
    mon = MonitorProc(prefix=PREFIX, args=[*args, "--fresh"], cwd=work)
    try:
        assert not tmp.exists() and "interrupted save" in mon.stderr, mon.stderr
        _replay_and_wait(mon, trial, n)
    finally:
        assert mon.stop() == 0, mon.stderr
    saved_at = float(_arrays(sf)["meta.saved_unix"])
    when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(saved_at))
    line = re.compile(rf"tracker state restored \(saved {re.escape(when)}, [^;]+ ago; {n - 1:,} samples learned, "
                      r"dictionary 100 of 100\)")
    for sig in (signal.SIGKILL, signal.SIGTERM):
        mon = MonitorProc(prefix=PREFIX, args=args, cwd=work)
        try:
            assert line.search(mon.stderr), mon.stderr
            if sig == signal.SIGKILL:
                _replay_and_wait(mon, trial, n)
        finally:
            rc = mon.stop(sig)
        assert rc == (-signal.SIGKILL if sig == signal.SIGKILL else 0), mon.stderr
        assert float(_arrays(sf)["meta.saved_unix"]) == saved_at or sig == signal.SIGTERM
    assert not tmp.exists()


# ---- file names --------------------------------------------------------------------------------------------
def _renamed_axis(work, tmp_path, machine: str, axis: str):
    text = (work / "z.model.toml").read_text().replace('machine = "linear-drive"', f'machine = "{machine}"')
    path = tmp_path / f"{machine}-{axis}.model.toml"
    path.write_text(text.replace('axis = "Z"', f'axis = "{axis}"'))
    return load_axes([path])[(machine, axis)]


def test_state_names_of_two_axes_never_collide(work, trial, tmp_path):
    """``cell_3``/``X`` and ``cell``/``3_X`` (the old ``<machine>_<axis>`` made both ``cell_3_X``): each keeps
    its own file and restores its own state."""
    store = StateStore(tmp_path / "s")
    a, b = _renamed_axis(work, tmp_path, "cell_3", "X"), _renamed_axis(work, tmp_path, "cell", "3_X")
    assert store.path_for(a) != store.path_for(b)
    blocks = [blk for _, blk in iter_blocks(work / "trial.mcap")]
    for ax, name in ((a, ("cell_3", "X")), (b, ("cell", "3_X"))):
        for blk in blocks[: 5 if ax is a else 9]:  # two different states
            ax.estimator.process(msgspec.structs.replace(blk, machine=name[0], axis=name[1]))
        store.save(ax)
    for ax in (a, b):
        again = _renamed_axis(work, tmp_path, *ax.key)
        res = StateStore(tmp_path / "s").load(again)
        assert res.origin == "restored" and again.estimator.trained == ax.estimator.trained > 0


def test_state_under_the_old_name_is_read_once_and_only_by_its_axis(work, saved, tmp_path, caplog):
    path, ax = saved
    d = tmp_path / "s"
    legacy = _write(d / "linear-drive_Z.state.npz", _arrays(path))
    other = _renamed_axis(work, tmp_path, "linear", "drive_Z")  # its old name was linear_drive_Z: not this file
    assert StateStore(d).load(other).origin == "fresh" and legacy.exists()
    lookalike = _renamed_axis(work, tmp_path, "linear-drive", "Z")
    store = StateStore(d)
    with caplog.at_level(logging.INFO, logger="monitor.state"):
        res = store.load(lookalike)
    assert res.origin == "restored" and "name of an older feedmon" in caplog.text
    assert lookalike.estimator.trained == ax.estimator.trained
    new = store.save(lookalike)
    assert new == d / "linear-drive+Z.state.npz" and new.exists() and not legacy.exists()
    # a file of the old name that holds another axis' state: not used, left alone
    _write(d / "cell_3_X.state.npz", {**_arrays(path), "meta.machine": np.array("cell"), "meta.axis": np.array("3_X")})
    mine = _renamed_axis(work, tmp_path, "cell_3", "X")
    res = StateStore(d).load(mine)
    assert res.origin == "fresh" and "another axis" in res.detail and (d / "cell_3_X.state.npz").exists()


def test_an_axis_that_learned_nothing_leaves_the_saved_state_alone(work, saved, tmp_path):
    path, _ = saved
    d = tmp_path / "s"
    kept = _write(d / path.name, _arrays(path))
    before = kept.read_bytes()
    idle = _axis(work)  # never saw a sample: its snapshot could not even be restored
    assert StateStore(d).save(idle) is None and kept.read_bytes() == before
