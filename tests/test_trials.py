"""MCAP trial files: writer, reader, plain-mcap compatibility, determinism, clear errors."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from feedio import schema as S
from feedio.mcapio import METADATA_NAME, TrialFileError, TrialWriter, iter_blocks, list_axes, read_trial
from replay.simulator import simulate_scenario, write_trial


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory):
    res = simulate_scenario("shaker-constant", seed=5, duration=6.0, config={"noise": {"glitch_rate": 0.01}})
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
        cols = {"t": [], "v_ref": [], "v_meas": [], "u": [], "force": [], "glitch": []}
        for _, ch, msg in reader.iter_messages():
            d = json.loads(msg.data)
            assert msg.log_time == round(d["t"][0] * 1e9)
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
    blocks = [b for k, b in iter_blocks(path)]
    assert all(isinstance(b, S.SampleBlock) for b in blocks) and sum(len(b) for b in blocks) == len(res)
    kinds = [k for k, _ in iter_blocks(path, kinds=("samples", "truth"))]
    assert kinds.count("truth") == kinds.count("samples")


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    paths = []
    for i, seed in enumerate((1, 1, 2)):
        p = tmp_path / f"t{i}.mcap"
        write_trial(simulate_scenario("milling-incdec", seed=seed, duration=3.0), p)
        paths.append(p.read_bytes())
    assert paths[0] == paths[1]
    assert paths[0] != paths[2]


def _meta(axis="X", machine="m"):
    return S.TrialMeta(Ts=0.001, form="force-input", machine=machine, axis=axis,
                       provenance=S.Provenance(source="test", tool="pytest", version="0"))


def _samples(axis="X", seq=0, n=10, t0=0.0, machine="m"):
    t = (t0 + np.arange(n) * 1e-3).tolist()
    return S.SampleBlock(machine=machine, axis=axis, seq=seq, t=t, v_ref=[0.0] * n, v_meas=[0.0] * n, u=[1.0] * n)


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
