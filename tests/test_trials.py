"""MCAP trial files: writer, reader, plain-mcap compatibility, determinism, clear errors."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from feedio import schema as S
from feedio.mcapio import (
    METADATA_NAME,
    TrialFileError,
    TrialWriter,
    iter_blocks,
    list_axes,
    parse_time,
    read_trial,
)
from feedmon.cli import main
from replay.simulator import simulate_scenario, write_trial

CREATED = "2024-05-01T08:00:00Z"


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory):
    res = simulate_scenario("shaker-constant", seed=5, duration=6.0, config={"noise": {"glitch_rate": 0.01}},
                            created=CREATED)
    path = tmp_path_factory.mktemp("trials") / "shaker.mcap"
    write_trial(res, path)
    return res, path


def test_round_trip_plain_mcap_reader(sim_file):
    res, path = sim_file
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()}
        assert topics == {"/linear-drive/Z/samples", "/linear-drive/Z/truth"}
        for ch in summary.channels.values():
            assert ch.message_encoding == "json"
            sch = summary.schemas[ch.schema_id]
            assert sch.encoding == "jsonschema"
            assert json.loads(sch.data)["$schema"].endswith("2020-12/schema")
        assert summary.statistics.chunk_count >= 6  # chunks closed every second of data
        meta = [m for m in reader.iter_metadata() if m.name == METADATA_NAME]
        assert len(meta) == 1 and meta[0].metadata["axis"] == "Z" and meta[0].metadata["form"] == "velocity-loop"
        # the start time (here the --created time) is in the metadata; log times count from it
        assert meta[0].metadata["start_time"] == "2024-05-01T08:00:00.000000Z"
        start = int(meta[0].metadata["start_time_ns"])
        assert start == 1714550400 * 10**9
        cols = {"t": [], "v_ref": [], "v_meas": [], "u": [], "force": [], "glitch": []}
        for _, ch, msg in reader.iter_messages():
            d = json.loads(msg.data)
            assert msg.log_time == msg.publish_time == start + round(d["t"][-1] * 1e9)  # time of the last sample
            if ch.topic.endswith("/samples"):
                for k in ("t", "v_ref", "v_meas", "u"):
                    cols[k] += d[k]
            else:
                cols["force"] += d["force"]
                cols["glitch"] += d["glitch"]
    tr = read_trial(path)
    # plain reader, feedmon reader and the simulator agree exactly
    for k in ("t", "v_ref", "v_meas", "u"):
        np.testing.assert_array_equal(np.array(cols[k]), getattr(tr, k))
        np.testing.assert_array_equal(getattr(res, k), getattr(tr, k))
    np.testing.assert_array_equal(np.array(cols["force"]), tr.truth.force)
    np.testing.assert_array_equal(np.array(cols["glitch"]), tr.truth.glitch)
    np.testing.assert_array_equal(tr.seq, np.arange(len(res)))
    np.testing.assert_array_equal(tr.truth.f, res.f)
    assert tr.meta == res.meta and tr.meta.truth.beta == list(res.beta)
    assert tr.Ts == pytest.approx(1 / 333) and tr.form == "velocity-loop"
    assert tr.current is not None and tr.position is not None and tr.spindle_rpm is None
    assert tr.start_ns == start
    blocks = [b for k, b in iter_blocks(path)]
    assert all(isinstance(b, S.SampleBlock) for b in blocks) and sum(len(b) for b in blocks) == len(res)
    kinds = [k for k, _ in iter_blocks(path, kinds=("samples", "truth"))]
    assert kinds.count("truth") == kinds.count("samples")


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    """Byte-identical for the same seed and the same creation (= start) time."""
    paths = []
    for i, seed in enumerate((1, 1, 2)):
        p = tmp_path / f"t{i}.mcap"
        write_trial(simulate_scenario("milling-incdec", seed=seed, duration=3.0, created=CREATED), p)
        paths.append(p.read_bytes())
    assert paths[0] == paths[1]
    assert paths[0] != paths[2]


def test_start_time_defaults_to_now_and_cli_options(tmp_path, capsys):
    """Without a creation time the start is the creation time (after 2020, not 1970); --created and
    import --start set it; a malformed time is a clear error."""
    import time as _time

    p = tmp_path / "now.mcap"
    before = _time.time_ns()
    write_trial(simulate_scenario("shaker-constant", seed=1, duration=1.0), p)
    tr = read_trial(p)
    assert before - 10**9 <= tr.start_ns <= _time.time_ns()
    with open(p, "rb") as fh:
        times = [m.log_time for _, _, m in make_reader(fh).iter_messages()]
    assert min(times) > 1577836800 * 10**9  # 2020-01-01
    out = tmp_path / "cli.mcap"
    assert main(["simulate", "shaker-constant", "-o", str(out), "--duration", "1", "--created",
                 "2023-03-04T05:06:07+01:00"]) == 0
    assert read_trial(out).start_ns == parse_time("2023-03-04T04:06:07Z")
    csv_path = tmp_path / "x.csv"
    csv_path.write_text("time,vr,vm\n" + "".join(f"{k * 0.001},{0.01},{0.0099}\n" for k in range(50)))
    out = tmp_path / "csv.mcap"
    assert main(["import", "csv", str(csv_path), "-o", str(out), "--map", "t=time,v_ref=vr,v_meas=vm",
                 "--start", "2022-01-02T03:04:05Z"]) == 0
    assert read_trial(out).start_ns == parse_time("2022-01-02T03:04:05Z")
    capsys.readouterr()
    assert main(["import", "csv", str(csv_path), "-o", str(out), "--map", "t=time,v_ref=vr,v_meas=vm",
                 "--start", "yesterday"]) == 2
    assert "'yesterday' is not an ISO 8601 time" in capsys.readouterr().err
    with pytest.raises(ValueError, match="not an ISO 8601 time"):
        parse_time("yesterday")
    with pytest.raises(ValueError, match="outside 1970"):
        parse_time("1969-12-31T23:59:59Z")


def _meta(axis="X", machine="m"):
    return S.TrialMeta(Ts=0.001, form="force-input", machine=machine, axis=axis,
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))


def _samples(axis="X", seq=0, n=10, t0=0.0, machine="m"):
    """A sample block; ``seq`` and ``t0`` are set after the schema's checks, so tests can hand the writer
    what a hostile caller might (its own validation must refuse it)."""
    t = (t0 + np.arange(n) * 1e-3).tolist()
    block = S.SampleBlock(machine=machine, axis=axis, seq=0, t=(np.arange(n) * 1e-3).tolist(), v_ref=[0.0] * n,
                          v_meas=[0.0] * n, u=[1.0] * n)
    block.seq, block.t = seq, t
    return block


def test_multi_axis_and_live_flush(tmp_path):
    p = tmp_path / "two.mcap"
    with TrialWriter(p, [_meta("X"), _meta("Y")]) as w:
        w.write_samples(_samples("X"))
        assert w.flush_if_due(now=0.0) is False
        assert w.flush_if_due(now=1e12) is True  # wall-clock flush for live writers
        w.write_samples(_samples("Y"))
        with pytest.raises(ValueError, match="no TrialMeta"):
            w.write_samples(_samples("Z"))
    assert list_axes(p) == ["m/X", "m/Y"]
    with pytest.raises(TrialFileError, match=r"2 axes \(m/X, m/Y\); choose one with axis="):
        read_trial(p)
    assert read_trial(p, axis="Y").axis == "Y"
    assert read_trial(p, axis="m/X").axis == "X"
    with pytest.raises(TrialFileError, match="no axis 'Q'; axes present: m/X, m/Y"):
        read_trial(p, axis="Q")


def test_nan_samples_survive_as_nan(tmp_path):
    p = tmp_path / "nan.mcap"
    b = _samples()
    b.v_meas[3] = float("nan")
    with TrialWriter(p, _meta()) as w:
        w.write_samples(b)
    tr = read_trial(p)
    assert np.isnan(tr.v_meas[3]) and np.isfinite(np.delete(tr.v_meas, 3)).all()


def test_random_bytes_not_mcap(tmp_path):
    p = tmp_path / "noise.mcap"
    p.write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(TrialFileError, match=r"noise\.mcap is not an MCAP file"):
        read_trial(p)


def test_truncated_file(sim_file, tmp_path):
    _, path = sim_file
    data = path.read_bytes()
    for cut in (len(data) // 2, len(data) - 5, 20):
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(data[:cut])
        with pytest.raises(TrialFileError, match=rf"cut{cut}\.mcap is truncated"):
            read_trial(p)
    # damaged in the middle (summary intact): still a clear TrialFileError
    bad = bytearray(data)
    mid = len(bad) // 3
    bad[mid:mid + 2000] = bytes(2000)
    p = tmp_path / "damaged.mcap"
    p.write_bytes(bytes(bad))
    with pytest.raises(TrialFileError, match=r"damaged\.mcap"):
        read_trial(p)


def test_missing_file():
    with pytest.raises(TrialFileError, match="cannot open trial file .*nope.mcap"):
        read_trial("/nonexistent/nope.mcap")


def _raw_mcap(path, topic, payloads, *, metadata=True, schema_enc="jsonschema"):
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        if metadata:
            w.add_metadata(METADATA_NAME, {"meta": S.encode(_meta()).decode(), "machine": "m", "axis": "X"})
        sid = w.register_schema("x", schema_enc, b"{}")
        cid = w.register_channel(topic, "json", sid)
        for i, data in enumerate(payloads):
            w.add_message(cid, i, data, i)
        w.finish()


def test_file_without_samples_channel(tmp_path):
    p = tmp_path / "nosamples.mcap"
    _raw_mcap(p, "/m/X/other", [b"{}"])
    with pytest.raises(TrialFileError, match=r"nosamples\.mcap has no samples channel .*channels present: /m/X/other"):
        read_trial(p)


def test_block_with_inconsistent_lengths_names_channel_and_index(tmp_path):
    p = tmp_path / "badblock.mcap"
    good = S.encode(_samples())
    bad = b'{"machine":"m","axis":"X","seq":10,"t":[0.01,0.011],"v_ref":[0,0],"v_meas":[0]}'
    _raw_mcap(p, "/m/X/samples", [good, bad])
    with pytest.raises(TrialFileError, match=r"badblock\.mcap: channel /m/X/samples, message 1 .*'v_meas' has 1 values but 't' has 2"):
        read_trial(p)


def test_missing_metadata_and_wrong_schema_encoding(tmp_path):
    p = tmp_path / "nometa.mcap"
    _raw_mcap(p, "/m/X/samples", [S.encode(_samples())], metadata=False)
    with pytest.raises(TrialFileError, match=r"nometa\.mcap: missing metadata record 'feedmon.trial' for axis m/X"):
        read_trial(p)
    p = tmp_path / "proto.mcap"
    _raw_mcap(p, "/m/X/samples", [S.encode(_samples())], schema_enc="protobuf")
    with pytest.raises(TrialFileError, match=r"channel /m/X/samples has schema encoding 'protobuf'"):
        read_trial(p)


# ---- a failed write never corrupts the writer (issue 9 #2) -----------------------------------------
def test_refused_blocks_leave_the_writer_consistent(tmp_path):
    """t = 2e10 s (log time beyond 2262), seq ≥ 2**64, a message over the size limit: each is a
    ValueError naming the block, and every good block before and after is in a complete file."""
    from feedio.mcapio import MAX_MESSAGE_BYTES

    p = tmp_path / "refused.mcap"
    good = 0
    with TrialWriter(p, _meta(), start=CREATED) as w:
        for k in range(3):
            w.write_samples(_samples(seq=10 * k, t0=0.01 * k))
            good += 1
        with pytest.raises(ValueError, match=r"field 't' has 20000000000\.0 at index 0; controller time must be finite"):
            w.write_samples(_samples(seq=30, t0=2e10))
        with pytest.raises(ValueError, match=r"field 't' has -10000000000\.0 at index 0"):
            w.write_samples(_samples(seq=30, n=1, t0=-1e10))
        with pytest.raises(ValueError, match=r"sequence number 18446744073709551616 .*SEQ_MAX"):
            w.write_samples(_samples(seq=2**64, t0=0.03))
        n = MAX_MESSAGE_BYTES // 20
        with pytest.raises(ValueError, match=r"more than the limit of 16777216; write it as several blocks"):
            w.write_samples(_samples(seq=30, n=n, t0=0.03))
        with pytest.raises(ValueError, match="log time .* is outside"):
            w.write_samples(_samples(seq=30, t0=0.03), log_time=2**64)
        for k in range(3, 300):  # 3 s of data: several chunks after the refusals
            w.write_samples(_samples(seq=10 * k, t0=0.01 * k))
            good += 1
        assert w.failed is None and w.messages == good
    tr = read_trial(p)  # footer, summary, every good block
    assert tr.seq.tolist() == list(range(10 * good))
    with pytest.raises(ValueError, match="is not a valid name"):  # would fail inside the mcap writer: refused before
        TrialWriter(tmp_path / "bad-name.mcap", _meta(axis="X\udc80"))
    with open(p, "rb") as fh:
        r = make_reader(fh)
        assert r.get_summary().statistics.message_count == good
        assert r.get_summary().statistics.chunk_count >= 3


_FSIZE_WRITER = """
import json, os, resource, shutil, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes beyond the limit fail with EFBIG instead of killing us
from feedio import schema as S
from feedio.mcapio import TrialWriter
path, snapshot = sys.argv[1], sys.argv[2]
meta = S.TrialMeta(Ts=0.001, form="force-input", machine="m", axis="X",
                   provenance=S.Provenance(source="test", tool="pytest", version="0"))
