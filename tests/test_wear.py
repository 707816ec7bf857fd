"""The wear alarm across parts (M7, monitor/process_monitor/wear.py): the rule on part series of the simulator
(per-section statistics from the true force of short parts), the history file and its refusals, and the
wiring through ``feedmon run --from … --wear-history``."""

from __future__ import annotations

import json
import os

import msgspec
import numpy as np
import pytest

from feedio.mcapio import iter_blocks, read_trial
from feedmon.cli import main
from monitor.model_file import save_model, truth_model
from monitor.process_monitor.settings import WearSettings
from monitor.process_monitor.wear import (
    MAX_HISTORY_BYTES,
    MAX_HISTORY_SECTIONS,
    WearHistory,
    WearMonitor,
    judge,
    load_history,
    save_history,
)
from replay import parts as PT
from replay import scenarios as SC
from replay.simulator import simulate

#: short parts: the mean force of a section does not depend on its length, the spread from part to part
#: (material, spindle speed, feed override, spindle phase) is that of the 20 s parts or larger
PART_S = 2.0


def _series(tmp_path, n_parts: int, seed: int, wear: float) -> tuple[list[int], WearMonitor]:
    """The parts (indices) whose end raised a wear alarm, part by part as ``feedmon run --wear-history`` does."""
    sc = SC.load_scenario("milling-part")
    sc["duration"] = PART_S
    mon = WearMonitor(WearSettings(history=str(tmp_path / f"wear-{seed}-{wear}.json")))
    alarmed = []
    for var in PT.part_variations(sc, n_parts, seed=seed, wear_per_part=wear):
        alarms = mon.add_run("m", "x", PT.truth_sections(simulate(PT.part_scenario(sc, var), seed=var.seed)),
                             f"part-{var.index}", "2026-11-28T00:00:00Z", (var.index, 1.0))
        assert all(a.kind == "wear" and a.monitor == "wear" and a.value > a.limit for a in alarms)
        if alarms:
            alarmed.append(var.index)
    return alarmed, mon


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_percent_per_part_alarms_by_part_20_and_200_nominal_parts_do_not(tmp_path, seed):
    alarmed, _ = _series(tmp_path, 21, seed, 0.01)
    assert alarmed and alarmed[0] <= 20, alarmed
    assert alarmed[-1] == 20  # once worn, every later part says so
    alarmed, mon = _series(tmp_path, 200, seed, 0.0)
    assert alarmed == [], mon.report
    mon.save()  # the file keeps the last `keep` parts of each cutting section (approach and retract: no cut)
    hist = load_history(mon.path)
    (ax,) = hist.axes
    assert [s.key for s in ax.sections] == ["T1/L20/0", "T1/L30/0", "T1/L40/0", "T1/L50/0"]
    assert all([p.part for p in s.parts] == [f"part-{i}" for i in range(150, 200)] for s in ax.sections)


def test_the_rule_needs_both_significance_and_rise():
    s = WearSettings(history="unused.json")
    rng = np.random.default_rng(5)
    assert judge(100.0 * (1 + 0.02 * np.arange(9)), s) is None  # fewer than min_parts
    v = judge(100.0 * (1 + 0.02 * np.arange(20)) + rng.normal(0, 0.5, 20), s)
    assert v.alarm and v.t > 5 and v.rise > 0.3 and v.limit == pytest.approx(0.10)
    v = judge(100.0 * (1 + 0.002 * np.arange(20)) + rng.normal(0, 0.05, 20), s)  # significant, but 4 %
    assert not v.alarm and v.t > 5 and v.rise < 0.10
    v = judge(100.0 * (1 + 0.02 * np.arange(20)) + rng.normal(0, 15.0, 20), s)  # a rise the spread explains
    assert not v.alarm and v.t < 5 and v.limit > v.rise
    v = judge(-100.0 * (1 + 0.02 * np.arange(25)), s)  # a force against the feed: its magnitude rises
    assert v.alarm and v.parts == 20


def _stats(line: int, force: float, energy: float) -> dict:
    return {"tool": 1, "program_line": line, "occurrence": 0, "rows": 100, "mean_force_N": force, "energy_J": energy}


def test_energy_statistic_and_the_section_bound(tmp_path):
    """``statistic = "energy"`` judges the cut energy (here rising while the mean force stays); a history that
    holds MAX_HISTORY_SECTIONS sections records no new one and says so."""
    force = WearMonitor(WearSettings(history=str(tmp_path / "f.json")))
    energy = WearMonitor(WearSettings(history=str(tmp_path / "e.json"), statistic="energy"))
    for i in range(15):
        run = [_stats(20, 30.0, 0.5 * (1 + 0.03 * i)), _stats(10, 0.5, 0.0)]  # line 10: no cut
        assert force.add_run("m", "x", run, f"p{i}", "", (i, 1.0)) == []
        got = energy.add_run("m", "x", run, f"p{i}", "", (i, 1.0))
    assert [(a.kind, a.program_line, a.seq) for a in got] == [("wear", 20, 14)]
    assert [s.key for s in energy.history.axes[0].sections] == ["T1/L20/0"]
    full = WearMonitor(WearSettings(history=str(tmp_path / "full.json")))
    for line in range(MAX_HISTORY_SECTIONS):
        full.add_run("m", "x", [_stats(line, 30.0, 1.0)], "p", "", None)
    full.save()
    full = WearMonitor(WearSettings(history=str(tmp_path / "full.json")))
    full.add_run("m", "y", [_stats(5, 30.0, 1.0)], "p", "", None)
    assert full.refused_sections == 1 and "1 new section(s) NOT recorded" in full.report[-1]
    assert [a.axis for a in full.history.axes] == ["x", "y"] and full.history.axes[1].sections == []


