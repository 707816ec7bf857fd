"""The context columns (NC ``program_line``, ``tool``): in the sample schema, carried to the estimate rows of
the same samples (also when the estimator drops a prefix of re-sent samples), in the offline run's MCAP log
and on the dashboard."""

from __future__ import annotations

import numpy as np
import pytest
from test_dashboard import est_block, open_rrd, rrd_scalars
from truth_models import truth_workdir

from feedio import schema as S
from feedio.mcapio import iter_blocks, read_trial, write_arrays
from feedmon.cli import main
from monitor.axes import load_axes


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "context", duration=3.0, seed=5)


def line_of(seq):
    return 100 + np.asarray(seq) // 40  # the NC line changes every 40 samples


def _block(tr, i: int, j: int, *, tool: bool = True) -> S.SampleBlock:
    seq = np.arange(i, j)
    return S.SampleBlock(machine=tr.machine, axis=tr.axis, seq=i, t=tr.t[i:j].tolist(), v_ref=tr.v_ref[i:j].tolist(),
                         v_meas=tr.v_meas[i:j].tolist(), program_line=line_of(seq).tolist(),
                         tool=[3] * (j - i) if tool else None)


def test_schema_bounds_and_lengths_of_the_context_columns():
    blk = S.SampleBlock(machine="m", axis="X", seq=0, t=[0.0, 0.001], v_ref=[0, 0], v_meas=[0, 0],
                        program_line=[12, None], tool=[2**31 - 1, -(2**31)])
    assert S.decode_samples(S.encode(blk)) == blk and "program_line" in S.SAMPLE_COLUMNS
    bad = S.encode(blk).replace(b"2147483647", b"2147483648")
    with pytest.raises(S.SchemaError, match="tool"):
        S.decode_samples(bad)
    with pytest.raises(S.SchemaError, match="'program_line' has 1 values but 't' has 2"):
        S.decode_samples(S.encode(blk).replace(b"[12,null]", b"[12]"))
    with pytest.raises(S.SchemaError, match="program_line"):
        S.decode_samples(S.encode(blk).replace(b"[12,null]", b"[12.5,1]"))


def test_estimate_rows_carry_the_context_of_their_samples_also_after_a_dropped_prefix(work):
    tr = read_trial(work / "trial.mcap")
    ax = next(iter(load_axes([work / "z.model.toml"]).values()))
    got_seq, got_line, got_tool = [], [], []
    for i, j in ((0, 100), (100, 150), (120, 200), (200, 260)):  # (120, 200) re-sends 120…149: a prefix dropped
        est = ax.estimator.process_rows(_block(tr, i, j, tool=i != 200))
        blk = est.block()
        assert est.json() == S.encode(blk)
        assert blk.seq == max(i, 150 if i == 120 else i) and len(blk.program_line) == len(blk)
        got_seq += range(blk.seq, blk.seq + len(blk))
        got_line += blk.program_line
        got_tool += blk.tool or [None] * len(blk)
    assert ax.estimator.counters["duplicate"] + ax.estimator.counters["out_of_order"] == 30
    assert got_seq == list(range(260))
    assert got_line == line_of(got_seq).tolist()
    assert got_tool == [3] * 200 + [None] * 60  # a block without the column: absent from its rows


def test_the_offline_run_logs_the_context_with_the_estimates(work, tmp_path):
    tr = read_trial(work / "trial.mcap")
    n = len(tr)
    trial = tmp_path / "ctx.mcap"
    write_arrays(trial, tr.meta, {"t": tr.t, "v_ref": tr.v_ref, "v_meas": tr.v_meas, "u": tr.u,
                                  "program_line": line_of(np.arange(n)), "tool": np.full(n, 7)}, block=64)
    assert read_trial(trial).program_line[-1] == line_of(n - 1)
    out = tmp_path / "out.mcap"
    assert main(["run", "--from", str(trial), "-o", str(out), "--model", str(work / "z.model.toml")]) == 0
    seq, lines, tools = [], [], []
    for _, blk in iter_blocks(out, kinds=("disturbance",)):
        seq += range(blk.seq, blk.seq + len(blk))
        lines += blk.program_line
        tools += blk.tool
    assert seq == list(range(n)) and lines == line_of(seq).tolist() and set(tools) == {7}


def test_the_dashboard_shows_the_nc_line_and_tool(tmp_path):
    """A series per context column at the row's own sample, and a panel for them on the axes that have them."""
    from rerun.chunk import RrdReader

    from monitor.sinks.rerun_sink import RerunSink

    rrd = tmp_path / "ctx.rrd"
    sink = RerunSink(rrd_path=rrd, batch_interval=0.02)
    for k in range(0, 300, 30):
        blk = est_block(k, 30)
        blk.program_line = line_of(np.arange(k, k + 30)).tolist()
        blk.tool = [4] * 30
        sink.offer(blk)
        sink.offer(est_block(k, 30, axis="Y"))  # an axis without context: no context panel, no entity
    assert sink.close(timeout=60)
    assert sink.status()["failures"] == 0
    store = open_rrd(rrd)
    seq, _, lines = rrd_scalars(store, "/mill/X/context/program_line")
    assert seq.tolist() == list(range(300)) and lines.tolist() == line_of(seq).tolist()  # at the row's own sample
    assert set(rrd_scalars(store, "/mill/X/context/tool")[2]) == {4.0}
    assert rrd_scalars(store, "/mill/Y/context/program_line")[0].size == 0
    reader = RrdReader(str(rrd))
    origins = {o for chunk in reader.stream(store=reader.blueprints()[-1]).to_chunks()
               for row in chunk.to_record_batch().to_pydict().get("ViewBlueprint:space_origin", []) for o in row or []}
    assert "/mill/X/context" in origins and "/mill/Y/context" not in origins and "/mill/Y/force" in origins
