"""The LinuxCNC bridge's parts that need no LinuxCNC: its configuration and the checks of HAL's wiring
(on ``halcmd`` output as LinuxCNC 2.9 prints it), the mapping of sampler rows (unwrapped counter, gaps,
sessions, units, non-finite values), blocks and their latency bound, the way back on a real Zenoh
session, the streamer file of a simulated trial, and the HAL plant's gains against its truth.
The same bridge against LinuxCNC itself: tests/test_linuxcnc.py."""

from __future__ import annotations

import math
import re
import sys
import time
import tomllib

import numpy as np
import pytest

from bridge.linuxcnc import wayback as W
from bridge.linuxcnc.config import AxisConfig, BridgeConfig, ConfigError, HalSide, load_config
from bridge.linuxcnc.helper import HalError, HalHelper, HalUnavailable
from bridge.linuxcnc.launch import HAL_DIR, SIM_DIR
from bridge.linuxcnc.mapper import WRAP, Mapper
from bridge.linuxcnc.run import Outlet, blocks_of, trial_metas
from bridge.linuxcnc.wiring import Wiring, check_wiring, parse_pins, parse_signals, parse_threads
from feedio import schema as S
from feedio import transport as T
from feedmon.cli import main
from kernels.feed_drive import physical_to_beta

PLANT_CFG = HAL_DIR / "bridge-333.toml"

# ``halcmd -s show pin sampler.0.`` / ``show sig`` / ``show thread`` of plant-333.hal, as LinuxCNC 2.9 prints them
PINS = """\
sampler s32   OUT 445 sampler.0.curr-depth
sampler bit   IN TRUE sampler.0.enable
sampler u32   IN 445 sampler.0.pin.0 <== count
sampler float IN -0.01974526 sampler.0.pin.1 <== v_ref
sampler float IN -0.01434442 sampler.0.pin.2 <== v
sampler float IN 0.01486439 sampler.0.pin.3 <== x
sampler float IN -26.06257 sampler.0.pin.4 <== u
"""
SIGS = """\
u32    442  count ==> sampler.0.pin.0 ==> sampler.1.pin.0 <== threadtest.0.count
u32    0  fm-x-sample ==> sampler.1.pin.2
float  -26.08967  u <== pid.0.output ==> sampler.0.pin.4 ==> sum2.0.in0
float  -0.01375568  v <== integ.0.out ==> integ.1.in ==> pid.0.feedback ==> sampler.0.pin.2 ==> sum2.0.in1
float  -0.0191711  v_ref ==> pid.0.command ==> sampler.0.pin.1 <== sum2.4.out
float  0.01499175  x <== integ.1.out ==> sampler.0.pin.3
"""
THREADS = ("3000000 YES servo-thread    16660 79356 threadtest.0.increment integ.0 integ.1 siggen.0.update "
           "pid.0.do-pid-calcs sum2.0 sampler.0 sampler.1\n")
TYPES = "uffff"


def _wiring(pins=PINS, sigs=SIGS, threads=THREADS) -> Wiring:
    return Wiring(parse_pins(pins), parse_signals(sigs), parse_threads(threads))


def _cfg(text: str, tmp_path, name="b.toml") -> BridgeConfig:
    path = tmp_path / name
    path.write_text(text)
    return load_config(path)


# ---- configuration -------------------------------------------------------------------------------
def test_shipped_configs_load():
    for path in (HAL_DIR / "bridge-333.toml", HAL_DIR / "bridge-1000.toml", SIM_DIR / "bridge-sim.toml"):
        cfg = load_config(path)
        assert cfg.counter in cfg.columns and cfg.axes
    sim = load_config(SIM_DIR / "bridge-sim.toml")
    assert sim.context() == {"program_line": "motion.program-line", "tool": "iocontrol.0.tool-number"}
    assert sim.axes["X"].resolved_form == "force-input" and sim.axes["X"].length_scale == 0.001


