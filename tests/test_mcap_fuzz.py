"""Hostile and damaged trial files through the real reader and the real CLI.

Every outcome is either a correct read or a clear :class:`TrialFileError` naming the file (and
where useful the offset, channel and message) — never a traceback, a hang or unbounded memory.
The fuzz tests are sized to run in seconds."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, MetadataIndex, Schema
from truth_models import model_from_truth

from feedio import schema as S
from feedio.mcapfile import MAX_CHANNELS, MAX_CHUNK_BYTES, MAX_JSON_DEPTH, MAX_METADATA_BYTES, Limits
from feedio.mcapio import TrialFileError, read_trial
from feedio.mcapspec import MAGIC
from feedmon.cli import main
from replay.recover import recover
from replay.simulator import simulate_scenario, write_trial

REPO = Path(__file__).resolve().parents[1]
CREATED = "2024-05-01T08:00:00Z"


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> tuple[Path, bytes]:
    d = tmp_path_factory.mktemp("fuzz")
    path = d / "good.mcap"
    write_trial(simulate_scenario("shaker-constant", seed=3, duration=2.0, created=CREATED), path)
    return path, path.read_bytes()


def _expect_clear_error(path: Path, *needles: str) -> str:
    with pytest.raises(TrialFileError) as info:
        read_trial(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for n in needles:
        assert n in msg, msg
    return msg


# ---- a raw MCAP builder for hostile files -------------------------------------------------------
def _rec(obj) -> bytes:
    rb = RecordBuilder()
    obj.write(rb)
    return rb.end()


def _meta_json(machine="m", axis="X", form="force-input", Ts=0.001, **extra) -> str:
    m = S.TrialMeta(Ts=Ts, form=form, machine=machine, axis=axis,
                    provenance=S.Provenance(source="test", tool="pytest", version="0"))
    d = json.loads(S.encode(m))
    d.update(extra)
    return json.dumps(d)


def build(chunks: list[bytes], *, meta: str | None = None, channels: int = 1, extra: bytes = b"",
          machine: str = "m", axis: str = "X", index: bool = True) -> bytes:
    """A complete MCAP file: header, one feedmon.trial metadata record, ``extra`` records, the given
    chunk records, DataEnd (no CRC), a summary with the schema, ``channels`` channels (the first is
    /m/X/samples, id 1) and the metadata index, footer (no CRC), end magic."""
    out = bytearray(MAGIC)
    out += _rec(Header("", "pytest"))
    meta_off = len(out)
    md = _rec(Metadata("feedmon.trial", {"meta": meta or _meta_json(machine, axis), "machine": machine, "axis": axis}))
    out += md
    out += extra
    for c in chunks:
        out += c
    out += _rec(DataEnd(0))
    s0 = len(out)
    summ = [_rec(Schema(1, b"{}", "jsonschema", "feedmon.SampleBlock"))]
    for i in range(1, channels + 1):
        summ.append(_rec(Channel(i, f"/{machine}/{axis}/samples" if i == 1 else f"/m/X{i}/other", "json", {}, 1)))
    if index:
        summ.append(_rec(MetadataIndex(meta_off, len(md), "feedmon.trial")))
    out += b"".join(summ)
    out += _rec(Footer(s0, 0, 0))
    out += MAGIC
    return bytes(out)


def samples_payload(seq: int = 0, n: int = 10, machine: str = "m", axis: str = "X") -> bytes:
    """JSON of a sample block; ``seq`` is set after the schema's checks (a hostile file may hold any number)."""
    block = S.SampleBlock(machine=machine, axis=axis, seq=0, t=[i * 1e-3 for i in range(n)],
                          v_ref=[0.0] * n, v_meas=[0.001] * n, u=[1.0] * n)
    block.seq = seq
    return S.encode(block)


def chunk(payloads: list[bytes], *, compression: str = "", size: int | None = None, data: bytes | None = None) -> bytes:
    inner = b"".join(_rec(Message(1, i, p, i, i)) for i, p in enumerate(payloads))
    if data is None:
        if compression == "zstd":
            import zstandard

            data = zstandard.compress(inner)
        else:
            data = inner
    return _rec(Chunk(compression=compression, data=data, message_end_time=0, message_start_time=0,
                      uncompressed_crc=0, uncompressed_size=len(inner) if size is None else size))


