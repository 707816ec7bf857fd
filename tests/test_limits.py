"""One source of truth for the input limits: ``feedio.limits`` is what the schema, the pipeline, the
daemon and the config loader use, and what the table of docs/limits.md says."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

import msgspec
import pytest

from feedio import limits as L
from feedio import schema as S

LIMITS_DOC = Path(__file__).resolve().parents[1] / "docs" / "limits.md"
SECTION = "The monitor's input"


def _section(title: str) -> str:
    text = LIMITS_DOC.read_text(encoding="utf-8")
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end]


def _rows(section: str) -> dict[str, list[str]]:
    """First-column name (backticks stripped) → cells of every table row of a section."""
    out = {}
    for line in section.splitlines():
        m = re.match(r"^\| `([^`]+)`(.*)\|$", line)
        if m:
            out[m.group(1)] = [c.strip() for c in m.group(2).split("|")[1:]]
    return out


def test_docs_table_lists_every_configurable_limit_with_its_default_and_range():
    rows = _rows(_section(SECTION))
    for name in L.InputLimits.__struct_fields__:
        assert name in rows, f"docs/limits.md '{SECTION}' has no row for {name}"
        default, allowed = rows[name][0], rows[name][1]
        assert default.split()[0] == repr(getattr(L.DEFAULT, name)), (name, default)
        lo, hi = L.field_range(L.InputLimits, name)
        assert allowed.startswith(f"{lo:g} … {hi:g}" if isinstance(lo, float) else f"{lo} … {hi}"), (name, allowed)


def test_contract_bounds_are_the_schemas():
    sec = _section(SECTION)
    assert L.NAME_PATTERN in LIMITS_DOC.read_text(encoding="utf-8")
    assert "2**53 − 1" in sec and "1e10" in sec and "1 000 000" in sec
    assert S.SEQ_MAX == L.SEQ_MAX == 2**53 - 1 and S.T_MAX == L.T_MAX == 1e10
    assert L.BLOCK_SAMPLES_MAX == L.field_range(L.InputLimits, "max_block_samples")[1]
    assert L.T_MAX * 1e9 < 2**64  # every allowed time is an MCAP log time (uint64 ns)


def test_estimator_uses_the_physical_limits_of_feedio_limits():
    from monitor.estimator import LIMITS

    assert LIMITS == L.LIMITS == {"v": L.SAMPLE_LIMITS.v_max, "u": L.SAMPLE_LIMITS.u_max, "t": L.SAMPLE_LIMITS.t_max}


def test_limits_are_validated_with_their_ranges():
    with pytest.raises(msgspec.ValidationError, match=r">= 1024 - at `\$.max_message_bytes`"):
        msgspec.convert({"max_message_bytes": 10}, L.InputLimits)
    with pytest.raises(msgspec.ValidationError, match="queue_bytes .* must be >= max_message_bytes"):
        msgspec.convert({"queue_bytes": 4096, "max_message_bytes": 8192}, L.InputLimits)
    assert L.range_text(L.InputLimits, "queue_messages") == "1 ≤ queue_messages ≤ 1000000"
    assert L.range_text(L.InputLimits, "status_refresh_s") == "0 ≤ status_refresh_s ≤ 60"


class _Axis(msgspec.Struct, forbid_unknown_fields=True):
    scale: L.bounded_float(0.0, 1e9, "units per m", open_low=True) = 1.0
    mode: Literal["a", "b"] = "a"


class _Root(msgspec.Struct, forbid_unknown_fields=True):
    axes: dict[str, _Axis] = {}
    steps: list[_Axis] = []
    limits: L.InputLimits = L.InputLimits()


def test_explain_names_the_key_its_range_and_the_known_keys():
    """One explainer for every settings file: through nested tables, a table of tables (msgspec names its
    key ``[...]``) and a list, the key and the range derived from the Struct; an unknown key lists the keys
    known there."""

    def explained(doc):
        with pytest.raises(msgspec.ValidationError) as info:
            msgspec.convert(doc, _Root)
        return L.explain(info.value, _Root)

    key, msg = explained({"axes": {"X": {"scale": -1.0}}})
    assert key == "axes[...].scale" and msg.endswith("(allowed: 0 < scale ≤ 1e+09)")
    key, msg = explained({"steps": [{}, {"mode": "c"}]})
    assert key == "steps[1].mode" and msg.endswith("(allowed: mode one of a, b)")
    key, msg = explained({"limits": {"queue_bytes": 1}})
    assert key == "limits.queue_bytes" and msg.endswith("(allowed: 1024 ≤ queue_bytes ≤ 17179869184)")
    key, msg = explained({"axes": {"X": {"scal": 2.0}}})
    assert key == "axes[...]" and msg.endswith("known keys here: scale, mode")
    key, msg = explained({"axis": {}})
    assert key == "(top level)" and msg.endswith("known keys here: axes, steps, limits")


def _loaders():
    from bridge.linuxcnc.config import load_config
    from feedmon.run_config import load_config_file
    from monitor.model_file import load_model
    from monitor.process_monitor.reference import MAX_REFERENCE_BYTES, load_reference
    from monitor.process_monitor.wear import MAX_HISTORY_BYTES, load_history
    from replay.scenarios import load_scenario

    return [("model file", load_model, L.MAX_CONFIG_BYTES), ("config file", load_config_file, L.MAX_CONFIG_BYTES),
            ("bridge config file", load_config, L.MAX_CONFIG_BYTES),
            ("scenario config", lambda p: load_scenario("shaker-constant", p), L.MAX_CONFIG_BYTES),
            ("reference file", load_reference, MAX_REFERENCE_BYTES), ("wear history", load_history, MAX_HISTORY_BYTES)]


@pytest.mark.parametrize("kind", ["file", "endless"])
def test_every_file_a_user_names_is_read_only_up_to_its_limit(tmp_path, kind):
    """Model, run config, bridge config, scenario config, reference and wear history files: one byte over the
    limit, or an endless stream (/dev/zero, whose size on disk is 0), is refused naming the file and the
    limit — never read whole."""
    for what, load, limit in _loaders():
        if kind == "endless":
            path = Path("/dev/zero")
        else:
            path = tmp_path / f"{what.replace(' ', '_')}.toml"
            path.write_bytes(b"#" * (limit + 1))
        with pytest.raises(ValueError, match="limit") as err:
            load(path)
        assert str(path) in str(err.value) and str(limit) in str(err.value) and what in str(err.value), err.value
