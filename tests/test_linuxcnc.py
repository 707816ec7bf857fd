"""The LinuxCNC bridge against LinuxCNC itself (Debian's linuxcnc-uspace 2.9, POSIX non-realtime threads).

* ``halrun`` plant (bridge/linuxcnc/hal, 333 Hz) → bridge → trial → ``feedmon identify`` (no flags) recovers
  the plant's mass, damping and Coulomb friction; then plant with a simulated cutting force → bridge → Zenoh →
  ``feedmon run`` (a real subprocess): the force estimate follows the injected force;
* the 1 kHz plant through the bridge is exactly its discrete model (the truth sampled beside it);
* bad HAL input (a wrong servo period, a sampler with other columns, a pin missing from the config, NaN)
  gets an error or a count naming the pin;
* full LinuxCNC (headless, linuxcncrsh) running a G-code program: estimates carry the program line and
  tool; a forced FIFO overrun is one gap and nothing else is lost; the bridge and LinuxCNC restart and the
  monitor follows; an alarm raised by the monitor holds the feed (``motion.feed-hold``, seen in HAL).

Without LinuxCNC these tests fail (never skip) and say how to install it. HAL threads are not realtime
here: every wait is on a condition with a generous timeout.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from monitor_proc import MonitorProc

from bridge.linuxcnc import launch as L
from bridge.linuxcnc.launch import HAL_DIR, SIM_DIR
from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_blocks, read_trial
from feedmon.cli import main
from monitor.model_file import load_model

MISSING = L.linuxcnc_missing()
PREFIX = "lcnc-test"
LEARNED = S.REJECTED | S.GAP | S.WARMUP


@pytest.fixture(scope="module", autouse=True)
def _linuxcnc_here():
    if MISSING:
        pytest.fail(f"the LinuxCNC tests need LinuxCNC: {MISSING}", pytrace=False)


@pytest.fixture(scope="module")
def work():
    d = L.workdir()
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _force(work: Path, scenario: str, *, seed: int, scale: float, duration: float, Ts: float) -> Path:
    """A cutting force simulated by ``feedmon simulate`` at the plant's rate, as a halstreamer file."""
    rate = work / f"rate-{Ts:g}.toml"
    rate.write_text(f"rate = {1.0 / Ts!r}\n")
    trial = work / f"{scenario}-{seed}-{Ts:g}.mcap"
    out = work / f"{scenario}-{seed}-{Ts:g}-{scale:g}.txt"
    assert main(["simulate", scenario, "-o", str(trial), "--seed", str(seed), "--duration", str(duration),
                 "--config", str(rate)]) == 0
    assert main(["bridge", "streamer-file", str(trial), "-o", str(out), "--scale", str(scale),
                 "--servo-period", str(Ts)]) == 0
    return out


def _sampler1(path: Path) -> np.ndarray:
    """``halsampler -t`` lines of the plant's sampler.1 → rows (counter, true force N, feedmon.X.sample)."""
    rows = [line.split() for line in path.read_text().splitlines()]
    return np.array([[float(x) for x in r[1:]] for r in rows if len(r) == 4])


def _truth(path: Path) -> dict[int, float]:
    """{counter: the true force (N) of that servo cycle}."""
    return {int(c): f for c, f, _ in _sampler1(path)}