@pytest.mark.parametrize("index", [True, False])
def test_builder_makes_a_readable_file(tmp_path, index):
    """(Without a metadata index — other writers — the metadata is found by a scan of the data section.)"""
    p = tmp_path / "built.mcap"
    p.write_bytes(build([chunk([samples_payload(0), samples_payload(10)], compression="zstd")], index=index))
    assert read_trial(p).seq.tolist()[:3] == [0, 1, 2] and len(read_trial(p)) == 20


# ---- integrity: CRCs ---------------------------------------------------------------
def test_every_bit_flip_is_detected(good, tmp_path):
    """feedmon files carry chunk, data-section and summary CRCs: a flipped bit anywhere (600 random
    positions and one in every record kind) is an error naming the file, never a changed value."""
    path, data = good
    rng = np.random.default_rng(12)
    positions = sorted(set(rng.integers(0, len(data), 600).tolist()))
    p = tmp_path / "flip.mcap"
    for pos in positions:
        buf = bytearray(data)
        buf[pos] ^= 1 << int(rng.integers(0, 8))
        p.write_bytes(bytes(buf))
        with pytest.raises(TrialFileError) as info:
            read_trial(p)
        assert str(p) in str(info.value), (pos, str(info.value))


def test_flipped_byte_inside_a_chunk_is_a_crc_error_with_recover_hint(good, tmp_path):
    """The message names the file, the byte offset and the fix; identify, run --from and replay all
    stop with it (exit 2), no traceback."""
    path, data = good
    from mcap.stream_reader import StreamReader

    offsets = []
    with open(path, "rb") as fh:
        for rec in StreamReader(fh, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                offsets.append(fh.tell() - len(rec.data))
                break
    buf = bytearray(data)
    buf[offsets[0] + 100] ^= 0x10
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(buf))
    _expect_clear_error(bad, "fails its CRC", "feedmon recover")
    model = model_from_truth(path, tmp_path / "z.model.toml")
    for argv in (["identify", str(bad), "-o", str(tmp_path / "m.toml"), "--period", "0.018"],
                 ["run", "--from", str(bad), "-o", str(tmp_path / "out.mcap"), "--model", str(model)],
                 ["replay", str(bad), "--max", "--wait", "0", "--quiet", "--listen",
                  f"tcp/127.0.0.1:{__import__('feedio.transport').transport.free_tcp_port()}"]):
        r = subprocess.run([sys.executable, "-m", "feedmon", *argv], capture_output=True, text=True, timeout=120,
                           cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)))
        assert r.returncode == 2, (argv, r.stderr)
        assert "Traceback" not in r.stderr and str(bad) in r.stderr and "CRC" in r.stderr, r.stderr


def test_chunk_crc_checked_when_the_file_has_no_data_crc(good, tmp_path):
    """Files of other writers may store no data-section CRC: the chunk's own CRC still catches a
    changed digit of v_meas in an uncompressed chunk."""
    from feedio.mcapio import TrialWriter

    p = tmp_path / "plain.mcap"
    meta = read_trial(good[0]).meta
    with TrialWriter(p, meta, start=CREATED, compression="none") as w:
        for k in range(20):
            w.write_samples(S.SampleBlock(machine=meta.machine, axis=meta.axis, seq=10 * k,
                                          t=[(10 * k + i) * 0.003 for i in range(10)], v_ref=[0.0] * 10,
                                          v_meas=[0.0123] * 10))
    buf = bytearray(p.read_bytes())
    foot = len(buf) - 8 - 29
    s0 = struct.unpack_from("<Q", buf, foot + 9)[0]
    buf[s0 - 4:s0] = bytes(4)  # DataEnd: no data-section CRC stored
    pos = bytes(buf).index(b"0.0123", 2000)
    buf[pos + 5] = ord("4")  # 0.0123 -> 0.0124: still valid JSON, a changed value
    p.write_bytes(bytes(buf))
    _expect_clear_error(p, "chunk: CRC mismatch", "feedmon recover")


# ---- absurd numbers --------------------------------------------------------------------
@pytest.mark.parametrize("seq", [2**64 + 5, 2**53, 10**30])
def test_seq_beyond_the_schema_is_a_clear_error(tmp_path, seq):
    p = tmp_path / "seq.mcap"
    p.write_bytes(build([chunk([samples_payload(0), samples_payload(seq)], compression="zstd")]))
    _expect_clear_error(p, "channel /m/X/samples, message 1", "$.seq", "9007199254740991")