@pytest.mark.parametrize("edit, message", [
    (("block = 1", "block = 0"), r"key publish\.block: .*allowed: 1 ≤ block ≤ 10000"),
    (("v_meas = \"v\"", "v_meas = \"speed\""), r"axes\.X\.v_meas = 'speed' is not one of the sampler's columns"),
    (("counter = \"threadtest.0.count\"", "counter = \"count\""), r"counter = 'count' is not one of the sampler"),
    (("max_delay = 0.01", "max_dela = 0.01"), r"unknown field `max_dela`.*known keys here: block, max_delay"),
    (("\"x\", \"u\"]", "\"u\", \"u\"]"), r"columns name u twice"),
    (("servo_period = 0.003", "servo_period = -1"), r"servo_period.*allowed: 1e-05 ≤ servo_period ≤ 1"),
    (("sample = \"fm-x-sample\"", "speed = \"fm-x-sample\""), r"axes\.X\.links\.speed: the bridge has no such pin"),
    (("u = \"u\"\n", ""), r"axes\.X: the force-input form needs u"),
])
def test_config_errors_name_the_key_and_the_pin(tmp_path, edit, message):
    text = PLANT_CFG.read_text()
    assert edit[0] in text
    with pytest.raises(ConfigError, match=message):
        _cfg(text.replace(edit[0], edit[1], 1), tmp_path)


def test_config_needs_a_measured_velocity_and_one_writer_per_signal(tmp_path):
    text = PLANT_CFG.read_text().replace('v_meas = "v"\n', "").replace('position = "x"\n', "")
    with pytest.raises(ConfigError, match="give the measured velocity as v_meas, or a position"):
        _cfg(text, tmp_path)
    two = PLANT_CFG.read_text() + '\n[axes.Y]\nu = "u"\nv_meas = "v"\n[axes.Y.links]\nsample = "fm-x-sample"\n'
    with pytest.raises(ConfigError, match="links drive signal fm-x-sample from two pins"):
        _cfg(two, tmp_path)
    with pytest.raises(ConfigError, match="not valid UTF-8 TOML"):
        _cfg("machine = [", tmp_path)


# ---- the wiring, as halcmd reports it ------------------------------------------------------------
def test_the_plant_is_wired_as_its_config_says():
    cfg = load_config(PLANT_CFG)
    w = _wiring()
    assert w.pins["sampler.0.pin.4"] == "u" and w.driver("u") == "pid.0.output"
    assert w.threads["servo-thread"][0] == 3_000_000
    check_wiring(cfg, TYPES, w)
    # a column named by any pin on its signal is that column
    check_wiring(cfg.__class__(**{**_fields(cfg), "columns": ["count", "sum2.4.out", "pid.0.feedback",
                                                                 "x", "sum2.0.in0"],
                                  "counter": "count", "axes": {"X": AxisConfig(
                                      u="sum2.0.in0", v_meas="pid.0.feedback", v_ref="sum2.4.out")}}).check(),
                 TYPES, w)


def _fields(cfg) -> dict:
    return {f: getattr(cfg, f) for f in cfg.__struct_fields__}


@pytest.mark.parametrize("change, message", [
    # a sampler with one more column than the config lists: the pin is named
    (lambda c: {"columns": c.columns[:-1], "axes": {"X": AxisConfig(v_ref="v_ref", v_meas="v")}},
     r"sampler\.0\.pin\.4 \(fed by signal u \(written by pid\.0\.output\)\) is not in the config's columns"),
    # columns out of order
    (lambda c: {"columns": ["threadtest.0.count", "v", "v_ref", "x", "u"]},
     r"sampler\.0\.pin\.1 is fed by signal v_ref \(written by sum2\.4\.out\), but the config's column 1 is v"),
    # the config lists a column the sampler does not have
    (lambda c: {"columns": [*c.columns, "extra"]}, r"column 5, extra, has no sampler pin: sampler\.0 was loaded "
                                                   r"with cfg=uffff"),
    # a wrong servo period
    (lambda c: {"servo_period": 0.001}, r"servo_period = 0\.001 s in the config, but sampler\.0 runs in "
                                        r"servo-thread every 0\.003 s \(3000000 ns\): set servo_period = 0\.003"),
    # the counter must be an integer column
    (lambda c: {"counter": "v"}, r"v \(counter\) is sampled as float by sampler\.0\.pin\.2; it needs u32 or s32"),
])
def test_wiring_mismatches_name_the_sampler_pin(change, message):
    cfg = load_config(PLANT_CFG)
    bad = BridgeConfig(**{**_fields(cfg), **change(cfg)})
    with pytest.raises(ConfigError, match=message):
        check_wiring(bad, TYPES, _wiring())