class Observer:
    """A Zenoh session on the monitor's endpoint collecting its estimate rows of one axis."""

    def __init__(self, endpoint: str, machine: str, axis: str = "X") -> None:
        self.session = T.open_session(connect=endpoint)
        self.rows: list[tuple[int, float, float, int, int | None, int | None]] = []  # seq, force, var, flags, line, tool
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(T.disturbance_key(PREFIX, machine, axis), self._take)

    def _take(self, sample) -> None:
        b = S.decode_estimates(sample.payload.to_bytes())
        n = len(b)
        force = b.force or [math.nan] * n
        var = b.force_var or [math.nan] * n
        line, tool = b.program_line or [None] * n, b.tool or [None] * n
        with self._lock:
            self.rows += [(b.seq + i, force[i], var[i], b.flags[i], line[i], tool[i]) for i in range(n)]

    def snapshot(self) -> list[tuple]:
        with self._lock:
            return list(self.rows)

    def wait_rows(self, n: int, timeout: float) -> list[tuple]:
        L.wait_for(lambda: len(self.snapshot()) >= n, timeout, f"{n} estimate rows from the monitor")
        return self.snapshot()

    def status(self) -> dict:
        replies = T.query_status(self.session, PREFIX, timeout=5.0)
        assert replies, "the monitor does not answer status queries"
        return replies[0]

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


# ---- the halrun plant: identified, then monitored with a cutting force ------------------------------
def test_plant_identified_from_a_hal_trial_then_its_force_estimated_live(work):
    """Identification on a light cut (3 % of the force), the monitor on another, full cut: out of sample,
    no flags. The plant integrates the exact ZOH model identify fits, so M, B, Fc come back within a
    few standard errors; corr(force estimate, injected force) ≥ 0.98. The way-back pin, sampled beside
    the counter, shows the newest answered sample: never one from the future, and it keeps up."""
    Ts = 0.003
    light = _force(work, "milling-inc", seed=1, scale=0.03, duration=14, Ts=Ts)
    cut = _force(work, "milling-dec", seed=2, scale=1.0, duration=14, Ts=Ts)
    cfg = L.bridge_config(HAL_DIR / "bridge-333.toml", work)
    trial, model = work / "plant-333.mcap", work / "plant-333.model.toml"
    with L.HalPlant(HAL_DIR / "plant-333.hal", work) as plant:
        plant.streamer(light)
        rec = L.start_bridge(cfg, work, "--record", str(trial), "--duration", "10", "--no-publish")
        assert rec.wait(120) == 0, rec.stderr
    tr = read_trial(trial)
    assert len(tr) >= 3333 and np.all(np.diff(tr.seq) == 1) and tr.meta.form == "force-input"
    assert main(["identify", str(trial), "-o", str(model)]) == 0
    phys, truth = load_model(model).physical, L.plant_truth()
    assert phys["inertia"] == pytest.approx(truth["mass"], rel=0.02)
    assert phys["damping"] == pytest.approx(truth["damping"], rel=0.02)
    assert phys["coulomb"] == pytest.approx(truth["coulomb"], rel=0.05)

    mon = MonitorProc(["--model", str(model)], work, prefix=PREFIX)
    obs = Observer(mon.endpoint, "plant")
    truth_file = work / "truth-333.txt"
    try:
        with L.HalPlant(HAL_DIR / "plant-333.hal", work) as plant:
            plant.streamer(cut)
            plant.sampler(truth_file, channel=1)
            bridge = L.start_bridge(cfg, work, "--connect", mon.endpoint, "--prefix", PREFIX)
            rows = obs.wait_rows(2800, timeout=120)  # 8.4 s of samples
            assert bridge.stop() == 0, bridge.stderr
    finally:
        obs.close()
        assert mon.stop() == 0, mon.stderr
    log = _sampler1(truth_file)
    count, echo = log[:, 0], log[:, 2]
    answered = echo > 0
    seen = echo[answered]
    assert np.all(echo <= count) and np.all(np.diff(seen) >= 0)  # never a sample from the future, never back
    assert seen[-1] - seen[0] >= 2000  # the pin followed the estimates through the run (seen in HAL)
    assert np.median((count - echo)[answered]) < 333  # behind by cycles, not by a growing backlog (generous)
    forces = _truth(truth_file)
    # row j's force is the filtered force of sample j − 1
    pairs = [(f, forces[seq - 1]) for seq, f, var, flags, *_ in rows
             if not flags & LEARNED and math.isfinite(f) and seq - 1 in forces]
    est, true = np.array(pairs).T
    corr = float(np.corrcoef(est, true)[0, 1])
    rms = float(np.sqrt(np.mean((est - true) ** 2)))
    print(f"halrun plant 333 Hz: corr(force estimate, injected force) = {corr:.4f}, rms error {rms:.1f} N (force "
          f"s.d. {true.std():.1f} N) over {est.size} samples; "
          f"identified J = {phys['inertia']:.3f} kg, B = {phys['damping']:.2f} N·s/m, Fc = {phys['coulomb']:.3f} N")
    assert est.size >= 2000 and true.std() > 10.0  # the cut is on
    assert corr >= 0.98


