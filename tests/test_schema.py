"""feedio.schema: one schema for samples, truth, estimates and trial metadata."""

import json
import math

import msgspec
import pytest

from feedio import schema as S


def _block(**kw):
    base = dict(machine="m1", axis="X", seq=0, t=[0.0, 0.003, 0.006], v_ref=[0.1, 0.1, 0.1], v_meas=[0.09, 0.095, 0.1])
    base.update(kw)
    return S.SampleBlock(**base)


def test_sample_block_round_trip_and_nan_as_null():
    b = _block(u=[1.0, float("nan"), float("inf")], v_meas=[0.09, None, 0.1])
    data = S.encode(b)
    assert b'"u":[1.0,null,null]' in data and b'"v_meas":[0.09,null,0.1]' in data
    assert b"current" not in data  # absent optional columns are not written
    back = S.decode_samples(data)
    assert back.u == [1.0, None, None] and back.v_meas[1] is None and back.current is None
    assert back.t == b.t and back.seq == 0 and len(back) == 3


def test_inconsistent_lengths_name_field_and_lengths():
    raw = b'{"machine":"m","axis":"X","seq":4,"t":[0,1,2],"v_ref":[1,2,3],"v_meas":[1,2]}'
    with pytest.raises(S.SchemaError, match=r"'v_meas' has 2 values but 't' has 3"):
        S.decode_samples(raw, what="message 7")
    with pytest.raises(ValueError, match="'u' has 1 values"):
        _block(u=[1.0])
    b = _block()
    b.position = [1.0]
    with pytest.raises(S.SchemaError, match="'position'"):
        b.validate()


def test_empty_block_unknown_field_bad_types_negative_seq():
    with pytest.raises(S.SchemaError, match=r"length >= 1 - at `\$.t`"):
        S.decode_samples(b'{"machine":"m","axis":"X","seq":0,"t":[],"v_ref":[],"v_meas":[]}')
    with pytest.raises(S.SchemaError, match="unknown field `curent`"):
        S.decode_samples(b'{"machine":"m","axis":"X","seq":0,"t":[0],"v_ref":[1],"v_meas":[1],"curent":[1]}')
    with pytest.raises(S.SchemaError, match=r"\$.v_ref\[0\]"):
        S.decode_samples(b'{"machine":"m","axis":"X","seq":0,"t":[0],"v_ref":["a"],"v_meas":[1]}')
    with pytest.raises(S.SchemaError, match="seq"):
        S.decode_samples(b'{"machine":"m","axis":"X","seq":-1,"t":[0],"v_ref":[1],"v_meas":[1]}')
    with pytest.raises(S.SchemaError, match="t"):  # a null time rejects the block
        S.decode_samples(b'{"machine":"m","axis":"X","seq":0,"t":[null],"v_ref":[1],"v_meas":[1]}')
    with pytest.raises(S.SchemaError, match="not valid JSON"):
        S.decode_samples(b'{"machine":')


def test_estimate_block_and_flags():
    n = 2
    e = S.EstimateBlock(
        machine="m", axis="X", seq=10, t=[0.0, 0.003], v_meas=[0.1] * n, v_pred=[0.1] * n, residual=[0.0] * n,
        f=[1e-4] * n, f_var=[1e-9] * n, f_next=[1e-4] * n, f_next_var=[1e-9] * n, dict_size=[1, 2],
        removed=[-1, -1], flags=[S.WARMUP, S.GAP | S.REJECTED],
    )
    back = S.decode_estimates(S.encode(e))
    assert back == e and back.force is None
    assert S.flag_names(back.flags[1]) == ["GAP", "REJECTED"]
    assert len({S.STALE, S.GAP, S.REJECTED, S.WARMUP, S.REDUCED}) == 5
    with pytest.raises(ValueError, match="'dict_size' has 1 values"):
        S.EstimateBlock(**{**msgspec.structs.asdict(e), "dict_size": [1]})


