"""The fast writing path of the per-sample ``disturbance/scalars`` channel: the MCAP record writer is
byte-compatible with the ``mcap`` package's, the columnar pairer releases the same messages as the
per-sample reference (``scalars_reference.py``), the compiled record builder writes the bytes
``msgspec`` writes, and a file written in bulk is byte-identical to one written message by message,
read by the plain ``mcap`` reader and by ``feedmon recover``."""

from __future__ import annotations

import io
import json
import math
import random

import numpy as np
import pytest
import scalars_reference as ref
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from feedio import schema as S
from feedio.mcapio import TrialWriter
from feedio.mcapwriter import McapWriter, message_header
from feedio.scalars import VALUES, ScalarsBatch, ScalarsPairer

TS = 0.003


# ---- the record writer -------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(40))
def test_record_writer_writes_the_bytes_of_the_mcap_writer(seed):
    """Random call sequences (metadata, schemas, channels, messages, bulk records, flushes; every
    compression; chunk sizes that close chunks inside a bulk append) through both writers."""
    rng = random.Random(seed)
    comp = rng.choice(["zstd", "lz4", ""])
    chunk_size = rng.choice([200, 1000, 5000, 1 << 20])
    a, b = io.BytesIO(), io.BytesIO()
    types = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}
    wa = Writer(a, chunk_size=chunk_size, compression=types[comp], enable_data_crcs=True)
    wb = McapWriter(b, chunk_size=chunk_size, compression=comp)
    wa.start(profile="", library="lib")
    wb.start(profile="", library="lib")
    channels: list[int] = []

    def data() -> bytes:
        return bytes(rng.randint(0, 255) for _ in range(rng.randint(0, 80)))

    for step in range(rng.randint(5, 60)):
        r = rng.random()
        if r < 0.05:
            for w in (wa, wb):
                w.add_metadata("m", {"k": str(step), "x": "y"})
        elif r < 0.07:
            d = data()
            for w in (wa, wb):
                w.add_attachment(create_time=step, log_time=10 * step, name=f"a{step}", media_type="text/plain",
                                 data=d)
        elif r < 0.1 or not channels:
            ids = []
            for w in (wa, wb):
                sid = w.register_schema("s", "jsonschema", b"{}")
                ids.append((sid, w.register_channel(f"/t{step}", "json", sid, {"a": "b"})))
            assert ids[0] == ids[1]
            channels.append(ids[0][1])
        elif r < 0.15:
            wa.flush()
            wb.flush()
        elif r < 0.6:
            c, lt, d, sq = rng.choice(channels), rng.randint(0, 10**12), data(), rng.randint(0, 2**32 - 1)
            wa.add_message(c, lt, d, lt, sq)
            wb.add_message(c, lt, d, lt, sq)
        else:
            c, n = rng.choice(channels), rng.randint(1, 30)
            msgs = [(rng.randint(0, 10**12), data(), rng.randint(0, 2**32 - 1)) for _ in range(n)]
            for lt, d, sq in msgs:
                wa.add_message(c, lt, d, lt, sq)
            recs = [message_header(c, sq, lt, lt, len(d)) + d for lt, d, sq in msgs]
            sizes, lts = np.array([len(x) for x in recs]), np.array([lt for lt, _, _ in msgs])
            i = 0
            while i < n:
                k = wb.records_fitting(sizes[i:])
                wb.add_records(c, b"".join(recs[i:i + k]), sizes[i:i + k], lts[i:i + k])
                i += k
    wa.finish()
    wb.finish()
    assert a.getvalue() == b.getvalue()


# ---- the pairer --------------------------------------------------------------------------------
def _estimate(axis: str, seq: int, n: int, rng: np.random.Generator, *, force: bool) -> S.EstimateBlock:
    t = [(seq + i) * TS for i in range(n)]

    def col(p_missing=0.05, scale=1e-3):
        x = (scale * rng.standard_normal(n)).tolist()
        return [None if rng.random() < p_missing else v for v in x]

    var = [None if rng.random() < 0.05 else float(abs(v) * 1e-3 - (1e-9 if rng.random() < 0.05 else 0.0))
           for v in rng.standard_normal(n)]
    return S.EstimateBlock(
        machine="m", axis=axis, seq=seq, t=t, v_meas=col(), v_pred=col(), residual=col(), f=col(), f_var=var,
        f_next=col(), f_next_var=var, dict_size=[5] * n, removed=[-1] * n,
        flags=[int(x) for x in rng.integers(0, 32, n)],
        force=col(scale=10.0) if force else None, force_var=[abs(v) for v in col(0.0)] if force else None,
        force_next=col(scale=10.0) if force else None)


