"""``feedmon recover``: salvage MCAP files whose writer was killed (SIGKILL) or that were cut off."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from feedio.mcapio import TrialFileError, read_trial
from feedmon.cli import main
from replay.recover import RECOVER_METADATA_NAME, recover

REPO = Path(__file__).resolve().parents[1]
TS = 0.001  # 1 kHz samples
BLOCK = 10  # samples per block; a block every 10 ms of wall time, so controller time ≈ wall time

# A live recorder: writes 1 kHz sample blocks in real time, closes a chunk every second
# (TrialWriter's controller-time rule plus flush_if_due on the wall clock), and logs to a
# side file how many samples it has produced ("wrote N") and how many were on disk after
# each completed flush ("flushed N"). It never closes the file: the test kills it.
WRITER = textwrap.dedent(
    """
    import sys, time
    from feedio import schema as S
    from feedio.mcapio import TrialWriter

    path, log_path = sys.argv[1], sys.argv[2]
    TS, BLOCK = {TS!r}, {BLOCK!r}
    meta = S.TrialMeta(Ts=TS, form="force-input", machine="mill", axis="X",
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))
    log = open(log_path, "w", buffering=1)
    w = TrialWriter(path, meta, chunk_seconds=1.0)
    orig_flush = w.flush

    def flush():
        orig_flush()
        log.write(f"flushed {{n}}\\n")

    w.flush = flush
    n = 0
    t_start = time.monotonic()
    while True:
        t = [(n + i) * TS for i in range(BLOCK)]
        w.write_samples(S.SampleBlock(machine="mill", axis="X", seq=n, t=t, v_ref=[0.01] * BLOCK,
                                      v_meas=[0.0099] * BLOCK, u=[float(n + i) for i in range(BLOCK)]))
        n += BLOCK
        log.write(f"wrote {{n}}\\n")
        w.flush_if_due()
        time.sleep(max(0.0, t_start + n * TS - time.monotonic()))
    """
).format(TS=TS, BLOCK=BLOCK)


def _log_values(log: Path, what: str) -> list[int]:
    out = []
    for line in log.read_text().splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0] == what:
            out.append(int(parts[1]))
    return out


def _messages_plain(path: Path) -> int:
    """Number of messages via mcap's plain (seeking, summary-based) reader; raises on a broken file."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        n = sum(1 for _ in reader.iter_messages())
        assert n == summary.statistics.message_count
        return n


def _records(path: Path, *, skip=(RECOVER_METADATA_NAME,)):
    """Comparable content of a complete MCAP file: header, schemas, channels, metadata, chunks, messages."""
    out = []
    with open(path, "rb") as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, DataEnd):
                break
            if isinstance(rec, Header):
                out.append(("header", rec.profile, rec.library))
            elif isinstance(rec, Metadata):
                if rec.name not in skip:
                    out.append(("metadata", rec.name, dict(rec.metadata)))
            elif isinstance(rec, Chunk):
                out.append(("chunk", rec.compression, rec.message_start_time, rec.message_end_time))
                for r in breakup_chunk(rec, validate_crc=True):
                    if isinstance(r, Schema):
                        out.append(("schema", r.id, r.name, r.encoding, r.data))
                    elif isinstance(r, Channel):
                        out.append(("channel", r.id, r.topic, r.message_encoding, r.schema_id, dict(r.metadata)))
                    elif isinstance(r, Message):
                        out.append(("message", r.channel_id, r.log_time, r.publish_time, r.sequence, r.data))
    return out