def test_an_unconnected_sampler_pin_and_a_counter_of_another_thread_are_refused():
    cfg = load_config(PLANT_CFG)
    with pytest.raises(ConfigError, match=r"sampler\.0\.pin\.3 is fed by nothing \(not connected\), but the "
                                          r"config's column 3 is x"):
        check_wiring(cfg, TYPES, _wiring(pins=PINS.replace(" <== x", "")))
    with pytest.raises(ConfigError, match=r"the counter threadtest\.0\.count must count the cycles of servo-thread.*"
                                          r"addf threadtest\.0\.increment servo-thread"):
        check_wiring(cfg, TYPES, _wiring(threads=THREADS.replace("threadtest.0.increment ", "")))
    with pytest.raises(ConfigError, match=r"sampler\.0 is in no HAL thread"):
        check_wiring(cfg, TYPES, _wiring(threads=THREADS.replace(" sampler.0 ", " ")))


# ---- mapping rows --------------------------------------------------------------------------------
def _mcfg(**axis) -> BridgeConfig:
    ax = AxisConfig(**({"v_ref": "v", "position": "x", "length_scale": 0.001} | axis))
    return BridgeConfig(machine="m", servo_period=0.001, counter="c", columns=["c", "v", "x", "line", "u"],
                        program_line="line", axes={"X": ax}).check()


def _rows(counts, x=None, v=5.0, line=7, u=0.0) -> np.ndarray:
    counts = np.asarray(counts, dtype=np.float64)
    x = 0.05 * np.arange(counts.size) if x is None else np.asarray(x, dtype=np.float64)
    return np.column_stack([counts, np.full(counts.size, v), x, np.full(counts.size, line), np.full(counts.size, u)])


def test_the_counter_is_unwrapped_and_a_jump_is_a_gap_of_exactly_the_missing_samples():
    m = Mapper(_mcfg(v_meas="v"))
    runs = m.map(_rows([WRAP - 2, WRAP - 1, 0, 1]), 100.0)  # u32 wraps
    assert [(r.seq0, len(r)) for r in runs] == [(WRAP - 2, 4)] and m.gaps == 0
    runs = m.map(_rows([2, 3, 10, 11, 12]), 100.01)       # 6 cycles not delivered (FIFO overrun)
    assert [(r.seq0, len(r)) for r in runs] == [(WRAP + 2, 2), (WRAP + 10, 3)]
    assert (m.gaps, m.missing, m.sessions, m.held) == (1, 6, 1, 0)
    t = np.concatenate([r.t for r in runs])
    np.testing.assert_allclose(np.diff(t), [0.001, 0.007, 0.001, 0.001], atol=1e-9)  # t = (seq + k0) Ts
    assert t[-1] == pytest.approx(100.0 + 11 * 0.001)  # k0 fixed by the session's first read: seq WRAP+1 at 100 s
    runs = m.map(_rows([-3, -2]), 100.02)                                          # an s32 counter: mod 2**32
    assert runs[0].seq0 == WRAP - 3 and m.sessions == 2                            # far back: a new session


def test_a_new_session_restarts_seq_while_time_goes_on():
    m = Mapper(_mcfg(v_meas="v"))
    first = m.map(_rows(np.arange(5000, 5010)), 50.0)[0]
    again = m.map(_rows([3, 4, 5]), 49.0)[0]  # LinuxCNC restarted; a read stamp even earlier than the last sample
    assert again.seq0 == 3 and m.sessions == 2
    assert again.t[0] > first.t[-1] and np.allclose(np.diff(again.t), 0.001)