def _truth(seq: int, n: int, rng: np.random.Generator) -> S.TruthBlock:
    return S.TruthBlock(seq=seq, t=[(seq + i) * TS for i in range(n)], force=rng.standard_normal(n).tolist(),
                        f=[None if rng.random() < 0.1 else float(x) for x in rng.standard_normal(n)],
                        dynamometer=rng.standard_normal(n).tolist() if rng.random() < 0.5 else None)


def _flat(batches: list[ScalarsBatch]) -> list[tuple]:
    return [(b.machine, b.axis, int(ns), msg) for b in batches for ns, msg in zip(b.log_ns.tolist(), b.messages())]


@pytest.mark.parametrize("seed", range(30))
@pytest.mark.parametrize("expect", [None, True, False, "set"])
def test_columnar_pairer_releases_what_the_per_sample_reference_releases(seed, expect):
    """Two axes, blocks of 1–40 rows with gaps, sequence restarts, repeated blocks, missing and
    negative variances, truth before, after and overlapping its rows, a small hold, expiry and a final
    drain: the same messages, stamps and order as the per-sample reference."""
    rng = np.random.default_rng(seed)
    exp = {("m", "X")} if expect == "set" else expect
    hold = int(rng.choice([3, 17, 4096]))
    new, old = ScalarsPairer(hold_samples=hold, expect_truth=exp), ref.ScalarsPairer(hold_samples=hold,
                                                                                     expect_truth=exp)
    seqs = {"X": 0, "Y": 100}
    truth_at = {"X": 0, "Y": 100}
    now = 1_700_000_000 * 10**9
    got, want = [], []
    for _ in range(60):
        axis = "X" if rng.random() < 0.6 else "Y"
        r = rng.random()
        if r < 0.45:
            n = int(rng.integers(1, 40))
            s = seqs[axis]
            if rng.random() < 0.1:
                s += int(rng.integers(1, 20))  # a gap
            elif rng.random() < 0.05:
                s = int(rng.integers(0, 50))  # the bridge restarted
            elif rng.random() < 0.05:
                s = max(0, s - n)  # a repeated block
            block = _estimate(axis, s, n, rng, force=axis == "X")
            now += int(rng.integers(0, 3 * 10**8))
            seqs[axis] = s + n
            got += _flat(new.add_estimates(block, now))
            want += old.add_estimates(block, now)
        elif r < 0.8:
            n = int(rng.integers(1, 40))
            s = truth_at[axis] + int(rng.integers(-30, 30))
            s = max(0, s)
            truth_at[axis] = s + n
            block = _truth(s, n, rng)
            got += _flat(new.add_truth("m", axis, block))
            want += old.add_truth("m", axis, block)
        else:
            cut = now - int(rng.integers(0, 10**9))
            got += _flat(new.expire(cut))
            want += old.expire(cut)
    got += _flat(new.drain())
    want += old.drain()
    assert len(got) == len(want) > 0
    for g, w in zip(got, want):
        assert g == w