def test_trial_meta_round_trip():
    m = S.TrialMeta(
        Ts=1 / 333, form="velocity-loop", machine="m", axis="X", units=dict(S.UNITS), loop_gain=1e5,
        provenance=S.Provenance(source="simulated", tool="t", version="0", seed=3),
        truth=S.TrialTruth(beta=[0.8, 0.2], omega=1e-3, coulomb=False, physical={"inertia": 300.0}),
    )
    assert S.decode_meta(S.encode(m)) == m
    with pytest.raises(S.SchemaError, match="form"):
        S.decode_meta(S.encode(m).replace(b"velocity-loop", b"velocity"))
    with pytest.raises(S.SchemaError, match="Ts"):
        S.decode_meta(S.encode(m).replace(b'"Ts":', b'"Ts":-', 1))


@pytest.mark.parametrize("name", sorted(S.JSON_SCHEMAS))
def test_json_schemas_generated_from_structs(name):
    sch = S.JSON_SCHEMAS[name]
    assert sch["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert sch["type"] == "object" and sch["additionalProperties"] is False
    json.dumps(sch)  # serialisable
    if name == "feedmon.SampleBlock":
        assert set(sch["required"]) == {"machine", "axis", "seq", "t", "v_ref", "v_meas"}
        assert sch["properties"]["v_meas"]["items"] == {"anyOf": [{"type": "number"}, {"type": "null"}]}
        assert sch["properties"]["seq"]["minimum"] == 0


def test_json_schema_validates_encoded_message_when_jsonschema_available():
    try:
        import jsonschema
    except ImportError:  # the structural checks above still run
        return
    jsonschema.validate(json.loads(S.encode(_block(u=[1.0, math.nan, 2.0]))), S.JSON_SCHEMAS["feedmon.SampleBlock"])


# ---- bounds (feedio.limits): names, seq, t, block length; checked on decode and on construction -------
def _raw(**kw) -> bytes:
    base = dict(machine="m1", axis="X", seq=0, t=[0.0, 0.003], v_ref=[0.1, 0.1], v_meas=[0.1, 0.1])
    base.update(kw)
    return json.dumps(base).encode()


@pytest.mark.parametrize("name", ["", "a" * 65, "[/]", "a\n", "a\r\nb", "x\x1b[31m", "-x", ".x", "a b", "a/b", "ä"])
def test_names_outside_the_pattern_are_refused(name):
    for field in ("machine", "axis"):
        with pytest.raises(S.SchemaError, match=field):
            S.decode_samples(_raw(**{field: name}))
        with pytest.raises(ValueError, match=field):
            _block(**{field: name})
    assert S.check_name("a" * 64, "name") == "a" * 64 and S.check_name("mill_1.x-2", "name")


def test_seq_and_time_bounds():
    assert S.SEQ_MAX == 2**53 - 1
    S.decode_samples(_raw(seq=S.SEQ_MAX - 1))  # last sample exactly at SEQ_MAX
    for seq in (S.SEQ_MAX, 2**63, 2**64, -1):
        with pytest.raises(S.SchemaError, match="seq"):
            S.decode_samples(_raw(seq=seq))
    S.decode_samples(_raw(t=[0.0, S.T_MAX]))
    for bad in (2e10, -1.0, -1e-300, 1e308):
        with pytest.raises(S.SchemaError, match=r"\$\.t\[1\]|'t'"):
            S.decode_samples(_raw(t=[0.0, bad]))
        with pytest.raises(ValueError, match="'t'"):
            _block(t=[0.0, bad, 1.0])
    with pytest.raises(ValueError, match="'t'"):
        _block(t=[0.0, math.nan, 1.0])
    with pytest.raises(ValueError, match="seq"):
        _block(seq=True)


def test_invalid_utf8_inside_a_string_is_a_schema_error():
    raw = _raw().replace(b'"v_meas"', b'"v\xa0meas"')
    with pytest.raises(S.SchemaError, match="UTF-8"):
        S.decode_samples(raw)


def test_json_schema_states_the_bounds():
    sch = S.JSON_SCHEMAS["feedmon.SampleBlock"]["properties"]
    assert sch["machine"]["pattern"] == S.NAME_PATTERN and sch["machine"]["maxLength"] == 64
    assert sch["seq"]["maximum"] == S.SEQ_MAX and sch["seq"]["minimum"] == 0
    assert sch["t"]["items"] == {"type": "number", "minimum": 0.0, "maximum": S.T_MAX}
    assert sch["t"]["minItems"] == 1 and sch["t"]["maxItems"] == 1_000_000