def test_velocity_from_position_units_and_nonfinite_values():
    m = Mapper(_mcfg())
    x = np.array([0.0, 0.1, 0.3, 0.6])  # mm
    a = m.map(_rows([1, 2, 3, 4], x=x), 1.0)[0]
    assert a.seq0 == 2 and m.held == 1  # the first sample has no velocity: it only gives the second one its own
    np.testing.assert_allclose(a.cols["X.v_meas"], [0.1, 0.2, 0.3])  # (Δx mm · 0.001)/Ts
    np.testing.assert_allclose(a.cols["X.v_ref"], 0.005)  # 5 mm/s
    b = m.map(_rows([5, 6], x=[1.0, 1.5]), 1.002)[0]  # continues: the previous frame's last position is used
    np.testing.assert_allclose(b.cols["X.v_meas"], [0.4, 0.5])
    c = m.map(_rows([7, 8, 9], x=[1.5, np.nan, 2.0], v=np.inf), 1.005)[0]
    assert np.isnan(c.cols["X.v_meas"][1:]).all() and np.isnan(c.cols["X.v_ref"]).all()
    assert m.nonfinite == {"x": 1, "v": 3}  # counted per HAL column
    blk = blocks_of(m.cfg, c)[0]
    decoded = S.decode_samples(S.encode(blk))  # NaN travels as null: the monitor rejects that sample
    assert decoded.v_ref == [None, None, None] and decoded.v_meas[0] is not None and decoded.v_meas[1] is None
    assert decoded.program_line == [7, 7, 7] and decoded.seq == 7
    assert [r.seq0 for r in m.map(_rows([20, 21, 22]), 1.02)] == [21] and m.held == 2  # after a gap, too


def test_blocks_carry_the_axis_columns_in_si_and_the_context():
    cfg = BridgeConfig(machine="m", servo_period=0.001, counter="c",
                       columns=["c", "rev", "rps", "line", "tool", "u", "v"], program_line="line", tool="tool",
                       axes={"Z": AxisConfig(u="u", v_meas="v", spindle_revs="rev", spindle_speed="rps",
                                             spindle_speed_unit="rps", force_scale=2.0)}).check()
    rows = np.array([[1, 0.5, 50.0, 12, 3, 10.0, 0.01], [2, 0.55, 50.0, 13, 3, 11.0, 0.02]])
    blk = blocks_of(cfg, Mapper(cfg).map(rows, 1.0)[0])[0]
    assert blk.spindle_angle == pytest.approx([math.pi, 1.1 * math.pi]) and blk.spindle_rpm == [3000.0, 3000.0]
    assert blk.u == [20.0, 22.0] and blk.v_meas == [0.01, 0.02] and blk.v_ref == [None, None]
    assert (blk.program_line, blk.tool, blk.position) == ([12, 13], [3, 3], None)
    meta = trial_metas(cfg, tool="test", version="0")[0]
    assert meta.form == "force-input" and meta.Ts == 0.001 and meta.units["spindle_angle"] == "rad"
    assert "position" not in meta.units and meta.units["program_line"] == "NC line"


class _Pub:
    def __init__(self):
        self.blocks = []

    def put(self, data: bytes) -> None:
        self.blocks.append(S.decode_samples(data))


def test_outlet_cuts_blocks_splits_at_gaps_and_bounds_the_wait():
    cfg = BridgeConfig(**{**_fields(_mcfg(v_meas="v")), "publish": type(_mcfg().publish)(block=4, max_delay=0.02)})
    pub = _Pub()
    out, m = Outlet(cfg, {"X": pub}, None), Mapper(cfg)
    out.add(m.map(_rows(range(1, 11)), 1.0), now=0.0)
    assert [(b.seq, len(b)) for b in pub.blocks] == [(1, 4), (5, 4)]       # 2 samples wait
    assert out.due(0.01) == pytest.approx(0.01)                             # … at most max_delay
    out.add(m.map(_rows([11, 20, 21]), 1.01), now=0.011)                     # a gap: the waiting samples go first
    assert [(b.seq, len(b)) for b in pub.blocks][2:] == [(9, 3)]
    assert out.due(0.030) == pytest.approx(0.001) and len(pub.blocks) == 3   # 20, 21 wait since 0.011
    out.due(0.032)
    assert [(b.seq, len(b)) for b in pub.blocks][3:] == [(20, 2)]
    assert out.counters["samples"] == 13 and out.counters["messages"] == 4


# ---- the way back ----------------------------------------------------------------------------------
@pytest.fixture
def zenoh_pair():
    port = T.free_tcp_port()
    a = T.open_session(listen=f"tcp/127.0.0.1:{port}")
    b = T.open_session(connect=f"tcp/127.0.0.1:{port}")
    deadline = time.monotonic() + 10
    while not b.info.peers_zid() and time.monotonic() < deadline:
        time.sleep(0.01)
    yield a, b
    b.close()
    a.close()


