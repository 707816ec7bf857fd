"""Process-monitoring scenarios with known answers: the per-tooth cutting model against its closed
forms, truth events through MCAP, the part series' variation as configured, and the trials of the
older scenarios unchanged byte for byte."""

import hashlib
import math

import numpy as np
import pytest

from feedio import schema as S
from feedio.mcapio import TRUTH_EVENTS, iter_blocks, read_trial, topic
from feedmon.cli import main
from replay import parts as PT
from replay import scenarios as SC
from replay.cutting import (
    MillingTool,
    ToothCondition,
    feed_force,
    feed_force_teeth,
    once_per_rev_amplitude,
    tooth_chips,
)
from replay.simulator import simulate, simulate_scenario, write_trial

PROCESS = ("milling-part", "milling-tooth-break", "milling-runout", "milling-collision", "milling-missing-cut")
QUIET = {"noise": {"v_meas_std": 0.0, "glitch_rate": 0.0, "dynamometer_std": 0.0}}
CREATED = "2024-05-01T08:00:00Z"


def _line(x: np.ndarray, dt: float, f: float) -> float:
    """Amplitude of the sinusoid of frequency f (Hz) in x sampled at dt over whole periods."""
    t = np.arange(x.size) * dt
    return 2.0 * abs(np.mean(x * np.exp(-2j * np.pi * f * t)))


def _tooth_means(per_tooth: np.ndarray, t: np.ndarray, t0: float, t1: float) -> np.ndarray:
    m = (t >= t0) & (t < t1)
    return per_tooth[m].mean(axis=0)


# ---------------------------------------------------------------------------------------------
# cutting model: runout, broken tooth, material
# ---------------------------------------------------------------------------------------------
def test_once_per_rev_component_matches_the_closed_form():
    """Runout ρ at λ = 0 on a 2-tooth slot: chips c ± 2ρ, spindle line (2 a Δc/3π)·√(K_tc² + 4K_rc²), Δc = 4ρ."""
    tool = MillingTool(runout=0.004, angle_step=0.25)
    c = 0.05  # mm per tooth
    feed = c * 1e-3 * tool.tooth_hz
    dt = 1.0 / (tool.spindle_hz * 720)  # 0.5° of spindle rotation per interval
    n = 720 * 20  # 20 revolutions
    force, teeth = feed_force_teeth(tool, 0.0, dt, np.full(n, feed))
    expected = once_per_rev_amplitude(tool, 4 * tool.runout)
    assert expected > 4.0  # N: a line a monitor can see
    assert _line(force, dt, tool.spindle_hz) == pytest.approx(expected, rel=5e-3)
    np.testing.assert_allclose(teeth.sum(axis=1), force, rtol=1e-12, atol=1e-9)
    # the older kernel agrees while every tooth cuts
    np.testing.assert_allclose(feed_force(tool, 0.0, dt, np.full(n, feed)), force, rtol=1e-9, atol=1e-9)
    # the same runout as per-tooth offsets in m (no ρ): the same line
    plain = MillingTool(runout=0.0, angle_step=0.25)
    cond = ToothCondition(offsets_m=(4e-6, -4e-6))
    force2, _ = feed_force_teeth(plain, 0.0, dt, np.full(n, feed), condition=cond)
    assert _line(force2, dt, tool.spindle_hz) == pytest.approx(expected, rel=5e-3)
    # sampled at 333 Hz (ZOH averages): the line shrinks by sinc(f Ts)
    Ts = 1.0 / 333.0
    sampled = feed_force(tool, 0.0, Ts, np.full(int(333 * 2), feed))  # 2 s = 100 whole revolutions
    x = tool.spindle_hz * Ts * math.pi
    assert _line(sampled, Ts, tool.spindle_hz) == pytest.approx(expected * math.sin(x) / x, rel=5e-3)