def _history_of(parts: list[float]) -> WearHistory:
    return msgspec.convert({"axes": [{"machine": "m", "axis": "x", "sections": [
        {"key": "T1/L20/0", "tool": 1, "program_line": 20, "occurrence": 0,
         "parts": [{"part": f"p{i}", "time": "2026-11-28T00:00:00Z", "mean_force_N": f, "energy_J": f / 40,
                    "rows": 170} for i, f in enumerate(parts)]}]}]}, WearHistory)


def test_history_round_trip_is_atomic(tmp_path):
    path = tmp_path / "h.json"
    assert load_history(path).axes == []  # not there yet: an empty history
    save_history(_history_of([30.0, 31.0]), path)
    assert load_history(path) == _history_of([30.0, 31.0])
    assert os.listdir(tmp_path) == ["h.json"]  # no temporary file left
    with pytest.raises(ValueError, match="its directory does not exist"):
        load_history(tmp_path / "no" / "h.json")


@pytest.mark.parametrize("content, why", [
    (b"{not json", "malformed|JSON"),
    (b'{"format_version": 2, "axes": []}', "format_version"),
    (json.dumps({"axes": [{"machine": "m", "axis": "x", "sections": [{"key": "k", "tool": None, "program_line": None,
                                                                       "occurrence": 0, "parts": [
        {"part": "p", "time": "", "mean_force_N": 1.0, "energy_J": 1.0, "rows": 0}]}]}]}).encode(), "rows"),
    (json.dumps({"axes": [{"machine": "m", "axis": "x", "sections": [
        {"key": "k", "tool": None, "program_line": None, "occurrence": 0,
         "parts": [{"part": "p", "time": "", "mean_force_N": 1.0, "energy_J": 1.0, "rows": 1}] * 201}]}]}).encode(),
     "length"),
    (None, "larger than the limit"),
])
def test_a_bad_history_is_refused_naming_the_file_and_the_fix_and_kept(tmp_path, content, why):
    path = tmp_path / "h.json"
    if content is None:  # over the size limit (sparse: nothing is written)
        with open(path, "wb") as fh:
            fh.truncate(MAX_HISTORY_BYTES + 1)
    else:
        path.write_bytes(content)
    before = path.read_bytes()
    with pytest.raises(ValueError, match=why) as err:
        WearMonitor(WearSettings(history=str(path)))
    assert str(path) in str(err.value) and "move it away" in str(err.value)
    assert path.read_bytes() == before


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    """Two short parts of a series and the truth model of the drive."""
    d = tmp_path_factory.mktemp("wear")
    assert main(["simulate", "milling-part", "--parts", "2", "--duration", str(PART_S), "-o", str(d),
                 "--seed", "4"]) == 0
    save_model(truth_model(read_trial(d / "part-0000.mcap").meta, period=1 / 50, budget=100), d / "m.model.toml")
    return d


def _run(d, part: str, history, out: str, *extra: str) -> int:
    return main(["run", "--from", str(d / part), "--model", str(d / "m.model.toml"), "-o", str(d / out),
                 "--wear-history", str(history), *extra])