def test_the_1khz_plant_through_the_bridge_is_its_exact_model(work):
    """v(k+1) = p v(k) + b (u(k) − Fc τ(v(k)) − F(k)) with the truth's p, b, Fc, Ω and the force sampled by
    sampler.1 beside it: the plant file, the counter and the bridge's alignment of the columns, at once."""
    Ts = 0.001
    # 14 s of force for a 2.5 s recording: the streamer runs from the plant's start, and the bridge may take
    # seconds to start recording on a loaded host (4 s once left it nothing but the force after the file)
    force = _force(work, "milling-inc", seed=3, scale=1.0, duration=14, Ts=Ts)
    cfg = L.bridge_config(HAL_DIR / "bridge-1000.toml", work)
    trial, truth_file = work / "plant-1000.mcap", work / "truth-1000.txt"
    with L.HalPlant(HAL_DIR / "plant-1000.hal", work) as plant:
        plant.streamer(force)
        plant.sampler(truth_file, channel=1)
        rec = L.start_bridge(cfg, work, "--record", str(trial), "--duration", "2.5", "--no-publish")
        assert rec.wait(120) == 0, rec.stderr
    tr, F, truth = read_trial(trial), _truth(truth_file), L.plant_truth()
    assert np.all(np.diff(tr.seq) == 1) and np.allclose(np.diff(tr.t), Ts, rtol=0, atol=1e-9)
    p = math.exp(-truth["damping"] * Ts / truth["mass"])
    b = (1.0 - p) / truth["damping"]
    f = np.array([F[s] for s in tr.seq])
    v, u = tr.v_meas, tr.u
    tau = (v >= truth["omega"]).astype(float) - (v <= -truth["omega"])
    res = v[1:] - (p * v[:-1] + b * (u[:-1] - truth["coulomb"] * tau[:-1] - f[:-1]))
    assert np.abs(f).max() > 10.0 and np.abs(v).max() > 0.03
    assert np.abs(res).max() < 2.0 * b * 5e-7  # halsampler prints the truth force with six decimals
    np.testing.assert_allclose(np.diff(tr.position) / Ts, v[1:], atol=1e-12)


# ---- bad input from the HAL side ----------------------------------------------------------------------
PROBE_HAL = """\
loadrt threads name1=servo-thread period1=1000000
loadrt threadtest
loadrt sampler depth=4096 cfg=uff
addf threadtest.0.increment servo-thread
addf sampler.0 servo-thread
net count threadtest.0.count => sampler.0.pin.0
net force => sampler.0.pin.1
net speed => sampler.0.pin.2
start
"""
PROBE_CFG = """\
machine = "probe"
servo_period = 0.001
counter = "threadtest.0.count"
columns = ["threadtest.0.count", "force", "speed"]
[axes.X]
u = "force"
v_meas = "speed"
"""