def test_runout_that_grows_moves_the_line_linearly():
    tool = MillingTool(runout=0.0, angle_step=0.25)
    rate = 2e-6  # m/s on tooth 0
    cond = ToothCondition(growth_m_per_s=(rate, 0.0), growth_from_s=0.5)
    c = 0.06
    dt = 1.0 / (tool.spindle_hz * 720)
    n = int(round(3.0 / dt))
    force, _ = feed_force_teeth(tool, 0.0, dt, np.full(n, c * 1e-3 * tool.tooth_hz), condition=cond)
    t = np.arange(n) * dt
    for t0 in (0.0, 1.0, 2.0):  # 10 revolutions from t0: runout offset 1e3·rate·(t_mid − 0.5) mm on tooth 0
        m = (t >= t0) & (t < t0 + 0.2)
        grown = 1e3 * rate * max(t0 + 0.1 - 0.5, 0.0)  # mean offset over the window (linear)
        if t0 == 0.0:
            assert _line(force[m], dt, tool.spindle_hz) < 1e-6
        else:  # r_0 − r_1 = grown: chips c ± grown, Δc = 2·grown
            assert _line(force[m], dt, tool.spindle_hz) == pytest.approx(once_per_rev_amplitude(tool, 2 * grown), rel=1e-2)


def test_broken_tooth_share_drops_to_zero_and_the_next_tooth_cuts_twice_the_chip():
    """3 teeth, slot, no runout: one tooth's mean force per revolution is a c K_rc/4 + a K_re/π; after
    tooth 1 breaks, tooth 0 (the one after it) cuts 2c and tooth 2 is unchanged."""
    tool = MillingTool(teeth=3, runout=0.0, angle_step=0.25)
    c = 0.05
    t_break = 0.5
    cond = ToothCondition(breaks=((1, t_break, 1e-3),))
    dt = 1.0 / (tool.spindle_hz * 720)
    n = int(round(1.0 / dt))
    force, teeth = feed_force_teeth(tool, 0.0, dt, np.full(n, c * 1e-3 * tool.tooth_hz), condition=cond)
    t = np.arange(n) * dt
    a = tool.depth

    def one(chip):
        return a * chip * tool.Krc / 4 + a * tool.Kre / math.pi

    before = _tooth_means(teeth, t, 0.0, 0.4)  # 20 revolutions
    after = _tooth_means(teeth, t, 0.6, 1.0)
    np.testing.assert_allclose(before, one(c), rtol=2e-3)
    assert after[1] == 0.0
    assert after[0] == pytest.approx(one(2 * c), rel=2e-3)
    assert after[0] - before[0] == pytest.approx(a * c * tool.Krc / 4, rel=5e-3)  # the rise: the chip of tooth 1
    assert after[2] == pytest.approx(before[2], rel=1e-3)
    np.testing.assert_array_equal(tooth_chips(tool, cond, c, 0.9), [2 * c, 0.0, c])
    # a chipped tooth (10 µm shorter): it cuts c − 0.01 mm, the tooth after it c + 0.01 mm
    chipped = ToothCondition(breaks=((1, 0.0, 1e-5),))
    np.testing.assert_allclose(tooth_chips(tool, chipped, c, 0.1), [c + 0.01, c - 0.01, c], rtol=1e-12)


def test_material_factor_scales_the_force():
    tool = MillingTool(runout=0.0)
    feed = np.full(2000, 0.05 * 1e-3 * tool.tooth_hz)
    base, _ = feed_force_teeth(tool, 0.0, 1 / 333.0, feed)
    hard, _ = feed_force_teeth(tool, 0.0, 1 / 333.0, feed, condition=ToothCondition(material=1.25))
    np.testing.assert_allclose(hard, 1.25 * base, rtol=1e-12)


def test_tooth_condition_refuses_what_does_not_fit():
    tool = MillingTool()
    for cond, match in ((ToothCondition(offsets_m=(1e-6,)), "offsets_m needs one value per tooth"),
                        (ToothCondition(breaks=((2, 1.0, 1e-3),)), "not one of the tool's teeth"),
                        (ToothCondition(breaks=((0, 1.0, 0.0),)), "loss in"),
                        (ToothCondition(material=0.0), "material factor"),
                        (ToothCondition(growth_m_per_s=(1.0, 0.0)), "growth_m_per_s")):
        with pytest.raises(ValueError, match=match):
            feed_force_teeth(tool, 0.0, 0.003, np.ones(3) * 0.005, condition=cond)