def _estimates(seq: int, force: float | None, flags: int = 0) -> S.EstimateBlock:
    one = [0.0]
    return S.EstimateBlock(machine="m", axis="X", seq=seq, t=[seq * 0.001], v_meas=one, v_pred=one, residual=one,
                           f=one, f_var=[1e-8], f_next=one, f_next_var=[1e-8], dict_size=[3], removed=[-1],
                           flags=[flags], force=None if force is None else [force], force_var=[4.0],
                           force_next=one)


def _health(state: str) -> S.Health:
    return S.Health(machine="m", axis="X", seq=1, t=1.0, state=state)


def _wait(cond, what: str):
    deadline = time.monotonic() + 10
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def test_way_back_pins_follow_the_monitor_and_a_second_alarm_source_plugs_in(zenoh_pair, monkeypatch):
    monitor, bridge_side = zenoh_pair
    sent: list[dict] = []
    process_key = lambda prefix, machine, axis: f"{prefix}/{machine}/{axis}/test-alarm"  # noqa: E731
    monkeypatch.setitem(W.ALARM_SOURCES, "process", W.AlarmSource(process_key, lambda p: (p == b"1", {})))
    cfg = _mcfg()
    wb = W.WayBack(cfg, "wb", lambda values: sent.append(values) or True)
    assert ("X.alarm", "bit") in wb.pins() and wb.current()["X.health"] == -1
    wb.subscribe(bridge_side)
    pubs = {k: monitor.declare_publisher(k) for k in (T.disturbance_key("wb", "m", "X"), T.health_key("wb", "m", "X"),
                                                      process_key("wb", "m", "X"))}
    for pub in pubs.values():
        assert T.wait_for_matching(pub, 10)
    dist, health, proc = pubs.values()
    dist.put(S.encode(_estimates(2**32 + 5, 12.5)))
    _wait(lambda: wb.current()["X.force"] == 12.5, "the estimate reaches the pins")
    assert wb.current()["X.sample"] == 5 and wb.current()["X.valid"] and wb.current()["X.force-sigma"] == 2.0
    dist.put(S.encode(_estimates(6, 99.0, flags=S.WARMUP)))                 # not learned: force kept, not valid
    _wait(lambda: wb.current()["X.sample"] == 6, "the second estimate")
    assert wb.current()["X.force"] == 12.5 and not wb.current()["X.valid"]
    health.put(S.encode(_health("warn")))
    _wait(lambda: wb.current()["X.health"] == 1, "the health report")
    assert not wb.current()["X.alarm"]
    proc.put(b"1")                                                          # the other source raises the alarm
    _wait(lambda: wb.current()["X.alarm"], "the second source's alarm")
    health.put(S.encode(_health("alarm")))
    proc.put(b"0")                                                          # health still in alarm
    _wait(lambda: wb.current()["X.health"] == 2 and wb.alarm_state("X") == {"health": True, "process": False},
          "both sources")
    assert wb.current()["X.alarm"]
    health.put(S.encode(_health("ok")))
    _wait(lambda: not wb.current()["X.alarm"], "the alarm clears when no source is in alarm")
    health.put(b'{"state": "alarm"}')                                       # malformed: counted, nothing changes
    _wait(lambda: wb.counters["malformed_health"] == 1, "the malformed report is counted")
    limit, W.MAX_REPORT_BYTES = W.MAX_REPORT_BYTES, 100
    try:
        health.put(S.encode(_health("alarm")))                             # too large: refused unread
        _wait(lambda: wb.counters["too_large"] == 1, "the large report is counted")
    finally:
        W.MAX_REPORT_BYTES = limit
    assert not wb.current()["X.alarm"] and any(v.get("X.alarm") for v in sent)
    wb.tick(time.monotonic() + 10)                                          # no estimate for 10 s: not valid
    dist.put(S.encode(_estimates(7, 1.0)))
    _wait(lambda: wb.current()["X.valid"], "valid again with a new estimate")
    wb.tick(time.monotonic() + cfg.hal.stale_after + 1)
    assert not wb.current()["X.valid"] and sent[-1] == {"X.valid": False}
    wb.close()