def test_bad_hal_input_is_refused_or_counted_naming_the_pin(work):
    src = work / "probe.hal"
    src.write_text(PROBE_HAL)
    good = work / "probe.toml"
    good.write_text(PROBE_CFG)
    good = L.bridge_config(good, work)
    early = L.Proc(["bridge", "linuxcnc", "--config", str(good), "--no-publish"], work)  # before LinuxCNC
    early.wait_line(r"waiting for HAL: sampler\.0 has no FIFO in shared memory", 60)
    bad = {
        "wrong-period": (PROBE_CFG.replace("servo_period = 0.001", "servo_period = 0.003"),
                         "servo_period = 0.003 s in the config, but sampler.0 runs in servo-thread every 0.001 s"),
        "pin-missing": (PROBE_CFG.replace(', "speed"]', "]").replace('v_meas = "speed"', 'v_meas = "force"'),
                        "sampler.0.pin.2 (fed by signal speed (no writer)) is not in the config's columns"),
        "other-columns": (PROBE_CFG.replace('"force", "speed"]', '"speed", "force"]'),
                          "sampler.0.pin.1 is fed by signal force (no writer), but the config's column 1 is speed"),
    }
    with L.HalPlant(src, work):
        early.wait_line(r"attached to sampler\.0", 60)  # HAL came: the bridge attached by itself
        assert early.stop() == 0, early.stderr
        for name, (text, message) in bad.items():
            cfg = work / f"probe-{name}.toml"
            cfg.write_text(text)
            proc = L.Proc(["bridge", "linuxcnc", "--config", str(L.bridge_config(cfg, work)), "--no-publish"], work)
            assert proc.wait(60) == 2, proc.stderr
            assert message in proc.stderr and "Traceback" not in proc.stderr
        L.halcmd("sets", "force", "12.5")
        L.halcmd("sets", "speed", "nan")
        trial = work / "probe.mcap"
        rec = L.start_bridge(good, work, "--record", str(trial), "--duration", "0.5", "--no-publish")
        assert rec.wait(60) == 0, rec.stderr
    assert "speed gave" in rec.stderr and "non-finite value(s) so far: those samples go out as null" in rec.stderr
    tr = read_trial(trial)
    assert len(tr) >= 400 and np.isnan(tr.v_meas).all() and np.all(tr.u == 12.5)


# ---- full LinuxCNC --------------------------------------------------------------------------------------
def _status_axis(obs: Observer) -> dict:
    return obs.status()["axes"]["sim/X"]