def test_seq_2_64_through_identify_run_from_and_replay(tmp_path, good):
    p = tmp_path / "seq64.mcap"
    ax = dict(machine="linear-drive", axis="Z")
    meta = read_trial(good[0]).meta
    p.write_bytes(build([chunk([samples_payload(0, **ax), samples_payload(2**64, **ax)], compression="zstd")],
                        meta=_meta_json(form="velocity-loop", Ts=meta.Ts, **ax), **ax))
    model = model_from_truth(good[0], tmp_path / "m.model.toml")
    for argv in (["identify", str(p), "-o", str(tmp_path / "m.toml"), "--period", "0.018"],
                 ["run", "--from", str(p), "-o", str(tmp_path / "out.mcap"), "--model", str(model)],
                 ["replay", str(p), "--max", "--wait", "0", "--quiet", "--listen",
                  f"tcp/127.0.0.1:{__import__('feedio.transport').transport.free_tcp_port()}"]):
        r = subprocess.run([sys.executable, "-m", "feedmon", *argv], capture_output=True, text=True, timeout=120,
                           cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)))
        assert r.returncode == 2, (argv, r.stdout, r.stderr)
        assert "Traceback" not in r.stderr and "OverflowError" not in r.stderr, r.stderr
        assert "$.seq" in r.stderr and "9007199254740991" in r.stderr and "message 1" in r.stderr, r.stderr


# ---- hostile content limits, counted and clear ----------------------------------------
_PEAK_RSS = """
import json, sys
from feedio.mcapio import TrialFileError, read_trial
from feedio.mcapspec import MAGIC
from replay.recover import recover
out = {}
try:
    read_trial(sys.argv[1])
    out["read"] = "ok"
except TrialFileError as exc:
    out["read"] = str(exc)
rep = recover(sys.argv[1], sys.argv[2])
out["recover"] = [s.reason for s in rep.skipped] + [rep.stop_reason or ""]
# peak RSS of this process image (VmHWM; ru_maxrss would include the forking parent's)
out["peak_mb"] = [int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM")][0] / 1024
print(json.dumps(out))
"""


def _zstd_bomb(n_mb: int) -> bytes:
    import zstandard

    cobj = zstandard.ZstdCompressor(level=19).compressobj()
    zero = bytes(1 << 20)
    out = b"".join(cobj.compress(zero) for _ in range(n_mb))
    return out + cobj.flush()