# ---- the real thing: a recorder killed with SIGKILL ---------------------------------------------
def test_recover_after_sigkill(tmp_path):
    broken, log, fixed = tmp_path / "live.mcap", tmp_path / "live.log", tmp_path / "fixed.mcap"
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, str(script), str(broken), str(log)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        # run until three chunks are on disk, then kill in the middle of the fourth second
        while not (log.exists() and len(_log_values(log, "flushed")) >= 3):
            assert proc.poll() is None, proc.communicate()[1].decode()
            assert time.monotonic() < deadline, "writer did not flush three chunks within 30 s"
            time.sleep(0.02)
        time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    produced = _log_values(log, "wrote")[-1]  # samples the writer had produced when it died
    flushed = _log_values(log, "flushed")[-1]  # samples known to be on disk (flush completed)
    assert produced > flushed >= 2000

    # the killed file: no footer, so neither read_trial nor mcap's summary reader can use it
    with pytest.raises(TrialFileError, match="truncated"):
        read_trial(broken)
    with pytest.raises(Exception):  # noqa: B017 - mcap raises several unrelated types here
        _messages_plain(broken)

    assert main(["recover", str(broken), "-o", str(fixed), "--json"]) == 0
    n_msgs = _messages_plain(fixed)  # the plain reader is happy now
    trial = read_trial(fixed)  # and so is feedmon's
    recovered = len(trial)
    assert n_msgs == recovered // BLOCK
    # nothing that was flushed before the kill is lost; at most ~1 s (one open chunk) + one chunk is
    assert flushed <= recovered <= produced
    print(f"produced {produced}, flushed {flushed}, recovered {recovered}")
    assert produced - recovered <= 2.0 / TS + BLOCK, (produced, flushed, recovered)
    # the samples are the writer's, in order, without holes
    assert trial.seq.tolist() == list(range(recovered))
    assert trial.u.tolist() == [float(i) for i in range(recovered)]
    assert trial.t[-1] == pytest.approx((recovered - 1) * TS)
    assert trial.meta.machine == "mill" and trial.meta.Ts == TS
    # the recovery is recorded in the file
    with open(fixed, "rb") as f:
        rec_meta = [m for m in make_reader(f).iter_metadata() if m.name == RECOVER_METADATA_NAME]
    assert len(rec_meta) == 1 and rec_meta[0].metadata["complete"] == "false"
    assert int(rec_meta[0].metadata["messages"]) == n_msgs