def test_run_appends_the_part_and_raises_wear_on_a_rising_history(parts, tmp_path, capsys):
    hist = tmp_path / "wear.json"
    assert _run(parts, "part-0000.mcap", hist, "out-0.mcap") == 0
    first = load_history(hist)
    (ax,) = first.axes
    assert (ax.machine, ax.axis) == ("cnc-mill", "X")
    assert [s.key for s in ax.sections] == ["T1/L20/0", "T1/L30/0", "T1/L40/0", "T1/L50/0"]
    assert all(len(s.parts) == 1 and s.parts[0].part == "part-0000.mcap" and s.parts[0].mean_force_N > 5
               for s in ax.sections)
    assert [b for _, b in iter_blocks(parts / "out-0.mcap", None, ("alarm",))] == []
    assert "wear cnc-mill/X T1/L20/0: 1 part(s), judged from 10" in capsys.readouterr().err
    # twelve earlier parts of a tool wearing 3 % a part, ending where this part's force is: it has risen
    for sec in ax.sections:
        now = sec.parts[0]
        sec.parts[:] = [msgspec.structs.replace(now, part=f"old-{i}", mean_force_N=now.mean_force_N * (1 - 0.03 * (12 - i)))
                        for i in range(12)]
    save_history(first, hist)
    assert _run(parts, "part-0001.mcap", hist, "out-1.mcap") == 0
    alarms = [b for _, b in iter_blocks(parts / "out-1.mcap", None, ("alarm",))]
    assert sorted(a.program_line for a in alarms) == [20, 30, 40, 50]
    last = [b for _, b in iter_blocks(parts / "out-1.mcap", None, ("disturbance",))][-1]
    assert all(a.kind == "wear" and a.monitor == "wear" and a.tool == 1 and a.value > a.limit >= 0.10
               and a.seq == last.seq + len(last.t) - 1 for a in alarms)
    assert all(len(s.parts) == 13 and s.parts[-1].part == "part-0001.mcap" for s in load_history(hist).axes[0].sections)
    assert "— WEAR (above" in capsys.readouterr().err
    assert main(["wear", "show", str(hist)]) == 0
    shown = capsys.readouterr().out
    assert shown.count("part-0001.mcap") == 4 and shown.count("WEAR") == 4 and "T1/L50/0" in shown


def test_run_refuses_a_bad_history_at_start_and_leaves_it(parts, tmp_path, capsys):
    hist = tmp_path / "wear.json"
    hist.write_bytes(b'{"format_version": 7}')
    assert _run(parts, "part-0000.mcap", hist, "refused.mcap") == 2
    err = capsys.readouterr().err
    assert str(hist) in err and "move it away" in err
    assert hist.read_bytes() == b'{"format_version": 7}' and not (parts / "refused.mcap").exists()
    cfg = tmp_path / "run.toml"
    cfg.write_text("[monitors.wear]\nhistory = 'w.json'\nwindow = 100\n")
    assert _run(parts, "part-0000.mcap", hist, "refused.mcap", "--config", str(cfg)) == 2
    assert "monitors.wear" in capsys.readouterr().err


def test_live_run_appends_at_stop_and_publishes_wear_before_the_sinks_close(parts, tmp_path):
    """The live monitor: the run is one part, appended when it stops; its wear alarms go out on Zenoh and into
    the MCAP log like every other alarm (the same section statistics as offline: a rising history ends there)."""
    import threading

    from live_monitor import Live

    from feedio import schema as S
    from feedio import transport as T
    from monitor.axes import load_axes
    from monitor.process_monitor import MonitorSettings, build_monitors
    from monitor.sinks.mcap_sink import McapProcessSink
    from monitor.sinks.rerun_events import alarm_line

    hist = tmp_path / "wear.json"
    assert _run(parts, "part-0000.mcap", hist, "live-ref.mcap") == 0
    rising = load_history(hist)
    for sec in rising.axes[0].sections:
        now = sec.parts[0]
        sec.parts[:] = [msgspec.structs.replace(now, part=f"old-{i}", mean_force_N=now.mean_force_N * (1 - 0.03 * (12 - i)))
                        for i in range(12)]
    save_history(rising, hist)
    axes = load_axes([str(parts / "m.model.toml")])
    trial = read_trial(parts / "part-0000.mcap")
    log = tmp_path / "live.mcap"
    settings = MonitorSettings(enabled=True, wear=WearSettings(history=str(hist)))
    live = Live(axes, prefix="feedmon-wear", key=T.samples_key("feedmon-wear", "cnc-mill", "X"),
                sinks=[McapProcessSink(log, metas=[trial.meta], start_timeout=60)],
                monitors=build_monitors(axes, settings))
    got: list[S.AlarmEvent] = []
    four = threading.Event()

    def on_alarm(sample):
        got.append(S.decode_alarm(sample.payload.to_bytes()))
        if len(got) >= 4:
            four.set()

    sub = live.s.declare_subscriber(T.alarm_key("feedmon-wear"), on_alarm)
    try:
        n = 0
        for _, b in iter_blocks(parts / "part-0000.mcap", None, ("samples",)):
            live.pub.put(S.encode(b))
            n += len(b.t)
        live.wait(lambda m: m.status()["axes"]["cnc-mill/X"]["samples_in"] >= n)
        assert live.monitor.stop() == []
        assert four.wait(30.0)
    finally:
        sub.undeclare()
        assert live.close() == []
    assert sorted((a.kind, a.program_line) for a in got) == [("wear", 20), ("wear", 30), ("wear", 40), ("wear", 50)]
    assert alarm_line(got[0]).startswith(f"ALARM wear at t = {got[0].t:.3f} s: rise {got[0].value:.1%} against limit")
    logged = [b for _, b in iter_blocks(log, None, ("alarm",))]
    assert sorted(a.program_line for a in logged) == [20, 30, 40, 50] and all(a.kind == "wear" for a in logged)
    assert all(len(s.parts) == 13 and s.parts[-1].part.startswith("live ") for s in load_history(hist).axes[0].sections)