w = TrialWriter(path, meta, start="2024-05-01T08:00:00Z", chunk_seconds=10.0)
refused, accepted, on_disk = 0, 0, None
for k in range(300):
    t = [(10 * k + i) * 0.001 for i in range(10)]
    w.write_samples(S.SampleBlock(machine="m", axis="X", seq=10 * k, t=t, v_ref=[0.0] * 10,
                                  v_meas=[0.001 * k] * 10, u=[float(k)] * 10))
    accepted += 1
    if k == 20:  # the disk fills up (a 24 kB file-size limit)
        resource.setrlimit(resource.RLIMIT_FSIZE, (24_000, resource.RLIM_INFINITY))
    try:
        w.flush()
    except OSError as exc:
        refused += 1
        errno = exc.errno
        if on_disk is None:
            on_disk = os.path.getsize(path)
            shutil.copyfile(path, snapshot)  # the file as the disk refused more
    if k == 200:  # space comes back
        resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
w.close()
print(json.dumps(dict(refused=refused, errno=errno, accepted=accepted, on_disk=on_disk, lost=w.messages_lost,
                      failed=w.failed, finished=w.finished)))
"""


def test_disk_refusing_writes_then_space_back_loses_nothing(tmp_path):
    """A real file-size limit (RLIMIT_FSIZE, in a subprocess) refuses the writer's flushes: each
    refusal is an OSError, the file meanwhile ends on a complete record (recover finds nothing
    damaged), and once writes work again every block reaches a complete file."""
    import errno
    import os
    import subprocess
    import sys

    from replay.recover import recover

    repo = str(__import__("pathlib").Path(__file__).resolve().parents[1])
    path, snap = tmp_path / "full.mcap", tmp_path / "snapshot.mcap"
    r = subprocess.run([sys.executable, "-c", _FSIZE_WRITER, str(path), str(snap)], capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONPATH=repo))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["refused"] > 100 and out["errno"] == errno.EFBIG
    assert out["lost"] == 0 and out["failed"] is None and out["finished"] is True
    assert 0 < out["on_disk"] <= 24_000
    rep = recover(snap, tmp_path / "snap-fixed.mcap")  # the file as it was while the disk refused
    assert rep.skipped_ranges == 0 and rep.bytes_dropped == 0 and "ends after a complete record" in rep.stop_reason
    assert 0 < len(read_trial(tmp_path / "snap-fixed.mcap")) < 10 * out["accepted"]
    tr = read_trial(path)  # after space came back: everything
    assert tr.seq.tolist() == list(range(10 * out["accepted"]))
    assert tr.u.tolist() == [float(k) for k in range(out["accepted"]) for _ in range(10)]