def test_recover_report(tmp_path, simulated, capsys):
    src = simulated("shaker-constant", seed=1, duration=4.0)
    capsys.readouterr()
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    out = tmp_path / "out.mcap"
    assert main(["recover", str(cut), "-o", str(out), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["complete"] is False and rep["data_complete"] is False
    assert rep["bytes_used"] + rep["bytes_dropped"] == len(data) * 2 // 3 and rep["bytes_dropped"] > 0
    assert "cut off" in rep["stop_reason"]
    chans = rep["channels"]
    assert set(chans) == {"/linear-drive/Z/samples", "/linear-drive/Z/truth"}
    assert sum(c["messages"] for c in chans.values()) == rep["messages"] == _messages_plain(out)
    assert rep["last_log_time_ns"] == max(c["last_log_time_ns"] for c in chans.values())
    assert chans["/linear-drive/Z/samples"]["message_encoding"] == "json"
    assert chans["/linear-drive/Z/samples"]["schema"] == "feedmon.SampleBlock"
    # the human-readable report names channels, last log time and the dropped bytes
    assert main(["recover", str(cut), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "/linear-drive/Z/samples" in text and "last log time" in text
    assert f"{rep['bytes_dropped']} byte(s) dropped" in text


# ---- healthy file: lossless copy ----------------------------------------------------------------
def test_recover_healthy_file_is_lossless(tmp_path, simulated, capsys):
    src = simulated("shaker-constant", seed=1, duration=3.0)
    capsys.readouterr()
    out = tmp_path / "copy.mcap"
    assert main(["recover", str(src), "-o", str(out)]) == 0
    assert "nothing lost" in capsys.readouterr().out
    assert _records(out) == _records(src)  # same header, metadata, schemas, channels, chunks, messages
    assert _messages_plain(out) == _messages_plain(src)
    # byte for byte: the whole data section of the source, then the recover record and a new summary
    orig, copy = src.read_bytes(), out.read_bytes()
    with open(src, "rb") as f:
        rd = StreamReader(f, emit_chunks=True)
        for rec in rd.records:
            if isinstance(rec, DataEnd):
                break
            data_end = f.tell() - 13  # DataEnd record = opcode + length + crc
    assert copy[:data_end] == orig[:data_end]
    a, b = read_trial(src), read_trial(out)
    assert (a.t == b.t).all() and (a.v_meas == b.v_meas).all() and a.meta == b.meta
    assert (a.truth.force == b.truth.force).all()
    with open(out, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta[RECOVER_METADATA_NAME]["complete"] == "true"
    assert meta[RECOVER_METADATA_NAME]["bytes_dropped"] == "0"


def test_recover_healthy_file_of_another_zstd_level_keeps_its_content(tmp_path, simulated, capsys):
    """A file whose chunks another writer compressed at zstd level 3 (mcap's default; feedmon writes 1):
    recover rewrites it at its own level with the same records — schemas, channels, metadata, chunk
    times, messages — and says nothing was lost."""
    from feedio.mcapio import TrialWriter, iter_blocks

    src = simulated("shaker-constant", seed=2, duration=3.0)
    tr = read_trial(src)
    level3 = tmp_path / "level3.mcap"
    with TrialWriter(level3, tr.meta, start="2024-05-01T08:00:00Z", compression_level=3) as w:
        for kind, block in iter_blocks(src, kinds=("samples", "truth")):
            if kind == "samples":
                w.write_samples(block)
            else:
                w.write_truth(block, tr.meta.machine, tr.meta.axis)
    capsys.readouterr()
    out = tmp_path / "copy.mcap"
    assert main(["recover", str(level3), "-o", str(out)]) == 0
    assert "nothing lost" in capsys.readouterr().out
    assert _records(out) == _records(level3)


def test_recover_summary_lost_keeps_all_messages(tmp_path, simulated):
    """Cut inside the summary section: every message is still there."""
    src = simulated("shaker-constant", seed=1, duration=3.0)
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:-30])
    rep = recover(cut, tmp_path / "out.mcap")
    assert not rep.complete and rep.data_complete
    assert rep.messages == _messages_plain(src)
    assert _records(tmp_path / "out.mcap") == _records(src)


# ---- anything cut off or damaged: a valid file or a clear error, never a crash ------------------
@pytest.fixture(scope="module")
def trial_bytes(tmp_path_factory):
    path = tmp_path_factory.mktemp("recover") / "src.mcap"
    assert main(["simulate", "shaker-constant", "-o", str(path), "--seed", "2", "--duration", "3"]) == 0
    data = path.read_bytes()
    return data, _messages_plain(path)


def _check_recover(tmp_path: Path, data: bytes, total: int, name: str) -> int:
    src, out = tmp_path / f"{name}.mcap", tmp_path / f"{name}-out.mcap"
    src.write_bytes(data)
    if out.exists():
        out.unlink()
    try:
        rep = recover(src, out)
    except ValueError as exc:
        assert str(src) in str(exc)  # a clear error naming the file
        assert not out.exists()
        return -1
    n = _messages_plain(out)  # always a valid, complete MCAP file
    assert n == rep.messages <= total
    assert rep.bytes_used + rep.bytes_dropped == len(data)
    assert not list(tmp_path.glob(f".{name}-out.mcap.*"))  # no temporary file left behind
    return n


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.0, 1.0))
def test_recover_truncated_anywhere(tmp_path, trial_bytes, frac):
    data, total = trial_bytes
    cut = int(round(frac * len(data)))
    n = _check_recover(tmp_path, data[:cut], total, "trunc")
    if cut == len(data):
        assert n == total


def test_recover_truncation_is_monotonic(tmp_path, trial_bytes):
    """Every byte offset in the first 300 bytes, and offsets across the file: more bytes never recover less."""
    data, total = trial_bytes
    offsets = list(range(0, 300)) + list(range(300, len(data), max(1, len(data) // 150))) + [len(data)]
    last = -1
    for cut in offsets:
        n = _check_recover(tmp_path, data[:cut], total, "mono")
        assert n >= last, (cut, n, last)
        last = max(last, n)
    assert last == total


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pos=st.floats(0.0, 1.0), xor=st.integers(1, 255))
def test_recover_corrupt_byte(tmp_path, trial_bytes, pos, xor):
    data, total = trial_bytes
    buf = bytearray(data)
    i = min(len(buf) - 1, int(pos * len(buf)))
    buf[i] ^= xor
    _check_recover(tmp_path, bytes(buf), total, "flip")


# ---- clear errors -------------------------------------------------------------------------------
def test_recover_not_an_mcap(tmp_path, capsys):
    bad = tmp_path / "notes.txt"
    bad.write_text("this is not a recording\n")
    assert main(["recover", str(bad), "-o", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "not an MCAP file" in err
    assert not (tmp_path / "x.mcap").exists()
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert main(["recover", str(empty), "-o", str(tmp_path / "x.mcap")]) == 2
    assert str(empty) in capsys.readouterr().err
    assert main(["recover", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "missing.mcap" in capsys.readouterr().err


def test_recover_refuses_to_overwrite_input(tmp_path, simulated, capsys):
    src = simulated("shaker-constant", seed=1, duration=3.0)
    capsys.readouterr()
    before = src.read_bytes()
    assert main(["recover", str(src), "-o", str(src)]) == 2
    assert "is the input file" in capsys.readouterr().err
    assert src.read_bytes() == before


def test_recover_nothing_complete_exit_1(tmp_path, trial_bytes, capsys):
    """Cut before the first chunk is complete: a valid (empty) file and exit code 1."""
    data, _ = trial_bytes
    capsys.readouterr()
    with open(tmp_path / "probe.mcap", "wb") as f:
        f.write(data)
    with open(tmp_path / "probe.mcap", "rb") as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                first_chunk_end = f.tell()
                break
    cut = tmp_path / "early.mcap"
    cut.write_bytes(data[: first_chunk_end - 10])
    assert main(["recover", str(cut), "-o", str(tmp_path / "early-out.mcap")]) == 1
    assert "0 message(s)" in capsys.readouterr().out
    assert _messages_plain(tmp_path / "early-out.mcap") == 0


def test_recover_skips_unknown_record_types(tmp_path, trial_bytes):
    """Records with opcodes this reader does not know (MCAP user range) are skipped, not taken as damage."""
    import struct

    data, total = trial_bytes
    header_len = struct.unpack("<Q", data[9:17])[0]
    pos = 8 + 9 + header_len
    unknown = bytes([0x80]) + struct.pack("<Q", 5) + b"hello"
    n = _check_recover(tmp_path, data[:pos] + unknown + data[pos:], total, "unknown")
    assert n == total


# ---- resynchronisation after damage (issue 9 #12) --------------------------------------------------
@pytest.fixture(scope="module")
def long_trial(tmp_path_factory):
    """A 12 s trial: 12 chunks of ~1 s; (bytes, [(chunk offset, record length, messages)], total messages)."""
    folder = tmp_path_factory.mktemp("recover-long")
    path = folder / "long.mcap"
    # 1 kHz: each ~1 s chunk holds > 128 kB of JSON, i.e. several zstd blocks, so a flip late in a chunk
    # leaves its start (with the channel declarations) decompressible, whatever the messages hold
    (folder / "rate.toml").write_text("rate = 1000.0\n")
    assert main(["simulate", "shaker-constant", "-o", str(path), "--seed", "4", "--duration", "12",
                 "--created", "2024-05-01T08:00:00Z", "--config", str(folder / "rate.toml")]) == 0
    data = path.read_bytes()
    chunks = []
    with open(path, "rb") as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                end = f.tell()
                n = sum(isinstance(r, Message) for r in breakup_chunk(rec))
                chunks.append((end, n))
    # a chunk record's start: its end minus its length (opcode + length + fields + data)
    out = []
    for end, n in chunks:
        start = data.rfind(b"\x06", 0, end)
        while True:
            length = int.from_bytes(data[start + 1:start + 9], "little")
            if start + 9 + length == end:
                break
            start = data.rfind(b"\x06", 0, start)
        out.append((start, end - start, n))
    assert len(out) >= 11
    return data, out, sum(n for _, _, n in out)


def _recover_bytes(tmp_path: Path, data: bytes, name: str, **kw):
    src, out = tmp_path / f"{name}.mcap", tmp_path / f"{name}-fixed.mcap"
    src.write_bytes(data)
    rep = recover(src, out, **kw)
    assert _messages_plain(out) == rep.messages
    return rep, out


def test_damaged_first_chunk_keeps_every_other_chunk(tmp_path, long_trial):
    """One flipped byte in the first chunk (which also holds the channel declarations): its messages
    are dropped and reported with the offset, every message of the other chunks is kept — with and
    without the summary section (the declarations then come from the damaged chunk's intact start)."""
    data, chunks, total = long_trial
    start, length, n0 = chunks[0]
    buf = bytearray(data)
    buf[start + length - 50] ^= 0x40  # late in the compressed data: the start still decompresses
    for name, blob in (("flip", bytes(buf)), ("flip-cut", bytes(buf[: chunks[-1][0] + chunks[-1][1]]))):
        rep, out = _recover_bytes(tmp_path, blob, name)
        assert rep.messages == total - n0, (name, rep.summary())
        assert rep.chunks == len(chunks) - 1 and rep.chunks_dropped == 1
        s = rep.skipped[0]
        # the messages that decoded before the damage are counted (zstd decodes a chunk block by block)
        assert (s.offset, s.length) == (start, length) and "damaged chunk" in s.reason
        assert 0 < s.messages_dropped <= n0 and rep.damaged_messages == s.messages_dropped
        tr = read_trial(out)
        first = tr.seq[0]
        assert tr.seq.tolist() == list(range(first, first + len(tr)))  # the rest, without holes
        text = rep.summary()
        assert f"bytes {start}…{start + length}" in text and f"{s.messages_dropped} message(s) dropped" in text
    # --salvage-damaged keeps the messages of the damaged chunk too (their bytes may be wrong)
    rep, _ = _recover_bytes(tmp_path, bytes(buf), "flip-salvage", salvage_damaged=True)
    assert rep.messages >= total - n0 and 0 < rep.damaged_messages <= n0


def test_zeroed_range_across_records_resynchronises(tmp_path, long_trial):
    """3000 zero bytes across the boundary of chunks 4 and 5 (a bad sector): recover skips exactly the
    damaged chunks and keeps all the others."""
    data, chunks, total = long_trial
    s4, l4, n4 = chunks[4]
    s5, l5, n5 = chunks[5]
    a = s5 - 1500
    buf = bytearray(data)
    buf[a:a + 3000] = bytes(3000)
    rep, out = _recover_bytes(tmp_path, bytes(buf), "zeroed")
    assert rep.messages == total - n4 - n5, rep.summary()
    assert rep.skipped_ranges >= 1 and rep.skipped[0].offset == s4
    assert rep.chunks == len(chunks) - 2


def test_full_disk_episode_of_the_old_writer(tmp_path, long_trial):
    """What a writer without staging left after a full disk: the first half of chunk 6, then (space
    back) the whole chunk 6 again and everything after. recover skips the half-written chunk and keeps
    every message once (the old recover kept 382 of 985 blocks)."""
    data, chunks, total = long_trial
    s6, l6, n6 = chunks[6]
    episode = data[:s6] + data[s6:s6 + l6 // 2] + data[s6:]
    rep, out = _recover_bytes(tmp_path, episode, "episode")
    assert rep.messages == total, rep.summary()
    assert rep.skipped[0].offset == s6 and rep.skipped[0].length == l6 // 2
    tr = read_trial(out)
    assert tr.seq.tolist() == list(range(len(tr)))  # every sample once
    # the same without the retry: the half chunk is lost, everything else kept
    lost = data[:s6] + data[s6:s6 + l6 // 2] + data[s6 + l6:]
    rep, _ = _recover_bytes(tmp_path, lost, "lost")
    assert rep.messages == total - n6


def test_cut_inside_the_last_chunk_keeps_its_complete_records(tmp_path):
    """A writer killed while writing one big chunk (zstd works in 128 kB blocks): the records of the
    blocks that made it to the disk are kept, in order, without holes."""
    from feedio import schema as S
    from feedio.mcapio import TrialWriter

    meta = S.TrialMeta(Ts=TS, form="force-input", machine="mill", axis="X",
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))
    path = tmp_path / "big.mcap"
    with TrialWriter(path, meta, chunk_seconds=100.0, start="2024-05-01T08:00:00Z") as w:
        for k in range(3000):
            t = [(k * BLOCK + i) * TS for i in range(BLOCK)]
            w.write_samples(S.SampleBlock(machine="mill", axis="X", seq=k * BLOCK, t=t, v_ref=[0.01] * BLOCK,
                                          v_meas=[0.0099] * BLOCK, u=[float(k * BLOCK + i) for i in range(BLOCK)]))
    data = path.read_bytes()
    with open(path, "rb") as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                end = f.tell()
                break
    rep, out = _recover_bytes(tmp_path, data[: end - len(rec.data) // 4], "tail")  # a quarter of it missing
    assert rep.chunks == 0 and rep.partial_chunks == 1 and 1000 < rep.partial_messages < 3000, rep.summary()
    assert rep.messages == rep.partial_messages and "Chunk record cut off" in rep.stop_reason
    tr = read_trial(out)
    assert tr.seq.tolist() == list(range(len(tr))) and tr.u.tolist() == [float(i) for i in range(len(tr))]