@pytest.mark.parametrize("claim", ["honest", "under-limit", "small"])
def test_zstd_bomb_is_refused_in_bounded_memory(tmp_path, claim):
    """A ~30 kB zstd chunk that inflates to 900 MB: refused by the declared-size limit, by the
    compression-ratio limit, or (declared small) by the bound on the output — in a subprocess whose
    peak memory is measured (the old reader took 0.9 GB). recover skips it the same way."""
    bomb = _zstd_bomb(900)
    size = {"honest": 900 << 20, "under-limit": MAX_CHUNK_BYTES - 1, "small": 4096}[claim]
    p = tmp_path / "bomb.mcap"
    p.write_bytes(build([chunk([], compression="zstd", size=size, data=bomb)]))
    assert p.stat().st_size < 200_000
    r = subprocess.run([sys.executable, "-c", _PEAK_RSS, str(p), str(tmp_path / "fixed.mcap")], capture_output=True,
                       text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    want = {"honest": "more than the limit of 67108864", "under-limit": "a decompression bomb",
            "small": "decompresses to more than the declared 4096 bytes"}[claim]
    assert want in out["read"] and str(p) in out["read"], out
    assert any(want in x for x in out["recover"]), out
    assert out["peak_mb"] < 150, out  # the reader alone needs ~35 MB; the old one 0.9 GB


def test_deeply_nested_metadata_is_refused(tmp_path, capsys):
    deep = "[" * 50_000 + "]" * 50_000
    p = tmp_path / "deep.mcap"
    p.write_bytes(build([chunk([samples_payload(0)])], meta=_meta_json(description="x").replace(
        '"description": "x"', f'"description": "x", "teeth": {deep}')))
    _expect_clear_error(p, "nests 50001 levels deep", f"limit of {MAX_JSON_DEPTH}")
    assert main(["identify", str(p), "-o", str(tmp_path / "m.toml"), "--period", "0.018"]) == 2
    err = capsys.readouterr().err
    assert "RecursionError" not in err and "nests 50001 levels deep" in err


def test_huge_metadata_record_and_too_many_channels_are_refused(tmp_path):
    p = tmp_path / "bigmeta.mcap"
    p.write_bytes(build([chunk([samples_payload(0)])], meta=_meta_json(description="x" * (MAX_METADATA_BYTES + 10))))
    _expect_clear_error(p, f"more than the limit of {MAX_METADATA_BYTES} for a metadata record")
    p = tmp_path / "channels.mcap"
    p.write_bytes(build([chunk([samples_payload(0)])], channels=MAX_CHANNELS + 1))
    _expect_clear_error(p, f"more than {MAX_CHANNELS} channels (the limit)")
    # the limits are configurable (Limits)
    p.write_bytes(build([chunk([samples_payload(0)])], channels=30))
    assert len(read_trial(p)) == 10
    with pytest.raises(TrialFileError, match="more than 20 channels"):
        read_trial(p, limits=Limits(channels=20))


def test_absurd_record_lengths(tmp_path):
    good_chunk = chunk([samples_payload(0)])
    # a chunk record whose length claims 2**62 bytes
    bad = bytearray(good_chunk)
    bad[1:9] = struct.pack("<Q", 2**62)
    p = tmp_path / "len.mcap"
    p.write_bytes(build([bytes(bad)]))
    _expect_clear_error(p, "is corrupt at byte")
    # a message inside a chunk that claims more bytes than the chunk holds
    inner = bytearray(_rec(Message(1, 0, samples_payload(0), 0, 0)))
    inner[1:9] = struct.pack("<Q", 10**12)
    p.write_bytes(build([_rec(Chunk("", bytes(inner), 0, 0, 0, len(inner)))]))
    _expect_clear_error(p, "declares 1000000000000 bytes")


# ---- fuzz: truncations, flips, random records ------------------------------------------------------
def test_truncations_are_clear_errors(good, tmp_path):
    path, data = good
    rng = np.random.default_rng(5)
    p = tmp_path / "cut.mcap"
    for cut in sorted(set(rng.integers(0, len(data), 250).tolist()) | {0, 7, 8, 9, len(data) - 1}):
        p.write_bytes(data[:cut])
        msg = _expect_clear_error(p)
        assert "truncated" in msg or "not an MCAP file" in msg, msg


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(where=st.floats(0.0, 1.0), records=st.lists(st.tuples(st.integers(0, 0x12), st.integers(0, 300),
                                                              st.binary(max_size=64)), min_size=1, max_size=4),
       lie=st.sampled_from([None, 0, 2**63, 2**32 + 1]))
def test_random_records_inserted(good, tmp_path_factory, where, records, lie):
    """Random records (opcode, declared length, body) spliced into a valid file: the reader gives a clear
    error (the CRCs and lengths no longer match) and recover writes a valid file or says why not."""
    path, data = good
    blob = b"".join(struct.pack("<BQ", op, ln if lie is None else lie) + body for op, ln, body in records)
    pos = 8 + int(where * (len(data) - 8))
    p = tmp_path_factory.mktemp("rand") / "r.mcap"
    p.write_bytes(data[:pos] + blob + data[pos:])
    _expect_clear_error(p)
    try:
        rep = recover(p, p.with_name("r-fixed.mcap"))
    except ValueError as exc:
        assert str(p) in str(exc)
        return
    assert rep.messages <= 2 * len(read_trial(path)) // 100 + 100
    with open(p.with_name("r-fixed.mcap"), "rb") as fh:
        from mcap.reader import make_reader

        summary = make_reader(fh).get_summary()
        assert summary.statistics.message_count == rep.messages


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(start=st.floats(0.0, 1.0), junk=st.binary(min_size=1, max_size=200))
def test_random_overwrites(good, tmp_path_factory, start, junk):
    path, data = good
    pos = int(start * (len(data) - 1))
    buf = bytearray(data)
    buf[pos:pos + len(junk)] = junk
    buf = bytes(buf[: len(data)])
    p = tmp_path_factory.mktemp("over") / "o.mcap"
    p.write_bytes(buf)
    if buf == data:
        assert len(read_trial(p)) == len(read_trial(path))
        return
    _expect_clear_error(p)