# ---------------------------------------------------------------------------------------------
# scenarios: sections, events at the configured times
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trials(tmp_path_factory):
    """Every process scenario, seed 1, written and read back."""
    d = tmp_path_factory.mktemp("process")
    out = {}
    for name in PROCESS:
        res = simulate_scenario(name, seed=1, created=CREATED)
        write_trial(res, d / f"{name}.mcap")
        out[name] = (res, read_trial(d / f"{name}.mcap"))
    return out


def test_sections_program_line_and_tool(trials):
    res, tr = trials["milling-part"]
    sc = SC.load_scenario("milling-part")
    assert tr.tool is not None and np.all(tr.tool == sc["program"]["tool"])
    lines = np.unique(tr.program_line)
    np.testing.assert_array_equal(lines, [10, 20, 30, 40, 50, 60])  # approach, 4 sections, retract
    # each feed section holds its level: feed per tooth = v_ref / (n N_t), mid-section
    for i, level in enumerate(sc["trajectory"]["levels"]):
        m = tr.program_line == 20 + 10 * i
        mid = np.flatnonzero(m)[np.flatnonzero(m).size // 2]
        assert tr.v_ref[mid] * 1e3 / (tr.spindle_rpm[mid] / 60 * 2) == pytest.approx(level, rel=1e-9)
    assert res.events == [] and tr.truth_events == []
    assert topic("cnc-mill", "X", TRUTH_EVENTS) not in tr.channels
    assert tr.spindle_angle is not None and tr.spindle_rpm is not None


def test_tooth_break_scenario(trials):
    res, tr = trials["milling-tooth-break"]
    (ev,) = tr.truth_events
    assert (ev.kind, ev.t_s, ev.value, ev.detail["next_tooth"]) == ("tooth_break", 9.0, 1.0, 0)
    assert ev.seq == int(9.0 / tr.Ts) and tr.t[ev.seq] <= 9.0 < tr.t[ev.seq] + tr.Ts
    assert ev.detail["spindle_rpm"] == tr.spindle_rpm[ev.seq] == 3000.0
    line = tr.program_line[ev.seq]  # the section it breaks in
    after = (res.t > 9.0 + tr.Ts) & (tr.program_line == line)
    before = (res.t < 9.0) & (tr.program_line == line) & (res.t > 8.0)
    assert after.sum() > 100 and before.sum() > 100
    assert np.all(res.tooth_force[after, 1] == 0.0)
    share = res.tooth_force[after, 0].mean() / res.tooth_force[before, 0].mean()
    assert 1.3 < share < 2.0  # chip 2c: the chip-proportional part doubles, the edge part stays
    np.testing.assert_allclose(res.tooth_force.sum(axis=1), res.force, rtol=1e-12, atol=1e-9)


def test_runout_scenario_event_at_30_percent(trials):
    res, tr = trials["milling-runout"]
    sc = SC.load_scenario("milling-runout")
    rate, t_g = sc["process"]["runout_growth_m_per_s"][0], sc["process"]["runout_growth_from_s"]
    start, level = tr.truth_events
    assert (start.kind, start.t_s, start.value) == ("runout_growth", t_g, rate)
    assert level.kind == "runout" and 0.3 <= level.value < 0.301
    # closed form: r_0 − r_1 grows by rate·(t − t_g), the chips c ± that: Δh grew by 2·rate·(t − t_g)
    c = level.detail["feed_per_tooth_mm"]
    t_cross = t_g + 0.3 * c / (2 * rate * 1e3)
    assert t_cross <= level.t_s < t_cross + tr.Ts
    line = tr.program_line[level.seq]
    inside = tr.t[tr.program_line == line]
    assert inside[0] + 1.0 < level.t_s < inside[-1] - 1.0  # mid-section, not at a change of feed
    # the spindle line grew: 1 s before against 1 s after the event
    rev = 1.0 / (sc["disturbance"]["spindle_rpm"] / 60)
    before = _line(res.force[(res.t >= level.t_s - 1.0) & (res.t < level.t_s - 1.0 + 25 * rev)], tr.Ts, 1 / rev)
    after = _line(res.force[(res.t >= level.t_s) & (res.t < level.t_s + 25 * rev)], tr.Ts, 1 / rev)
    assert after > before * 1.1


def test_collision_impulse_in_the_asked_range(trials):
    res, tr = trials["milling-collision"]
    nominal = trials["milling-part"][0]
    (ev,) = tr.truth_events
    assert ev.kind == "collision" and ev.t_s == 8.0
    pulse = res.force - nominal.force  # same seed and constants but the pulse
    on = np.flatnonzero(np.abs(pulse) > 1e-9)
    np.testing.assert_array_equal(on, np.arange(int(8.0 / tr.Ts), int(np.ceil(8.006 / tr.Ts))))
    assert pulse.max() == pytest.approx(ev.value, rel=1e-12)
    f_cut = ev.detail["cutting_force_N"]
    window = (res.t >= 7.9) & (res.t < 8.0)
    assert f_cut == pytest.approx(np.abs(nominal.force[window]).mean(), rel=1e-2)
    assert 5.0 <= pulse.max() / f_cut <= 20.0
    assert 5.0 <= (res.force[on].max() - f_cut) / f_cut <= 20.0  # as the monitor sees it above the cut


def test_missing_cut_scenario(trials):
    res, tr = trials["milling-missing-cut"]
    start, end = tr.truth_events
    assert (start.kind, start.t_s, end.kind, end.t_s) == ("missing_cut", 11.0, "missing_cut_end", 13.0)
    inside = (res.t >= 11.0) & (res.t + tr.Ts <= 13.0)
    assert np.all(res.force[inside] == 0.0)
    assert np.all(tr.program_line[inside] == tr.program_line[inside][0])  # inside one NC section
    outside = (res.t > 13.1) & (tr.program_line == tr.program_line[inside][0])
    assert res.force[outside].mean() > 20.0


def test_truth_events_round_trip_through_mcap(trials, tmp_path):
    res, tr = trials["milling-runout"]
    assert tr.truth_events == res.events and all(type(e) is S.TruthEvent for e in tr.truth_events)
    assert topic("cnc-mill", "X", TRUTH_EVENTS) == "/cnc-mill/X/truth/events" and \
        "/cnc-mill/X/truth/events" in tr.channels
    assert [b for k, b in iter_blocks(tr.path, kinds=("truth/events",))] == res.events
    win = tr.window(5.0, 12.0)
    assert [e.kind for e in win.truth_events] == [e.kind for e in res.events if 5.0 <= e.t_s < 12.0]
    # an event of its own: every field and the detail survive; a bad one is refused by the schema
    ev = S.TruthEvent(kind="collision", t_s=1.25, seq=416, value=812.5, detail={"cutting_force_N": 81.25, "n": [1, 2]})
    assert S.decode_truth_event(S.encode(ev)) == ev
    with pytest.raises(S.SchemaError, match="t_s"):
        S.decode_truth_event(b'{"kind":"x","t_s":-1.0,"seq":0,"value":1.0}')
    with pytest.raises(S.SchemaError, match="kind"):
        S.decode_truth_event(b'{"kind":"","t_s":1.0,"seq":0,"value":1.0}')


def test_process_constants_are_checked():
    for override, match in (({"process": {"breaks": [[2, 9.0, 0.001]]}}, "not one of the tool's teeth"),
                            ({"process": {"breaks": [[1, 25.0, 0.001]]}}, "not inside the trial"),
                            ({"process": {"impulses": [[8.0, 60.0, 0.006]]}}, "factor in"),
                            ({"process": {"impulses": [[8.0, 10.0]]}}, "list of 3 finite numbers"),
                            ({"process": {"missing": [[13.0, 11.0]]}}, "start < stop"),
                            ({"process": {"material": 0.0}}, "material factor"),
                            ({"process": {"runout_event_fraction": 0.0}}, "runout_event_fraction"),
                            ({"program": {"tool": -1}}, "program.tool"),
                            ({"program": {"line_step": 0}}, "program.line_step")):
        with pytest.raises(ValueError, match=match):
            SC.load_scenario("milling-part", override)
    with pytest.raises(ValueError, match="unknown scenario key 'process'"):
        SC.load_scenario("milling-incdec", {"process": {"material": 1.1}})


def test_same_seed_same_bytes_with_events(tmp_path):
    blobs = []
    for i, seed in enumerate((2, 2, 3)):
        p = tmp_path / f"{i}.mcap"
        write_trial(simulate_scenario("milling-collision", seed=seed, created=CREATED), p)
        blobs.append(p.read_bytes())
    assert blobs[0] == blobs[1] != blobs[2]


#: sha256 of trials of the older scenarios written before the process scenarios existed (4 s, seed 5,
#: created 2024-05-01T08:00:00Z): the per-tooth model and the truth events leave them as they were
OLD_BYTES = {
    "milling-incdec": "75cbb85a0815e76f88bad183211d958cbd630221930a167f8461e3ef4efa268d",
    "milling-spindle-change": "4dd08f510b2ac52649d025ffe3d92d24ee5b390ea04638cd9ac7dab80afe6ca3",
    "shaker-control": "e796272058e35c15930c80697492e978625c19409ace67d9be3e6a4370acf7ab",
}


@pytest.mark.parametrize("name", sorted(OLD_BYTES))
def test_older_scenarios_byte_identical(name, tmp_path):
    cfg = {"spindle": {"schedule": [[1.0, 2400.0], [2.5, 3600.0]]}} if name == "milling-spindle-change" else None
    p = tmp_path / "t.mcap"
    res = simulate_scenario(name, seed=5, duration=4.0, config=cfg, created=CREATED)
    assert res.events == [] and res.program_line is None
    write_trial(res, p)
    assert hashlib.sha256(p.read_bytes()).hexdigest() == OLD_BYTES[name]


# ---------------------------------------------------------------------------------------------
# part series
# ---------------------------------------------------------------------------------------------
def test_series_variation_statistics_as_configured():
    sc = SC.load_scenario("milling-part")
    cfg = sc["series"]
    var = PT.part_variations(sc, 400, seed=7, wear_per_part=0.01)
    mat = np.array([v.material for v in var])
    spin = np.array([v.spindle for v in var])
    ovr = np.array([v.feed_override for v in var])
    # sample statistics of 400 draws: std of the std ≈ σ/√800 (3.5 %), of a uniform's mean ≈ half-width/√1200
    assert np.std(mat) == pytest.approx(cfg["material_std"], rel=0.15)
    assert abs(np.mean(mat) - 1.0) < 4 * cfg["material_std"] / math.sqrt(400)
    assert np.all(np.abs(mat - 1.0) <= 3 * cfg["material_std"] + 1e-15)
    for x, half in ((spin, cfg["spindle_rel"]), (ovr, cfg["feed_override_rel"])):
        assert np.all(np.abs(x - 1.0) <= half)
        assert np.std(x) == pytest.approx(half / math.sqrt(3), rel=0.15)  # uniform on ±half
        assert x.max() - x.min() > 1.8 * half
    np.testing.assert_allclose([v.wear for v in var], 1.0 + 0.01 * np.arange(400), rtol=1e-12)
    assert len({v.seed for v in var}) == 400 and len({round(v.phase_deg, 9) for v in var}) == 400
    starts = np.array([v.start_s for v in var])
    durations = [PT.part_duration(sc, v.feed_override) for v in var]
    np.testing.assert_allclose(np.diff(starts), np.array(durations[:-1]) + cfg["gap_s"], rtol=1e-12)
    assert sum(durations) > 3600.0  # ≥ 1 h of machining in 200 … 400 parts
    # the first parts of a longer series are those of a shorter one
    assert PT.part_variations(sc, 20, seed=7, wear_per_part=0.01) == var[:20]
    with pytest.raises(ValueError, match="1 … 100000 parts"):
        PT.part_variations(sc, 0)
    with pytest.raises(ValueError, match="series.wear_per_part"):
        PT.part_variations(sc, 3, wear_per_part=0.5)
    with pytest.raises(ValueError, match="no \\[series\\] table"):
        PT.part_variations(SC.load_scenario("milling-incdec"), 3)


def _section_mean(res, line: int) -> float:
    m = np.flatnonzero(res.program_line == line)
    core = m[m.size // 4: 3 * m.size // 4]  # away from the ramps
    return float(res.force[core].mean())


def test_series_force_follows_the_drawn_factors():
    """Mean slot force per section a N_t (c' K_rc/4 + K_re/π)·m·w with c' = c·o/s (closed form, per part)."""
    sc = SC.load_scenario("milling-part", QUIET)
    var = PT.part_variations(sc, 25, seed=3, wear_per_part=0.01)
    d = sc["disturbance"]
    for v in (var[0], var[1], var[24]):
        res = simulate(PT.part_scenario(sc, v), seed=v.seed)
        for i, level in enumerate(sc["trajectory"]["levels"]):
            chip = level * v.feed_override / v.spindle
            k = v.material * v.wear
            expected = k * d["teeth"] * d["depth"] * (chip * d["Krc"] / 4 + d["Kre"] / math.pi)
            assert _section_mean(res, 20 + 10 * i) == pytest.approx(expected, rel=0.01)
    assert var[24].wear == pytest.approx(1.24)


def test_cli_part_series(tmp_path, capsys):
    out = tmp_path / "series"
    assert main(["simulate", "milling-part", "--parts", "3", "-o", str(out), "--seed", "4", "--wear", "0.01",
                 "--created", CREATED]) == 0
    assert "wrote 3 parts of milling-part" in capsys.readouterr().out
    files = sorted(out.glob("part-*.mcap"))
    assert [f.name for f in files] == ["part-0000.mcap", "part-0001.mcap", "part-0002.mcap"]
    var = PT.part_variations(SC.load_scenario("milling-part"), 3, seed=4, wear_per_part=0.01)
    for f, v in zip(files, var):
        tr = read_trial(f)
        ev = tr.truth_events[0]
        assert (ev.kind, ev.t_s, ev.value) == ("part", 0.0, float(v.index))
        assert ev.detail == v.to_dict() == tr.meta.provenance.details["part"]
        assert tr.meta.provenance.seed == v.seed
        assert tr.t[-1] == pytest.approx(PT.part_duration(SC.load_scenario("milling-part"), v.feed_override), abs=0.01)
        assert abs(tr.start_ns - read_trial(files[0]).start_ns - v.start_s * 1e9) <= 1e3  # µs in the ISO stamp
    assert main(["simulate", "milling-part", "--wear", "0.01", "-o", str(out)]) == 2
    assert "--wear belongs to a part series" in capsys.readouterr().err
    assert main(["simulate", "milling-incdec", "--parts", "2", "-o", str(out / "x")]) == 2
    assert "no [series] table" in capsys.readouterr().err


def test_series_with_an_event_from_part_k(tmp_path):
    """A running series in which tooth 1 breaks in part 2: parts 0, 1 are good parts."""
    sc = SC.load_scenario("milling-tooth-break", {"series": {"events_from_part": 2}})
    paths = PT.simulate_series(sc, 3, tmp_path, seed=1, created=CREATED)
    kinds = [[e.kind for e in read_trial(p).truth_events] for p in paths]
    assert kinds == [["part"], ["part"], ["part", "tooth_break"]]
    good, broken = read_trial(paths[1]), read_trial(paths[2])
    assert good.truth_events[0].detail["events"] is False and broken.truth_events[0].detail["events"] is True
    late = lambda tr: tr.truth.force[(tr.t > 9.5) & (tr.t < 10.0)]  # noqa: E731 - after the break, same section
    # a 2-tooth slot always has a tooth in the cut; with one tooth left, whole samples without force
    assert np.all(late(good) != 0.0) and np.mean(late(broken) == 0.0) > 0.2
    with pytest.raises(ValueError, match="series.events_from_part"):
        PT.part_variations(SC.load_scenario("milling-part", {"series": {"events_from_part": -1}}), 2)