# ---- the records ---------------------------------------------------------------------------------
def test_records_are_header_plus_the_msgspec_json_of_each_message():
    rng = np.random.default_rng(1)
    n = 400
    values = rng.standard_normal((len(VALUES), n)) * 10.0 ** rng.integers(-300, 300, (len(VALUES), n))
    values[rng.random(values.shape) < 0.2] = np.nan
    values[0, :5] = (-0.0, 0.0, 1e16, 1e-5, 123456789.125)
    batch = ScalarsBatch("m", "X", log_ns=np.arange(n, dtype=np.int64) * 3_000_000 + 2**40,
                         seq=np.arange(n, dtype=np.int64) + 2**32 - 3, t=np.arange(n) * TS + 0.1,
                         flags=rng.integers(0, 32, n), values=values)
    records, sizes = batch.records(7)
    assert sizes.sum() == records.size
    pos = 0
    for i, msg in enumerate(batch.messages()):
        data = S.encode(msg)
        assert b"null" not in data and b"NaN" not in data
        seq = int(batch.seq[i])
        want = message_header(7, seq & 0xFFFFFFFF, int(batch.log_ns[i]), int(batch.log_ns[i]), len(data)) + data
        assert records[pos:pos + sizes[i]].tobytes() == want
        pos += int(sizes[i])


def _meta(axis: str) -> S.TrialMeta:
    return S.TrialMeta(Ts=TS, form="velocity-loop", machine="m", axis=axis,
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))


@pytest.mark.parametrize("chunk_seconds,chunk_size", [(1.0, 4 << 20), (0.05, 4 << 20), (1.0, 3000), (0.2, 9000)])
def test_bulk_scalars_file_is_the_file_written_message_by_message(tmp_path, chunk_seconds, chunk_size):
    """The same blocks, estimates and scalars through write_scalars_batch and through write_scalars (one
    message at a time): the same bytes, chunks closed by time and by size alike; the plain mcap reader
    reads every message and feedmon recover finds nothing to skip."""
    from replay.recover import recover

    rng = np.random.default_rng(3)
    paths = [tmp_path / "bulk.mcap", tmp_path / "single.mcap"]
    for path in paths:
        pairer = ScalarsPairer(expect_truth=False)
        with TrialWriter(path, [_meta("X"), _meta("Y")], start=0, chunk_seconds=chunk_seconds,
                         chunk_size=chunk_size) as w:
            seq = {"X": 0, "Y": 0}
            r = np.random.default_rng(3)
            for k in range(80):
                axis = "XY"[k % 2]
                n = int(r.integers(1, 60))
                est = _estimate(axis, seq[axis], n, r, force=True)
                seq[axis] += n
                lt = 10**15 + int(est.t[-1] * 1e9)
                w.write_estimates(est, log_time=lt)
                for batch in pairer.add_estimates(est, lt):
                    if path.name == "bulk.mcap":
                        w.write_scalars_batch(batch)
                    else:
                        w.write_scalars(batch.machine, batch.axis, list(zip(batch.log_ns.tolist(), batch.messages())))
            for batch in pairer.drain():
                if path.name == "bulk.mcap":
                    w.write_scalars_batch(batch)
                else:
                    w.write_scalars(batch.machine, batch.axis, list(zip(batch.log_ns.tolist(), batch.messages())))
    assert paths[0].read_bytes() == paths[1].read_bytes()
    del rng
    with open(paths[0], "rb") as f:
        reader = make_reader(f)
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in reader.iter_messages(log_time_order=False)]
        chunks = reader.get_summary().statistics.chunk_count
    scal = [m for t, m in msgs if t.endswith("/scalars")]
    assert len(scal) == sum(len(m["t"]) for t, m in msgs if t.endswith("/disturbance"))
    assert chunks > (3 if chunk_seconds < 1 or chunk_size < 10_000 else 0)
    assert all(isinstance(v, (int, float)) and math.isfinite(v) for m in scal for v in m.values())
    rep = recover(paths[0], tmp_path / "fixed.mcap")
    assert rep.skipped_ranges == 0 and rep.bytes_dropped == 0, rep.summary()


def test_bulk_scalars_refuse_what_cannot_be_written_before_writing_anything(tmp_path):
    batch = ScalarsBatch("m", "X", log_ns=np.array([5, 6]), seq=np.array([0, S.SEQ_MAX + 1]), t=np.array([0.0, TS]),
                         flags=np.zeros(2, dtype=np.int64), values=np.full((len(VALUES), 2), np.nan))
    with TrialWriter(tmp_path / "x.mcap", _meta("X"), start=0) as w:
        with pytest.raises(ValueError, match="scalars seq"):
            w.write_scalars_batch(batch)
        assert w.messages == 0