def test_linuxcnc_program_overrun_restarts_and_feed_hold(work):
    cfg = L.bridge_config(SIM_DIR / "bridge-sim.toml", work)
    trial, model, log = work / "sim.mcap", work / "sim.model.toml", work / "sim-log.mcap"
    cnc = L.LinuxCNC(work)
    mon = obs = bridge = None
    try:
        cnc.rsh.run_program(work / "program.ngc")
        rec = L.start_bridge(cfg, work, "--record", str(trial), "--duration", "6", "--no-publish")
        assert rec.wait(120) == 0, rec.stderr
        assert main(["identify", str(trial), "-o", str(model)]) == 0  # the machine's own recording, no flags
        # the way back is what is tested here, with the tracker of the model file: with the online disturbance
        # search on, a loaded host (the plant's HAL thread stalling) let the searched disturbance model take up
        # the damping jump (mean ν² ≈ 0, the damping "not determined", no alarm) — an open defect, see
        # docs/method.md §10 "Limits"
        text = model.read_text()
        assert "\nsearch = true" in text
        model.write_text(text.replace("\nsearch = true", "\nsearch = false"))
        mon = MonitorProc(["--model", str(model), "--mcap", str(log)], work, prefix=PREFIX)
        obs = Observer(mon.endpoint, "sim")
        bridge = L.start_bridge(cfg, work, "--connect", mon.endpoint, "--prefix", PREFIX)

        # the estimates carry the NC line and the tool of their sample
        rows = obs.wait_rows(3000, timeout=120)
        lines = {r[4] for r in rows}
        assert lines & {9, 10} and lines <= set(range(0, 20)), lines  # the o100 loop's G1 lines (program.ngc)
        assert {r[5] for r in rows[-500:]} == {1}

        # a forced overrun: the helper stops reading for 2.5 s, the FIFO (1 s deep) overflows
        before = _status_axis(obs)
        pid = int(bridge.wait_line(r"HAL helper pid (\d+)", 10)[1])
        os.kill(pid, signal.SIGSTOP)
        time.sleep(2.5)
        os.kill(pid, signal.SIGCONT)
        missing = int(bridge.wait_line(r"gap: (\d+) sample\(s\) not delivered", 30)[1])
        assert 1000 < missing < 4000
        after = L.wait_for(lambda: (a := _status_axis(obs))["gaps"] > before["gaps"] and a, 30, "the monitor's gap")
        assert after["gaps"] == before["gaps"] + 1, after
        assert after["missing_samples"] == before["missing_samples"] + missing + 1, after  # + the held first sample
        assert after["dropped_total"] == before["dropped_total"], after
        seqs = np.array(sorted(r[0] for r in obs.wait_rows(len(obs.snapshot()) + 500, 60)))
        steps = np.diff(seqs)
        assert np.count_nonzero(steps != 1) == 1 and steps.max() == missing + 2  # nothing else lost

        # the bridge restarts: the monitor follows (the HAL clock went on: a gap)
        assert bridge.stop() == 0, bridge.stderr
        last = max(r[0] for r in obs.snapshot())
        bridge = L.start_bridge(cfg, work, "--connect", mon.endpoint, "--prefix", PREFIX)
        L.wait_for(lambda: max(r[0] for r in obs.snapshot()) > last + 1000, 60, "estimates after the bridge restart")

        # LinuxCNC restarts: the bridge waits and attaches again; the monitor sees a new session
        resets = _status_axis(obs)["counters"].get("seq_resets", 0)
        cnc.stop()
        bridge.wait_line(r"HAL went away|waiting for HAL", 60)
        cnc = L.LinuxCNC(work)
        cnc.rsh.run_program(work / "program.ngc")
        bridge.wait_line(r"attached to sampler", 120, n=2)
        L.wait_for(lambda: _status_axis(obs)["counters"].get("seq_resets", 0) > resets, 60, "a new session")
        n = len(obs.snapshot())
        obs.wait_rows(n + 2000, 60)
        assert mon.proc.poll() is None and bridge.proc.poll() is None

        # the plant changes (damping ×5, mass ×2): the monitor's health goes to alarm, the bridge holds the feed
        assert L.halcmd("getp", "motion.feed-hold").strip() == "FALSE"
        L.halcmd("setp", "lin.gain1", "-1000")                   # damping ×5
        gain = float(L.halcmd("getp", "plant-gain.gain"))
        L.halcmd("setp", "plant-gain.gain", repr(gain / 2))          # and the mass ×2: a heavy fixture
        L.wait_for(lambda: L.halcmd("getp", "motion.feed-hold").strip() == "TRUE", 120, "motion.feed-hold")
        assert L.halcmd("getp", "feedmon.X.alarm").strip() == "TRUE"
        L.wait_for(lambda: float(L.halcmd("getp", "motion.current-vel")) == 0.0, 30, "the feed to stop")
        assert bridge.count("alarm RAISED") >= 1
        assert bridge.stop() == 0, bridge.stderr
        bridge = None
    finally:
        for proc in (bridge,):
            if proc is not None:
                proc.stop()
        if obs is not None:
            obs.close()
        cnc.stop()
        if mon is not None:
            rc = mon.stop()
            # exit 1 only for a sink that lost messages (its idle-priority logger starved on a loaded host: the
            # stop says so); every other failure is a failure
            assert rc == 0 or (rc == 1 and "messages not written" in mon.stderr), mon.stderr
    # the log, or the file of its last logger when a starved one was replaced (its own file left unfinished)
    last = sorted(work.glob(f"{log.stem}-*.mcap"))[-1:] or [log]
    logged = [b for _, b in iter_blocks(last[0], kinds=("disturbance",))]
    assert any(b.program_line and set(b.program_line) & {9, 10} for b in logged)  # the MCAP log carries them