# ---- the streamer file and the plant ------------------------------------------------------------------
def test_streamer_file_is_the_trial_truth_force(simulated, tmp_path, capsys):
    trial = simulated("shaker-constant", seed=3, duration=1.0)
    out = tmp_path / "force.txt"
    assert main(["bridge", "streamer-file", str(trial), "-o", str(out), "--scale", "0.5"]) == 0
    from feedio.mcapio import read_trial

    truth = read_trial(trial).truth.force
    np.testing.assert_array_equal(np.loadtxt(out), 0.5 * truth)
    capsys.readouterr()
    assert main(["bridge", "streamer-file", str(trial), "-o", str(out), "--servo-period", "0.001"]) == 2
    err = capsys.readouterr().err
    assert "sampled every 0.003003 s, but the servo period is 0.001 s" in err and "(command line: --servo-period)" in err


def _setp(text: str) -> dict[str, float]:
    return {m[1]: float(m[2]) for m in re.finditer(r"^setp (\S+) (\S+)", text, re.M)}


@pytest.mark.parametrize("hal, prefix", [("plant-333.hal", ""), ("plant-1000.hal", ""), ("sim", "sim")])
def test_the_hal_plants_are_the_exact_discretisation_of_their_truth(hal, prefix):
    """integ adds Ts·in per cycle and in = g·(u − B v − Fc τ(v) − F): v(k+1) = (1 − g B Ts) v(k) + g Ts (…), which
    is the ZOH model of truth.toml (what identify fits) exactly when g = b/Ts and B, Fc, Ω as in the truth."""
    truth = tomllib.loads((HAL_DIR / "truth.toml").read_text())
    if prefix == "sim":
        text, Ts = (SIM_DIR / "plant-sim.hal").read_text(), 0.001
        ini = (SIM_DIR / "feedmon-sim.ini").read_text()
        assert re.search(r"^SERVO_PERIOD = 1000000$", ini, re.M)
        names = {"gain": "plant-gain.gain", "B": "lin.gain1", "Fc": "coulomb.gain1", "min": "coulomb-band.min",
                 "max": "coulomb-band.max", "Kv": "x-vel.Pgain"}
    else:
        text, Ts = (HAL_DIR / hal).read_text(), truth["rates"][hal]
        assert re.search(rf"period1={round(Ts * 1e9)}\b", text)
        names = {"gain": "scale.0.gain", "B": "sum2.0.gain1", "Fc": "sum2.3.gain1", "min": "wcomp.0.min",
                 "max": "wcomp.0.max", "Kv": "pid.0.Pgain"}
    p = _setp(text)
    beta = physical_to_beta("force-input", Ts, truth["mass"], truth["damping"], coulomb_pos=truth["coulomb"],
                            coulomb_neg=truth["coulomb"])
    b, pole = beta[0], beta[1]
    assert p[names["gain"]] == pytest.approx(b / Ts, rel=1e-15)
    assert 1.0 - p[names["gain"]] * -p[names["B"]] * Ts == pytest.approx(pole, rel=1e-15)
    assert (p[names["Fc"]], p[names["max"]], -p[names["min"]]) == (truth["coulomb"], truth["omega"], truth["omega"])
    assert p[names["Kv"]] == truth["loop_gain"]


def test_the_hal_helper_says_what_is_missing():
    """The helper runs under [hal] python: one without LinuxCNC's hal module, or none at all, is an error
    naming the fix (not a wait for HAL)."""
    cfg = _mcfg()
    no_hal = BridgeConfig(**{**_fields(cfg), "hal": HalSide(python=sys.executable)})  # this venv: no hal module
    helper = HalHelper(no_hal, [], {})
    with pytest.raises(HalError, match=r"cannot import LinuxCNC's hal module.*apt-get install linuxcnc-uspace") as err:
        helper.start()
    assert not isinstance(err.value, HalUnavailable) and helper.proc.returncode == 3
    missing = BridgeConfig(**{**_fields(cfg), "hal": HalSide(python="/nonexistent/python3")})
    with pytest.raises(HalError, match=r"/nonexistent/python3 not found \(\[hal\] python"):
        HalHelper(missing, [], {})
